"""Render downward-looking camera frames from the simulated seafloor: the simulator's labelled
renderer (it knows which pixel shows which object). Only the simulation and the referee use it;
the scripted operator's eye (:mod:`coex_apps.demo.eye`) never imports it, and its parameters
(the appearance of every kind of object, :data:`APPEARANCE`) are set here, apart from the eye's.

A pinhole camera looks straight down from the vehicle with a co-located light. Each pixel is
projected to the seafloor plane at the vehicle's altitude (an object's top is drawn over its
footprint, without the perspective of its height), where the sand's albedo (a procedural texture,
or one built from real dive frames, :mod:`coex_apps.demo.seabed`), the ripples' shading and any
object set its brightness. The objects, by ``kind`` (:class:`~coex_plugins.bathymetry.sim.Target`):

* ``car``: a box with mottled paint of its ``albedo`` (dark by default; a scenario draws light
  ones too), encrusting growth and a hard dark rim;
* ``container``: a box with a corrugated roof (ribs across it every 0.28 m), rust and a dark rim;
* ``hull``: a small boat's hull, its bow tapering, a pale gunwale round a darker, fouled inside;
* ``debris``: a patch of pieces of wreckage, each a box with its own tone and hard edges;
* ``rock``: a lumpy boulder of the sand's colour; ``dark rock``: the same, dark (basalt),
  mottled; ``biology``: a low lobed mound of dark living things with pale specks.

Then comes the light's fall-off with range and off-axis angle (domes, mounds and hulls are shaded
by their slopes), water attenuation (which also tints the colour), backscatter haze and sensor
noise. Everything is vectorised numpy. The result looks like the NUI dive images in the ways that
matter to the pipeline: 640 x 480, low contrast, vignetted.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from coex_plugins.bathymetry.sim import Target, debris_pieces, hull_halfwidth, object_height

__all__ = ["APPEARANCE", "BoxLike", "CameraModel", "SandTexture", "render_labelled", "footprint"]

#: the renderer's appearance of each kind of object: the default albedo of its top (``None``: the
#: sand's own), and how much its surface is mottled (a fraction of its albedo)
APPEARANCE: dict[str, tuple[float | None, float]] = {
    "car": (0.07, 0.35),
    "container": (0.30, 0.25),
    "hull": (0.60, 0.20),
    "debris": (0.15, 0.40),
    "rock": (None, 0.15),
    "dark rock": (0.12, 0.30),
    "biology": (0.10, 0.30),
}

HeightFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


class BoxLike(Protocol):
    """An object on the seafloor (``coex_plugins.bathymetry.sim.Target``): centre, size (m),
    heading (deg)."""

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


def _local(obj: BoxLike, gx: np.ndarray, gy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ground points in the object's frame (metres along and across it, as the seafloor
    simulator takes them: :func:`~coex_plugins.bathymetry.sim.object_height`)."""
    h = np.deg2rad(obj.heading)
    dx, dy = gx - obj.x, gy - obj.y
    return dx * np.sin(h) + dy * np.cos(h), dx * np.cos(h) - dy * np.sin(h)


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
    above, below = coarse[r0], coarse[r0 + 1]
    a, b = above[:, c0], above[:, c0 + 1]
    c, d = below[:, c0], below[:, c0 + 1]
    return np.asarray(a * (1 - fr) * (1 - fc) + b * (1 - fr) * fc + c * fr * (1 - fc) + d * fr * fc)


def _noise(gx: np.ndarray, gy: np.ndarray, k: float, phase: float) -> np.ndarray:
    """A smooth mottling pattern in [-1, 1] (sums of skewed sinusoids; vectorised)."""
    return np.asarray(0.5 * np.sin(k * gx + 2.0 * np.sin(0.7 * k * gy + phase))
                      * np.cos(1.3 * k * gy + 1.5 * np.sin(0.9 * k * gx - phase)), np.float64)


