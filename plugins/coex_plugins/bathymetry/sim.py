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

__all__ = ["DemSeafloor", "Floor", "Seafloor", "Survey", "Target", "simulate_survey"]

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Target:
    """An object on the seafloor: centre (x, y), length, width, height (m) and heading (deg from
    north). ``shape`` is ``"box"`` (a car: flat top) or ``"dome"`` (a boulder: a half-ellipsoid
    inscribed in the same box)."""

    x: float
    y: float
    length: float = 4.5
    width: float = 1.8
    height: float = 1.5
    heading: float = 0.0
    shape: str = "box"


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
            if t.shape == "dome":
                r2 = (u / (t.length / 2)) ** 2 + (v / (t.width / 2)) ** 2
                top = base + t.height * np.sqrt(np.clip(1.0 - r2, 0.0, 1.0))
                z = np.where(r2 < 1.0, np.maximum(z, top), z)
                continue
            inside = (np.abs(u) <= t.length / 2) & (np.abs(v) <= t.width / 2)
            z = np.where(inside, np.maximum(z, base + t.height), z)
        return z


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
