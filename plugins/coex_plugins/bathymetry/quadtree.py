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
* in a sparser cell, the 4 x 4-cell block around it (level 2), or the 16 x 16-cell block
  (level 4) where that is sparse too: rejected when
  ``|z - block mean| > max(outlier_threshold, outlier_k * block std)`` and the block holds at
  least ``min_count`` soundings. A real target raises its block's spread and passes; an isolated
  spike does not.

A sounding with too few neighbours to be judged (fewer than ``min_count`` soundings in its cell
and in both blocks) is held back (``pending``) and judged again with the next batch, until it is
``max_pending_age`` seconds older than the newest sounding (or ``max_pending`` are waiting); then
it is added unjudged. ``flush(force=True)`` adds every held sounding at once (end of a file).

Rejected soundings are counted (``rejected``), never added. Non-finite soundings, soundings
outside the addressable area (|x|, |y| beyond ``resolution * 2**16``) and soundings that would
need more than ``max_tiles`` tiles (1024 by default, about 470 MB, 16 km² at 1 m) are dropped and
counted (``dropped``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from coex_core.errors import CoexError
from coex_core.state import persistent

__all__ = ["InputError", "QuadtreeMap", "LevelBlock"]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

_ADDED, _REJECTED, _DROPPED, _HELD = 0, 1, 2, 3

#: Level-0 cell indices are limited to +-2**16 (the wire's subgrid index range at level 0).
MAX_CELL_INDEX = 1 << 16


class InputError(CoexError, ValueError):
    """Sensor input that cannot be ingested (wrong shape or type, unreadable file)."""


@persistent("bathymetry.LevelBlock")
@dataclass(frozen=True)
class LevelBlock:
    """Statistics of one subgrid-sized block at one level (row 0 = south, column 0 = west)."""

    count: npt.NDArray[np.int64]
    mean: FloatArray
    std: FloatArray
    updated: float


@persistent("bathymetry.QuadtreeMap")
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
        max_tiles: int = 1024,
        max_pending_age: float = 60.0,
        max_pending: int = 200_000,
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
        self._times_cache: dict[tuple[int, int], tuple[int, FloatArray]] = {}
        #: Root of the quadtree above the tiles: ``2**root_level`` tiles per side from ``root_origin``.
        self.root_level = 0
        self.root_origin: tuple[int, int] | None = None
        self.accepted = 0
        self.rejected = 0
        self.dropped = 0
        self.last_update = -np.inf
        #: Time of the newest ``add_points`` call.
        self.last_input = -np.inf
        self.batch_points = int(batch_points)
        #: At most this many tiles (about 460 KB each with the defaults): a memory guard against
        #: soundings scattered over a huge area (a navigation glitch); the rest are dropped.
        self.max_tiles = int(max_tiles)
        self._buffer: list[tuple[FloatArray, float]] = []
        self._buffered = 0
        self.max_pending_age = float(max_pending_age)
        self.max_pending = int(max_pending)
        self._pending_pts = np.zeros((0, 3))
        self._pending_t = np.zeros(0)
        self._pending_ids = np.zeros(0, np.int64)
        self._next_id = 0
        #: With ``track_rejections``, the input positions (0 = first sounding ever added) of the
        #: soundings outlier rejection removed, one array per ingested batch (for measurements).
        self.track_rejections = False
        self.rejected_ids: list[npt.NDArray[np.int64]] = []

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
        self.last_input = max(self.last_input, t)
        self._buffered += pts.shape[0]
        if self._buffered >= self.batch_points:
            self.flush()
        return int(pts.shape[0])

    def flush(self, force: bool = False) -> None:
        """Ingest the buffered soundings now. With ``force``, soundings held back because they could
        not be judged yet (see the module docstring) are ingested too, unjudged."""
        if not self._buffer and not (force and self._pending_n):
            return
        chunks, self._buffer, self._buffered = self._buffer, [], 0
        n_new = sum(c[0].shape[0] for c in chunks)
        ids = np.arange(self._next_id, self._next_id + n_new)
        self._next_id += n_new
        parts = [self._pending_pts] + [c[0] for c in chunks]
        pts = np.concatenate(parts) if len(parts) > 1 else parts[0]
        times = np.concatenate([self._pending_t, np.repeat(np.array([c[1] for c in chunks]),
                                                           [c[0].shape[0] for c in chunks])])
        all_ids = np.concatenate([self._pending_ids, ids])
        status = self._ingest(pts, times, force)
        held = status == _HELD
        self._pending_pts, self._pending_t, self._pending_ids = pts[held], times[held], all_ids[held]
        if self.track_rejections:
            self.rejected_ids.append(all_ids[status == _REJECTED])

    @property
    def _pending_n(self) -> int:
        return int(self._pending_t.size)

    @property
    def pending(self) -> int:
        """Soundings held back until their neighbourhood has enough data to judge them."""
        return self._pending_n

    def _ingest(self, pts: FloatArray, times: FloatArray, force: bool) -> npt.NDArray[np.int8]:
        """Ingest; return per sounding _ADDED, _REJECTED, _DROPPED or _HELD."""
        x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
        with np.errstate(invalid="ignore"):
            ci = np.floor(x / self.resolution)
            cj = np.floor(y / self.resolution)
            ok = np.isfinite(z) & (np.abs(ci) < MAX_CELL_INDEX) & (np.abs(cj) < MAX_CELL_INDEX)
        status = np.full(z.size, _DROPPED, np.int8)
        if not ok.all():
            self.dropped += int(np.count_nonzero(~ok))
            ci, cj, z, times = ci[ok], cj[ok], z[ok], times[ok]
            if z.size == 0:
                return status
        col = ci.astype(np.int64)
        row = cj.astype(np.int64)
        tx = col >> self._shift
        ty = row >> self._shift
        uniq_x, uniq_y, inv = _group_tiles(tx, ty)
        new = np.array([(int(a), int(b)) not in self._slots for a, b in zip(uniq_x, uniq_y, strict=True)])
        room = max(self.max_tiles - len(self._keys), 0)
        if int(new.sum()) > room:
            # Memory guard: soundings that would need more tiles than max_tiles are dropped.
            refused = np.zeros(new.size, bool)
            refused[np.flatnonzero(new)[room:]] = True
            bad = refused[inv]
            self.dropped += int(bad.sum())
            ok_idx = np.flatnonzero(ok)
            ok = ok.copy()
            ok[ok_idx[bad]] = False
            col, row, z, times, tx, ty = col[~bad], row[~bad], z[~bad], times[~bad], tx[~bad], ty[~bad]
            if z.size == 0:
                return status
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
        hold = np.zeros(z.size, bool)
        if self.outlier_rejection:
            keep, judged = self._screen(slots, flat, local, inv, z, n_b, s_b, ss_b)
            if not force:
                hold = ~judged & (times > times.max() - self.max_pending_age)
                if hold.sum() + 0 > self.max_pending:
                    cut = np.sort(times[hold])[-self.max_pending]
                    hold &= times >= cut
            rejected = ~keep
            self.rejected += int(np.count_nonzero(rejected))
            keep &= ~hold
            if not keep.all():
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
        st = np.where(keep, _ADDED, np.where(hold, _HELD, _REJECTED)).astype(np.int8)
        status[ok] = st
        return status

    def _screen(
        self,
        slots: IntArray,
        flat: IntArray,
        local: IntArray,
        inv: IntArray,
        z: FloatArray,
        n_b: npt.NDArray[Any],
        s_b: npt.NDArray[Any],
        ss_b: npt.NDArray[Any],
    ) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
        """Which soundings of a batch to keep, and which could be judged (see the module docstring).

        Two passes: the first judges every sounding against references that may include the
        outliers themselves; the second recomputes the references from the map and the soundings
        the first pass kept, and judges again (a clipped, robust mean per cell and per block)."""
        m = slots.size
        size = m * self._tt
        c_map = self._count[slots].ravel()
        s_map = self._sum[slots].ravel()
        ss_map = self._sumsq[slots].ravel()
        row = local >> self._shift
        col = local & (self.tile - 1)
        blocks = []
        for f in (4, 16):  # 4 x 4 cells (level 2), then 16 x 16 cells (level 4) where sparser
            if f > self.tile:
                break
            tf = self.tile // f
            blocks.append(((m, tf, f, tf, f), inv * (tf * tf) + (row // f) * tf + (col // f)))

        def judge(c: IntArray, sm: FloatArray, ss: FloatArray) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
            mean = sm / np.maximum(c, 1)
            dense = c[flat] >= self.min_count
            bad = dense & (np.abs(z - mean[flat]) > self.outlier_threshold)
            judged = dense.copy()
            for shape, b in blocks:
                cb = c.reshape(shape).sum(axis=(2, 4)).ravel()
                sb = sm.reshape(shape).sum(axis=(2, 4)).ravel()
                ssb = ss.reshape(shape).sum(axis=(2, 4)).ravel()
                mb = sb / np.maximum(cb, 1)
                sd = np.sqrt(np.maximum(ssb / np.maximum(cb, 1) - mb * mb, 0.0))
                thr = np.maximum(self.outlier_threshold, self.outlier_k * sd[b])
                here = ~judged & (cb[b] >= self.min_count)
                bad |= here & (np.abs(z - mb[b]) > thr)
                judged |= here
            return ~bad, judged

        keep, judged = judge(c_map + n_b, s_map + s_b, ss_map + ss_b)
        if keep.all():
            return keep, judged
        w = keep.astype(np.float64)
        n_k = np.bincount(flat, weights=w, minlength=size).astype(np.int64)
        s_k = np.bincount(flat, weights=z * w, minlength=size)
        ss_k = np.bincount(flat, weights=z * z * w, minlength=size)
        return judge(c_map + n_k, s_map + s_k, ss_map + ss_k)

    # --------------------------------------------------------------------------- queries

    def subgrids_per_tile(self, level: int) -> int:
        """Subgrids a tile holds per side at ``level`` (0 .. ``levels - 1``)."""
        if not 0 <= level < self.levels:
            raise InputError(f"level {level} outside 0..{self.levels - 1}")
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
        version = int(self._version[s])
        hit = self._times_cache.get((s, level))
        if hit is not None and hit[0] == version:
            return hit[1]
        p = self.subgrids_per_tile(level)
        span = self.tile // p
        result: FloatArray = self._time[s].reshape(p, span, p, span).max(axis=(1, 3))
        result.flags.writeable = False
        self._times_cache[(s, level)] = (version, result)
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
        for tx, ty in self._keys:
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


def _grow(a: npt.NDArray[Any], cap: int, fill: float) -> Any:
    shape = (cap, *a.shape[1:])
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
