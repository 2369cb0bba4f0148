"""Relief anomalies of a map grid, measured: what an object standing on the seafloor looks like
in a 1 m map (height above the local background, footprint, length, width, orientation, flatness
of its top), and how well that matches an object of a given size.

One source for everyone who measures bumps: the vehicle's relief detector
(:mod:`coex_plugins.detections.relief`) on the vehicle's own map, and the demo's scripted
operator on the map topside received.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from .export import Candidate, find_targets, opening

__all__ = ["CAR", "FLAT", "SIZES", "SPREAD", "Bump", "bumps", "despike", "likeness", "measure_bump",
           "range_likeness"]

#: a flat top (a car's): mean over maximum height across its footprint
FLAT = 0.93
#: what the NUI 2022 dives looked for: a car, length, width, height (m)
CAR = (4.5, 1.8, 1.5)
#: the spreads a 1 m map allows: length, width, height (m), and flatness
SPREAD = (1.5, 1.0, 0.6, 0.2)
#: the sizes sought by default (length, width, height ranges, m): objects of 2 to 8 m, from a
#: debris patch or a small car to a 20-ft container or a small boat's hull
SIZES: tuple[tuple[float, float], tuple[float, float], tuple[float, float]] = ((2.0, 8.0), (1.0, 3.0), (0.6, 3.0))
#: the spread of the flatness term when sizes are ranges: a hull's rounded deck or a debris
#: patch is less flat than a car's roof, and still sought
RANGE_FLATNESS_SPREAD = 0.35


@dataclass(frozen=True)
class Bump:
    """A bump measured in a grid: centre (m), height above the local background (m), cells
    above half its height and their area (m²), length and width from their second moments (m),
    orientation of the long axis (degrees clockwise from north, 0..180), flatness of its top."""

    x: float
    y: float
    height: float
    cells: int
    footprint: float
    length: float
    width: float
    orientation: float
    flatness: float


def likeness(height: float, length: float, width: float, flatness: float = FLAT,
             target: tuple[float, float, float] = CAR,
             spread: tuple[float, float, float, float] = SPREAD) -> float:
    """How well a bump matches an object of ``target`` length, width and height with a flat
    top, in [0, 1]: the product of Gaussian likelihoods with the given ``spread``s (a rounded
    top, flatness below :data:`FLAT`, scores lower; a flatter one is not better)."""
    l0, w0, h0 = target
    sl, sw, sh, sf = spread
    s = (((height - h0) / sh) ** 2 + ((length - l0) / sl) ** 2 + ((width - w0) / sw) ** 2
         + ((min(flatness, FLAT) - FLAT) / sf) ** 2)
    return float(math.exp(-0.5 * s))


def _outside(x: float, lo: float, hi: float) -> float:
    """How far ``x`` lies outside ``[lo, hi]`` (0 inside)."""
    return lo - x if x < lo else (x - hi if x > hi else 0.0)


def range_likeness(height: float, length: float, width: float, flatness: float = FLAT,
                   sizes: tuple[tuple[float, float], tuple[float, float], tuple[float, float]] = SIZES,
                   spread: tuple[float, float, float, float] = (SPREAD[0], SPREAD[1], SPREAD[2],
                                                                RANGE_FLATNESS_SPREAD)) -> float:
    """How well a bump matches an object whose length, width and height lie in ``sizes``
    (ranges, m), in [0, 1]: 1 inside every range, falling off as a Gaussian of the distance
    outside each with the given ``spread``s, and lower for a rounded top (flatness below
    :data:`FLAT`). With ranges of one value each it is :func:`likeness`."""
    (l0, l1), (w0, w1), (h0, h1) = sizes
    sl, sw, sh, sf = spread
    s = ((_outside(height, h0, h1) / sh) ** 2 + (_outside(length, l0, l1) / sl) ** 2
         + (_outside(width, w0, w1) / sw) ** 2 + ((min(flatness, FLAT) - FLAT) / sf) ** 2)
    return float(math.exp(-0.5 * s))


def measure_bump(grid: npt.ArrayLike, cell: float, x0: float, y0: float, peak_x: float, peak_y: float,
                 height: float) -> Bump | None:
    """Measure the bump whose highest cell is at ``(peak_x, peak_y)`` (a :func:`find_targets`
    candidate of that ``height``): the connected cells standing more than half its height above
    the local background (a 4.5 m opening), their second moments giving length, width and
    orientation (a uniform L x W rectangle has variances L^2/12 and W^2/12); flatness is the mean
    over the maximum excess across its footprint (cells above 30 % of its height). None when the
    peak is not part of the grid or does not stand out."""
    g = np.asarray(grid, float)
    ny, nx = g.shape
    ci = int((peak_x - x0) / cell)
    ri = int((peak_y - y0) / cell)
    r = 12
    r0, r1, c0, c1 = max(ri - r, 0), min(ri + r + 1, ny), max(ci - r, 0), min(ci + r + 1, nx)
    win = g[r0:r1, c0:c1]
    if win.size < 9 or not np.isfinite(win).any():
        return None
    excess = win - opening(win, max(1, round(4.5 / cell)))
    with np.errstate(invalid="ignore"):
        above = np.isfinite(excess) & (excess > 0.5 * height)
    pr, pc = ri - r0, ci - c0
    if not (0 <= pr < win.shape[0] and 0 <= pc < win.shape[1]) or not above[pr, pc]:
        return None
    comp = grow(above, pr, pc)
    with np.errstate(invalid="ignore"):
        foot = grow(np.isfinite(excess) & (excess > 0.3 * height), pr, pc)
    flatness = float(np.nanmean(excess[foot]) / max(float(np.nanmax(excess[foot])), 1e-6))
    rows, cols = np.nonzero(comp)
    n = rows.size
    ys = (rows + 0.5) * cell
    xs = (cols + 0.5) * cell
    orientation = 0.0
    if n >= 2:
        ev, vec = np.linalg.eigh(np.cov(np.stack([xs, ys])))
        ev = ev[::-1]
        major = vec[:, 1]  # eigh: ascending, the last is the long axis (x, y)
        orientation = float(math.degrees(math.atan2(major[0], major[1])) % 180.0)
    else:
        ev = np.zeros(2)
    # a cell's own extent adds cell^2 / 12 to each variance
    length = float(math.sqrt(12.0 * max(ev[0], 0.0) + cell * cell))
    width = float(math.sqrt(12.0 * max(ev[1], 0.0) + cell * cell))
    top = float(np.nanmax(excess[comp]))
    cx = float(x0 + (c0 + cols.mean() + 0.5) * cell)
    cy = float(y0 + (r0 + rows.mean() + 0.5) * cell)
    return Bump(cx, cy, top, int(n), float(n * cell * cell), length, width, orientation, flatness)


def grow(mask: npt.NDArray[np.bool_], r: int, c: int) -> npt.NDArray[np.bool_]:
    """The 8-connected part of ``mask`` containing cell (r, c) (vectorised growth steps)."""
    comp = np.zeros_like(mask)
    comp[r, c] = bool(mask[r, c])
    while True:
        p = np.pad(comp, 1)
        grown = comp.copy()
        for dy in (0, 1, 2):
            for dx in (0, 1, 2):
                grown |= p[dy:dy + comp.shape[0], dx:dx + comp.shape[1]]
        grown &= mask
        if np.array_equal(grown, comp):
            return comp
        comp = grown


def _nanmedian0(a: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """``np.nanmedian(a, axis=0)``, bit for bit (NaN where a column is all NaN), for a short
    first axis: one sort (NaN sorts last) and the middle one or two of each column's numbers;
    numpy's own goes through masked arrays and warns once per all-NaN column."""
    s = np.sort(a, axis=0)
    n = np.sum(~np.isnan(a), axis=0)
    lo = np.take_along_axis(s, np.maximum((n - 1) // 2, 0)[None], 0)[0]
    hi = np.take_along_axis(s, (n // 2)[None], 0)[0]
    hi = np.where(n > 0, hi, np.nan)
    return np.where(n % 2 == 1, hi, (lo + hi) / 2)


def despike(grid: npt.ArrayLike, threshold: float = 1.0) -> npt.NDArray[np.float64]:
    """``grid`` with its spikes replaced by the median of their 8 neighbours: a cell more than
    ``threshold`` metres above or below that median with at most one neighbour within half of
    ``threshold`` of it (a sounding the outlier rejection let through: it would stand for the
    height of an object it sits on, or lower the background around it). An object two cells or
    more across keeps every cell: its cells have neighbours of their height. Vectorised."""
    z = np.asarray(grid, np.float64)
    if z.ndim != 2 or min(z.shape) < 3:
        return z.copy()
    p = np.pad(z, 1, constant_values=np.nan)
    h, w = z.shape
    nb = np.stack([p[1 + dy:1 + dy + h, 1 + dx:1 + dx + w] for dy in (-1, 0, 1) for dx in (-1, 0, 1)
                   if dy or dx])
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN neighbourhoods
        med = _nanmedian0(nb)
        alike = np.sum(np.abs(nb - z) <= 0.5 * threshold, axis=0)
        spike = np.isfinite(z) & np.isfinite(med) & (np.abs(z - med) > threshold) & (alike <= 1)
    return np.where(spike, med, z)


def bumps(grid: npt.ArrayLike, *, cell: float, x0: float = 0.0, y0: float = 0.0, threshold: float = 0.7,
          min_cells: int = 2, max_area: float = 40.0, spikes: float | None = 1.0,
          foot: float | None = None) -> list[tuple[Candidate, Bump]]:
    """Every bump of ``grid`` higher than ``threshold`` above its background
    (:func:`find_targets`), measured (:func:`measure_bump`); highest first. With ``spikes``
    (metres) the grid is first despiked (:func:`despike`): a single wild sounding on a car would make
    it a one-cell spike. With ``foot`` (metres, below ``threshold``) a bump is the cells standing
    more than ``foot`` above the background around a peak higher than ``threshold``, and
    ``min_cells`` and ``max_area`` count those (hysteresis): an object whose highest part fills
    one map cell (a debris patch's main piece a metre or so long, its smaller pieces around it)
    stands on a foot of raised cells where a spike does not. (Despiking is the same either way:
    keeping a high cell because cells around it are raised kept a wild sounding on the edge of a
    boulder, issue 56's fourth pass.)"""
    if spikes is not None:
        grid = despike(grid, spikes)
    out = []
    low = threshold if foot is None else min(float(foot), threshold)
    for c in find_targets(grid, cell=cell, x0=x0, y0=y0, threshold=low, min_cells=min_cells,
                          max_area=max_area):
        if c.height <= threshold:
            continue  # a foot without a peak
        b = measure_bump(grid, cell, x0, y0, c.peak_x, c.peak_y, c.height)
        if b is not None:
            out.append((c, b))
    return out
