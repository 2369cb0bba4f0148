"""The topside side: levels held as tiles (spilled to storage beyond a memory budget), drawn
overviews, per-subgrid holdings and ages, region requests and retries.

Every level is cut into *receiver tiles* of ``tile_subgrids x tile_subgrids`` subgrids (16 x 16
subgrids of 8 x 8 cells: 128 x 128 cells). A tile holds the cells (float64, NaN where nothing)
and, per subgrid, its stamp, its arrival time and whether it is held. Tiles stay in memory up to
``memory_budget`` bytes; beyond it the least recently used one is written to the receiver's
:class:`~coex_core.storage.Storage` (``tile/<level>/<tx>/<ty>``, the plugin's tile store
:mod:`.tilestore`, as the vehicle's map: the tile's arrays, zstd at level ``tile_compression``)
and read back when needed. Each level also keeps one drawn
*overview* array of at most ``max_mosaic_cells`` cells: the level at full resolution while it
fits, else block means over 2 x 2, 4 x 4 ... cells (``meta["step"]`` of its product), so a level
of any extent is drawn in bounded memory and nothing held is left out. :meth:`window` reads what
is on screen (or a tile of an export) from the tiles.

The tiles and their stored form are in :mod:`.tiles`, the overviews in :mod:`.overview`, a
tracked region request in :mod:`.regions` (its states and retries are the core tracker's,
:mod:`coex_core.tracker`), what version 1 saved in :mod:`.legacy`.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from coex import (
    STAMP_MODULUS,
    ConfigError,
    MemoryStorage,
    ModalityReceiver,
    Product,
    RequestRejected,
    StateError,
    Storage,
    merged_config,
    persistent,
)
from coex.messages import (
    MapMetadata,
    MapRoiReply,
    MapRoiRequest,
    Message,
    SubgridMessage,
)
from coex.tracker import Event

from .legacy import import_v1
from .overview import CHUNK, Overview, blocks_from, cells_from, window_blocks
from .predicted_rx import PredictedInput
from .regions import Region, plan
from .tiles import LevelIndex, LevelStats, Tile, decode_tile, encode_tile, same_storage, tile_name
from .tilestore import TileCache

__all__ = ["BathymetryReceiver", "RECEIVER_DEFAULTS", "Region"]

FloatArray = npt.NDArray[np.float64]

#: Receiver configuration keys and defaults.
RECEIVER_DEFAULTS: dict[str, Any] = {
    "resolution": 1.0,
    "subgrid_side": 8,
    "levels": 5,
    "origin_lat": None,
    "origin_lon": None,
    "request_timeout": 60.0,
    "subgrid_wait": 4.0,
    "standing_recheck": 1800.0,
    "auto_fill": True,
    "auto_fill_interval": 300.0,
    "max_regions": 256,
    "max_requests_per_poll": 4,
    "max_mosaic_cells": 16 * 1024 * 1024,
    "memory_budget": 256 * 1024 * 1024,
    "tile_subgrids": 16,
    "tile_compression": 1,
}

#: Largest array :meth:`BathymetryReceiver.window` returns by default (cells).
WINDOW_CELLS = 4 * 1024 * 1024



def _upgrade_receiver(fields: dict[str, Any], saved: int) -> dict[str, Any]:
    """Version 1 held one ``Held`` per subgrid and one dense mosaic per level: keep them aside
    for :meth:`BathymetryReceiver._after_restore`, which moves them into tiles. Version 3
    stores its tiles and overview chunks in the tile store's format (:mod:`.tilestore`); the
    ``CXRT`` tiles and ``CXOV`` chunks of version 2 are read as they are (same fields)."""
    if saved < 2:
        fields["_legacy"] = (fields.pop("held", {}), fields.pop("_mosaics", {}),
                             fields.pop("off_mosaic", set()))
        fields["config"] = {**RECEIVER_DEFAULTS, **dict(fields.get("config") or {})}
    if saved < 4:  # version 4 keeps each level's vertical resolution (predicted subgrids)
        fields.update(_vres={}, set_aside=0, resolved=0)
    return fields


@persistent("bathymetry.Receiver", version=4, upgrade=_upgrade_receiver,
            transient=("_tiles", "_cache", "_overviews", "_ov_dirty", "_waiting"))
class BathymetryReceiver(PredictedInput, ModalityReceiver):
    """Assembles every level as subgrids arrive and keeps, per subgrid, its stamp and arrival time.

    Requests: :meth:`request_region` (stamps of what topside holds, the implicit ack; the vehicle
    re-sends newer or missing subgrids) and :meth:`request_gaps` (everything missing in a region,
    one bitmap). Each region is re-requested after ``request_timeout`` (plus ``subgrid_wait`` per
    subgrid the vehicle said it queued) until the vehicle answers that it has nothing newer, so
    lost requests, replies and subgrids are all recovered. A region the vehicle has not surveyed
    all of stands there (``MapRoiReply.waiting``): its subgrids follow when they are surveyed, and
    it is shown as waiting, and asked again only after ``standing_recheck`` seconds (the vehicle's
    ``standing_expiry``). With ``auto_fill`` the receiver asks
    for the gaps of every level over the whole map whenever the vehicle reports its background
    queue empty (at most every ``auto_fill_interval`` seconds, and again only when the map changed
    or the last round found gaps). ``poll`` emits at most ``max_requests_per_poll`` requests,
    coarsest level first.

    Memory (a day-long survey: 100 km² at 1 m): the levels are held as tiles of
    ``tile_subgrids`` x ``tile_subgrids`` subgrids; at most ``memory_budget`` bytes of tiles
    (default 256 MB, :meth:`resident_bytes`) stay in memory, the least recently used beyond it
    go to the storage the node attaches (:meth:`attach_storage`; by default a
    :class:`~coex_core.storage.MemoryStorage` saved with the receiver), compressed by the tile
    store's codec at zstd level ``tile_compression`` (0: not compressed; a zlib level before
    the tile store, same range). Each level's drawn overview (its product) holds at most
    ``max_mosaic_cells`` cells (8 bytes each). A storage attached, the receiver's saved state
    holds the tile index and summaries only; :meth:`sync_storage` (called before every
    snapshot) writes what the storage lacks.
    """

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        cfg = merged_config(config, RECEIVER_DEFAULTS, "bathymetry receiver")
        self.config = cfg
        self.request_timeout = float(cfg["request_timeout"])
        self.subgrid_wait = float(cfg["subgrid_wait"])
        self.standing_recheck = float(cfg["standing_recheck"])
        self.auto_fill = bool(cfg["auto_fill"])
        self.auto_fill_interval = float(cfg["auto_fill_interval"])
        self.max_regions = int(cfg["max_regions"])
        self.max_requests_per_poll = int(cfg["max_requests_per_poll"])
        if self.max_requests_per_poll < 1:
            raise ConfigError("max_requests_per_poll must be at least 1")
        if self.request_timeout <= 0:
            raise ConfigError("request_timeout must be positive")
        self.metadata: MapMetadata | None = None
        self._versions: dict[int, int] = {}
        self._geometry: dict[int, tuple[float, int]] = {}
        #: each level's vertical resolution (the parent level's is a predicted subgrid's)
        self._vres: dict[int, float] = {}
        self.set_aside = 0
        self.resolved = 0
        self.regions: list[Region] = []
        self._by_id: dict[int, Region] = {}
        self._next_id = 0
        self._next_auto = -math.inf
        self._auto_stamp: int | None = None
        self._auto_found = False
        self.duplicates = 0
        self._init_tiles(cfg)

    def _init_tiles(self, cfg: Mapping[str, Any]) -> None:
        self.max_mosaic_cells = int(cfg["max_mosaic_cells"])
        self.memory_budget = int(cfg["memory_budget"])
        self.tile_subgrids = int(cfg["tile_subgrids"])
        self.tile_compression = int(cfg["tile_compression"])
        if self.max_mosaic_cells < 64:
            raise ConfigError("max_mosaic_cells must be at least 64")
        if not 1 <= self.tile_subgrids <= 255:
            raise ConfigError("tile_subgrids must be within 1..255")
        if not 0 <= self.tile_compression <= 9:
            raise ConfigError("tile_compression must be a compression level, 0..9 (0: none)")
        #: Subgrids that came with another geometry than the level's first one (ignored).
        self.mismatched = 0
        self._stats: dict[int, LevelStats] = {}
        self._index: dict[int, LevelIndex] = {}
        #: overview geometry as last written to an attached storage: level -> (step, ox0, oy0, nx, ny)
        self._overview_meta: dict[int, tuple[int, int, int, int, int]] = {}
        #: bytes of each overview chunk in that storage: (level, cx, cy) -> size
        self._ov_stored: dict[tuple[int, int, int], int] = {}
        # With the receiver's own MemoryStorage, the resident tiles and the overviews are saved
        # with its state (``_own_*`` are the same objects); with a storage the node attached,
        # the state holds the index only and the rest is in the storage.
        self._own_store: MemoryStorage | None = MemoryStorage()
        self._own_tiles: OrderedDict[tuple[int, int, int], Tile] = OrderedDict()
        self._own_overviews: dict[int, Overview] = {}
        self._after_restore()

    def _after_restore(self) -> None:
        self._init_waiting()
        legacy = self.__dict__.pop("_legacy", None)
        if legacy is not None:
            self._init_tiles(self.config)
            import_v1(self, *legacy)
            return
        self._ov_dirty: dict[int, set[tuple[int, int]]] = {}
        store: Storage | None
        if self._own_store is not None:
            store, resident = self._own_store, self._own_tiles
            self._overviews = self._own_overviews
        else:  # the tiles are in the node's storage: attach_storage reads the overviews back
            store, resident = None, OrderedDict()
            self._overviews = {}
        #: the resident tiles under ``memory_budget`` (the plugin's tile store)
        self._cache: TileCache[tuple[int, int, int], Tile] = TileCache(
            name=tile_name, encode=lambda key, t: encode_tile(t, self.tile_compression),
            decode=self._decode_tile, nbytes=lambda t: t.nbytes, budget=lambda: self.memory_budget,
            min_resident=1, written=self._written, storage=store, owner="bathymetry receiver",
            resident=resident, dirty=[k for k, t in resident.items() if t.dirty])
        self._tiles = self._cache.resident

    def _before_save(self) -> None:
        for key, t in self._own_tiles.items():  # saved with the state: whether the storage lacks it
            t.dirty = key in self._cache.dirty

    @property
    def _store(self) -> Storage | None:
        return self._cache.storage

    # ---------------------------------------------------------------------------- storage

    def attach_storage(self, storage: Storage) -> None:
        """Keep spilled tiles (and, for snapshots, the overviews) in ``storage`` from now on.
        What the receiver's own storage held moves there; a receiver restored from a snapshot
        taken with a storage attached reads its overviews back from it."""
        if same_storage(storage, self._store):
            self._cache.storage = storage
            return
        old = self._store
        if old is not None:
            for key in old.keys("tile/"):
                data = old.get(key)
                if data:
                    storage.put(key, data)
            for level, ov in self._overviews.items():
                self._ov_dirty[level] = ov.chunks()
            self._overview_meta = {}
            self._ov_stored = {}
        else:
            for level, (step, ox0, oy0, nx, ny) in self._overview_meta.items():
                ov = Overview(step)
                ov.include(ox0, ox0 + nx, oy0, oy0 + ny)
                prefix = f"ov/{level}/{step}/"
                for key in storage.keys(prefix):
                    data = storage.get(key)
                    if data:
                        cx, cy = (int(v) for v in key[len(prefix):].split("/"))
                        ov.paste_chunk(cx, cy, data, key)
                self._overviews[level] = ov
        self._cache.storage = storage
        self._own_store = None
        self._own_tiles = OrderedDict()
        self._own_overviews = {}

    def sync_storage(self) -> None:
        """Write the tiles and overview chunks changed since the last call to the attached
        storage (nothing with the receiver's own storage: they are saved with its state)."""
        store = self._store
        if store is None or self._own_store is not None:
            self._ov_dirty.clear()
            return
        self._cache.sync()
        for level, ov in self._overviews.items():
            meta = self._overview_meta.get(level)
            dirty = self._ov_dirty.get(level, set())
            if meta is not None and meta[0] != ov.step:
                for name in store.keys(f"ov/{level}/{meta[0]}/"):
                    store.put(name, b"")  # a coarser step replaced these
                self._ov_stored = {k: v for k, v in self._ov_stored.items() if k[0] != level}
                dirty = ov.chunks()
            for cx, cy in dirty:
                data = ov.encode_chunk(cx, cy, self.tile_compression)
                store.put(f"ov/{level}/{ov.step}/{cx}/{cy}", data)
                self._ov_stored[(level, cx, cy)] = len(data)
            self._overview_meta[level] = (ov.step, ov.ox0, ov.oy0, ov.nx, ov.ny)
        self._ov_dirty.clear()

    def resident_bytes(self) -> int:
        """Bytes of the tiles held in memory (at most ``memory_budget``, or one tile)."""
        return self._cache.nbytes

    def overview_bytes(self) -> int:
        """Bytes of the levels' drawn overviews (each at most ``max_mosaic_cells`` cells)."""
        return sum(ov.mean.nbytes + (0 if ov.count is None else ov.count.nbytes)
                   for ov in self._overviews.values())

    def disk_bytes(self) -> int:
        """Bytes the storage holds for this receiver: its tiles and overview chunks, as last
        written (counted as they are written, never read back)."""
        tiles = sum(int(ix.stored[:ix.n].sum()) for ix in self._index.values())
        return tiles + sum(self._ov_stored.values())

    def _tile(self, level: int, tx: int, ty: int, create: bool = False) -> Tile | None:
        """Tile (tx, ty) of ``level``, read back from storage if spilled; made when ``create``."""
        key = (level, tx, ty)
        if key in self._cache:
            return self._cache.get(key)
        index = self._index.get(level)
        row = None if index is None else index.pos.get((tx, ty))
        if row is not None:
            return self._cache.get(key)
        if not create:
            return None
        if index is None:
            index = self._index[level] = LevelIndex()
        index.add(tx, ty)
        side = self._geometry[level][1] if level in self._geometry else 0
        return self._cache.add(key, Tile(self.tile_subgrids, side))

    def _decode_tile(self, key: tuple[int, int, int], data: bytes) -> Tile:
        side = self._geometry[key[0]][1] if key[0] in self._geometry else 0
        return decode_tile(data, self.tile_subgrids, side, tile_name(key))

    def _written(self, key: tuple[int, int, int], t: Tile, size: int) -> None:
        """A tile was written: its summary in the index and the bytes stored follow."""
        index = self._index[key[0]]
        row = index.pos[(key[1], key[2])]
        index.summarise(row, t)
        index.stored[row] = size

    def _level_tiles(self, level: int, tx0: int | None = None, ty0: int | None = None,
                     tx1: int | None = None, ty1: int | None = None) -> Iterable[tuple[int, int, Tile]]:
        """The level's tiles (within the tile range, end exclusive, if given), read as needed."""
        index = self._index.get(level)
        if index is None:
            return
        keys = index.keys[:index.n]
        if tx0 is not None and ty0 is not None and tx1 is not None and ty1 is not None:
            if (tx1 - tx0) * (ty1 - ty0) <= index.n:
                cand = [(tx, ty) for ty in range(ty0, ty1) for tx in range(tx0, tx1) if (tx, ty) in index.pos]
            else:
                m = (keys[:, 0] >= tx0) & (keys[:, 0] < tx1) & (keys[:, 1] >= ty0) & (keys[:, 1] < ty1)
                cand = [(int(a), int(b)) for a, b in keys[m].tolist()]
        else:
            cand = [(int(a), int(b)) for a, b in keys.tolist()]
        for tx, ty in cand:
            t = self._tile(level, tx, ty)
            if t is not None:
                yield tx, ty, t

    # ---------------------------------------------------------------------------- receive

    def receive(self, message: Message, now: float) -> list[Product]:
        if isinstance(message, SubgridMessage):
            return self._subgrid(message, now)
        if isinstance(message, MapMetadata):
            self.metadata = message
            # Gap filling when the background is done, again only if the map changed since or
            # the last round found gaps.
            fresh = message.stamp != self._auto_stamp or self._auto_found
            if self.auto_fill and message.pending == 0 and now >= self._next_auto and fresh:
                if self._schedule_auto_fill(message):
                    self._next_auto = now + self.auto_fill_interval
                    self._auto_stamp = message.stamp
                    self._auto_found = False
            return []
        if isinstance(message, MapRoiReply):
            # A reply to any copy of a region's request counts: on a TDMA link the answer often
            # arrives after the request was retried under a new id (the retry timer is shorter
            # than a cycle), and an answer to an older copy, which listed no more than topside
            # holds now, is as good ("nothing" then is nothing now).
            region = self._by_id.get(message.request_id)
            if region is not None and not region.done:
                region.queued = message.queued
                region.waiting = message.waiting
                if message.queued == 0 and message.waiting == 0:
                    region.track.apply(Event.ACCEPT, now)
                elif message.queued == 0:  # it stands on the vehicle: the data follows when surveyed
                    region.track.apply(Event.STAND, now, due=now + self.standing_recheck)
                else:
                    self._auto_found |= region.auto
                    region.track.apply(Event.STAND, now,
                                       due=now + self.request_timeout + self.subgrid_wait * message.queued)
            return []
        return []

    def _hold(self, level: int, ix: int, iy: int, stamp: float, values: FloatArray, received: float,
              draw: bool) -> None:
        n = self.tile_subgrids
        tx, lx = divmod(ix, n)
        ty, ly = divmod(iy, n)
        if level not in self._stats:
            self._stats[level] = LevelStats()
        tile = self._tile(level, tx, ty, create=True)
        assert tile is not None
        self._put(level, tile, ix, iy, lx, ly, stamp, values, received, draw=draw)

    def _put(self, level: int, tile: Tile, ix: int, iy: int, lx: int, ly: int, stamp: float,
             values: FloatArray, now: float, draw: bool) -> None:
        side = values.shape[0]
        r, c = ly * side, lx * side
        block = tile.values[r:r + side, c:c + side]
        st = self._stats[level]
        cells = int(np.count_nonzero(values == values))  # not NaN
        old: FloatArray | None = None
        if tile.held[ly, lx]:
            old = block.copy()
            st.cells += cells - int(np.count_nonzero(~np.isnan(old)))
            if tile.stamp[ly, lx] <= st.oldest or tile.received[ly, lx] <= st.oldest_rx:
                st.stale = True
        else:
            if st.subgrids == 0:
                st.ix0, st.iy0, st.ix1, st.iy1 = ix, iy, ix + 1, iy + 1
            else:
                st.ix0, st.iy0 = min(st.ix0, ix), min(st.iy0, iy)
                st.ix1, st.iy1 = max(st.ix1, ix + 1), max(st.iy1, iy + 1)
            st.subgrids += 1
            st.cells += cells
            tile.held[ly, lx] = True
        block[...] = values
        tile.stamp[ly, lx] = stamp
        tile.received[ly, lx] = now
        self._cache.touch((level, ix // self.tile_subgrids, iy // self.tile_subgrids))
        st.newest = max(st.newest, stamp)
        st.oldest = min(st.oldest, stamp)
        st.oldest_rx = min(st.oldest_rx, now)
        if cells:
            flat = values.ravel()
            lo, hi = float(np.fmin.reduce(flat)), float(np.fmax.reduce(flat))  # NaN ignored
            if lo < st.zmin:
                st.zmin = lo
            if hi > st.zmax:
                st.zmax = hi
        if draw:
            self._draw(level, ix * side, iy * side, values, old)

    def _draw(self, level: int, gx: int, gy: int, values: FloatArray, old: FloatArray | None) -> None:
        ov = self._overviews.get(level)
        if ov is None:
            ov = self._overviews[level] = Overview()
        side = values.shape[0]
        a, b, c, d = ov.span(gx, gy, side)
        if not ov.fits(a, b, c, d, self.max_mosaic_cells):
            # Too large to draw cell by cell: coarser until it fits (a far-away or bogus subgrid
            # too: it is drawn, small, never left out).
            while not ov.fits(a, b, c, d, self.max_mosaic_cells):
                ov.coarsen()
                a, b, c, d = ov.span(gx, gy, side)
        ov.include(a, b, c, d)
        ov.draw(gx, gy, values, old)
        dirty = self._ov_dirty.setdefault(level, set())
        for cy in range(c // CHUNK, (d - 1) // CHUNK + 1):
            for cx in range(a // CHUNK, (b - 1) // CHUNK + 1):
                dirty.add((cx, cy))

    def forget(self, level: int, ix: int, iy: int) -> bool:
        """Drop a held subgrid (a bad one, or to ask for it again: the next region or gap request
        lacks it). False if it was not held."""
        n = self.tile_subgrids
        tx, lx = divmod(ix, n)
        ty, ly = divmod(iy, n)
        tile = self._tile(level, tx, ty)
        if tile is None or not tile.held[ly, lx]:
            return False
        side = self._geometry[level][1]
        r, c = ly * side, lx * side
        block = tile.values[r:r + side, c:c + side]
        old = block.copy()
        st = self._stats[level]
        st.subgrids -= 1
        st.cells -= int(np.count_nonzero(~np.isnan(old)))
        st.stale = True
        block[...] = np.nan
        tile.held[ly, lx] = False
        tile.stamp[ly, lx] = tile.received[ly, lx] = 0.0
        self._cache.touch((level, tx, ty))
        self._draw(level, ix * side, iy * side, np.full((side, side), np.nan), old)
        self._versions[level] = self._versions.get(level, 0) + 1
        return True

    # ---------------------------------------------------------------------------- products

    def _overview(self, level: int) -> Overview:
        ov = self._overviews.get(level)
        if ov is None and level in self._overview_meta and self._store is None:
            raise StateError("bathymetry receiver: its levels are in the node's storage, which is "
                             "not attached (Node.attach_storage; NodeStore.restore does it)")
        if ov is None:
            raise KeyError(level)
        return ov

    def level_product(self, level: int, now: float | None = None) -> Product:
        """Level ``level`` as one array (row 0 = south, NaN where nothing is held) of at most
        ``max_mosaic_cells`` cells: the level's own cells while they fit, else means of
        ``meta["step"] x meta["step"]`` cells (a decimated overview; :meth:`window` reads any part
        at full resolution). ``meta``: ``level``, ``cell_size`` (of the array's cells),
        ``step``, ``level_cell`` (the level's cell size), the south-west corner ``x0``, ``y0``,
        ``subgrids``, ``cells`` (held cells), ``newest``, ``zmin``/``zmax`` (depth range
        received), the origin, and with ``now`` ``oldest_age`` (seconds since the longest-held
        subgrid arrived)."""
        ov = self._overview(level)
        cell, _ = self._geometry[level]
        st = self._stats[level]
        k = ov.step
        lat, lon = self.origin()
        meta: dict[str, Any] = {
            "level": level,
            "cell_size": cell * k,
            "step": k,
            "level_cell": cell,
            "x0": ov.ox0 * k * cell,
            "y0": ov.oy0 * k * cell,
            "subgrids": st.subgrids,
            "cells": st.cells,
            "newest": st.newest if st.subgrids else 0.0,
            "origin_lat": lat,
            "origin_lon": lon,
        }
        if st.zmin <= st.zmax:
            meta["zmin"], meta["zmax"] = st.zmin, st.zmax
        if now is not None:
            self._refresh(level)
            meta["oldest_age"] = now - st.oldest_rx if st.subgrids else 0.0
        return Product("map-level", f"level-{level}", self._versions.get(level, 0), ov.mean, meta)

    def products(self) -> list[Product]:
        levels = set(self._overviews) | set(self._overview_meta)
        return [self.level_product(k) for k in sorted(levels)]

    def levels(self) -> list[int]:
        """The levels of which something is held, finest first."""
        return sorted(k for k, st in self._stats.items() if st.subgrids)

    def geometry(self, level: int) -> tuple[float, int] | None:
        """``(cell size in m, subgrid side in cells)`` of a level, once a subgrid of it came."""
        return self._geometry.get(level)

    def level_version(self, level: int) -> int:
        """Changes whenever the level does (the version of its product)."""
        return self._versions.get(level, 0)

    def origin(self) -> tuple[float, float]:
        lat, lon = self.config["origin_lat"], self.config["origin_lon"]
        if lat is None and self.metadata is not None:
            lat = self.metadata.origin_lat
        if lon is None and self.metadata is not None:
            lon = self.metadata.origin_lon
        return float(lat or 0.0), float(lon or 0.0)

    def _refresh(self, level: int) -> None:
        """Recompute a level's newest and oldest stamps and oldest arrival, if stale."""
        st = self._stats[level]
        if not st.stale:
            return
        index = self._index.get(level)
        if index is not None:
            for (lv, tx, ty), t in self._tiles.items():
                if lv == level and (lv, tx, ty) in self._cache.dirty:
                    index.summarise(index.pos[(tx, ty)], t)
            m = index.count[:index.n] > 0
            if m.any():
                st.newest = float(index.newest[:index.n][m].max())
                st.oldest = float(index.oldest[:index.n][m].min())
                st.oldest_rx = float(index.oldest_rx[:index.n][m].min())
            else:
                st.newest, st.oldest, st.oldest_rx = -math.inf, math.inf, math.inf
        st.stale = False

    def level_summary(self, level: int) -> dict[str, Any] | None:
        """What a level holds, without reading its tiles: ``subgrids``, ``cells`` (held cells),
        ``newest`` and ``oldest`` stamp (seconds), ``oldest_received``, ``extent`` (subgrid
        indices ``(ix0, iy0, ix1, iy1)``, end exclusive, of everything received), ``cell``,
        ``side``, ``zmin``/``zmax``. None before any subgrid of it."""
        st = self._stats.get(level)
        geometry = self._geometry.get(level)
        if st is None or geometry is None:
            return None
        self._refresh(level)
        held = st.subgrids > 0
        return {"subgrids": st.subgrids, "cells": st.cells,
                "newest": st.newest if held else None, "oldest": st.oldest if held else None,
                "oldest_received": st.oldest_rx if held else None,
                "extent": (st.ix0, st.iy0, st.ix1, st.iy1) if held else None,
                "cell": geometry[0], "side": geometry[1],
                "zmin": st.zmin if st.zmin <= st.zmax else None,
                "zmax": st.zmax if st.zmin <= st.zmax else None}

    def held_subgrids(self, level: int) -> tuple[npt.NDArray[np.int64], FloatArray, FloatArray]:
        """Every subgrid held at ``level``: ``(keys, stamps, received)``, keys an ``n x 2``
        array of ``(ix, iy)``, stamps and arrival times in seconds. Reads every tile of the
        level (from storage when spilled): for a whole big level prefer :meth:`coverage`."""
        n = self.tile_subgrids
        keys, stamps, received = [], [], []
        for tx, ty, t in self._level_tiles(level):
            ly, lx = np.nonzero(t.held)
            keys.append(np.column_stack([tx * n + lx, ty * n + ly]))
            stamps.append(t.stamp[ly, lx])
            received.append(t.received[ly, lx])
        if not keys:
            return np.zeros((0, 2), np.int64), np.zeros(0), np.zeros(0)
        return (np.concatenate(keys).astype(np.int64), np.concatenate(stamps), np.concatenate(received))

    def holdings(self, level: int) -> dict[tuple[int, int], int]:
        """``(ix, iy) -> stamp`` of every subgrid held at ``level`` (reads the whole level)."""
        keys, stamps, _ = self.held_subgrids(level)
        wire = (np.floor(stamps).astype(np.int64) % STAMP_MODULUS).tolist()
        return dict(zip(map(tuple, keys.tolist()), wire, strict=True))

    def coverage(self, level: int, max_blocks: int = 4096
                 ) -> tuple[int, npt.NDArray[np.int64], FloatArray]:
        """What a level holds, in at most ``max_blocks`` blocks: ``(span, keys, oldest)``, block
        ``(bx, by)`` of ``keys`` covering subgrids ``[bx*span, (bx+1)*span) x [by*span, (by+1)*span)``
        and holding something, ``oldest`` its oldest stamp (seconds). ``span`` is 1 (every held
        subgrid) when the level holds at most ``max_blocks`` subgrids, else a multiple of
        ``tile_subgrids`` (from the tile summaries, no tile read)."""
        st = self._stats.get(level)
        if st is None or st.subgrids == 0:
            return 1, np.zeros((0, 2), np.int64), np.zeros(0)
        if st.subgrids <= max_blocks:
            keys, stamps, _ = self.held_subgrids(level)
            return 1, keys, stamps
        index = self._index[level]
        for (lv, tx, ty), t in self._tiles.items():
            if lv == level and (lv, tx, ty) in self._cache.dirty:
                index.summarise(index.pos[(tx, ty)], t)
        m = index.count[:index.n] > 0
        keys, oldest = index.keys[:index.n][m], index.oldest[:index.n][m]
        shift = 0
        while True:
            uniq, inv = np.unique(keys >> shift, axis=0, return_inverse=True)
            if len(uniq) <= max(1, max_blocks):
                break
            shift += 1
        out = np.full(len(uniq), np.inf)
        np.minimum.at(out, inv.ravel(), oldest)
        return self.tile_subgrids << shift, uniq.astype(np.int64), out

    def age(self, level: int, ix: int, iy: int, now: float) -> float | None:
        """Seconds since the newest data in a held subgrid was measured (None if not held)."""
        if level not in self._geometry:
            return None
        n = self.tile_subgrids
        tx, lx = divmod(ix, n)
        ty, ly = divmod(iy, n)
        t = self._tile(level, tx, ty)
        if t is None or not t.held[ly, lx]:
            return None
        return now - float(t.stamp[ly, lx])

    def _region(self, level: int, x0: int, y0: int, w: int, h: int) -> tuple[npt.NDArray[np.bool_], FloatArray]:
        """Held flags and stamps (seconds) of subgrids ``[x0, x0+w) x [y0, y0+h)``, row 0 = y0."""
        held = np.zeros((h, w), bool)
        stamp = np.zeros((h, w))
        if level not in self._geometry:
            return held, stamp
        n = self.tile_subgrids
        for tx, ty, t in self._level_tiles(level, x0 // n, y0 // n, (x0 + w - 1) // n + 1,
                                           (y0 + h - 1) // n + 1):
            a, b = max(x0, tx * n), min(x0 + w, tx * n + n)
            c, d = max(y0, ty * n), min(y0 + h, ty * n + n)
            src = (slice(c - ty * n, d - ty * n), slice(a - tx * n, b - tx * n))
            dst = (slice(c - y0, d - y0), slice(a - x0, b - x0))
            held[dst] = t.held[src]
            stamp[dst] = t.stamp[src]
        return held, stamp

    def region_stamps(self, level: int, x0: int, y0: int, w: int, h: int) -> list[int | None]:
        """Per subgrid of the region, row-major (rows = y): the stamp held (wire form), or None."""
        held, stamp = self._region(level, x0, y0, w, h)
        wire = np.floor(stamp).astype(np.int64) % STAMP_MODULUS
        return [int(s) if k else None for k, s in zip(held.ravel().tolist(), wire.ravel().tolist(), strict=True)]

    def window(self, level: int, x_min: float, y_min: float, x_max: float, y_max: float,
               max_cells: int = WINDOW_CELLS) -> tuple[FloatArray, tuple[float, float, float]]:
        """The part of a level over ``[x_min, x_max) x [y_min, y_max)`` (metres): ``(array,
        (x0, y0, cell))``, row 0 = south, NaN where nothing is held, ``(x0, y0)`` its south-west
        corner and ``cell`` its cell size. At most ``max_cells`` cells: a larger window is
        decimated (the mean of the held cells of each ``2^j x 2^j`` block, blocks aligned on
        the level's grid, so a pan shows the same cells). Reads only the tiles it covers (or,
        when decimated at least as much as the level's overview, the overview)."""
        cell = (self._geometry.get(level) or self._geometry_for(level))[0]
        s, (bx0, by0, bx1, by1) = window_blocks(cell, x_min, y_min, x_max, y_max, max_cells)
        geo = (bx0 * s * cell, by0 * s * cell, s * cell)
        st = self._stats.get(level)
        if st is None or st.subgrids == 0:
            return np.full((by1 - by0, bx1 - bx0), np.nan), geo
        cx0, cy0, cx1, cy1 = bx0 * s, by0 * s, bx1 * s, by1 * s
        ov = self._overviews.get(level)
        if s > 1 and ov is not None and s % ov.step == 0 and ov.nx:
            k = ov.step
            return blocks_from(ov, cx0 // k, cy0 // k, cx1 // k, cy1 // k, s // k), geo
        size = self.tile_subgrids * self._geometry[level][1]
        tiles = self._level_tiles(level, cx0 // size, cy0 // size, (cx1 - 1) // size + 1, (cy1 - 1) // size + 1)
        return cells_from(((tx * size, ty * size, t.values) for tx, ty, t in tiles), cx0, cy0, cx1, cy1, s), geo

    # ---------------------------------------------------------------------------- requests

    def _geometry_for(self, level: int) -> tuple[float, int]:
        meta = self.metadata
        res = meta.resolution if meta else float(self.config["resolution"])
        side = meta.subgrid_side if meta else int(self.config["subgrid_side"])
        return res * (1 << level), side

    def subgrid_index(self, level: int, x: float, y: float) -> tuple[int, int]:
        """The subgrid holding point (x, y) at ``level``."""
        cell, side = self._geometry_for(level)
        return math.floor(x / (cell * side)), math.floor(y / (cell * side))

    def _add(self, region: Region) -> None:
        active = [r for r in self.regions if not r.done]
        if len(active) >= self.max_regions:
            raise RequestRejected(f"more than {self.max_regions} active region requests")
        self.regions = [*active, region]

    def request_region(self, level: int, x0: int, y0: int, w: int, h: int) -> list[Region]:
        """Ask for subgrids ``[x0, x0+w) x [y0, y0+h)`` at ``level`` that the vehicle has newer
        than topside (or topside lacks). Split into requests of at most 8 x 8 subgrids."""
        return self._regions(level, x0, y0, w, h, fill_gaps=False)

    def request_gaps(self, level: int, x0: int, y0: int, w: int, h: int) -> list[Region]:
        """Ask for everything missing at ``level`` in the region (16 x 16 subgrids per request)."""
        return self._regions(level, x0, y0, w, h, fill_gaps=True)

    def request_area(self, level: int, x_min: float, y_min: float, x_max: float, y_max: float,
                     fill_gaps: bool = False) -> list[Region]:
        """:meth:`request_region` (or :meth:`request_gaps`) for an area in metres."""
        ax, ay = self.subgrid_index(level, x_min, y_min)
        bx, by = self.subgrid_index(level, x_max, y_max)
        return self._regions(level, ax, ay, bx - ax + 1, by - ay + 1, fill_gaps=fill_gaps)

    def _regions(self, level: int, x0: int, y0: int, w: int, h: int, *, fill_gaps: bool,
                 auto: bool = False) -> list[Region]:
        levels = self.metadata.levels if self.metadata else int(self.config["levels"])
        out = plan(level, x0, y0, w, h, levels=levels, fill_gaps=fill_gaps, auto=auto, max_regions=self.max_regions)
        for r in out:
            self._add(r)
        return out

    def _schedule_auto_fill(self, meta: MapMetadata) -> bool:
        if any(r.auto and not r.done for r in self.regions):
            return False
        if meta.x_max <= meta.x_min or meta.y_max <= meta.y_min:
            return False
        for level in range(meta.levels - 1, -1, -1):
            ax, ay = self.subgrid_index(level, meta.x_min, meta.y_min)
            bx, by = self.subgrid_index(level, meta.x_max - 1e-6, meta.y_max - 1e-6)
            try:
                self._regions(level, ax, ay, bx - ax + 1, by - ay + 1, fill_gaps=True, auto=True)
            except RequestRejected:
                break
        return True

    def _message(self, r: Region) -> MapRoiRequest:
        rid = self._next_id
        self._next_id = (self._next_id + 1) % 256
        old = self._by_id.get(rid)
        if old is not None and old.request_id == rid:
            old.request_id = None
        self._by_id[rid] = r
        r.request_id = rid
        if r.fill_gaps:
            held, _ = self._region(r.level, r.x0, r.y0, r.w, r.h)
            have = 0
            for k in held.ravel().tolist():
                have = (have << 1) | k
            return MapRoiRequest(rid, r.level, r.x0, r.y0, r.w, r.h, True, (), have)
        stamps = tuple(self.region_stamps(r.level, r.x0, r.y0, r.w, r.h))
        return MapRoiRequest(rid, r.level, r.x0, r.y0, r.w, r.h, False, stamps)

    def poll(self, now: float) -> list[Message]:
        out: list[Message] = []
        self.regions = [r for r in self.regions if not r.done]
        # Coarse levels first, then in the order asked; a few requests per poll (the uplink is
        # slow), the rest on the next polls.
        for r in sorted(self.regions, key=lambda r: -r.level):
            if len(out) >= self.max_requests_per_poll:
                break
            if r.track.is_due(now):
                out.append(self._message(r))
                r.track.send(now, self.request_timeout)
        return out

    def supersedes(self, old: Message, new: Message) -> bool:
        """A region request retried (same level, rectangle and kind) replaces the earlier one: it
        carries what topside holds now, so the channel must not re-send the old one after it."""
        return (isinstance(old, MapRoiRequest) and isinstance(new, MapRoiRequest)
                and old.request_id != new.request_id
                and (old.level, old.x0, old.y0, old.w, old.h, old.fill_gaps)
                == (new.level, new.x0, new.y0, new.w, new.h, new.fill_gaps))

    def active_regions(self) -> list[Region]:
        return [r for r in self.regions if not r.done]
