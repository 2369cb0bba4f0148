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

Rejected soundings are counted (``rejected``), never added. Non-finite soundings and soundings
outside the addressable area (|x|, |y| beyond ``resolution * 2**16``) are dropped and counted
(``dropped``), and so are soundings that would need a new tile once ``disk_budget`` or the
optional ``max_tiles`` is reached or the storage fails; ``overflow`` then says why (the sender
logs it and tells topside in ``MapMetadata.dropped_k``).

Out of core: at most ``memory_budget`` bytes of tiles stay in memory (least recently used leave
first); the others are kept, losslessly compressed, in the map's :mod:`coex_core.storage` and
read back on demand (see :class:`QuadtreeMap`). The resident tiles, their budget and their
stored form are the plugin's one tile store (:mod:`.tilestore`), which the topside receiver
uses too.

Beside this module: the outlier screen (``_outliers.py``) and the array helpers (``_arrays.py``).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from coex import CoexError, MemoryStorage, StateError, Storage, persistent

from . import tilestore
from ._arrays import _group_tiles, _grow, _pool
from ._outliers import screen

__all__ = ["InputError", "QuadtreeMap", "LevelBlock"]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

_ADDED, _REJECTED, _DROPPED, _HELD = 0, 1, 2, 3

#: Level-0 cell indices are limited to +-2**16 (the wire's subgrid index range at level 0).
MAX_CELL_INDEX = 1 << 16

#: Memory the map's resident tiles may use by default (bytes): 512 MB.
DEFAULT_MEMORY_BUDGET = 512 * 2**20
#: Disk the map's stored tiles may use by default (bytes): 16 GB (a 100 km² map at 1 m takes
#: about 1.3 GB).
DEFAULT_DISK_BUDGET = 16 * 2**30


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


def _tile_name(key: tuple[int, int]) -> str:
    return f"tile/{key[0]}/{key[1]}"


def _upgrade_map(fields: dict[str, Any], saved: int) -> dict[str, Any]:
    """A map saved by version 1 (every tile in four arrays of the saved state) keeps its tiles
    in a :class:`MemoryStorage` of the saved state now; ``_after_restore`` finishes the index.
    Version 3 writes its tiles in the tile store's format (:mod:`.tilestore`, ``CXTS``); the
    ``CXT1`` tiles a version-2 map stored are read as they are (its fields are unchanged).
    A version-1 ``max_tiles`` of 1024 or less was the old memory guard, which the storage
    replaces: it becomes None (no limit)."""
    if saved < 2 and "_count" in fields:
        if fields.get("max_tiles") is not None and fields["max_tiles"] <= 1024:
            fields["max_tiles"] = None
        fields["_v1_arrays"] = {k: fields.pop(k) for k in ("_count", "_sum", "_sumsq", "_time")}
        fields.pop("_times_cache", None)
        fields["_mem"] = MemoryStorage()  # where its tiles go
    return fields


def _check_geometry(resolution: float, vertical_resolution: float, subgrid_side: int, levels: int,
                    max_tiles: int | None) -> None:
    """:class:`InputError` unless the map's cell sizes, subgrid side, levels and tile limit hold."""
    if not resolution > 0 or not vertical_resolution > 0:
        raise InputError("resolution and vertical_resolution must be positive")
    if subgrid_side < 2 or subgrid_side & (subgrid_side - 1):
        raise InputError("subgrid_side must be a power of two >= 2")
    if not 1 <= levels <= 8:
        raise InputError("levels must be in 1..8")
    if subgrid_side << (levels - 1) > 4096:
        raise InputError("subgrid_side * 2**(levels - 1) must be at most 4096 cells")
    if max_tiles is not None and int(max_tiles) < 1:
        raise InputError("max_tiles must be at least 1 (or None: no limit)")


@persistent("bathymetry.QuadtreeMap", version=3,
            transient=("_res", "_cache", "_ext", "_free", "_changed_all", "_summ", "_summ_ok"),
            upgrade=_upgrade_map)
