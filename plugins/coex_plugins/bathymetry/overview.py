"""A level drawn in bounded memory: the receiver's overview arrays (the level at full resolution
while it fits, else block means), stored in chunks (the plugin's tile store, :mod:`.tilestore`;
chunks stored before it in ``CXOV`` form still read), and reading blocks back out of them."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from coex import StateError, persistent

from . import tilestore

__all__ = ["CHUNK", "Overview", "block_sums", "blocks_from", "cells_from", "weighted", "window_blocks"]

FloatArray = npt.NDArray[np.float64]

#: Overview cells per side of one stored overview chunk (``ov/<level>/<step>/<cx>/<cy>``).
CHUNK = 128


def _starts(g0: int, n: int, s: int) -> npt.NDArray[np.intp]:
    """Local indices where a global block of ``s`` cells starts, for ``n`` cells from global ``g0``."""
    first = (-g0) % s
    starts = np.arange(first, n, s)
    if first:
        starts = np.concatenate(([0], starts))
    return starts


def block_sums(z: FloatArray, w: FloatArray, gy: int, gx: int, s: int) -> tuple[int, int, FloatArray, FloatArray]:
    """Per global ``s x s`` block: the sums of ``z`` and of the weights ``w`` of an array whose
    cell (0, 0) is global cell (gy, gx). Returns (first block row, first block column, sums, weights)."""
    rs, cs = _starts(gy, z.shape[0], s), _starts(gx, z.shape[1], s)
    sz = np.add.reduceat(np.add.reduceat(z, rs, axis=0), cs, axis=1)
    sw = np.add.reduceat(np.add.reduceat(w, rs, axis=0), cs, axis=1)
    return gy // s, gx // s, sz, sw


def weighted(values: FloatArray) -> tuple[FloatArray, FloatArray]:
    fin = ~np.isnan(values)
    return np.where(fin, values, 0.0), fin.astype(np.float64)


@persistent("bathymetry.Overview")
@dataclass
class Overview:
    """One level drawn in bounded memory: overview cell (i, j) is the mean of level cells
    ``[j*step, (j+1)*step) x [i*step, (i+1)*step)``; the array covers overview cells
    ``[ox0, ox0 + nx) x [oy0, oy0 + ny)`` (row 0 = south), grown with slack as subgrids come.
    At ``step`` 1 ``mean`` holds the cells themselves (float64); beyond, float32 means and how
    many cells each is of (``count``)."""

    step: int = 1
    ox0: int = 0
    oy0: int = 0
    nx: int = 0
    ny: int = 0
    mean: npt.NDArray[Any] = field(default_factory=lambda: np.full((0, 0), np.nan))
    count: npt.NDArray[np.float32] | None = None

    def span(self, gx: int, gy: int, side: int) -> tuple[int, int, int, int]:
        k = self.step
        return gx // k, (gx + side - 1) // k + 1, gy // k, (gy + side - 1) // k + 1

    def fits(self, a: int, b: int, c: int, d: int, max_cells: int) -> bool:
        """Whether overview cells [a, b) x [c, d) fit with the rest in ``max_cells`` (growth
        may double a side, so the bounding box is held to a quarter)."""
        if self.nx == 0:
            return True
        w = max(self.ox0 + self.nx, b) - min(self.ox0, a)
        h = max(self.oy0 + self.ny, d) - min(self.oy0, c)
        return w * h <= max_cells // 4

    def include(self, a: int, b: int, c: int, d: int) -> None:
        """Grow the array (with slack, so steady growth costs amortised O(1)) to cover [a, b) x [c, d)."""
        if self.nx == 0:
            self.ox0, self.oy0, self.nx, self.ny = a, c, b - a, d - c
            self.mean = np.full((d - c, b - a), np.nan, np.float64 if self.step == 1 else np.float32)
            self.count = None if self.step == 1 else np.zeros((d - c, b - a), np.float32)
            return
        if self.ox0 <= a and b <= self.ox0 + self.nx and self.oy0 <= c and d <= self.oy0 + self.ny:
            return
        x0, y0 = min(self.ox0, a), min(self.oy0, c)
        x1, y1 = max(self.ox0 + self.nx, b), max(self.oy0 + self.ny, d)
        gx = max(x1 - x0, 2 * self.nx) if (x1 - x0) > self.nx else self.nx
        gy = max(y1 - y0, 2 * self.ny) if (y1 - y0) > self.ny else self.ny
        if a < self.ox0:
            x0 = self.ox0 + self.nx - gx
        if c < self.oy0:
            y0 = self.oy0 + self.ny - gy
        r, q = self.oy0 - y0, self.ox0 - x0
        new = np.full((gy, gx), np.nan, self.mean.dtype)
        new[r:r + self.ny, q:q + self.nx] = self.mean
        self.mean = new
        if self.count is not None:
            cnt = np.zeros((gy, gx), np.float32)
            cnt[r:r + self.ny, q:q + self.nx] = self.count
            self.count = cnt
        self.ox0, self.oy0, self.nx, self.ny = x0, y0, gx, gy

    def weights(self, rows: slice = slice(None)) -> tuple[FloatArray, FloatArray]:
        """(mean x count, count) of the overview cells of ``rows``, as float64."""
        if self.count is None:
            return weighted(self.mean[rows])
        cnt = self.count[rows].astype(np.float64)
        return np.where(cnt > 0, self.mean[rows].astype(np.float64) * cnt, 0.0), cnt

    def coarsen(self) -> None:
        """Twice the step: every new cell the mean of 2 x 2 old ones (weighted by their counts),
        a band of rows at a time (no full-size temporaries)."""
        x0, y0 = self.ox0 // 2, self.oy0 // 2
        px, py = self.ox0 - 2 * x0, self.oy0 - 2 * y0
        nx, ny = (px + self.nx + 1) // 2, (py + self.ny + 1) // 2
        mean = np.full((ny, nx), np.nan, np.float32)
        count = np.zeros((ny, nx), np.float32)
        band = 128
        for r in range(0, ny, band):
            h = min(band, ny - r)
            lo, hi = max(0, 2 * r - py), min(self.ny, 2 * (r + h) - py)
            z, w = self.weights(slice(lo, hi))
            zz = np.zeros((2 * h, 2 * nx))
            ww = np.zeros((2 * h, 2 * nx))
            o = lo + py - 2 * r
            zz[o:o + hi - lo, px:px + self.nx] = z
            ww[o:o + hi - lo, px:px + self.nx] = w
            zs = zz.reshape(h, 2, nx, 2).sum(axis=(1, 3))
            ws = ww.reshape(h, 2, nx, 2).sum(axis=(1, 3))
            mean[r:r + h] = np.where(ws > 0, zs / np.maximum(ws, 1.0), np.nan)
            count[r:r + h] = ws
        self.step *= 2
        self.ox0, self.oy0, self.nx, self.ny = x0, y0, nx, ny
        self.mean, self.count = mean, count

    def draw(self, gx: int, gy: int, values: FloatArray, old: FloatArray | None) -> None:
        """Level cells from global cell (gx, gy) now hold ``values`` (they held ``old``)."""
        side = values.shape[0]
        if self.count is None:
            r, c = gy - self.oy0, gx - self.ox0
            self.mean[r:r + side, c:c + side] = values
            return
        by, bx, sz, sw = block_sums(*weighted(values), gy, gx, self.step)
        if old is not None:
            _, _, oz, ow = block_sums(*weighted(old), gy, gx, self.step)
            sz, sw = sz - oz, sw - ow
        r, c = by - self.oy0, bx - self.ox0
        h, w = sz.shape
        m = self.mean[r:r + h, c:c + w]
        n = self.count[r:r + h, c:c + w]
        cnt = n.astype(np.float64)
        tot = np.where(cnt > 0, m.astype(np.float64) * cnt, 0.0) + sz
        cnt += sw
        m[...] = np.where(cnt > 0.5, tot / np.maximum(cnt, 1.0), np.nan)
        n[...] = np.maximum(cnt, 0.0)

    def chunks(self) -> set[tuple[int, int]]:
        """Every stored chunk the array touches."""
        if self.nx == 0:
            return set()
        return {(cx, cy) for cy in range(self.oy0 // CHUNK, (self.oy0 + self.ny - 1) // CHUNK + 1)
                for cx in range(self.ox0 // CHUNK, (self.ox0 + self.nx - 1) // CHUNK + 1)}

    def _chunk_overlap(self, cx: int, cy: int) -> tuple[tuple[slice, slice], tuple[slice, slice]] | None:
        """Where chunk ``(cx, cy)`` and this overview overlap: the overview's slices and the
        chunk's (None: they do not)."""
        a, c = cx * CHUNK, cy * CHUNK
        x0, x1 = max(a, self.ox0), min(a + CHUNK, self.ox0 + self.nx)
        y0, y1 = max(c, self.oy0), min(c + CHUNK, self.oy0 + self.ny)
        if not (x0 < x1 and y0 < y1):
            return None
        return ((slice(y0 - self.oy0, y1 - self.oy0), slice(x0 - self.ox0, x1 - self.ox0)),
                (slice(y0 - c, y1 - c), slice(x0 - a, x1 - a)))

    def encode_chunk(self, cx: int, cy: int, compression: int) -> bytes:
        mean = np.full((CHUNK, CHUNK), np.nan, self.mean.dtype)
        count = np.zeros((CHUNK, CHUNK), np.float32)
        overlap = self._chunk_overlap(cx, cy)
        if overlap is not None:
            mine, theirs = overlap
            mean[theirs] = self.mean[mine]
            if self.count is not None:
                count[theirs] = self.count[mine]
        arrays = {"step": np.array([self.step], np.int64), "mean": mean}
        if self.count is not None:
            arrays["count"] = count
        # float32 means of blocks compress better byte-shuffled, the level's own decimetres as they are
        return tilestore.encode(arrays, compression, shuffle=self.count is not None)

    def paste_chunk(self, cx: int, cy: int, data: bytes, where: str) -> None:
        try:
            arrays = tilestore.decode(data)
            step, mean, count = int(arrays["step"][0]), arrays["mean"], arrays.get("count")
            if step != self.step or (count is None) != (self.count is None):
                raise ValueError(f"step {step}{' with counts' if count is not None else ''}")
            if mean.shape != (CHUNK, CHUNK) or (count is not None and count.shape != (CHUNK, CHUNK)):
                raise ValueError(f"a chunk of {mean.shape}, not {CHUNK} x {CHUNK}")
        except (ValueError, KeyError, IndexError) as exc:
            raise StateError(f"bathymetry receiver: stored overview chunk {where} is damaged ({exc})") from exc
        overlap = self._chunk_overlap(cx, cy)
        if overlap is not None:
            mine, theirs = overlap
            self.mean[mine] = mean[theirs]
            if self.count is not None and count is not None:
                self.count[mine] = count[theirs]


