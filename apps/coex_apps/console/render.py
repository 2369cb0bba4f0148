"""Pictures of the console: image thumbnails; the PNG writer and the depth colour map with
hillshade are the shared ones of :mod:`coex_plugins.render`. No state, no I/O."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from coex_plugins.render import elevation_rgba as elevation_rgb
from coex_plugins.render import png_bytes

__all__ = ["THUMB_SIDE", "elevation_rgb", "png_bytes"]

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
