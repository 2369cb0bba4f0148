"""The subsea side: the map, the default sending policy and region requests."""

from __future__ import annotations

import heapq
import logging
import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from coex import (
    ConfigError,
    ModalitySender,
    Options,
    RequestRejected,
    Storage,
    merged_config,
    persistent,
    to_stamp,
    unwrap,
    wire,
)
from coex.messages import (
    MapMetadata,
    MapRoiReply,
    MapRoiRequest,
    Message,
    SubgridMessage,
)
from coex.options import anything, flag, integer, number
from coex.wire import SUBGRID_RESOLUTIONS as RESOLUTIONS
from coex.wire import SUBGRID_VERTICAL_RESOLUTIONS as VERTICAL_RESOLUTIONS

from ._arrays import _grow
from .coding import Built, SubgridCoding
from .context import ContextBook
from .points import pointcloud2_xyz
from .quadtree import InputError, QuadtreeMap

__all__ = ["BathymetrySender", "SENDER_DEFAULTS", "SENDER_OPTIONS"]

log = logging.getLogger(__name__)

Key = tuple[int, int, int]  # (level, ix, iy)

#: The sender's options (the NUI 2022 values where they exist): the one declaration of their
#: types, ranges and units (``coex config check`` and the constructor check them alike).
SENDER_OPTIONS = Options(
    resolution=number(1.0, "finest cell size (the wire's table)", unit="m", choices=tuple(RESOLUTIONS)),
    vertical_resolution=number(0.1, "depth quantum (the wire's table)", unit="m",
                               choices=tuple(VERTICAL_RESOLUTIONS)),
    subgrid_side=integer(8, "cells per subgrid side", choices=(2, 4, 8)),
    levels=integer(5, "quadtree levels", lo=1, hi=8),
    send_delay=number(20.0, "a changed subgrid waits this quiet before it is sent", unit="s", lo=0),
    metadata_interval=number(60.0, "between two MapMetadata", unit="s", lo=0),
    origin_lat=number(0.0, "the map's origin", unit="deg", lo=-90, hi=90),
    origin_lon=number(0.0, "the map's origin", unit="deg", lo=-180, hi=180),
    outlier_rejection=flag(True, "drop soundings far from their cell's median"),
    outlier_threshold=number(1.0, "an outlier is at least this far from the median", unit="m", lo=0),
    outlier_k=number(3.0, "... and this many spreads", lo=0),
    batch_points=integer(20_000, "soundings gridded at a time", lo=1),
    max_tiles=integer(None, "tiles held at most (None: no limit)", lo=1, none=True),
    memory_budget=integer(512 * 2**20, "tiles kept in memory", unit="B", lo=0),
    disk_budget=integer(16 * 2**30, "tiles kept on disk (None: no limit)", unit="B", lo=0, none=True),
    topic=anything(None, "the input's topic name (a label)"),
    max_queue=integer(4096, "subgrids queued at most", lo=1),
    standing_expiry=number(1800.0, "a standing region request lasts", unit="s", lo=0),
    max_standing=integer(32, "standing region requests kept", lo=0),
)
#: their defaults (a name kept for 0.x code)
SENDER_DEFAULTS: dict[str, Any] = SENDER_OPTIONS.defaults()

#: Smallest possible subgrid message (a predicted block equal to its prediction): stop filling
#: below this.
MIN_SUBGRID_BYTES = 10
#: a provisional subgrid (spare work) has been quiet for at least this long (s)
PROVISIONAL_QUIET = 3.0
#: After this many subgrids that did not fit, ``fill`` stops looking for smaller ones (keeps it cheap).
MAX_MISSES = 8
#: a request for a region at most STALE_REQUEST_IDS ids older than the newest one handled for it
#: within STALE_REQUEST_S seconds is a late copy (ids wrap at 256)
STALE_REQUEST_S = 300.0
STALE_REQUEST_IDS = 32
#: regions whose newest request id is remembered
MAX_REGIONS_REMEMBERED = 1024
#: a subgrid queued around a detection (:meth:`BathymetrySender.focus`) that is lost is queued
#: again until this long after the detection
FOCUS_EXPIRY = 1800.0


