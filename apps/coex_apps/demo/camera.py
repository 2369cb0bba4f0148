"""Render downward-looking camera frames from the simulated seafloor.

A pinhole camera looks straight down from the vehicle with a co-located light. Each pixel is
projected to the seafloor (the local height field), where a procedural sand texture, the ripples'
shading, and any target (a car: a box with a darker, mottled paint and sharp edges) set its
brightness; then comes the light's fall-off with range and off-axis angle, water attenuation
(which also tints the colour), backscatter haze and sensor noise. Everything is vectorised numpy.

The result looks like the NUI dive images in the ways that matter to the pipeline: 640 x 480,
low contrast, vignetted, with a target that is recognisable when it is in frame.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

__all__ = ["BoxLike", "CameraModel", "SandTexture", "render_labelled", "footprint"]

HeightFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


class BoxLike(Protocol):
    """A box-shaped target (``coex_plugins.bathymetry.sim.Target``, a frozen dataclass: read
    only): centre, size (m), heading (deg)."""

    @property
    def x(self) -> float: ...
    @property
    def y(self) -> float: ...
    @property
    def length(self) -> float: ...
    @property
    def width(self) -> float: ...
    @property
    def height(self) -> float: ...
    @property
    def heading(self) -> float: ...


def _inside(box: BoxLike, gx: np.ndarray, gy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mask of ground points under the box, and their coordinates along and across it."""
    h = np.deg2rad(90.0 - box.heading)  # heading clockwise from north -> angle from east
    dx, dy = gx - box.x, gy - box.y
    u = dx * np.cos(h) + dy * np.sin(h)
    v = -dx * np.sin(h) + dy * np.cos(h)
    mask = (np.abs(u) <= box.length / 2) & (np.abs(v) <= box.width / 2)
    return mask, u, v


@dataclass(frozen=True)
class CameraModel:
    width: int = 640
    height: int = 480
    hfov_deg: float = 62.0
    attenuation: float = 0.12  # 1/m, mean over the visible band
    tint: tuple[float, float, float] = (0.96, 1.0, 0.95)  # red is absorbed first
    noise: float = 2.5  # sensor noise, grey levels
    gain: float = 420.0