def _paint(obj: Target, kind: str, u: np.ndarray, v: np.ndarray, gx: np.ndarray, gy: np.ndarray,
           sand: np.ndarray, tex: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> np.ndarray:
    """Albedo of ``obj``'s top at its points (``u``, ``v``: along and across it; ``sand``: the
    sand's albedo there)."""
    base, mottle = APPEARANCE.get(kind, APPEARANCE["car"])
    own = obj.albedo if obj.albedo is not None else base
    tone = 0.55 if own is None else float(own)  # the sand's mean: only a boulder of the sand's colour has none
    ph = float((obj.x * 7.3 + obj.y * 3.1) % (2 * np.pi))
    if kind == "car":
        # a wreck: corroded panels, bright encrusting growth, a frame of hard dark edges
        clutter = np.sin(5.3 * u + 2.0 * np.sin(3.1 * v)) * np.cos(6.7 * v + 1.5 * np.sin(4.3 * u))
        paint = tone * (1.0 + mottle * clutter) + 0.25 * (tex(gx * 2.3, gy * 1.9) - 0.55)
        growth = clutter > 0.8
        rim = (np.abs(np.abs(u) - obj.length / 2) < 0.1) | (np.abs(np.abs(v) - obj.width / 2) < 0.1)
        return np.where(rim, 0.35 * tone, np.where(growth, np.maximum(0.2, 1.4 * tone), paint))
    if kind == "container":
        ribs = np.sin(2 * np.pi * u / 0.28)
        rust = _noise(gx, gy, 2.1, ph)
        paint = tone * (1.0 + 0.18 * ribs + mottle * rust)
        rim = (np.abs(np.abs(u) - obj.length / 2) < 0.08) | (np.abs(np.abs(v) - obj.width / 2) < 0.08)
        return np.where(rim, 0.4 * tone, paint)
    if kind == "hull":
        w = hull_halfwidth(obj, u)
        gunwale = np.abs(v) > w - 0.15
        fouled = tone * (1.0 + mottle * _noise(gx, gy, 3.3, ph))
        return np.where(gunwale, np.minimum(1.2 * tone, 0.95), 0.55 * fouled)
    if kind == "debris":
        rim = (np.abs(np.abs(u) - obj.length / 2) < 0.05) | (np.abs(np.abs(v) - obj.width / 2) < 0.05)
        return np.where(rim, 0.5 * tone, tone * (1.0 + mottle * _noise(gx, gy, 4.1, ph)))
    if kind == "biology":
        # pale polyps, arms and shells over a dark mat: blobs of an irregular pattern
        n = _noise(gx, gy, 19.0, ph) + 0.7 * _noise(gy, gx, 31.7, 2.0 * ph) + 0.5 * _noise(gx + gy, gx - gy, 13.3, ph)
        specks = n > 0.55
        return np.where(specks, 0.45, tone * (1.0 + mottle * _noise(gx, gy, 6.0, ph)))
    lumps = np.sin(9.0 * u / max(obj.length, 0.1) * 4.5) * np.cos(8.0 * v / max(obj.width, 0.1) * 2.6)
    if kind == "dark rock":
        return tone * (1.0 + mottle * (0.6 * lumps + 0.4 * _noise(gx, gy, 5.0, ph)))
    # a boulder of the sand's colour, lightly mottled
    return np.asarray((sand if own is None else np.full_like(sand, tone)) * (0.95 + mottle * lumps))


def _as_target(obj: BoxLike, decoy: bool) -> Target:
    """``obj`` as a :class:`Target` with its kind: a dome or a mound that names no natural kind
    is a boulder or living things; a decoy without a shape of its own a boulder."""
    shape = str(getattr(obj, "shape", "dome" if decoy else "box"))
    kind = str(getattr(obj, "kind", "") or ("rock" if decoy else "car"))
    if shape == "dome" and kind not in ("rock", "dark rock"):
        kind = "rock"
    elif shape == "mound" and kind != "biology":
        kind = "biology"
    return Target(obj.x, obj.y, obj.length, obj.width, obj.height, obj.heading, shape, kind,
                  getattr(obj, "albedo", None))


def render_labelled(
    height_fn: HeightFn,
    x: float,
    y: float,
    vehicle_z: float,
    heading_deg: float,
    *,
    targets: Sequence[BoxLike] = (),
    rocks: Sequence[BoxLike] = (),
    texture: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    camera: CameraModel | None = None,
    rng: np.random.Generator | None = None,
    grey: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """A frame from a camera at (x, y, vehicle_z) looking down (uint8, H x W x 3, or H x W if
    ``grey``) and the frame's truth: a label image (uint8, H x W) that is 0 on the
    seafloor, ``k + 1`` where object ``k`` of ``targets`` is seen and ``len(targets) + k + 1``
    where object ``k`` of ``rocks`` (the decoys) is seen. Each object is drawn by its ``kind``
    (see the module docstring); an object without one (a plain box) is a car, a decoy without
    one a boulder of the sand's colour."""
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
    albedo = np.asarray(tex(gx, gy), np.float64)
    labels = np.zeros(gz.shape, np.uint8)
    reach = float(np.hypot(gx - x, gy - y).max())
    for label, obj in enumerate([*targets, *rocks], 1):
        if np.hypot(obj.x - x, obj.y - y) > reach + max(obj.length, obj.width):
            continue  # nowhere near the frame
        full = _as_target(obj, decoy=label > len(targets))
        kind = full.kind
        parts = debris_pieces(full) if full.shape == "debris" else (full,)
        for part in parts:
            u, v = _local(part, gx, gy)
            hz = object_height(part, u, v)
            mask = np.isfinite(hz)
            if not mask.any():
                continue
            gz = np.where(mask, gz + np.where(mask, hz, 0.0), gz)
            albedo[mask] = _paint(part, kind, u[mask], v[mask], gx[mask], gy[mask], albedo[mask], tex)
            labels[mask] = label
    albedo = np.clip(albedo, 0.01, 1.2)
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
    # each channel clipped and cast into the frame as it is made (the values of stacking the
    # channels, clipping and casting, without the stacked copy); the noise drawn in channel order
    lit = signal + haze
    img = np.empty((*signal.shape, len(cam.tint)), np.uint8)
    for i, tint in enumerate(cam.tint):
        chan = lit * tint
        chan += rng.normal(0.0, cam.noise, signal.shape)
        img[..., i] = np.clip(chan, 0, 255, out=chan)
    if grey:
        g = 0.299 * img[..., 0] + 0.587 * img[..., 1] + 0.114 * img[..., 2]
        return np.round(g).astype(np.uint8), labels
    return img, labels
