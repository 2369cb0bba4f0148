"""A seafloor and multibeam survey simulator (numpy, vectorised, seeded).

The seafloor: a base depth, a gentle regional slope, smooth random relief (optional metres to
tens of metres), sand ripples (decimetres, a few metres wavelength, slowly turning crests) and
car-sized boxes (4.5 x 1.8 x 1.5 m by default) lying on the bottom.

The survey: a lawnmower pattern of north/south lines at constant altitude; every ping fans
``beams`` soundings over ``swath_deg`` across track. Each sounding lands where the beam meets a
flat bottom at the vehicle's altitude (good enough at these slopes), takes the true elevation
there, plus vertical noise growing with slant range, and a small fraction of soundings (mostly at
the swath edge) are outliers metres off, as seen in the field.

Used by the tests, the benchmark, ``coex bathy roundtrip`` sample data and the demo::

    floor = Seafloor.default(size=256.0, seed=1)
    survey = simulate_survey(floor, seed=2)
    for t, xyz in survey.pings(batch=25):
        qmap.add_points(xyz, t)
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

__all__ = ["SHAPES", "DemSeafloor", "Floor", "Seafloor", "Survey", "Target", "debris_pieces", "hull_halfwidth",
           "object_height", "outline_scale", "simulate_survey"]

FloatArray = npt.NDArray[np.float64]


#: the shapes of :class:`Target` (how it stands on the seafloor)
SHAPES = ("box", "dome", "hull", "debris", "mound")


@dataclass(frozen=True)
class Target:
    """An object on the seafloor: centre (x, y), length, width, height (m) and heading (deg from
    north). ``shape`` is ``"box"`` (a car or a container: flat top), ``"dome"`` (a boulder: a
    lumpy half-ellipsoid inscribed in the same box, its outline lobed), ``"hull"`` (a small
    boat's hull: a rounded deck, its bow tapering over the last third of its length, the bow
    towards ``heading``), ``"debris"`` (a patch of wreckage: a main piece and scattered smaller
    ones inside the box, :func:`debris_pieces`) or ``"mound"`` (a low lobed mound, e.g. of
    living things). ``kind`` names what it is (``"car"``, ``"container"``, ``"hull"``,
    ``"debris"``, ``"rock"``, ``"dark rock"``, ``"biology"``: the renderer's business, not the
    map's) and ``albedo`` the reflectance of its top (``None``: its kind's own)."""

    x: float
    y: float
    length: float = 4.5
    width: float = 1.8
    height: float = 1.5
    heading: float = 0.0
    shape: str = "box"
    kind: str = "car"
    albedo: float | None = None


def _object_rng(t: Target, salt: int = 0) -> np.random.Generator:
    """A generator fixed by the object's placement (its shape details are part of the object)."""
    return np.random.default_rng([round(t.x * 10) & 0xFFFFFF, round(t.y * 10) & 0xFFFFFF,
                                  round(t.length * 100), salt])


def lobes(t: Target) -> FloatArray:
    """The lobes of a dome's or a mound's outline: rows of (harmonic, amplitude, phase); the
    outline's radius at angle a is ``1 + sum(amp * sin(k * a + phase))`` of the ellipse's."""
    rng = _object_rng(t, 1)
    ks = np.array([2.0, 3.0, 5.0])
    amp = rng.uniform(0.04, 0.12 if t.shape == "dome" else 0.18, 3)
    return np.stack([ks, amp, rng.uniform(0, 2 * np.pi, 3)], axis=1)


def outline_scale(t: Target, angle: npt.NDArray[np.float64]) -> FloatArray:
    """:func:`lobes` evaluated at ``angle`` (radians in the object's frame)."""
    lb = lobes(t)
    return np.asarray(1.0 + (lb[:, 1] * np.sin(np.multiply.outer(angle, lb[:, 0]) + lb[:, 2])).sum(-1), np.float64)


def debris_pieces(t: Target) -> tuple[Target, ...]:
    """The pieces of a ``"debris"`` patch (boxes, in world coordinates): a main piece of about
    half the patch's length and its full height, and 4 to 7 smaller, lower ones scattered inside
    the patch at their own headings. Fixed by the patch's placement."""
    rng = _object_rng(t, 2)
    h = np.radians(t.heading)
    along, across = np.array([np.sin(h), np.cos(h)]), np.array([np.cos(h), -np.sin(h)])
    pieces = []
    main_l = 0.5 * t.length
    main_w = min(0.6 * t.width, 0.6 * main_l)
    pieces.append(Target(float(t.x), float(t.y), main_l, main_w, t.height, t.heading + float(rng.uniform(-15, 15)),
                         "box", t.kind, t.albedo))
    for _ in range(int(rng.integers(4, 8))):
        pl = float(rng.uniform(0.3, 0.3 * t.length + 0.3))
        pw = float(rng.uniform(0.25, max(0.35, 0.6 * pl)))
        u = float(rng.uniform(-0.5, 0.5)) * (t.length - pl)
        v = float(rng.uniform(-0.5, 0.5)) * (t.width - pw)
        cx, cy = np.array([t.x, t.y]) + u * along + v * across
        pieces.append(Target(float(cx), float(cy), pl, pw, float(rng.uniform(0.2, 0.5)) * t.height,
                             float(rng.uniform(0, 180)), "box", t.kind, t.albedo))
    return tuple(pieces)