class SandTexture:
    """Deterministic procedural albedo: sums of oriented sinusoids and a coarse speckle."""

    def __init__(self, seed: int = 0, octaves: int = 8) -> None:
        rng = np.random.default_rng(seed)
        self.k = rng.uniform(2.0, 40.0, octaves)  # wavenumbers, rad/m
        self.theta = rng.uniform(0, np.pi, octaves)
        self.phase = rng.uniform(0, 2 * np.pi, octaves)
        self.amp = 1.0 / np.sqrt(self.k)
        self.amp /= self.amp.sum()

    def __call__(self, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
        gx = np.asarray(gx, np.float32)
        gy = np.asarray(gy, np.float32)
        acc = np.zeros_like(gx)
        for k, th, ph, a in zip(self.k, self.theta, self.phase, self.amp):
            acc += np.float32(a) * np.sin(np.float32(k * np.cos(th)) * gx + np.float32(k * np.sin(th)) * gy
                                          + np.float32(ph))
        # sparse dark pebbles and shell fragments: a thresholded high-frequency pattern
        grit = np.sin(61.0 * gx + 3.0 * np.sin(17.0 * gy)) * np.sin(53.0 * gy + 2.0 * np.sin(23.0 * gx))
        return 0.55 + 0.10 * acc - 0.12 * (grit > 0.93)


def footprint(altitude: float, camera: CameraModel | None = None) -> tuple[float, float]:
    """Width and height (m) of the seafloor in frame at ``altitude``."""
    cam = camera or CameraModel()
    w = 2 * altitude * np.tan(np.deg2rad(cam.hfov_deg) / 2)
    return float(w), float(w * cam.height / cam.width)


def _coarse_heights(height_fn: HeightFn, gx: np.ndarray, gy: np.ndarray, step: int = 8) -> np.ndarray:
    """The height field sampled every ``step`` pixels and bilinearly interpolated (seafloor
    relief and ripples are smooth at that scale; the camera's targets are added separately)."""
    h, w = gx.shape
    rows = np.unique(np.r_[np.arange(0, h, step), h - 1])
    cols = np.unique(np.r_[np.arange(0, w, step), w - 1])
    coarse = np.asarray(height_fn(gx[np.ix_(rows, cols)], gy[np.ix_(rows, cols)]), float)
    ri = np.interp(np.arange(h), rows, np.arange(len(rows)))
    ci = np.interp(np.arange(w), cols, np.arange(len(cols)))
    r0 = np.minimum(ri.astype(int), len(rows) - 2)
    c0 = np.minimum(ci.astype(int), len(cols) - 2)
    fr = (ri - r0)[:, None]
    fc = (ci - c0)[None, :]
    a = coarse[r0][:, c0]
    b = coarse[r0][:, c0 + 1]
    c = coarse[r0 + 1][:, c0]
    d = coarse[r0 + 1][:, c0 + 1]
    out: np.ndarray = a * (1 - fr) * (1 - fc) + b * (1 - fr) * fc + c * fr * (1 - fc) + d * fr * fc
    return out


def render_labelled(
    height_fn: HeightFn,
    x: float,
    y: float,
    vehicle_z: float,
    heading_deg: float,
    *,
    targets: Sequence[BoxLike] = (),
    rocks: Sequence[BoxLike] = (),
    texture: SandTexture | None = None,
    camera: CameraModel | None = None,
    rng: np.random.Generator | None = None,
    grey: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """A frame from a camera at (x, y, vehicle_z) looking down (uint8, H x W x 3, or H x W if
    ``grey``) and the frame's truth: a label image (uint8, H x W) that is 0 on the
    seafloor, ``k + 1`` where box ``k`` of ``targets`` is seen and ``len(targets) + k + 1`` where
    rock ``k`` of ``rocks`` is seen.

    A rock is a car-sized boulder: a rounded, lumpy dome of the sand's colour (lightly mottled,
    no hard edges); a car is a box with dark, mottled paint and sharp edges."""
    cam = camera or CameraModel()
    tex = texture or SandTexture()
    rng = rng or np.random.default_rng(0)
    floor_z = float(np.asarray(height_fn(np.array([x]), np.array([y])))[0])
    altitude = max(vehicle_z - floor_z, 0.3)
    f = (cam.width / 2) / np.tan(np.deg2rad(cam.hfov_deg) / 2)
    cols = (np.arange(cam.width) - cam.width / 2 + 0.5) / f
    rows = (cam.height / 2 - np.arange(cam.height) - 0.5) / f
    px, py = np.meshgrid(cols, rows)  # image-plane directions, camera frame (right, forward)
    h = np.deg2rad(heading_deg)
    # camera right = (cos h, -sin h), forward = (sin h, cos h) for a heading clockwise from north
    ex, ey = px * np.cos(h) + py * np.sin(h), -px * np.sin(h) + py * np.cos(h)
    gx, gy = x + ex * altitude, y + ey * altitude
    gz = _coarse_heights(height_fn, gx, gy)
    albedo = tex(gx, gy)
    labels = np.zeros(gz.shape, np.uint8)
    for k, rock in enumerate(rocks):
        mask, u, v = _inside(rock, gx, gy)
        if not mask.any():
            continue
        # an ellipsoidal dome inscribed in the box, with lumps; the colour of the sand, mottled
        um, vm = u[mask] / (rock.length / 2), v[mask] / (rock.width / 2)
        r2 = um**2 + vm**2
        dome = r2 < 1.0
        lumps = 0.12 * np.sin(7.0 * um + 2.0) * np.sin(5.0 * vm + 1.0)
        hz = np.where(dome, rock.height * np.sqrt(np.clip(1.0 - r2, 0.0, 1.0)) * (1.0 + lumps), 0.0)
        idx = np.flatnonzero(mask.ravel())[dome]
        gz.ravel()[np.flatnonzero(mask.ravel())] += hz
        albedo = albedo.astype(np.float64)
        albedo.ravel()[idx] = albedo.ravel()[idx] * (0.9 + 0.15 * np.sin(9.0 * um[dome]) * np.cos(8.0 * vm[dome]))
        labels.ravel()[idx] = len(targets) + k + 1
    top = np.zeros_like(gz, dtype=bool)
    for k, box in enumerate(targets):
        mask, u, v = _inside(box, gx, gy)
        gz = np.where(mask, gz + box.height, gz)
        # a wreck: dark corroded panels, bright encrusting growth, a frame of hard dark edges
        if not mask.any():
            continue
        um, vm = u[mask], v[mask]
        clutter = np.sin(5.3 * um + 2.0 * np.sin(3.1 * vm)) * np.cos(6.7 * vm + 1.5 * np.sin(4.3 * um))
        paint = 0.07 + 0.03 * clutter + 0.25 * (tex(gx[mask] * 2.3, gy[mask] * 1.9) - 0.55)
        growth = clutter > 0.8
        edge = (np.abs(np.abs(um) - box.length / 2) < 0.1) | (np.abs(np.abs(vm) - box.width / 2) < 0.1)
        albedo = albedo.astype(np.float64)
        albedo[mask] = np.where(edge, 0.03, np.where(growth, 0.2, paint))
        top |= mask
        labels[mask] = k + 1
    # surface normals from the height field (finite differences in image space)
    dzx = np.gradient(gz, axis=1) / np.maximum(np.gradient(gx, axis=1) ** 2 + np.gradient(gy, axis=1) ** 2, 1e-9) ** 0.5
    dzy = np.gradient(gz, axis=0) / np.maximum(np.gradient(gx, axis=0) ** 2 + np.gradient(gy, axis=0) ** 2, 1e-9) ** 0.5
    normal_z = 1.0 / np.sqrt(1.0 + dzx**2 + dzy**2)
    rng_m = np.sqrt((gx - x) ** 2 + (gy - y) ** 2 + (vehicle_z - gz) ** 2)
    cos_in = np.clip(normal_z * (vehicle_z - gz) / np.maximum(rng_m, 1e-6), 0.0, 1.0)
    falloff = (altitude / np.maximum(rng_m, 0.1)) ** 2
    vignette = (1.0 + px**2 + py**2) ** -1.0
    # light relative to the centre of the frame, then an overall loss that grows with altitude
    light = cos_in * falloff * vignette * np.exp(-2 * cam.attenuation * (rng_m - altitude))
    signal = cam.gain * albedo * light * np.exp(-0.05 * max(altitude - 3.0, 0.0))
    haze = 12.0 * (1.0 - np.exp(-cam.attenuation * altitude)) * vignette
    channels = []
    for tint in cam.tint:
        chan = (signal + haze) * tint + rng.normal(0.0, cam.noise, signal.shape)
        channels.append(chan)
    img = np.clip(np.stack(channels, axis=-1), 0, 255).astype(np.uint8)
    if grey:
        g = 0.299 * img[..., 0] + 0.587 * img[..., 1] + 0.114 * img[..., 2]
        return np.round(g).astype(np.uint8), labels
    return img, labels