def blocks_from(ov: Overview, ox0: int, oy0: int, ox1: int, oy1: int, s: int) -> FloatArray:
    """Overview cells ``[ox0, ox1) x [oy0, oy1)`` (multiples of ``s``) in blocks of ``s``, means
    weighted by the cells each overview cell is of."""
    ny, nx = (oy1 - oy0) // s, (ox1 - ox0) // s
    a, b = max(ox0, ov.ox0), min(ox1, ov.ox0 + ov.nx)
    c, d = max(oy0, ov.oy0), min(oy1, ov.oy0 + ov.ny)
    if a >= b or c >= d:
        return np.full((ny, nx), np.nan)
    part = Overview(ov.step, a, c, b - a, d - c,
                     ov.mean[c - ov.oy0:d - ov.oy0, a - ov.ox0:b - ov.ox0],
                     None if ov.count is None else ov.count[c - ov.oy0:d - ov.oy0, a - ov.ox0:b - ov.ox0])
    if s == 1:
        out = np.full((ny, nx), np.nan)
        out[c - oy0:d - oy0, a - ox0:b - ox0] = part.mean
        return out
    by, bx, z, w = block_sums(*part.weights(), c, a, s)
    zs, ws = np.zeros((ny, nx)), np.zeros((ny, nx))
    r, q = by - oy0 // s, bx - ox0 // s
    zs[r:r + z.shape[0], q:q + z.shape[1]] = z
    ws[r:r + z.shape[0], q:q + z.shape[1]] = w
    return np.where(ws > 0, zs / np.maximum(ws, 1.0), np.nan)


