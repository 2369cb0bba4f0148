"""Pictures of depth and PNG files, drawn one way for the console, the demo report and the
bathymetry exports.

* :func:`depth_cmap`: the depth colour map, a matplotlib colormap (deep = dark blue, shallow =
  yellow, perceptually ordered). The console's colour bar (``console/static/style.css``,
  ``.cb-ramp``) shows the same five stops.
* :func:`hillshade`: Lambertian hillshade, light from the north-west.
* :func:`elevation_rgba`: an elevation grid (row 0 = south) through the colour map, times the
  hillshade, no-data cells transparent, flipped north up.
* :func:`png_bytes` / :func:`write_png`: the one PNG writer (Pillow).

matplotlib and Pillow are imported when first used: the vehicle imports the bathymetry plugin
(and so this module) without drawing anything.
"""

from __future__ import annotations

import io
import os
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from matplotlib.colors import Colormap

__all__ = ["DEPTH_COLOURS", "DEPTH_STOPS", "depth_cmap", "elevation_rgba", "hillshade",
           "png_bytes", "write_png"]

FloatArray = npt.NDArray[np.float64]

#: positions (0 = deepest shown, 1 = shallowest) and RGB (0..255) of the depth colour map
DEPTH_STOPS = (0.0, 0.25, 0.5, 0.75, 1.0)
DEPTH_COLOURS = ((38, 20, 90), (40, 95, 160), (40, 160, 140), (140, 205, 80), (250, 230, 60))

#: how much the hillshade darkens: brightness ``SHADE_FLOOR + (1 - SHADE_FLOOR) * hillshade``
SHADE_FLOOR = 0.55


@cache
def depth_cmap() -> Colormap:
    """The depth colour map (``coex_depth``): 0 deep, 1 shallow."""
    from matplotlib.colors import LinearSegmentedColormap

    return LinearSegmentedColormap.from_list(
        "coex_depth", [(p, tuple(c / 255.0 for c in rgb)) for p, rgb in zip(DEPTH_STOPS, DEPTH_COLOURS)],
        N=1024)


def hillshade(grid: npt.ArrayLike, cell: float, azimuth: float = 315.0, altitude: float = 45.0,
              fill: float | None = None) -> FloatArray:
    """Lambertian hillshade in 0..1 (row 0 = south); NaN cells give 1 (unshaded). NaN cells are
    taken at ``fill`` for the slopes of their neighbours (default: the grid's mean)."""
    z = np.asarray(grid, np.float64)
    if z.size == 0:
        return np.ones_like(z)
    if fill is None:
        fill = float(np.nanmean(z)) if np.isfinite(z).any() else 0.0
    fill_grid = np.where(np.isfinite(z), z, fill)
    if min(z.shape) < 2:
        return np.ones_like(z)
    dzdy, dzdx = np.gradient(fill_grid, cell)
    az, alt = np.radians(azimuth), np.radians(altitude)
    # sun direction (east, north, up)
    sx, sy, sz = np.sin(az) * np.cos(alt), np.cos(az) * np.cos(alt), np.sin(alt)
    norm = np.sqrt(dzdx**2 + dzdy**2 + 1.0)
    shade = (-dzdx * sx - dzdy * sy + sz) / norm
    shade = np.clip(shade, 0.0, 1.0)
    return np.asarray(np.where(np.isfinite(z), shade, 1.0), np.float64)


#: :func:`elevation_rgba` draws a big grid this many cells at a time (its temporaries, about 80
#: bytes a cell, stay this size whatever the grid's)
BAND_CELLS = 1 << 18


def elevation_rgba(z: npt.ArrayLike, lo: float, hi: float, cell: float = 1.0) -> npt.NDArray[np.uint8]:
    """RGBA image of an elevation grid (row 0 = south) coloured from ``lo`` (deep) to ``hi``
    (shallow), times a hillshade; NaN cells are transparent. Row 0 of the image is the north edge.
    A big grid is drawn in bands of rows (:data:`BAND_CELLS` cells; each band with a row of its
    neighbours for the slopes): the same picture, a bounded memory beside the grid and the
    image (the console draws windows of 4 Mpx)."""
    z = np.asarray(z, np.float64)
    out = np.zeros((*z.shape, 4), np.uint8)
    if z.size == 0:
        return out[::-1]
    rows, cols = z.shape[0], max(1, z.shape[1])
    fill = float(np.nanmean(z)) if np.isfinite(z).any() else 0.0
    band = max(1, BAND_CELLS // cols)
    span = max(hi - lo, 1e-9)
    cmap = depth_cmap()
    for r0 in range(0, rows, band):
        r1 = min(rows, r0 + band)
        a, b = max(0, r0 - 1), min(rows, r1 + 1)  # a row of the neighbours each side: the slopes
        zb = z[r0:r1]
        ok = np.isfinite(zb)
        t = np.clip((np.where(ok, zb, lo) - lo) / span, 0.0, 1.0)
        rgb = np.asarray(cmap(t))[..., :3] * 255.0
        shade = hillshade(z[a:b], cell, fill=fill)[r0 - a:r0 - a + (r1 - r0)] if rows >= 2 else np.ones_like(zb)
        rgb *= (SHADE_FLOOR + (1.0 - SHADE_FLOOR) * shade)[..., None]
        out[r0:r1, :, :3] = np.clip(rgb, 0, 255).astype(np.uint8)
        out[r0:r1, :, 3] = np.where(ok, 255, 0)
    return out[::-1]


def png_bytes(image: npt.ArrayLike, compress_level: int = 6) -> bytes:
    """A PNG file of a uint8 image: ``H x W`` (grey), ``H x W x 3`` (RGB) or ``H x W x 4`` (RGBA),
    row 0 at the top. ``compress_level`` 0..9 (1 is fast, for files rewritten often)."""
    from PIL import Image

    img = np.ascontiguousarray(np.asarray(image, np.uint8))
    if img.ndim == 3 and img.shape[2] not in (3, 4):
        raise ValueError(f"expected 1, 3 or 4 channels, got {img.shape[2]}")
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG", compress_level=compress_level)
    return buf.getvalue()


def write_png(path: str | Path, image: Any, compress_level: int = 6) -> Path:
    """Write :func:`png_bytes` of ``image`` to ``path`` atomically (a ``.part`` file, renamed)."""
    out = Path(path)
    tmp = f"{out}.part"
    with open(tmp, "wb") as f:
        f.write(png_bytes(image, compress_level))
    os.replace(tmp, out)
    return out
