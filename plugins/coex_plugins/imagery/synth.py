"""Synthetic seafloor images for tests, demos and benchmarks when no dive images are at hand.

The images imitate the NUI dive-040 frames: low contrast (grey std about 15-35), a vignetted
light cone, fractal sediment texture, a few rocks with shadows and some speckle. Everything is
vectorised numpy and seeded, so a seed always gives the same image.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = ["seafloor", "seafloor_series"]


def _fractal(rng: np.random.Generator, h: int, w: int, beta: float) -> npt.NDArray[np.float64]:
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    f = np.sqrt(fx * fx + fy * fy)
    f[0, 0] = 1.0
    amp = f ** (-beta / 2.0)
    amp[0, 0] = 0.0
    phase = rng.uniform(0, 2 * np.pi, amp.shape)
    field = np.fft.irfft2(amp * np.exp(1j * phase), s=(h, w))
    field -= field.mean()
    out: npt.NDArray[np.float64] = field / (field.std() + 1e-12)
    return out


def seafloor(
    height: int = 480, width: int = 640, *, seed: int = 0, colour: bool = False, rocks: int = 6
) -> npt.NDArray[np.uint8]:
    """One synthetic seafloor image, ``(height, width)`` uint8 or ``(height, width, 3)`` if colour."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    cy, cx = height * rng.uniform(0.4, 0.6), width * rng.uniform(0.4, 0.6)
    r2 = ((yy - cy) / height) ** 2 + ((xx - cx) / width) ** 2
    light = np.exp(-r2 / rng.uniform(0.08, 0.16))
    texture = 0.6 * _fractal(rng, height, width, 2.4) + 0.4 * _fractal(rng, height, width, 1.2)
    img = 40.0 + 80.0 * light + rng.uniform(7, 13) * texture * (0.5 + light)
    if rocks:
        ry = rng.uniform(0, height, rocks)[:, None, None]
        rx = rng.uniform(0, width, rocks)[:, None, None]
        rr = rng.uniform(0.02, 0.08, rocks)[:, None, None] * min(height, width)
        d2 = ((yy[None] - ry) ** 2 + (xx[None] - rx) ** 2) / rr**2
        body = np.exp(-d2 * 2.0)
        shadow = np.exp(-(((yy[None] - ry - 0.6 * rr) ** 2 + (xx[None] - rx - 0.6 * rr) ** 2) / rr**2) * 2.0)
        img += (25.0 * body - 18.0 * shadow).sum(axis=0) * (0.4 + light)
    img += rng.normal(0.0, 1.2, img.shape)
    grey = np.clip(np.rint(img), 0, 255)
    if not colour:
        return _u8(grey)
    tint = np.array([0.75, 1.05, 1.0]) + rng.normal(0, 0.03, 3)
    rgb = grey[..., None] * tint[None, None, :]
    return _u8(np.clip(np.rint(rgb), 0, 255))


def seafloor_series(
    n: int, height: int = 480, width: int = 640, *, seed: int = 0, colour: bool = False
) -> list[npt.NDArray[np.uint8]]:
    """``n`` different images (seeds ``seed``, ``seed + 1`` ...)."""
    return [seafloor(height, width, seed=seed + i, colour=colour) for i in range(n)]


def _u8(a: npt.NDArray[Any]) -> npt.NDArray[np.uint8]:
    out: npt.NDArray[np.uint8] = np.asarray(a).astype(np.uint8)
    return out
