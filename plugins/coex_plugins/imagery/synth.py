"""Synthetic seafloor images for tests, demos and benchmarks when no dive images are at hand.

The images imitate the NUI dive-040 frames: low contrast (grey std about 15-35), a vignetted
light cone, fractal sediment texture, a few rocks with shadows and some speckle
(:func:`seafloor`); or textured sand ripples (:func:`sand_ripples`: the frames that cost a
JPEG 2000 coder the most). Everything is vectorised numpy and seeded, so a seed always gives
the same image.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = ["sand_ripples", "seafloor", "seafloor_series"]


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


def _blur(a: npt.NDArray[np.float64], sigma: float) -> npt.NDArray[np.float64]:
    """Gaussian blur of ``sigma`` pixels (in the frequency domain, periodic edges)."""
    h, w = a.shape
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    gain = np.exp(-2.0 * (np.pi * sigma) ** 2 * (fx * fx + fy * fy))
    out: npt.NDArray[np.float64] = np.fft.irfft2(np.fft.rfft2(a) * gain, s=(h, w))
    return out


def sand_ripples(height: int = 480, width: int = 640, *, seed: int = 0) -> npt.NDArray[np.uint8]:
    """A textured sand-ripple frame, ``(height, width)`` uint8: asymmetric ripples (a long stoss
    side, a short lee side in shadow) 12 to 40 px apart with wavy crests, lit from one side in a
    vignetted light cone, fine grain, shell fragments (bright and dark specks), sensor noise and a
    slight optical blur. Every parameter is drawn from the seed."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    wavelength = rng.uniform(12.0, 40.0)
    theta = rng.uniform(0.0, np.pi)
    warp = _fractal(rng, height, width, 4.5) * rng.uniform(2.0, 5.0)
    phase = (2.0 * np.pi * (xx * np.cos(theta) + yy * np.sin(theta)) / wavelength + warp) / (2.0 * np.pi)
    t = phase - np.floor(phase)
    lee = rng.uniform(0.15, 0.35)
    profile = np.where(t < 1.0 - lee, t / (1.0 - lee), (1.0 - t) / lee)
    height_field = 2.5 * profile * (1.0 + 0.35 * _fractal(rng, height, width, 3.0)) * wavelength / (2.0 * np.pi)
    gy, gx = np.gradient(height_field)
    light_dir = rng.uniform(0.0, 2.0 * np.pi)
    shade = np.clip(gx * np.cos(light_dir) + gy * np.sin(light_dir), -2.0, 2.0)
    cy, cx = height * rng.uniform(0.35, 0.65), width * rng.uniform(0.35, 0.65)
    r2 = ((yy - cy) / height) ** 2 + ((xx - cx) / width) ** 2
    light = np.exp(-r2 / rng.uniform(0.08, 0.2))
    relief, grain = rng.uniform(8.0, 22.0), rng.uniform(2.0, 7.0)
    img = 60.0 + 95.0 * light + (relief * shade + grain * _fractal(rng, height, width, 1.4)) * (0.4 + light)
    n = int(rng.uniform(200, 2500) * height * width / (480 * 640))
    specks = np.zeros((height, width))
    np.add.at(specks, (rng.integers(0, height, n), rng.integers(0, width, n)),
              rng.choice([-1.0, 1.0], n, p=[0.7, 0.3]) * rng.uniform(15.0, 50.0, n))
    img += 3.0 * _blur(specks, 0.7) + rng.normal(0.0, rng.uniform(0.8, 1.8), img.shape)
    return _u8(np.clip(np.rint(_blur(img, rng.uniform(0.4, 0.8))), 0, 255))


def _u8(a: npt.NDArray[Any]) -> npt.NDArray[np.uint8]:
    out: npt.NDArray[np.uint8] = np.asarray(a).astype(np.uint8)
    return out