class QuadtreeMap:
    """A 2.5-D seafloor map: mean elevation per cell at ``resolution`` metres (level 0) and at every
    coarser level up to ``levels - 1`` (cell size ``resolution * 2**level``).

    ``add_points(xyz, now)`` takes an ``N x 3`` array (x east, y north, z up, metres) in a local
    frame. Elevations are kept as float sums; ``vertical_resolution`` is the quantum used when
    cells are sent.

    Out of core: at most ``memory_budget`` bytes of tiles stay in memory (the most recently used);
    the others live in the map's storage (:mod:`coex_core.storage`: the node's SQLite file when it
    has a store, else in memory) and come back when soundings land on them or a query needs
    them. The index every query of the sender uses (tile versions, the last update of every
    subgrid at every level) stays in memory: about 3 KB per tile.
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
        max_tiles: int | None = None,
        memory_budget: int = DEFAULT_MEMORY_BUDGET,
        disk_budget: int | None = DEFAULT_DISK_BUDGET,
        max_pending_age: float = 60.0,
        max_pending: int = 200_000,
    ) -> None:
        _check_geometry(resolution, vertical_resolution, subgrid_side, levels, max_tiles)
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
        #: tile key -> tile number (creation order); ``_keys[number]`` is the key
        self._slots: dict[tuple[int, int], int] = {}
        self._keys: list[tuple[int, int]] = []
        cap = 4
        self._version = np.zeros(cap, np.int64)
        #: the version of each tile its storage holds (-1: none)
        self._stored = np.full(cap, -1, np.int64)
        #: bytes the storage holds for each tile
        self._stored_size = np.zeros(cap, np.int64)
        #: last update of every subgrid node, per level: ``(tiles, p, p)`` (-inf where empty)
        self._stimes = [np.full((cap, p, p), -np.inf) for p in self._per_tile()]
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
        #: At most this many tiles in all (None: no limit but the addressable area and the disk
        #: budget); soundings that would need more are dropped, counted and reported.
        self.max_tiles = None if max_tiles is None else int(max_tiles)
        self.memory_budget = int(memory_budget)
        self.disk_budget = None if disk_budget is None else int(disk_budget)
        #: Why soundings are being dropped (a budget exhausted, the storage failing), or None.
        self.overflow: str | None = None
        #: tiles written to and read back from the storage
        self.spills = 0
        self.loads = 0
        self._mem: MemoryStorage | None = MemoryStorage()
        self.max_pending_age = float(max_pending_age)
        self.max_pending = int(max_pending)
        self._init_intake()
        self._after_restore()

    def _init_intake(self) -> None:
        """Empty input buffers: soundings batched for :meth:`add_points`, and those pending
        outlier rejection (a cell's first few)."""
        self._buffer: list[tuple[FloatArray, float]] = []
        self._buffered = 0
        self._pending_pts = np.zeros((0, 3))
        self._pending_t = np.zeros(0)
        self._pending_ids = np.zeros(0, np.int64)
        self._next_id = 0
        #: With ``track_rejections``, the input positions (0 = first sounding ever added) of the
        #: soundings outlier rejection removed, one array per ingested batch (for measurements).
        self.track_rejections = False
        self.rejected_ids: list[npt.NDArray[np.int64]] = []
        #: tiles changed since :meth:`take_changed` was last called
        self._changed: set[tuple[int, int]] = set()

    def _after_restore(self) -> None:
        #: resident tiles (the tile store's cache), least recently used first: number -> (4, T*T)
        #: [count, sum, sumsq, time]; ``max_resident`` tiles at most
        self._cache: tilestore.TileCache[int, FloatArray] = tilestore.TileCache(
            name=lambda n: _tile_name(self._keys[n]), encode=self._encode_cells, decode=self._decode_cells,
            nbytes=lambda cells: self.tile_bytes, budget=lambda: self.max_resident * self.tile_bytes,
            min_resident=0, written=self._written, dropped=self._dropped, failed=self._failed,
            storage=self._mem, owner="bathymetry map")
        self._res: OrderedDict[int, FloatArray] = self._cache.resident
        #: per tile, its cells at level ``levels - 2`` (count, sum, sumsq, time): the two
        #: coarsest levels' subgrids are built from it without bringing the tile back (a cache,
        #: filled as tiles are ingested or read; not saved)
        self._summ_level = max(self.levels - 2, 0)
        ns = self.tile >> self._summ_level
        cap = int(np.asarray(self._version).shape[0])
        self._summ = np.zeros((cap, 4, ns, ns))
        self._summ_ok = np.zeros(cap, bool)
        self._ext: Storage | None = None
        self._free: list[FloatArray] = []
        #: the sender must look at every tile (after a restore, or a map of an older version)
        self._changed_all = True
        old = self.__dict__.pop("_v1_arrays", None)
        if old is not None:  # a version-1 map: its tiles go to a memory storage, its index is built
            self._ext = None
            n = len(self._keys)
            self.memory_budget = DEFAULT_MEMORY_BUDGET
            self.disk_budget = DEFAULT_DISK_BUDGET
            self.overflow, self.spills, self.loads = None, 0, 0
            self._changed = set()
            cap = max(4, n)
            self._stored = np.full(cap, -1, np.int64)
            self._stored_size = np.zeros(cap, np.int64)
            self._version = _grow(np.asarray(self._version)[:n], cap, 0)
            self._stimes = [np.full((cap, p, p), -np.inf) for p in self._per_tile()]
            self._summ = np.zeros((cap, *self._summ.shape[1:]))
            self._summ_ok = np.zeros(cap, bool)
            for i in range(n):
                cells = np.stack([np.asarray(old["_count"][i], np.float64), old["_sum"][i], old["_sumsq"][i],
                                  old["_time"][i]])
                self._index_times(np.array([i]), cells[None, 3])
                self._cache.write(i, cells)

    # ------------------------------------------------------------------------- structure

    def _per_tile(self) -> list[int]:
        return [self.tile // (self.subgrid_side << lv) for lv in range(self.levels)]

    @property
    def tiles(self) -> list[tuple[int, int]]:
        """Tile keys ``(tx, ty)`` in creation order (a tile covers ``tile`` level-0 cells a side)."""
        self.flush()
        return list(self._keys)

    def has_tile(self, key: tuple[int, int]) -> bool:
        return key in self._slots

    @property
    def tile_bytes(self) -> int:
        """Memory one resident tile holds."""
        return 4 * 8 * self._tt

    @property
    def max_resident(self) -> int:
        """Tiles kept in memory at most: half of ``memory_budget`` less the index and the coarse
        summaries (the other half is for the batch in flight, snapshots and the sender's
        bookkeeping)."""
        index = self._version.nbytes * 3 + sum(a.nbytes for a in self._stimes) + self._summ.nbytes
        return max(4, (self.memory_budget // 2 - index) // self.tile_bytes)

    @property
    def resident(self) -> int:
        """Tiles in memory now."""
        return len(self._res)

    def nbytes(self) -> int:
        """Memory held by the resident tiles and the index."""
        index = self._version.nbytes * 3 + sum(a.nbytes for a in self._stimes) + self._summ.nbytes
        return int(len(self._res) * self.tile_bytes + index)

    def disk_bytes(self) -> int:
        """Bytes the storage holds for this map's tiles."""
        return int(self._stored_size[: len(self._keys)].sum())

    @property
    def storage(self) -> Storage:
        st = self._ext if self._ext is not None else self._mem
        if st is None:
            raise CoexError("the map's tiles are in a storage that is not attached "
                            "(restore the node with its NodeStore)")
        return st

    def attach_storage(self, storage: Storage) -> None:
        """Keep spilled tiles in ``storage`` from now on (what the memory storage held moves there)."""
        if self._mem is not None:
            for key in self._mem.keys():
                data = self._mem.get(key)
                if data is not None:
                    storage.put(key, data)
        self._mem = None
        self._ext = storage
        self._cache.storage = storage

    def sync(self) -> None:
        """Write every resident tile that changed since it was last stored (before a snapshot)."""
        self.flush()
        self._cache.sync()

    def _before_save(self) -> None:
        self.sync()

    def take_changed(self) -> set[tuple[int, int]] | None:
        """Tiles changed since the last call (None: look at every tile, e.g. after a restore)."""
        self.flush()
        if self._changed_all:
            self._changed_all = False
            self._changed = set()
            return None
        out, self._changed = self._changed, set()
        return out

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

    def _new_tile(self, key: tuple[int, int]) -> int:
        n = len(self._keys)
        if n == self._version.shape[0]:
            cap = 2 * n
            self._version = _grow(self._version, cap, 0)
            self._stored = _grow(self._stored, cap, -1)
            self._stored_size = _grow(self._stored_size, cap, 0)
            self._stimes = [_grow(a, cap, -np.inf) for a in self._stimes]
            self._summ = _grow(self._summ, cap, 0.0)
            self._summ_ok = _grow(self._summ_ok, cap, False)
        self._slots[key] = n
        self._keys.append(key)
        self._grow_root(*key)
        return n

    def _blank(self) -> FloatArray:
        cells = self._free.pop() if self._free else np.empty((4, self._tt))
        cells[:3] = 0.0
        cells[3] = -np.inf
        return cells

    def _cells(self, n: int, protect: set[int] | frozenset[int] = frozenset()) -> FloatArray:
        """Tile ``n``'s cells, brought into memory if needed (others may leave)."""
        if n in self._cache or self._stored[n] >= 0:
            return self._cache.get(n, protect)
        return self._cache.add(n, self._blank(), protect)

    # The tile store's hooks: a tile's stored form (the count, in the smallest integer type that
    # holds it, and the sums, sums of squares and times), what a write and an eviction leave.

    def _encode_cells(self, n: int, cells: FloatArray) -> bytes:
        return tilestore.encode({"count": cells[0].astype(np.int64), "stats": cells[1:]})

    def _decode_cells(self, n: int, data: bytes) -> FloatArray:
        try:
            arrays = tilestore.decode(data)
            cells = self._blank()
            cells[0] = arrays["count"]
            cells[1:] = arrays["stats"]
        except (ValueError, KeyError) as exc:
            raise StateError(f"bathymetry map: stored tile {self._keys[n]} is damaged ({exc})") from exc
        self.loads += 1
        if not self._summ_ok[n]:
            self._summarise(np.array([n]), cells[None, 0], cells[None, 1], cells[None, 2], cells[None, 3])
        return cells

    def _written(self, n: int, cells: FloatArray, size: int) -> None:
        self._stored[n] = self._version[n]
        self._stored_size[n] = size
        self.spills += 1

    def _dropped(self, cells: FloatArray) -> None:
        if len(self._free) < 4:
            self._free.append(cells)

    def _failed(self, exc: Exception) -> None:
        # a full disk: the tile stays in memory (the cache keeps it), say so, never crash
        self.overflow = f"the map's storage failed ({exc}): new ground is not mapped"

    def _room(self) -> int:
        """New tiles allowed now (the tile cap and the disk budget)."""
        room = 1 << 62
        if self.max_tiles is not None:
            room = max(self.max_tiles - len(self._keys), 0)
            if room == 0:
                self.overflow = f"max_tiles ({self.max_tiles}) reached: new ground is not mapped"
        if self.disk_budget is not None and self._ext is not None:
            # about the size a tile takes on disk, measured on those written so far
            n = int(np.count_nonzero(self._stored[: len(self._keys)] >= 0))
            per = self.disk_bytes() / n if n else self.tile_bytes / 2
            fit = int((self.disk_budget - self.disk_bytes()) // max(per, 1.0)) - len(self._res)
            if fit <= 0:
                self.overflow = (f"disk budget ({self.disk_budget / 2**20:.0f} MB) reached: "
                                 "new ground is not mapped")
            room = min(room, max(fit, 0))
        if self.overflow is not None and self.overflow.startswith("the map's storage failed"):
            room = 0
        return room

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
        keys = list(zip(uniq_x.tolist(), uniq_y.tolist(), strict=True))
        new = np.array([k not in self._slots for k in keys])
        if new.any():
            room = self._room()
            if int(new.sum()) > room:
                # A budget is exhausted: soundings that need new tiles are dropped (counted and
                # reported in ``overflow``; the sender tells topside).
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
                keys = list(zip(uniq_x.tolist(), uniq_y.tolist(), strict=True))
        tmax = float(times.max())
        limit = max(1, self.max_resident // 2)
        if len(keys) <= limit:
            st = self._ingest_tiles(keys, inv, col, row, z, times, tmax, force)
        else:  # scattered soundings: a few tiles at a time, so that they fit in memory
            st = np.empty(z.size, np.int8)
            for c in range(0, len(keys), limit):
                sel = np.flatnonzero((inv >= c) & (inv < c + limit))
                st[sel] = self._ingest_tiles(keys[c:c + limit], inv[sel] - c, col[sel], row[sel], z[sel],
                                             times[sel], tmax, force)
        status[ok] = st
        return status

    def _ingest_tiles(self, keys: list[tuple[int, int]], inv: IntArray, col: IntArray, row: IntArray,
                      z: FloatArray, times: FloatArray, tmax: float, force: bool) -> npt.NDArray[np.int8]:
        ns = np.array([self._slots[k] if k in self._slots else self._new_tile(k) for k in keys], np.int64)
        m = ns.size
        protect = set(ns.tolist())
        tt = self._tt
        cnt, sm, ssq, tim = (np.empty((m, tt)) for _ in range(4))
        tiles = []
        for i, n in enumerate(ns.tolist()):
            cells = self._cells(n, protect)
            tiles.append(cells)
            cnt[i], sm[i], ssq[i], tim[i] = cells
        t = self.tile
        tx = np.array([k[0] for k in keys], np.int64)[inv]
        ty = np.array([k[1] for k in keys], np.int64)[inv]
        local = ((row - ty * t) << self._shift) + (col - tx * t)
        flat = inv * tt + local
        size = m * tt
        n_b = np.bincount(flat, minlength=size)
        s_b = np.bincount(flat, weights=z, minlength=size)
        ss_b = np.bincount(flat, weights=z * z, minlength=size)
        keep = np.ones(z.size, bool)
        hold = np.zeros(z.size, bool)
        if self.outlier_rejection:
            keep, judged = screen(m, self.tile, cnt.ravel(), sm.ravel(), ssq.ravel(), flat, local, inv, z,
                                  n_b, s_b, ss_b, min_count=self.min_count,
                                  threshold=self.outlier_threshold, k=self.outlier_k)
            if not force:
                hold = ~judged & (times > tmax - self.max_pending_age)
                if hold.sum() > self.max_pending:
                    cut = np.sort(times[hold])[-self.max_pending]
                    hold &= times >= cut
            self.rejected += int(np.count_nonzero(~keep))
            keep &= ~hold
            if not keep.all():
                w = keep.astype(np.float64)
                n_b = np.bincount(flat, weights=w, minlength=size).astype(np.int64)
                s_b = np.bincount(flat, weights=z * w, minlength=size)
                ss_b = np.bincount(flat, weights=z * z * w, minlength=size)
        cnt += n_b.reshape(m, tt)
        sm += s_b.reshape(m, tt)
        ssq += ss_b.reshape(m, tt)
        np.maximum.at(tim.reshape(-1), flat[keep], times[keep])
        for i, cells in enumerate(tiles):
            cells[0], cells[1], cells[2], cells[3] = cnt[i], sm[i], ssq[i], tim[i]
        self._version[ns] += 1
        for n in ns.tolist():
            self._cache.touch(n)
        self._index_times(ns, tim)
        self._summarise(ns, cnt, sm, ssq, tim)
        self._changed.update(keys)
        added = int(np.count_nonzero(keep))
        self.accepted += added
        if added:
            self.last_update = max(self.last_update, float(times[keep].max()))
        return np.where(keep, _ADDED, np.where(hold, _HELD, _REJECTED)).astype(np.int8)

    def _summarise(self, ns: IntArray, cnt: FloatArray, sm: FloatArray, ssq: FloatArray, tim: FloatArray) -> None:
        m, f = ns.size, 1 << self._summ_level
        k = self.tile >> self._summ_level
        out = self._summ
        out[ns, 0] = _pool(cnt, m, k, f, np.add)
        out[ns, 1] = _pool(sm, m, k, f, np.add)
        out[ns, 2] = _pool(ssq, m, k, f, np.add)
        out[ns, 3] = _pool(tim, m, k, f, np.maximum)
        self._summ_ok[ns] = True

    def _index_times(self, ns: IntArray, tim: FloatArray) -> None:
        """Update the index's last update of every subgrid node of tiles ``ns`` (times ``(m, T*T)``)."""
        m, side = ns.size, self.subgrid_side
        p = self.tile // side
        cur = _pool(tim, m, p, side, np.maximum)
        self._stimes[0][ns] = cur
        for lv in range(1, self.levels):
            p //= 2
            cur = _pool(cur, m, p, 2, np.maximum)
            self._stimes[lv][ns] = cur

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
        cells = self._cells(self._slots[key])
        t = self.tile
        f = 1 << level
        n = t >> level
        shape = (n, f, n, f)
        cnt = cells[0].reshape(shape).sum(axis=(1, 3)).astype(np.int64)
        sm = cells[1].reshape(shape).sum(axis=(1, 3))
        ss = cells[2].reshape(shape).sum(axis=(1, 3))
        tm = cells[3].reshape(shape).max(axis=(1, 3))
        return cnt, sm, ss, tm

    def subgrid_times(self, key: tuple[int, int], level: int) -> FloatArray:
        """Last update of each subgrid node of a tile at ``level`` (``-inf`` where empty), from the
        index (the tile stays where it is)."""
        self.flush()
        view: FloatArray = self._stimes[level][self._slots[key]]
        view.flags.writeable = False
        return view

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
        if level >= self._summ_level and self._summ_ok[s]:
            f = 1 << (level - self._summ_level)
            span = side * f
            part = self._summ[s][:, b * span:(b + 1) * span, a * span:(a + 1) * span]
            part = part.reshape(4, side, f, side, f)
            cnt = part[0].sum(axis=(1, 3)).astype(np.int64)
            sm, ss = part[1].sum(axis=(1, 3)), part[2].sum(axis=(1, 3))
            upd = float(part[3].max())
            return _block(cnt, sm, ss, upd)
        cells = self._cells(s)
        f = 1 << level
        span = side * f
        t = self.tile
        sl = np.s_[b * span:(b + 1) * span, a * span:(a + 1) * span]
        shape = (side, f, side, f)
        cnt = cells[0].reshape(t, t)[sl].reshape(shape).sum(axis=(1, 3)).astype(np.int64)
        sm = cells[1].reshape(t, t)[sl].reshape(shape).sum(axis=(1, 3))
        ss = cells[2].reshape(t, t)[sl].reshape(shape).sum(axis=(1, 3))
        upd = float(cells[3].reshape(t, t)[sl].max())
        return _block(cnt, sm, ss, upd)

    def grid(self, level: int = 0) -> tuple[FloatArray, float, float]:
        """The whole map at ``level`` as one array (NaN where empty), row 0 = south, and the
        (x, y) of its south-west corner (small maps: it is one array in memory)."""
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

    def window(self, x0: float, y0: float, x1: float, y1: float,
               level: int = 0) -> tuple[FloatArray, FloatArray, float, float]:
        """The cells of ``[x0, x1) x [y0, y1)`` (metres) at ``level``, snapped outwards to the
        level's cells: ``(mean, updated, wx0, wy0)``, mean elevation (NaN where empty) and last
        update (``-inf`` where empty), row 0 = south, and the south-west corner of the window.
        Only the tiles it covers are read."""
        self.flush()
        cell = self.resolution * (1 << level)
        c0, c1 = math.floor(x0 / cell), max(math.ceil(x1 / cell), math.floor(x0 / cell) + 1)
        r0, r1 = math.floor(y0 / cell), max(math.ceil(y1 / cell), math.floor(y0 / cell) + 1)
        mean = np.full((r1 - r0, c1 - c0), np.nan)
        upd = np.full((r1 - r0, c1 - c0), -np.inf)
        n = self.tile >> level
        for ty in range(r0 // n, (r1 - 1) // n + 1):
            for tx in range(c0 // n, (c1 - 1) // n + 1):
                if (tx, ty) not in self._slots:
                    continue
                cnt, sm, _, tm = self.level_stats((tx, ty), level)
                # the part of the tile inside the window, in tile and window coordinates
                a0, a1 = max(c0, tx * n), min(c1, (tx + 1) * n)
                b0, b1 = max(r0, ty * n), min(r1, (ty + 1) * n)
                part = np.s_[b0 - ty * n:b1 - ty * n, a0 - tx * n:a1 - tx * n]
                c = cnt[part]
                with np.errstate(invalid="ignore", divide="ignore"):
                    mean[b0 - r0:b1 - r0, a0 - c0:a1 - c0] = np.where(c > 0, sm[part] / np.maximum(c, 1), np.nan)
                upd[b0 - r0:b1 - r0, a0 - c0:a1 - c0] = np.where(c > 0, tm[part], -np.inf)
        return mean, upd, c0 * cell, r0 * cell

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


def _block(cnt: IntArray, sm: FloatArray, ss: FloatArray, upd: float) -> LevelBlock:
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(cnt > 0, sm / np.maximum(cnt, 1), np.nan)
        var = np.where(cnt > 0, ss / np.maximum(cnt, 1) - mean * mean, np.nan)
    return LevelBlock(cnt, mean, np.sqrt(np.maximum(var, 0.0)), upd)
