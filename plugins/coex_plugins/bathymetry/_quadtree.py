"""The subsea map: a sparse quadtree of elevation cells with vectorised ingest.

Structure. The tree's bottom ``levels`` levels are stored as dense *bricks* ("tiles") of
``T x T`` level-0 cells (``T = subgrid_side * 2**(levels - 1)``, 128 cells by default), so that a
tile is exactly one subgrid at the coarsest level sent. Tiles exist only where data landed:
memory grows with the area covered (about 28 bytes per level-0 cell of a touched tile), never
with the number of soundings. Above the tiles the quadtree is implicit: the root is a square of
``2**root_level`` tiles that grows by adding a new root (the old root becomes one of its four
children) whenever data lands outside it; there is no fixed extent.

Per level-0 cell a tile keeps the count, the sum and the sum of squares of the accepted
soundings (mean and standard deviation follow) and the time of the last update. A coarser cell's
statistics are the sums of its children; a node's last update is the maximum over its
descendants (computed on demand by reshaping, no per-node Python objects). The sender keeps the
last-transmitted time per subgrid node.

Ingest is numpy only: cell indices, one ``np.bincount`` per statistic over the touched tiles, and a
per-tile Python step only for the handful of tiles a batch touches.

Outlier rejection (on by default). Multibeam swath edges produce single soundings metres off.
Each sounding is compared with a reference built from the map *and* the batch:

* in a cell holding at least ``min_count`` soundings (including this batch), the cell mean:
  rejected when ``|z - mean| > outlier_threshold``;
* in a sparser cell, the 4 x 4-cell block around it (level 2): rejected when
  ``|z - block mean| > max(outlier_threshold, outlier_k * block std)`` and the block holds at
  least ``min_count`` soundings. A real target raises its block's spread and passes; an isolated
  spike does not.

Rejected soundings are counted (``rejected``), never added. Non-finite soundings and soundings
outside the addressable area (|x|, |y| beyond ``resolution * 2**16``) are dropped and counted
(``dropped``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from coex_core.errors import CoexError

__all__ = ["InputError", "QuadtreeMap", "LevelBlock"]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: Level-0 cell indices are limited to +-2**16 (the wire's subgrid index range at level 0).
MAX_CELL_INDEX = 1 << 16


class InputError(CoexError, ValueError):
    """Sensor input that cannot be ingested (wrong shape or type, unreadable file)."""


@dataclass(frozen=True)
class LevelBlock:
    """Statistics of one subgrid-sized block at one level (row 0 = south, column 0 = west)."""

    count: npt.NDArray[np.int64]
    mean: FloatArray
    std: FloatArray
    updated: float


class QuadtreeMap:
    """A 2.5-D seafloor map: mean elevation per cell at ``resolution`` metres (level 0) and at every
    coarser level up to ``levels - 1`` (cell size ``resolution * 2**level``).

    ``add_points(xyz, now)`` takes an ``N x 3`` array (x east, y north, z up, metres) in a local
    frame. Elevations are kept as float sums; ``vertical_resolution`` is the quantum used when
    cells are sent.
    """

    def __init__(
        self,
        resolution: float = 1.0,
        vertical_resolution: float = 0.1,
        *,
        subgrid_side: int = 8,
        levels: int = 5,
        outlier_rejection: bool = True,
        outlier_threshold: float = 1.0,
        outlier_k: float = 3.0,
        min_count: int = 3,
        batch_points: int = 20_000,
    ) -> None:
        if not resolution > 0 or not vertical_resolution > 0:
            raise InputError("resolution and vertical_resolution must be positive")
        if subgrid_side < 2 or subgrid_side & (subgrid_side - 1):
            raise InputError("subgrid_side must be a power of two >= 2")
        if not 1 <= levels <= 8:
            raise InputError("levels must be in 1..8")
        self.resolution = float(resolution)
        self.vertical_resolution = float(vertical_resolution)
        self.subgrid_side = int(subgrid_side)
        self.levels = int(levels)
        self.outlier_rejection = bool(outlier_rejection)
        self.outlier_threshold = float(outlier_threshold)
        self.outlier_k = float(outlier_k)
        self.min_count = int(min_count)
        self.tile = self.subgrid_side << (self.levels - 1)
        self._shift = self.tile.bit_length() - 1
        self._tt = self.tile * self.tile
        self._slots: dict[tuple[int, int], int] = {}
        self._keys: list[tuple[int, int]] = []
        cap = 4
        self._count = np.zeros((cap, self._tt), np.int64)
        self._sum = np.zeros((cap, self._tt), np.float64)
        self._sumsq = np.zeros((cap, self._tt), np.float64)
        self._time = np.full((cap, self._tt), -np.inf, np.float64)
        self._version = np.zeros(cap, np.int64)
        #: Root of the quadtree above the tiles: ``2**root_level`` tiles per side from ``root_origin``.
        self.root_level = 0
        self.root_origin: tuple[int, int] | None = None
        self.accepted = 0
        self.rejected = 0
        self.dropped = 0
        self.last_update = -np.inf
        self.batch_points = int(batch_points)
        self._buffer: list[tuple[FloatArray, float]] = []
        self._buffered = 0
        #: With ``track_rejections``, one boolean array per ingested batch (input order):
        #: True where a sounding was rejected or dropped (for measurements).
        self.track_rejections = False
        self.rejection_log: list[npt.NDArray[np.bool_]] = []

    # ------------------------------------------------------------------------- structure

    @property
    def tiles(self) -> list[tuple[int, int]]:
        """Tile keys ``(tx, ty)`` in creation order (a tile covers ``tile`` level-0 cells a side)."""
        self.flush()
        return list(self._keys)

    def nbytes(self) -> int:
        """Memory held by the cell arrays."""
        return int(self._count.nbytes + self._sum.nbytes + self._sumsq.nbytes + self._time.nbytes)

    def _grow_root(self, tx: int, ty: int) -> None:
        if self.root_origin is None:
            self.root_origin = (tx, ty)
            self.root_level = 0
            return
        ox, oy = self.root_origin
        while True:
            size = 1 << self.root_level
            if ox <= tx < ox + size and oy <= ty < oy + size:
                break
            # New root twice the size; the old root becomes the child on the side away from the data.
            if tx < ox:
                ox -= size
            if ty < oy:
                oy -= size
            self.root_level += 1
        self.root_origin = (ox, oy)

    def _slot(self, key: tuple[int, int]) -> int:
        s = self._slots.get(key)
        if s is not None:
            return s
        s = len(self._keys)
        if s == self._count.shape[0]:
            cap = 2 * s
            self._count = _grow(self._count, cap, 0)
            self._sum = _grow(self._sum, cap, 0.0)
            self._sumsq = _grow(self._sumsq, cap, 0.0)
            self._time = _grow(self._time, cap, -np.inf)
            self._version = _grow(self._version, cap, 0)
        self._slots[key] = s
        self._keys.append(key)
        self._grow_root(*key)
        return s

    # ---------------------------------------------------------------------------- ingest

    def add_points(self, xyz: npt.ArrayLike, now: float) -> int:
        """Add soundings (``N x 3``: x, y, z in metres, captured at or before ``now``).

        Soundings are buffered and ingested together once ``batch_points`` are waiting (and
        before any query), so that per-ping calls cost almost nothing and outlier rejection sees
        several pings at once. Returns the number of soundings taken (before rejection)."""
        pts = np.asarray(xyz)
        if pts.ndim != 2 or pts.shape[1] < 3:
            raise InputError(f"expected an N x 3 array of points, got shape {pts.shape}")
        if not (np.issubdtype(pts.dtype, np.integer) or np.issubdtype(pts.dtype, np.floating)):
            raise InputError(f"expected numbers, got dtype {pts.dtype}")
        try:
            t = float(now)
        except (TypeError, ValueError):
            raise InputError(f"now must be a number, got {now!r}") from None
        if pts.shape[0] == 0:
            return 0
        self._buffer.append((np.array(pts[:, :3], np.float64), t))
        self._buffered += pts.shape[0]
        if self._buffered >= self.batch_points:
            self.flush()
        return int(pts.shape[0])

    def flush(self) -> None:
        """Ingest the buffered soundings now."""
        if not self._buffer:
            return
        chunks, self._buffer, self._buffered = self._buffer, [], 0
        pts = chunks[0][0] if len(chunks) == 1 else np.concatenate([c[0] for c in chunks])
        times = np.repeat(np.array([c[1] for c in chunks]), [c[0].shape[0] for c in chunks])
        keep = self._ingest(pts, times)
        if self.track_rejections:
            self.rejection_log.append(~keep)

    def _ingest(self, pts: FloatArray, times: FloatArray) -> npt.NDArray[np.bool_]:
        x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
        with np.errstate(invalid="ignore"):
            ci = np.floor(x / self.resolution)
            cj = np.floor(y / self.resolution)
            ok = np.isfinite(z) & (np.abs(ci) < MAX_CELL_INDEX) & (np.abs(cj) < MAX_CELL_INDEX)
        kept = np.zeros(z.size, bool)
        if not ok.all():
            self.dropped += int(np.count_nonzero(~ok))
            ci, cj, z, times = ci[ok], cj[ok], z[ok], times[ok]
            if z.size == 0:
                return kept
        col = ci.astype(np.int64)
        row = cj.astype(np.int64)
        tx = col >> self._shift
        ty = row >> self._shift
        uniq_x, uniq_y, inv = _group_tiles(tx, ty)
        slots = np.array([self._slot((int(a), int(b))) for a, b in zip(uniq_x, uniq_y, strict=True)], np.int64)
        m = slots.size
        t = self.tile
        local = ((row - ty * t) << self._shift) + (col - tx * t)
        flat = inv * self._tt + local
        size = m * self._tt
        n_b = np.bincount(flat, minlength=size)
        s_b = np.bincount(flat, weights=z, minlength=size)
        ss_b = np.bincount(flat, weights=z * z, minlength=size)
        keep = np.ones(z.size, bool)
        if self.outlier_rejection:
            keep = self._screen(slots, flat, local, inv, z, n_b, s_b, ss_b)
            if not keep.all():
                self.rejected += int(np.count_nonzero(~keep))
                w = keep.astype(np.float64)
                n_b = np.bincount(flat, weights=w, minlength=size).astype(np.int64)
                s_b = np.bincount(flat, weights=z * w, minlength=size)
                ss_b = np.bincount(flat, weights=z * z * w, minlength=size)
        n2 = n_b.reshape(m, self._tt)
        self._count[slots] += n2
        self._sum[slots] += s_b.reshape(m, self._tt)
        self._sumsq[slots] += ss_b.reshape(m, self._tt)
        tm = self._time[slots].ravel()
        np.maximum.at(tm, flat[keep], times[keep])
        self._time[slots] = tm.reshape(m, self._tt)
        self._version[slots] += 1
        added = int(n2.sum())
        self.accepted += added
        if added:
            self.last_update = max(self.last_update, float(times[keep].max()))
        kept[ok] = keep
        return kept

    def _screen(
        self,
        slots: IntArray,
        flat: IntArray,
        local: IntArray,
        inv: IntArray,
        z: FloatArray,
        n_b: IntArray,
        s_b: FloatArray,
        ss_b: FloatArray,
    ) -> npt.NDArray[np.bool_]:
        """Which soundings of a batch to keep (see the module docstring).

        Two passes: the first judges every sounding against references that may include the
        outliers themselves; the second recomputes the references from the map and the soundings
        the first pass kept, and judges again (a clipped, robust mean per cell and per block)."""
        m = slots.size
        size = m * self._tt
        c_map = self._count[slots].ravel()
        s_map = self._sum[slots].ravel()
        ss_map = self._sumsq[slots].ravel()
        t4 = self.tile >> 2
        row = local >> self._shift
        col = local & (self.tile - 1)
        b2 = inv * (t4 * t4) + (row >> 2) * t4 + (col >> 2)
        shape = (m, t4, 4, t4, 4)

        def judge(c: IntArray, sm: FloatArray, ss: FloatArray) -> npt.NDArray[np.bool_]:
            mean = sm / np.maximum(c, 1)
            dense = c[flat] >= self.min_count
            dev = np.abs(z - mean[flat])
            c2 = c.reshape(shape).sum(axis=(2, 4)).ravel()
            s2 = sm.reshape(shape).sum(axis=(2, 4)).ravel()
            ss2 = ss.reshape(shape).sum(axis=(2, 4)).ravel()
            mean2 = s2 / np.maximum(c2, 1)
            std2 = np.sqrt(np.maximum(ss2 / np.maximum(c2, 1) - mean2 * mean2, 0.0))
            thr2 = np.maximum(self.outlier_threshold, self.outlier_k * std2[b2])
            bad_sparse = (c2[b2] >= self.min_count) & (np.abs(z - mean2[b2]) > thr2)
            return ~np.where(dense, dev > self.outlier_threshold, bad_sparse)

        keep = judge(c_map + n_b, s_map + s_b, ss_map + ss_b)
        if keep.all():
            return keep
        w = keep.astype(np.float64)
        n_k = np.bincount(flat, weights=w, minlength=size).astype(np.int64)
        s_k = np.bincount(flat, weights=z * w, minlength=size)
        ss_k = np.bincount(flat, weights=z * z * w, minlength=size)
        return judge(c_map + n_k, s_map + s_k, ss_map + ss_k)

    # --------------------------------------------------------------------------- queries

    def subgrids_per_tile(self, level: int) -> int:
        """Subgrids a tile holds per side at ``level``."""
        return self.tile // (self.subgrid_side << level)

    def tile_version(self, key: tuple[int, int]) -> int:
        self.flush()
        s = self._slots.get(key)
        return -1 if s is None else int(self._version[s])

    def level_stats(self, key: tuple[int, int], level: int) -> tuple[IntArray, FloatArray, FloatArray, FloatArray]:
        """``(count, sum, sumsq, updated)`` of a tile's cells at ``level`` (shape ``T>>level`` square)."""
        self.flush()
        s = self._slots[key]
        t = self.tile
        f = 1 << level
        n = t >> level
        shape = (n, f, n, f)
        cnt = self._count[s].reshape(shape).sum(axis=(1, 3))
        sm = self._sum[s].reshape(shape).sum(axis=(1, 3))
        ss = self._sumsq[s].reshape(shape).sum(axis=(1, 3))
        tm = self._time[s].reshape(shape).max(axis=(1, 3))
        return cnt, sm, ss, tm

    def subgrid_times(self, key: tuple[int, int], level: int) -> FloatArray:
        """Last update of each subgrid node of a tile at ``level`` (``-inf`` where empty)."""
        self.flush()
        s = self._slots[key]
        p = self.subgrids_per_tile(level)
        span = self.tile // p
        result: FloatArray = self._time[s].reshape(p, span, p, span).max(axis=(1, 3))
        return result

    def tile_of_subgrid(self, level: int, ix: int, iy: int) -> tuple[tuple[int, int], int, int]:
        """The tile holding subgrid ``(ix, iy)`` at ``level`` and the subgrid's position in it."""
        p = self.subgrids_per_tile(level)
        return (ix // p, iy // p), ix % p, iy % p

    def block(self, level: int, ix: int, iy: int) -> LevelBlock | None:
        """The cells of subgrid ``(ix, iy)`` at ``level``, or None where the map has no tile."""
        self.flush()
        key, a, b = self.tile_of_subgrid(level, ix, iy)
        s = self._slots.get(key)
        if s is None:
            return None
        side = self.subgrid_side
        f = 1 << level
        span = side * f
        t = self.tile
        sl = np.s_[b * span:(b + 1) * span, a * span:(a + 1) * span]
        shape = (side, f, side, f)
        cnt = self._count[s].reshape(t, t)[sl].reshape(shape).sum(axis=(1, 3))
        sm = self._sum[s].reshape(t, t)[sl].reshape(shape).sum(axis=(1, 3))
        ss = self._sumsq[s].reshape(t, t)[sl].reshape(shape).sum(axis=(1, 3))
        upd = float(self._time[s].reshape(t, t)[sl].max())
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(cnt > 0, sm / np.maximum(cnt, 1), np.nan)
            var = np.where(cnt > 0, ss / np.maximum(cnt, 1) - mean * mean, np.nan)
        return LevelBlock(cnt, mean, np.sqrt(np.maximum(var, 0.0)), upd)

    def grid(self, level: int = 0) -> tuple[FloatArray, float, float]:
        """The whole map at ``level`` as one array (NaN where empty), row 0 = south, and the
        (x, y) of its south-west corner."""
        self.flush()
        if not self._keys:
            return np.full((0, 0), np.nan), 0.0, 0.0
        keys = np.array(self._keys)
        x0, y0 = keys.min(axis=0)
        x1, y1 = keys.max(axis=0) + 1
        n = self.tile >> level
        out = np.full(((y1 - y0) * n, (x1 - x0) * n), np.nan)
        for (tx, ty), s in self._slots.items():
            cnt, sm, _, _ = self.level_stats((tx, ty), level)
            with np.errstate(invalid="ignore", divide="ignore"):
                val = np.where(cnt > 0, sm / np.maximum(cnt, 1), np.nan)
            out[(ty - y0) * n:(ty - y0 + 1) * n, (tx - x0) * n:(tx - x0 + 1) * n] = val
        return out, float(x0 * self.tile * self.resolution), float(y0 * self.tile * self.resolution)

    def extent(self) -> tuple[float, float, float, float] | None:
        """``(x_min, y_min, x_max, y_max)`` in metres of the tiles holding data."""
        self.flush()
        if not self._keys:
            return None
        keys = np.array(self._keys)
        span = self.tile * self.resolution
        x0, y0 = keys.min(axis=0) * span
        x1, y1 = (keys.max(axis=0) + 1) * span
        return float(x0), float(y0), float(x1), float(y1)


def _grow(a: npt.NDArray[np.generic], cap: int, fill: float) -> npt.NDArray[np.generic]:
    shape = (cap,) + a.shape[1:]
    out = np.full(shape, fill, dtype=a.dtype)
    out[: a.shape[0]] = a
    return out


def _group_tiles(tx: IntArray, ty: IntArray) -> tuple[IntArray, IntArray, IntArray]:
    """Distinct tiles of a batch and each point's index among them (O(n) for compact batches)."""
    x0, y0 = int(tx.min()), int(ty.min())
    wx, wy = int(tx.max()) - x0 + 1, int(ty.max()) - y0 + 1
    if wx * wy <= 1 << 16:
        key = (tx - x0) * wy + (ty - y0)
        present = np.bincount(key, minlength=wx * wy) > 0
        ids = np.flatnonzero(present)
        lookup = np.zeros(wx * wy, np.int64)
        lookup[ids] = np.arange(ids.size)
        return ids // wy + x0, ids % wy + y0, lookup[key]
    pairs = np.stack([tx, ty], axis=1)
    uniq, inv = np.unique(pairs, axis=0, return_inverse=True)
    return uniq[:, 0], uniq[:, 1], inv.ravel()