def hull_halfwidth(t: Target, u: npt.NDArray[np.float64]) -> FloatArray:
    """Half the width of a ``"hull"`` at ``u`` metres along it from its centre (the bow at
    ``+length / 2``): full abeam and aft, tapering to a point over the last third (a bow curve)."""
    half = t.length / 2
    bow = half - t.length / 3
    f = np.clip((u - bow) / max(half - bow, 1e-6), 0.0, 1.0)
    w = (t.width / 2) * np.clip(1.0 - f**1.6, 0.0, 1.0)
    return np.asarray(np.where(np.abs(u) <= half, w, 0.0), np.float64)


@dataclass(frozen=True)
class Seafloor:
    """A seafloor over ``[x0, x0 + size] x [y0, y0 + size]`` (metres, z up, so depths are negative)."""

    size: float = 512.0
    x0: float = 0.0
    y0: float = 0.0
    depth: float = 500.0
    slope: tuple[float, float] = (0.01, -0.005)
    relief: float = 2.0
    ripple_amplitude: float = 0.15
    ripple_wavelength: float = 3.0
    targets: tuple[Target, ...] = ()
    seed: int = 0
    _modes: FloatArray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        rng = np.random.default_rng(self.seed)
        n = 24
        # Relief wavelengths from a sixth of the area to twice its size, never below 60 m (a small
        # scene is a piece of gently rolling bottom, not a field of 45-degree bumps).
        size = max(self.size, 1.0)
        lo, hi = max(size / 6.0, 60.0), max(2.0 * size, 120.0)
        k = 2 * np.pi / rng.uniform(lo, hi, n)
        ang = rng.uniform(0, 2 * np.pi, n)
        amp = rng.normal(0, 1, n) / (k * size / (2 * np.pi))
        amp *= self.relief / max(np.sqrt((amp**2).sum() / 2), 1e-9)
        phase = rng.uniform(0, 2 * np.pi, n)
        object.__setattr__(self, "_modes", np.stack([k * np.cos(ang), k * np.sin(ang), amp, phase], axis=1))

    @classmethod
    def default(cls, size: float = 512.0, seed: int = 0, relief: float = 2.0, depth: float = 500.0) -> Seafloor:
        """The reference scene: two cars about a third and two thirds across the area."""
        targets = (
            Target(size * 0.35, size * 0.42, heading=30.0),
            Target(size * 0.63, size * 0.58, heading=-65.0),
        )
        return cls(size=size, relief=relief, depth=depth, targets=targets, seed=seed)

    def ground(self, x: npt.ArrayLike, y: npt.ArrayLike) -> FloatArray:
        """Elevation of the bare bottom (no targets)."""
        xa = np.asarray(x, np.float64) - self.x0
        ya = np.asarray(y, np.float64) - self.y0
        z = -self.depth + self.slope[0] * xa + self.slope[1] * ya
        m = self._modes
        z = z + (m[:, 2] * np.sin(np.multiply.outer(xa, m[:, 0]) + np.multiply.outer(ya, m[:, 1]) + m[:, 3])).sum(-1)
        # Ripples: crests turning slowly across the area, wavelength ripple_wavelength.
        turn = 0.35 * np.sin(2 * np.pi * ya / max(self.size, 1.0))
        along = xa * np.cos(turn) + ya * np.sin(turn)
        env = 0.6 + 0.4 * np.sin(2 * np.pi * xa / (0.7 * max(self.size, 1.0)))
        z = z + self.ripple_amplitude * env * np.sin(2 * np.pi * along / self.ripple_wavelength)
        return np.asarray(z, np.float64)

    def elevation(self, x: npt.ArrayLike, y: npt.ArrayLike) -> FloatArray:
        """Elevation including the targets."""
        xa = np.asarray(x, np.float64)
        ya = np.asarray(y, np.float64)
        z = self.ground(xa, ya)
        for t in self.targets:
            h = np.radians(t.heading)
            dx, dy = xa - t.x, ya - t.y
            u = dx * np.sin(h) + dy * np.cos(h)
            v = dx * np.cos(h) - dy * np.sin(h)
            base = float(self.ground(t.x, t.y))
            z = np.maximum(z, base + object_height(t, u, v)) if t.shape != "debris" else z
            if t.shape == "debris":
                for p in debris_pieces(t):
                    hp = np.radians(p.heading)
                    dxp, dyp = xa - p.x, ya - p.y
                    up = dxp * np.sin(hp) + dyp * np.cos(hp)
                    vp = dxp * np.cos(hp) - dyp * np.sin(hp)
                    z = np.maximum(z, base + object_height(p, up, vp))
        return z