def window_blocks(cell: float, x_min: float, y_min: float, x_max: float, y_max: float,
                  max_cells: int) -> tuple[int, tuple[int, int, int, int]]:
    """The blocks of a window over ``[x_min, x_max) x [y_min, y_max)`` metres on a level of
    ``cell`` metres: ``(s, (bx0, by0, bx1, by1))``, blocks of ``s x s`` cells (``s`` the
    smallest power of two that keeps the window within ``max_cells``), aligned on the level's
    grid so a pan shows the same cells."""
    cx0 = math.floor(x_min / cell + 1e-9)
    cy0 = math.floor(y_min / cell + 1e-9)
    cx1 = max(cx0 + 1, math.ceil(x_max / cell - 1e-9))
    cy1 = max(cy0 + 1, math.ceil(y_max / cell - 1e-9))
    s = 1
    while -(-(cx1 - cx0) // s) * -(-(cy1 - cy0) // s) > max(1, max_cells):
        s *= 2
    return s, (cx0 // s, cy0 // s, -(-cx1 // s), -(-cy1 // s))


def cells_from(parts: Iterable[tuple[int, int, FloatArray]], cx0: int, cy0: int, cx1: int, cy1: int,
               s: int) -> FloatArray:
    """Level cells ``[cx0, cx1) x [cy0, cy1)`` (multiples of ``s``) in blocks of ``s`` (the mean
    of the held cells of each block, NaN where none), from ``parts``: ``(gx, gy, values)``, a
    tile's cells with its south-west cell at ``(gx, gy)``."""
    ny, nx = (cy1 - cy0) // s, (cx1 - cx0) // s
    out = np.full((ny, nx), np.nan)
    zs, ws = np.zeros((ny, nx)), np.zeros((ny, nx))
    for gx, gy, values in parts:
        h, w = values.shape
        a, b = max(cx0, gx), min(cx1, gx + w)
        c, d = max(cy0, gy), min(cy1, gy + h)
        if a >= b or c >= d:
            continue
        part = values[c - gy:d - gy, a - gx:b - gx]
        if s == 1:
            out[c - cy0:d - cy0, a - cx0:b - cx0] = part
            continue
        by, bx, z, wt = block_sums(*weighted(part), c, a, s)
        r, q = by - cy0 // s, bx - cx0 // s
        zs[r:r + z.shape[0], q:q + z.shape[1]] += z
        ws[r:r + z.shape[0], q:q + z.shape[1]] += wt
    if s == 1:
        return out
    return np.where(ws > 0, zs / np.maximum(ws, 1.0), np.nan)
