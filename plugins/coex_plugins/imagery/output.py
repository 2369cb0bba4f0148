"""Writing topside images: ``image_<id>.tiff`` and ``image_<id>.png`` after every improvement (an
image as topside shows it, its crops pasted over it), ``crop_<id>.tiff`` and ``.png`` for a crop
(what it shows of its box)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from coex import Product
from coex_plugins.render import write_png as _write_png

from .product import CropProduct, ImageProduct

__all__ = ["ImageWriter", "outlined", "write_png", "write_tiff"]


def outlined(image: Any, box: tuple[int, int, int, int] | list[int]) -> Any:
    """A copy of the image with the box (x0, y0, x1, y1; x1, y1 exclusive) drawn in white (grey)
    or yellow (colour), 1 px."""
    out = np.array(image, copy=True)
    x0, y0, x1, y1 = (int(v) for v in box)
    colour = 255 if out.ndim == 2 else np.array([255, 220, 0], np.uint8)
    out[y0, x0:x1] = colour
    out[y1 - 1, x0:x1] = colour
    out[y0:y1, x0] = colour
    out[y0:y1, x1 - 1] = colour
    return out


def write_png(path: str | Path, image: Any) -> None:
    """The shared PNG writer (atomic), fast compression: written at every improvement."""
    _write_png(path, np.asarray(image, np.uint8), compress_level=1)


def write_tiff(path: str | Path, image: Any, description: str = "") -> None:
    import tifffile

    tmp = f"{path}.part"
    tifffile.imwrite(tmp, np.asarray(image, np.uint8), description=description or None)
    os.replace(tmp, path)


class ImageWriter:
    """A product listener that writes each improved image (atomically: write, then rename)."""

    def __init__(self, out_dir: str | Path) -> None:
        # the folder is made with the first image, not here: building a receiver (as `coex
        # config check` does, to check its options) must not leave folders behind
        self.out_dir = Path(out_dir)
        self.written = 0

    def __call__(self, product: Product) -> None:
        if not isinstance(product, ImageProduct | CropProduct) or product.data is None:
            return
        self.out_dir.mkdir(parents=True, exist_ok=True)
        name = "image" if isinstance(product, ImageProduct) else "crop"
        base = self.out_dir / f"{name}_{int(product.image_id):04d}"
        desc = f"coex image {product.key} version {product.version} bytes {product.bytes_used}"
        write_tiff(f"{base}.tiff", product.data, desc)
        write_png(f"{base}.png", product.data)
        self.written += 1
