"""Pictures of the console: PNG files from arrays, a depth colour ramp with hillshade, image
thumbnails. No state, no I/O."""

from __future__ import annotations

import math
import zlib
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = ["THUMB_SIDE", "elevation_rgb", "png_bytes"]

FloatArray = npt.NDArray[np.float64]


def png_bytes(rgb: npt.NDArray[np.uint8]) -> bytes:
    """A PNG file of an ``H x W x 3`` (RGB) or ``H x W x 4`` (RGBA) uint8 image, row 0 at the top."""
    img = np.ascontiguousarray(rgb, dtype=np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    h, w, c = img.shape
    if c not in (3, 4):
        raise ValueError(f"expected 3 or 4 channels, got {c}")
    raw = np.zeros((h, 1 + w * c), np.uint8)  # filter byte 0 (None) before each row
    raw[:, 1:] = img.reshape(h, w * c)

    def chunk(tag: bytes, data: bytes) -> bytes:
        body = tag + data
        return len(data).to_bytes(4, "big") + body + zlib.crc32(body).to_bytes(4, "big")

    ihdr = w.to_bytes(4, "big") + h.to_bytes(4, "big") + bytes([8, 6 if c == 4 else 2, 0, 0, 0])
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr)
            + chunk(b"IDAT", zlib.compress(raw.tobytes(), 6)) + chunk(b"IEND", b""))


# A perceptually ordered colour ramp for depth (deep = dark blue, shallow = yellow).
_RAMP_POS = np.array([0.0, 0.25, 0.5, 0.75, 1.0])
_RAMP_RGB = np.array([[38, 20, 90], [40, 95, 160], [40, 160, 140], [140, 205, 80], [250, 230, 60]],
                     float)


def elevation_rgb(z: FloatArray, lo: float, hi: float, cell: float = 1.0) -> npt.NDArray[np.uint8]:
    """RGBA image of an elevation grid (row 0 = south): colour ramp times a hillshade; NaN cells
    are transparent. The image is flipped so that north is up."""
    z = np.asarray(z, float)
    ok = np.isfinite(z)
    span = max(hi - lo, 1e-9)
    t = np.clip((np.where(ok, z, lo) - lo) / span, 0.0, 1.0)
    rgb = np.stack([np.interp(t, _RAMP_POS, _RAMP_RGB[:, k]) for k in range(3)], axis=-1)
    from coex_plugins.bathymetry import hillshade  # the one hillshade (light from the NW)

    rgb *= (0.55 + 0.45 * hillshade(z, cell))[..., None]
    out = np.zeros((*z.shape, 4), np.uint8)
    out[..., :3] = np.clip(rgb, 0, 255).astype(np.uint8)
    out[..., 3] = np.where(ok, 255, 0)
    return out[::-1]


#: The side of an image thumbnail (px); the viewer shows the full picture.
THUMB_SIDE = 320


def _picture(a: npt.NDArray[Any], max_side: int) -> npt.NDArray[np.uint8]:
    """An image as 8-bit RGB or grey, decimated to at most ``max_side`` pixels a side."""
    if a.ndim == 3 and a.shape[2] >= 3:
        step = max(1, math.ceil(max(a.shape[:2]) / max_side))
        return np.ascontiguousarray(a[::step, ::step, :3]).astype(np.uint8)
    return _grey_thumbnail(a, max_side)


def _grey_thumbnail(img: npt.NDArray[Any], max_side: int = 160) -> npt.NDArray[np.uint8]:
    a = np.asarray(img)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.dtype != np.uint8:
        f = a.astype(float)
        lo, hi = float(np.nanmin(f)), float(np.nanmax(f))
        a = ((f - lo) / max(hi - lo, 1e-9) * 255).astype(np.uint8)
    step = max(1, math.ceil(max(a.shape[0], a.shape[1]) / max_side))
    return np.ascontiguousarray(a[::step, ::step])