def _upgrade_sender(fields: dict[str, Any], saved: int) -> dict[str, Any]:
    """Version 1 (0.1.0 and early 0.2 work) was saved before detections (no focused subgrids,
    no low-link flag) or before spare work (no re-send list, confirmations or standing region
    requests), and before that with one sent-array per (tile, level) (``_sent``, ``_sent_at``:
    :meth:`BathymetrySender._after_restore` moves them into the per-level arrays, which need the
    restored map). Version 2 always has them."""
    out = dict(fields)
    if out.get("_focused") is None:
        out.update(_focused={}, _low=False, focus_bytes=0)
    if out.get("_resend") is None:
        out.update(_resend={}, _confirmed={}, _standing={}, _standing_checked=-math.inf)
        out.setdefault("standing_expiry", float(SENDER_DEFAULTS["standing_expiry"]))
        out.setdefault("max_standing", int(SENDER_DEFAULTS["max_standing"]))
    if saved < 3:
        # version 3 predicts subgrids from what topside holds (ContextBook, built in
        # _after_restore) and confirms versions by their cells, not their bytes: the cache and
        # the confirmations of version 2 are dropped (at worst a confirmed subgrid goes again)
        out.update(_cache={}, _confirmed={}, _book=None)
    return out


@persistent("bathymetry.Sender", version=3, upgrade=_upgrade_sender)
class BathymetrySender(SubgridCoding, ModalitySender):
    """Ingests soundings into a :class:`QuadtreeMap` and answers ``fill(max_bytes, now)``.

    Policy: requested subgrids first (FIFO), then background subgrids, coarsest level first; a
    subgrid is eligible when it changed since it was last sent and has been quiet for
    ``send_delay`` seconds. Each version is sent once by :meth:`fill`. A subgrid whose frame
    was not acknowledged (:meth:`lost`, from the channel manager) is offered again as spare
    work (:meth:`spare`, coarsest level first) until a frame that carried its current version
    is acknowledged; topside can still repair gaps with :class:`MapRoiRequest`. A
    :class:`MapMetadata` goes out every ``metadata_interval`` seconds and when the background
    queue empties.
    """

    options = SENDER_OPTIONS
    #: per level, by the map's tile number: the oldest update among its changed subgrids and
    #: their count (the index of changed tiles; made by ``_reset_index``)
    _tmin: list[npt.NDArray[np.float64]]
    _dcount: list[npt.NDArray[np.int64]]

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        # subgrid_side 2, 4 or 8: 8 x 8 cells of up to 20 bits always fit one message; 16 x 16
        # rough blocks may not
        cfg = merged_config(config, self.options, "bathymetry sender")
        self.config = cfg
        try:
            self.map = QuadtreeMap(
                float(cfg["resolution"]), float(cfg["vertical_resolution"]),
                subgrid_side=int(cfg["subgrid_side"]), levels=int(cfg["levels"]),
                outlier_rejection=bool(cfg["outlier_rejection"]),
                outlier_threshold=float(cfg["outlier_threshold"]), outlier_k=float(cfg["outlier_k"]),
                batch_points=int(cfg["batch_points"]),
                max_tiles=None if cfg["max_tiles"] is None else int(cfg["max_tiles"]),
                memory_budget=int(cfg["memory_budget"]),
                disk_budget=None if cfg["disk_budget"] is None else int(cfg["disk_budget"]),
            )
        except InputError as exc:
            raise ConfigError(str(exc)) from exc
        self.send_delay = float(cfg["send_delay"])
        self.metadata_interval = float(cfg["metadata_interval"])
        self.origin = (float(cfg["origin_lat"]), float(cfg["origin_lon"]))
        self.max_queue = int(cfg["max_queue"])
        self.standing_expiry = float(cfg["standing_expiry"])
        self.max_standing = int(cfg["max_standing"])
        self._init_sent()
        self._queue: list[Key] = []
        self._queued: set[Key] = set()
        self._init_requests()
        self._last_meta = -math.inf
        self._meta_due = False
        self._had_background = False
        self._pending = 0
        self._cache: dict[Key, Built] = {}
        #: Subgrids whose elevations do not fit the wire (|z| >= 2**19 vertical units): skipped.
        self.unsendable: set[Key] = set()
        self._init_spare()

    def _init_spare(self) -> None:
        #: level-0 subgrids queued around detections (key -> until when a loss queues it again)
        self._focused: dict[Key, float] = {}
        #: the channel finds the link low: the finest level is spare work, not background
        self._low = False
        #: bytes of the subgrids sent because a detection pointed at them (:meth:`focus`)
        self.focus_bytes = 0
        #: subgrids whose last sent version was lost: spare work (key -> when it was lost)
        self._resend: dict[Key, float] = {}
        #: key -> the newest version (content digest) a frame ack confirmed (its other copies'
        #: losses do not make it spare work again)
        self._confirmed: dict[Key, int] = {}
        #: standing region requests: region -> (subgrids awaiting survey, expiry time)
        self._standing: dict[tuple[int, int, int, int, int, bool], tuple[set[Key], float]] = {}
        self._standing_checked = -math.inf

    def _init_sent(self) -> None:
        #: per level, by the map's tile number: the update time of the version of each subgrid
        #: last sent (-inf: never) and when it was handed to the link (NaN: never)
        cap = 4
        self._sent_t = [np.full((cap, p, p), -np.inf) for p in self._per_tile()]
        self._sent_when = [np.full((cap, p, p), np.nan) for p in self._per_tile()]
        #: what topside is known to hold of the parent levels (subgrids predicted from them)
        self._book: ContextBook | None = ContextBook(self._per_tile(), cap)
        #: tiles that may hold subgrids changed since they were sent (the sender looks only there)
        self._reset_index()
        #: what the map reported when it began dropping soundings (logged once)
        self._overflow_logged: str | None = None

    def _per_tile(self) -> list[int]:
        return [self.map.subgrids_per_tile(lv) for lv in range(self.map.levels)]

    def _after_restore(self) -> None:
        old_sent = self.__dict__.pop("_sent", None)
        old_at = self.__dict__.pop("_sent_at", None)
        if old_sent is not None:  # saved by a version that kept one array per (tile, level)
            self._init_sent()
            for (tile, level), arr in old_sent.items():
                if self.map.has_tile(tuple(tile)):
                    n = self._sent_row(tuple(tile))
                    self._sent_t[level][n] = arr
            for key, when in (old_at or {}).items():
                level, ix, iy = key
                tile, a, b = self.map.tile_of_subgrid(level, ix, iy)
                if self.map.has_tile(tile):
                    self._sent_when[level][self._sent_row(tile), b, a] = when
        if self._book is None:  # saved by version 2 (before predicted subgrids)
            self._book = ContextBook(self._per_tile(), self._sent_t[0].shape[0])

    # ---------------------------------------------------------------------------- ingest

    def ingest(self, data: Any, now: float) -> None:
        """Take an ``N x 3`` array (x east, y north, z up, metres) or a deserialised
        ``sensor_msgs/PointCloud2`` message. No I/O here: files and bags are read by the caller
        (``iter_points``, ``coex bathy roundtrip``)."""
        if isinstance(data, np.ndarray | list | tuple):
            self.map.add_points(np.asarray(data), now)
            return
        if all(hasattr(data, a) for a in ("fields", "data", "point_step", "width", "height")):
            self.map.add_points(pointcloud2_xyz(data), now)
            return
        raise InputError(f"cannot ingest {type(data).__name__}: give an N x 3 array or a PointCloud2 message")

    def journal_form(self, data: Any) -> Any:
        """A PointCloud2 message is journaled as its N x 3 array of points."""
        if not isinstance(data, np.ndarray | list | tuple) and all(
                hasattr(data, a) for a in ("fields", "data", "point_step", "width", "height")):
            return pointcloud2_xyz(data)
        return data

    def detector_view(self) -> QuadtreeMap:
        """Detectors look at the vehicle's full-resolution map (a ``coex.MapView``)."""
        return self.map

    def attach_storage(self, storage: Storage) -> None:
        """Spilled map tiles go to ``storage`` (the node's store)."""
        self.map.attach_storage(storage)

    def sync_storage(self) -> None:
        self.map.sync()

    def _report_overflow(self) -> None:
        """Log, once per cause, that the map drops soundings (topside sees ``MapMetadata.dropped``)."""
        if self.map.overflow is not None and self.map.overflow != self._overflow_logged:
            self._overflow_logged = self.map.overflow
            log.warning("bathymetry map: %s (%d soundings dropped so far)", self.map.overflow, self.map.dropped)

    # ------------------------------------------------------------------------ subgrids

    def _sent_row(self, tile: tuple[int, int]) -> int:
        """The map's number of ``tile`` (which must exist), the sender's arrays grown to hold it."""
        n = self.map._slots[tile]
        if n >= self._sent_t[0].shape[0]:
            cap = max(2 * self._sent_t[0].shape[0], n + 1)
            self._sent_t = [_grow(a, cap, -np.inf) for a in self._sent_t]
            self._sent_when = [_grow(a, cap, np.nan) for a in self._sent_when]
            self._tmin = [_grow(a, cap, np.inf) for a in self._tmin]
            self._dcount = [_grow(a, cap, 0) for a in self._dcount]
            self.book.grow(cap)
        return n

    def _refresh(self, tile: tuple[int, int], levels: Iterable[int] | None = None) -> None:
        """Recount the changed subgrids of ``tile`` (at ``levels``, default all) for the index."""
        n = self._sent_row(tile)
        for level in range(self.map.levels) if levels is None else levels:
            times = self.map.subgrid_times(tile, level)
            changed = np.isfinite(times) & (times > self._sent_t[level][n])
            count = int(np.count_nonzero(changed))
            self._changed_total += count - int(self._dcount[level][n])
            self._dcount[level][n] = count
            tmin = float(times[changed].min()) if count else math.inf
            if tmin != self._tmin[level][n]:
                self._tmin[level][n] = tmin
                if count:
                    heapq.heappush(self._heaps[level], (tmin, n))
        last = float(self.map._stimes[-1][n].max())
        if math.isfinite(last):
            self._recent[n] = max(self._recent.get(n, -math.inf), last)

    def _absorb(self) -> None:
        """Take the map's changed tiles into the index (every tile after a restore)."""
        changed = self.map.take_changed()
        if changed is None:
            self._reset_index()
            changed = set(self.map._keys)
        for tile in changed:
            self._refresh(tile)

    def _reset_index(self) -> None:
        #: per level, by tile number: changed subgrids and the oldest update among them (the
        #: index of changed tiles: the sender never scans the whole map)
        cap = self._sent_t[0].shape[0]
        self._tmin = [np.full(cap, math.inf) for _ in range(self.map.levels)]
        self._dcount = [np.zeros(cap, np.int64) for _ in range(self.map.levels)]
        self._changed_total = 0
        #: per level, a heap of (oldest changed update, tile number); stale entries are skipped
        self._heaps: list[list[tuple[float, int]]] = [[] for _ in range(self.map.levels)]
        #: tiles changed recently (number -> their newest update): provisional spare work
        self._recent: dict[int, float] = {}

    def subgrid_time(self, key: Key) -> float:
        """Last update of subgrid ``key`` (``-inf`` when it holds no data)."""
        level, ix, iy = key
        tile, a, b = self.map.tile_of_subgrid(level, ix, iy)
        if tile not in self.map._slots:
            return -math.inf
        return float(self.map.subgrid_times(tile, level)[b, a])

    def _mark_sent(self, key: Key, updated: float, now: float | None = None) -> None:
        entry = self._cache.pop(key, None)
        self._resend.pop(key, None)
        level, ix, iy = key
        tile, a, b = self.map.tile_of_subgrid(level, ix, iy)
        if not self.map.has_tile(tile):
            return
        n = self._sent_row(tile)
        if entry is not None and now is not None:  # a version went to the link (not a skip)
            self.book.on_sent(n, key, entry[5])
        arr = self._sent_t[level][n]
        arr[b, a] = max(arr[b, a], updated)
        if now is not None:
            self._sent_when[level][n, b, a] = now
        self._refresh(tile, (level,))

    def _sent_time(self, key: Key) -> float:
        """The update time of the version of ``key`` last sent (``-inf``: never sent)."""
        level, ix, iy = key
        tile, a, b = self.map.tile_of_subgrid(level, ix, iy)
        if not self.map.has_tile(tile):
            return -math.inf
        n = self._sent_row(tile)  # first: it may grow the arrays
        return float(self._sent_t[level][n, b, a])

    def last_transmitted(self, key: Key) -> float | None:
        """When subgrid ``key`` (level, ix, iy) was last handed to the link (None: never)."""
        level, ix, iy = key
        if not 0 <= level < self.map.levels:
            return None
        tile, a, b = self.map.tile_of_subgrid(level, ix, iy)
        if not self.map.has_tile(tile):
            return None
        n = self._sent_row(tile)  # first: it may grow the arrays
        when = float(self._sent_when[level][n, b, a])
        return None if math.isnan(when) else when

    def _background(self, now: float, limit: int = 64, quiet: bool = True) -> list[tuple[int, float, Key]]:
        """Up to ``limit`` eligible background subgrids: coarsest level first, then the
        longest-quiet first. With ``quiet`` False, changed subgrids that are not quiet yet
        (provisional spare work) instead. Only tiles the index of changed tiles names are
        looked at, so the cost does not grow with the map."""
        self._absorb()
        out: list[tuple[int, float, Key]] = []
        if not quiet:
            for n, last in list(self._recent.items()):
                if now - last > self.send_delay + 1.0:
                    del self._recent[n]  # settled now: the background sends it
        # on a low link the finest level is not background (only what is asked for, what
        # detections point at and spare work send it: docs/channel.md)
        lowest = 1 if quiet and self._low and self.map.levels > 1 else 0
        for level in range(self.map.levels - 1, lowest - 1, -1):
            need = limit - len(out)
            if need <= 0:
                break
            found = self._eligible_quiet(level, now, need) if quiet else self._eligible_recent(level, now)
            found.sort()
            out.extend(found[:need])
        self._pending = self._changed_total + len(self._queue)
        return out

    def _tile_found(self, level: int, n: int, now: float, quiet: bool) -> list[tuple[int, float, Key]]:
        tile = self.map._keys[n]
        p = self.map.subgrids_per_tile(level)
        times = self.map.subgrid_times(tile, level)
        changed = np.isfinite(times) & (times > self._sent_t[level][n])
        settled = now - times >= self.send_delay
        # provisional: quiet for a few seconds at least (a version sent in the middle of a
        # second of pings would go again with the same stamp)
        mask = changed & (settled if quiet else ~settled & (now - times >= PROVISIONAL_QUIET))
        rows, cols = np.nonzero(mask)
        return [(-level, float(times[b, a]), (level, tile[0] * p + a, tile[1] * p + b))
                for b, a in zip(rows.tolist(), cols.tolist(), strict=True)]

    def _eligible_quiet(self, level: int, now: float, need: int) -> list[tuple[int, float, Key]]:
        """Changed subgrids quiet for ``send_delay`` at ``level``: tiles in order of their oldest
        change, until ``need`` are found and no other tile can hold an older one."""
        heap, tmin = self._heaps[level], self._tmin[level]
        found: list[tuple[int, float, Key]] = []
        taken: list[tuple[float, int]] = []
        seen: set[int] = set()
        cutoff = now - self.send_delay
        while heap:
            t, n = heap[0]
            if t != tmin[n] or n in seen:
                heapq.heappop(heap)  # stale: the tile changed or was sent since
                continue
            if t > cutoff:
                break
            if len(found) >= need and t > sorted(f[1] for f in found)[need - 1]:
                break
            taken.append(heapq.heappop(heap))
            seen.add(n)
            found.extend(self._tile_found(level, n, now, True))
        for entry in taken:
            heapq.heappush(heap, entry)
        return found

    def _eligible_recent(self, level: int, now: float) -> list[tuple[int, float, Key]]:
        found: list[tuple[int, float, Key]] = []
        for n in sorted(self._recent):
            if self._dcount[level][n]:
                found.extend(self._tile_found(level, n, now, False))
        return found

    def inventory(self) -> dict[Key, int]:
        """Every subgrid holding data, with the stamp it would be sent with."""
        self.map.flush()
        inv: dict[Key, int] = {}
        keys = np.array(self.map._keys, np.int64).reshape(-1, 2)
        for level in range(self.map.levels):
            p = self.map.subgrids_per_tile(level)
            times = self.map._stimes[level][: len(keys)]
            ns, bs, as_ = np.nonzero(np.isfinite(times))
            for n, b, a, t in zip(ns.tolist(), bs.tolist(), as_.tolist(), times[ns, bs, as_].tolist(), strict=True):
                inv[(level, int(keys[n, 0]) * p + a, int(keys[n, 1]) * p + b)] = to_stamp(t)
        return inv

    def metadata(self, now: float) -> MapMetadata:
        ext = self.map.extent() or (0.0, 0.0, 0.0, 0.0)
        lim = 65535

        def clamp(v: float) -> int:
            return int(min(max(math.floor(v), -lim - 1), lim))

        stamp = to_stamp(self.map.last_update if math.isfinite(self.map.last_update) else now)
        return MapMetadata(
            stamp=stamp, resolution=self.map.resolution, vertical_resolution=self.map.vertical_resolution,
            subgrid_side=self.map.subgrid_side, levels=self.map.levels,
            origin_lat=round(self.origin[0], 6), origin_lon=round(self.origin[1], 6),
            x_min=clamp(ext[0]), y_min=clamp(ext[1]), x_max=clamp(ext[2]), y_max=clamp(ext[3]),
            pending=min(self._pending, 65535),
            dropped_k=min(-(-self.map.dropped // 1000), 65535),
        )

    # ----------------------------------------------------------------------------- fill

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        out: list[Message] = []
        left = int(max_bytes)
        if left <= 0:
            return out
        # Soundings held back for lack of neighbours go in once the input has been quiet.
        self.map.flush(force=now - self.map.last_input >= self.send_delay)
        if not self.map._keys:
            return out
        self._report_overflow()
        background = self._background(now)
        if background:
            self._had_background = True
        elif self._had_background and not self._queue:
            self._had_background = False
            self._meta_due = True  # tell topside the background is done (it may fill gaps)
        if self._meta_due or now - self._last_meta >= self.metadata_interval:
            meta = self.metadata(now)
            size = wire.encoded_size(meta)
            if size <= left:
                out.append(meta)
                left -= size
                self._last_meta = now
                self._meta_due = False
        self._serve_standing(now)
        # Requested subgrids first.
        remaining: list[Key] = []
        misses = 0
        answered: set[Key] = set()
        for key in self._queue:
            if left < MIN_SUBGRID_BYTES or misses >= MAX_MISSES:
                remaining.append(key)
                continue
            built = self._built(key)
            if built is None:
                self._queued.discard(key)
                self._gap_queued.discard(key)
                continue
            sg, size = built
            if size <= left:
                out.append(sg)
                left -= size
                self._queued.discard(key)
                self._gap_queued.discard(key)
                answered.add(key)
                if key in self._focused:
                    self.focus_bytes += size
                self._mark_sent(key, self.subgrid_time(key), now)
            else:
                misses += 1
                remaining.append(key)
        self._queue = remaining
        misses = 0
        for _, updated, key in background:
            if left < MIN_SUBGRID_BYTES or misses >= MAX_MISSES:
                break
            if key in self._queued or key in answered:  # requested: sent above, or still queued
                continue
            built = self._built(key)
            if built is None:
                continue
            sg, size = built
            if size <= left:
                out.append(sg)
                left -= size
                self._mark_sent(key, updated, now)
            else:
                misses += 1
        return out

    def pending_bytes(self) -> int:
        return 40 * (self._pending + len(self._queue))

    def standing(self) -> list[tuple[tuple[int, int, int, int, int, bool], int, float]]:
        """Standing region requests: ``(region, subgrids still awaited, expiry time)``."""
        return [(r, len(keys), exp) for r, (keys, exp) in self._standing.items()]

    def _serve_standing(self, now: float) -> None:
        """Queue, as requested, the awaited subgrids of standing requests that now hold data
        quiet for ``send_delay`` (at most once a second); drop expired and fulfilled ones."""
        if not self._standing or now - self._standing_checked < 1.0:
            return
        self._standing_checked = now
        for region, (keys, expires) in list(self._standing.items()):
            if now > expires:
                del self._standing[region]
                continue
            ready = {k for k in keys if now - self.subgrid_time(k) >= self.send_delay}
            for key in sorted(ready):
                if self._sent_time(key) >= self.subgrid_time(key):
                    continue  # the background (or spare work) has sent this version already
                if key not in self._queued and len(self._queue) < self.max_queue:
                    self._queue.append(key)
                    self._queued.add(key)
            keys -= ready
            if not keys:
                del self._standing[region]

    # --------------------------------------------------------------------------- requests

    def _init_requests(self) -> None:
        #: queued by gap-filling requests (a newer gap request saying topside has them unqueues them)
        self._gap_queued: set[Key] = set()
        #: newest request id and arrival time per requested region
        self._last_request: dict[tuple[int, int, int, int, int, bool], tuple[int, float]] = {}
        #: requests ignored because a newer one for the same region had been handled
        self.stale_requests = 0

    def _unqueue(self, keys: set[Key]) -> None:
        self._queued -= keys
        self._gap_queued -= keys
        self._queue = [k for k in self._queue if k not in keys]

    def acked(self, message: Message, now: float) -> None:
        """A frame that carried a subgrid was acknowledged: a re-send of it (spare work) or a
        request for it still queued is answered, if the acknowledged copy is its current version
        (a newer version stays queued); at a parent level, topside now holds its cells
        (predicted children may use them, :mod:`.context`)."""
        got = self._version(message)
        if got is None:
            return
        assert isinstance(message, SubgridMessage)
        key, version = got
        if version is not None:
            self._confirmed[key] = version  # a copy of this version arrived
            rec = self.book.version(message)
            tile, _, _ = self.map.tile_of_subgrid(*key)
            if rec is not None and self.map.has_tile(tile):
                self.book.on_acked(self._sent_row(tile), key, rec[2])
        if key not in self._queued and key not in self._resend:
            return
        if self._is_current(key, message, version):
            self._resend.pop(key, None)
            if key in self._queued:
                self._unqueue({key})

    def lost(self, message: Message, now: float) -> None:
        """No frame that carried a subgrid was acknowledged: if it is still the subgrid's
        current version (a newer one goes out with the background anyway), it becomes spare
        work. A message built before a restart whose version the sender no longer knows is
        taken as current when it has the current version's stamp (``_is_current``)."""
        got = self._version(message)
        if got is None:
            return
        assert isinstance(message, SubgridMessage)
        key, version = got
        if version is not None and self._confirmed.get(key) == version:
            return  # another copy of this version arrived (its ack may come after this copy's loss)
        if self._is_current(key, message, version, lost=True):
            if self._focused.get(key, -math.inf) >= now and key not in self._queued \
                    and len(self._queue) < self.max_queue:
                self._queue.append(key)  # around a detection: again, ahead of the background
                self._queued.add(key)
                return
            self._focused.pop(key, None)
            self._resend[key] = now

    def spare(self, max_bytes: int, now: float) -> list[Message]:
        """Spare work, coarsest level first: re-sends of subgrids whose frames were not
        acknowledged (the longest lost first; each goes again until an ack of its current
        version arrives), then *provisional* subgrids, changed but not yet quiet for
        ``send_delay`` (the survey is still over them): topside sees them sooner, and the
        background sends them again only if they change after this."""
        out: list[Message] = []
        lost = sorted(self._resend, key=lambda k: (-k[0], self._resend[k], k))
        left, misses = self._pack(((k, None) for k in lost), int(max_bytes), 0, out, now)
        if self._low and left >= MIN_SUBGRID_BYTES and misses < MAX_MISSES:
            # a low link: the finest level's background, longest quiet first
            self._absorb()
            fine = sorted(self._eligible_quiet(0, now, 64))
            left, misses = self._pack(((k, u) for _, u, k in fine), left, misses, out, now)
        if left >= MIN_SUBGRID_BYTES and misses < MAX_MISSES:
            self._pack(((k, u) for _, u, k in self._background(now, quiet=False)), left, misses, out, now)
        return out

    def throughput(self, bytes_per_second: float, low: bool, now: float) -> None:
        """While the channel finds the link low, the finest level leaves the background: it
        goes where it is asked for (requests), where a detection points (:meth:`focus`) and as
        spare work; the coarse levels stay the background (docs/channel.md)."""
        self._low = bool(low)

    def focus(self, x: float, y: float, radius: float, now: float) -> int:
        """A detection at ``(x, y)``: queue the finest level's subgrids within ``radius`` metres
        of it (the square around it, nearest first), as a region request would, without the
        round trip: those holding data whose current version was not sent, or was found lost.
        A subgrid so queued that is lost is queued again (for :data:`FOCUS_EXPIRY` seconds).
        Returns how many it queued."""
        self.map.flush()
        side = self.map.resolution * self.map.subgrid_side
        if not (math.isfinite(x) and math.isfinite(y) and radius >= 0):
            return 0
        if len(self._focused) > self.max_queue:
            self._focused = {k: t for k, t in self._focused.items() if t >= now}
        ix0, ix1 = math.floor((x - radius) / side), math.floor((x + radius) / side)
        iy0, iy1 = math.floor((y - radius) / side), math.floor((y + radius) / side)
        if ix1 - ix0 > 16 or iy1 - iy0 > 16 or not (-8192 <= ix0 and ix1 < 8192 and -8192 <= iy0 and iy1 < 8192):
            return 0  # bounded like a region request (16 x 16 subgrids)
        keys = [(0, ix, iy) for iy in range(iy0, iy1 + 1) for ix in range(ix0, ix1 + 1)]
        keys.sort(key=lambda k: math.hypot((k[1] + 0.5) * side - x, (k[2] + 0.5) * side - y))
        queued = 0
        for key in keys:
            updated = self.subgrid_time(key)
            if not math.isfinite(updated) or key in self._queued or len(self._queue) >= self.max_queue:
                continue
            self._focused[key] = now + FOCUS_EXPIRY
            if self._sent_time(key) >= updated and key not in self._resend:
                continue  # this version went out (a loss queues it again)
            self._queue.append(key)
            self._queued.add(key)
            queued += 1
        return queued

    def _pack(self, keys: Iterable[tuple[Key, float | None]], left: int, misses: int, out: list[Message],
              now: float) -> tuple[int, int]:
        """Append to ``out`` the current versions of ``keys`` (not queued for a request) that fit
        in ``left`` bytes, marking each sent at its update time (``None``: now's); stop after
        :data:`MAX_MISSES` that did not fit. Returns the bytes and misses left."""
        for key, updated in keys:
            if left < MIN_SUBGRID_BYTES or misses >= MAX_MISSES:
                break
            if key in self._queued:
                continue  # a request will send it
            built = self._built(key)
            if built is None:
                self._resend.pop(key, None)
                continue
            sg, size = built
            if size > left:
                misses += 1
                continue
            out.append(sg)
            left -= size
            # sent: off the re-send list (a loss brings it back), not changed since
            self._mark_sent(key, self.subgrid_time(key) if updated is None else updated, now)
        return left, misses

    def spare_bytes(self) -> int:
        """Lost subgrids to send again, and changed ones not quiet yet (provisional)."""
        return 40 * (len(self._resend) + self._pending)

    def handle(self, message: Message, now: float) -> list[Message]:
        if not isinstance(message, MapRoiRequest):
            raise RequestRejected(f"the bathymetry sender does not handle {type(message).__name__}")
        r = message
        self.map.flush()
        if not (isinstance(r.level, int) and 0 <= r.level < self.map.levels):
            raise RequestRejected(f"level {r.level} outside 0..{self.map.levels - 1}")
        if not (isinstance(r.w, int) and isinstance(r.h, int) and 1 <= r.w <= 16 and 1 <= r.h <= 16):
            raise RequestRejected(f"region {r.w} x {r.h} subgrids is outside 1..16 x 1..16")
        if not (-8192 <= r.x0 and r.x0 + r.w <= 8192 and -8192 <= r.y0 and r.y0 + r.h <= 8192):
            raise RequestRejected("region outside the addressable map")
        if not 0 <= r.request_id <= 255:
            raise RequestRejected("request id outside 0..255")
        n = r.w * r.h
        if r.fill_gaps:
            if r.held or r.have is None or not 0 <= r.have < (1 << n):
                raise RequestRejected("a gap-filling request carries a w*h-bit 'have' bitmap and no stamps")
        elif len(r.held) != n or n > 64:
            raise RequestRejected(f"a region request lists one stamp per subgrid (w*h = {n} <= 64)")
        if len(self._queue) + n > self.max_queue:
            raise RequestRejected("too many subgrids already queued for requests")
        # The newest request for a region wins: the channel may deliver an older copy (re-sent
        # after its ack timeout, with what topside lacked back then) after a newer one.
        region = (r.level, r.x0, r.y0, r.w, r.h, r.fill_gaps)
        last = self._last_request.get(region)
        if (last is not None and 0 < (last[0] - r.request_id) % 256 <= STALE_REQUEST_IDS
                and now - last[1] < STALE_REQUEST_S):
            self.stale_requests += 1
            return [MapRoiReply(r.request_id, r.level, 0)]
        self._last_request[region] = (r.request_id, now)
        if len(self._last_request) > MAX_REGIONS_REMEMBERED:
            del self._last_request[next(iter(self._last_request))]
        queued = 0
        held_now: set[Key] = set()
        unsurveyed: set[Key] = set()
        for i in range(n):
            key = (r.level, r.x0 + i % r.w, r.y0 + i // r.w)
            updated = self.subgrid_time(key)
            if not math.isfinite(updated):
                if not r.fill_gaps or not (r.have or 0) >> (n - 1 - i) & 1:
                    unsurveyed.add(key)
                continue
            if r.fill_gaps:
                assert r.have is not None
                want = not (r.have >> (n - 1 - i)) & 1
                lacks = want
            else:
                held = r.held[i]
                want = held is None or math.floor(updated) > unwrap(held, now)
                lacks = held is None
            if lacks:
                self._lacks(key)
            if want:
                queued += 1
                if key not in self._queued:
                    self._queue.append(key)
                    self._queued.add(key)
                    if r.fill_gaps:
                        self._gap_queued.add(key)
            elif r.fill_gaps and key in self._gap_queued:
                held_now.add(key)  # asked for by an earlier gap request, held by topside now
        if held_now:
            self._unqueue(held_now)
        waiting = self._stand(region, unsurveyed, now)
        return [MapRoiReply(r.request_id, r.level, min(queued, 1023), min(waiting, 1023))]

    def _lacks(self, key: Key) -> None:
        """Topside says it lacks ``key`` (whatever frame acks said): no confirmation of it
        stands, and no child is predicted from its cells until a copy is acknowledged again."""
        self._confirmed.pop(key, None)
        tile, _, _ = self.map.tile_of_subgrid(*key)
        if self.map.has_tile(tile):
            self.book.forget(self._sent_row(tile), key)

    def _stand(self, region: tuple[int, int, int, int, int, bool], keys: set[Key], now: float) -> int:
        """Make the request for ``region`` stand for its ``keys`` not surveyed yet (replacing an
        earlier one for the same region); returns how many it waits for (0: it does not stand,
        none is missing or standing requests are off)."""
        self._standing.pop(region, None)
        if not keys or self.max_standing == 0 or self.standing_expiry <= 0:
            return 0
        while len(self._standing) >= self.max_standing:  # the oldest gives way
            del self._standing[next(iter(self._standing))]
        self._standing[region] = (keys, now + self.standing_expiry)
        self._standing_checked = -math.inf
        return len(keys)