def object_height(t: Target, u: npt.ArrayLike, v: npt.ArrayLike) -> FloatArray:
    """Height (m) of ``t`` above its base at (``u`` along, ``v`` across) metres from its centre,
    -inf outside it (not for ``"debris"``: its pieces are boxes)."""
    ua, va = np.asarray(u, np.float64), np.asarray(v, np.float64)
    if t.shape in ("dome", "mound"):
        scale = outline_scale(t, np.arctan2(va / max(t.width, 1e-6), ua / max(t.length, 1e-6)))
        r2 = ((ua / (t.length / 2)) ** 2 + (va / (t.width / 2)) ** 2) / scale**2
        power = 0.5 if t.shape == "dome" else 1.0  # a mound: lower flanks than a boulder
        top = t.height * np.clip(1.0 - r2, 0.0, 1.0) ** power
        return np.asarray(np.where(r2 < 1.0, top, -np.inf), np.float64)
    if t.shape == "hull":
        w = hull_halfwidth(t, ua)
        inside = (w > 0) & (np.abs(va) < w)
        top = t.height * np.sqrt(np.clip(1.0 - (va / np.maximum(w, 1e-6)) ** 4, 0.0, 1.0))
        return np.asarray(np.where(inside, top, -np.inf), np.float64)
    inside = (np.abs(ua) <= t.length / 2) & (np.abs(va) <= t.width / 2)
    return np.asarray(np.where(inside, t.height, -np.inf), np.float64)


class Floor(Protocol):
    """What :func:`simulate_survey` surveys: a square ``[x0, x0 + size] x [y0, y0 + size]`` and
    its elevation (z up, metres)."""

    @property
    def size(self) -> float: ...
    @property
    def x0(self) -> float: ...
    @property
    def y0(self) -> float: ...
    def elevation(self, x: npt.ArrayLike, y: npt.ArrayLike) -> FloatArray: ...


#: the real digital elevation model matplotlib ships (``matplotlib.cbook.get_sample_data``): a
#: 3-arc-second (about 80 m) grid of the Jacksboro fault, Tennessee, 344 x 403 samples, whole metres
JACKSBORO = "jacksboro_fault_dem.npz"


@dataclass(frozen=True)
class DemSeafloor:
    """A seafloor cut from a real digital elevation model: the square of ``size`` metres whose
    south-west corner is sample ``(row, col)`` of the DEM (row 0 its southernmost row), each DEM
    sample ``pixel`` metres apart, heights scaled like the distances (``pixel / sample`` with
    ``sample`` the DEM's own spacing, 80 m: the real terrain's slopes, shrunk) around ``-depth``,
    bilinear between samples. With the defaults (Jacksboro, 1.5 m per sample) a 256 m square
    has about 13 m of relief and a median slope of 24 %: rough ground, real in its shapes.

    ``DemSeafloor.load()`` reads matplotlib's sample DEM (matplotlib is in the bathymetry extra)."""

    heights: FloatArray
    size: float = 256.0
    row: int = 0
    col: int = 0
    pixel: float = 1.5
    sample: float = 80.0
    depth: float = 500.0
    x0: float = 0.0
    y0: float = 0.0

    @classmethod
    def load(cls, name: str = JACKSBORO, **kw: float) -> DemSeafloor:
        """A square of matplotlib's sample DEM ``name`` (its ``elevation`` array, north row first)."""
        import matplotlib.cbook as cbook

        data: Any = cbook.get_sample_data(name)  # an NpzFile for a .npz
        heights = np.asarray(data["elevation"], np.float64)[::-1]  # row 0 south
        return cls(heights, **kw)  # type: ignore[arg-type]

    def __post_init__(self) -> None:
        need = int(np.ceil(self.size / self.pixel)) + 1
        rows, cols = self.heights.shape
        if not (0 <= self.row and self.row + need <= rows and 0 <= self.col and self.col + need <= cols):
            raise ValueError(f"a {self.size:g} m square at {self.pixel:g} m per sample needs {need} x {need} "
                             f"samples from ({self.row}, {self.col}); the DEM has {rows} x {cols}")

    def elevation(self, x: npt.ArrayLike, y: npt.ArrayLike) -> FloatArray:
        fx = (np.asarray(x, np.float64) - self.x0) / self.pixel + self.col
        fy = (np.asarray(y, np.float64) - self.y0) / self.pixel + self.row
        rows, cols = self.heights.shape
        j0 = np.clip(np.floor(fx).astype(np.int64), 0, cols - 2)
        i0 = np.clip(np.floor(fy).astype(np.int64), 0, rows - 2)
        tx = np.clip(fx - j0, 0.0, 1.0)
        ty = np.clip(fy - i0, 0.0, 1.0)
        h = self.heights
        v = (h[i0, j0] * (1 - tx) * (1 - ty) + h[i0, j0 + 1] * tx * (1 - ty)
             + h[i0 + 1, j0] * (1 - tx) * ty + h[i0 + 1, j0 + 1] * tx * ty)
        mean = float(h[self.row:self.row + int(self.size / self.pixel), self.col:self.col + int(self.size / self.pixel)].mean())
        return np.asarray(-self.depth + (v - mean) * (self.pixel / self.sample), np.float64)


@dataclass
class Survey:
    """Soundings of a simulated survey, in ping order."""

    points: FloatArray
    times: FloatArray
    ping: npt.NDArray[np.int64]
    outlier: npt.NDArray[np.bool_]
    beams: int

    def pings(self, batch: int = 1) -> Iterator[tuple[float, FloatArray]]:
        """``(time, N x 3 points)`` per group of ``batch`` consecutive pings."""
        if self.ping.size == 0:
            return
        starts = np.flatnonzero(np.diff(self.ping, prepend=-1))
        starts = np.append(starts[::batch], self.ping.size)
        for a, b in itertools.pairwise(starts):
            yield float(self.times[b - 1]), self.points[a:b]

    def __len__(self) -> int:
        return int(self.points.shape[0])


def simulate_survey(
    floor: Floor,
    *,
    altitude: float = 30.0,
    swath_deg: float = 135.0,
    beams: int = 256,
    ping_rate: float = 4.0,
    speed: float = 1.5,
    line_spacing: float | None = None,
    noise: float = 0.03,
    noise_per_metre: float = 0.0015,
    outlier_fraction: float = 0.002,
    outlier_range: tuple[float, float] = (2.0, 20.0),
    t0: float = 0.0,
    turn_time: float = 60.0,
    seed: int = 0,
) -> Survey:
    """A lawnmower survey of ``floor`` (north/south lines, first line on the west edge)."""
    rng = np.random.default_rng(seed)
    half = np.radians(swath_deg / 2)
    swath = 2 * altitude * np.tan(half)
    spacing = line_spacing or 0.7 * swath
    n_lines = max(1, int(np.ceil(floor.size / spacing)) + 1)
    xs = floor.x0 + np.minimum(np.arange(n_lines) * spacing, floor.size)
    step = speed / ping_rate
    n_ping = max(1, int(floor.size / step) + 1)
    along = np.arange(n_ping) * step
    angles = np.linspace(-half, half, beams)
    offsets = altitude * np.tan(angles)
    slant = altitude / np.cos(angles)
    pts, times, pings = [], [], []
    t = t0
    for i, x in enumerate(xs):
        ys = floor.y0 + (along if i % 2 == 0 else floor.size - along)
        heading_sign = 1.0 if i % 2 == 0 else -1.0
        px = x + heading_sign * offsets[None, :] + 0.0 * ys[:, None]
        py = np.broadcast_to(ys[:, None], px.shape)
        pt = t + np.arange(n_ping) / ping_rate
        pts.append(np.stack([px.ravel(), py.ravel()], axis=1))
        times.append(np.repeat(pt, beams))
        pings.append(np.repeat(np.arange(n_ping) + i * n_ping, beams))
        t = float(pt[-1]) + turn_time
    xy = np.concatenate(pts)
    tt = np.concatenate(times)
    pg = np.concatenate(pings)
    z = floor.elevation(xy[:, 0], xy[:, 1])
    sl = np.tile(slant, xy.shape[0] // beams)
    z = z + rng.normal(0.0, 1.0, z.size) * (noise + noise_per_metre * sl)
    # Outliers: mostly at the swath edge (weight grows with the beam angle to the 6th power).
    edge = np.tile((np.abs(angles) / half) ** 6, xy.shape[0] // beams)
    p = outlier_fraction * edge / edge.mean()
    out = rng.random(z.size) < p
    err = rng.uniform(*outlier_range, int(out.sum())) * rng.choice([-1.0, 1.0], int(out.sum()))
    z[out] += err
    return Survey(np.column_stack([xy, z]), tt, pg.astype(np.int64), out, beams)
