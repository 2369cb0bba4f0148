"""The subsea side: the map, the default sending policy and region requests."""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from coex_core import wire
from coex_core.config import merged_config
from coex_core.errors import ConfigError, RequestRejected
from coex_core.messages import MapMetadata, MapRoiReply, MapRoiRequest, Message, Subgrid
from coex_core.modality import ModalitySender
from coex_core.state import persistent
from coex_core.timefmt import to_stamp, unwrap
from coex_core.wire import SUBGRID_RESOLUTIONS as RESOLUTIONS
from coex_core.wire import SUBGRID_VERTICAL_RESOLUTIONS as VERTICAL_RESOLUTIONS

from .codec import encode_subgrid, subgrid_bits
from .points import pointcloud2_xyz
from .quadtree import InputError, QuadtreeMap

__all__ = ["BathymetrySender", "SENDER_DEFAULTS"]

log = logging.getLogger(__name__)

Key = tuple[int, int, int]  # (level, ix, iy)

#: Sender configuration keys and defaults (the NUI 2022 values where they exist).
SENDER_DEFAULTS: dict[str, Any] = {
    "resolution": 1.0,
    "vertical_resolution": 0.1,
    "subgrid_side": 8,
    "levels": 5,
    "send_delay": 20.0,
    "metadata_interval": 60.0,
    "origin_lat": 0.0,
    "origin_lon": 0.0,
    "outlier_rejection": True,
    "outlier_threshold": 1.0,
    "outlier_k": 3.0,
    "batch_points": 20_000,
    "max_tiles": 1024,
    "topic": None,
    "max_queue": 4096,
    "standing_expiry": 1800.0,
    "max_standing": 32,
}

#: Smallest possible subgrid message (an all-equal block): stop filling below this.
MIN_SUBGRID_BYTES = 12
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


@persistent("bathymetry.Sender")
class BathymetrySender(ModalitySender):
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

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        cfg = merged_config(config, SENDER_DEFAULTS, "bathymetry sender")
        self.config = cfg
        if float(cfg["resolution"]) not in RESOLUTIONS:
            raise ConfigError(f"resolution must be one of {RESOLUTIONS} m (the wire's table)")
        if float(cfg["vertical_resolution"]) not in VERTICAL_RESOLUTIONS:
            raise ConfigError(f"vertical_resolution must be one of {VERTICAL_RESOLUTIONS} m (the wire's table)")
        if not 1 <= int(cfg["levels"]) <= 8:
            raise ConfigError("levels must be in 1..8")
        if int(cfg["subgrid_side"]) not in (2, 4, 8):
            # 8 x 8 cells of up to 20 bits always fit one message; 16 x 16 rough blocks may not.
            raise ConfigError("subgrid_side must be 2, 4 or 8")
        try:
            self.map = QuadtreeMap(
                float(cfg["resolution"]), float(cfg["vertical_resolution"]),
                subgrid_side=int(cfg["subgrid_side"]), levels=int(cfg["levels"]),
                outlier_rejection=bool(cfg["outlier_rejection"]),
                outlier_threshold=float(cfg["outlier_threshold"]), outlier_k=float(cfg["outlier_k"]),
                batch_points=int(cfg["batch_points"]), max_tiles=int(cfg["max_tiles"]),
            )
        except InputError as exc:
            raise ConfigError(str(exc)) from exc
        self.send_delay = float(cfg["send_delay"])
        self.metadata_interval = float(cfg["metadata_interval"])
        self.origin = (float(cfg["origin_lat"]), float(cfg["origin_lon"]))
        self.max_queue = int(cfg["max_queue"])
        self.standing_expiry = float(cfg["standing_expiry"])
        self.max_standing = int(cfg["max_standing"])
        if not (self.standing_expiry >= 0 and self.max_standing >= 0):
            raise ConfigError("standing_expiry and max_standing must not be negative")
        self._sent: dict[tuple[tuple[int, int], int], npt.NDArray[np.float64]] = {}
        self._queue: list[Key] = []
        self._queued: set[Key] = set()
        self._init_requests()
        self._last_meta = -math.inf
        self._meta_due = False
        self._had_background = False
        self._pending = 0
        self._cache: dict[Key, tuple[int, Subgrid, int]] = {}
        self._sent_at: dict[Key, float] = {}
        #: Subgrids whose elevations do not fit the wire (|z| >= 2**19 vertical units): skipped.
        self.unsendable: set[Key] = set()
        self._after_restore()

    def _after_restore(self) -> None:
        if getattr(self, "_resend", None) is None:  # a sender saved before spare work existed
            #: subgrids whose last sent version was lost: spare work (key -> when it was lost)
            self._resend: dict[Key, float] = {}
            #: key -> hash of the newest version a frame ack confirmed (its other copies' losses
            #: do not make it spare work again)
            self._confirmed: dict[Key, int] = {}
            #: standing region requests: region -> (subgrids awaiting survey, expiry time)
            self._standing: dict[tuple[int, int, int, int, int, bool], tuple[set[Key], float]] = {}
            self._standing_checked = -math.inf
            self.standing_expiry = float(getattr(self, "standing_expiry", SENDER_DEFAULTS["standing_expiry"]))
            self.max_standing = int(getattr(self, "max_standing", SENDER_DEFAULTS["max_standing"]))

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

    # ------------------------------------------------------------------------ subgrids

    def _sent_array(self, tile: tuple[int, int], level: int) -> npt.NDArray[np.float64]:
        arr = self._sent.get((tile, level))
        if arr is None:
            p = self.map.subgrids_per_tile(level)
            arr = np.full((p, p), -np.inf)
            self._sent[(tile, level)] = arr
        return arr

    def subgrid_time(self, key: Key) -> float:
        """Last update of subgrid ``key`` (``-inf`` when it holds no data)."""
        level, ix, iy = key
        tile, a, b = self.map.tile_of_subgrid(level, ix, iy)
        if tile not in self.map._slots:
            return -math.inf
        return float(self.map.subgrid_times(tile, level)[b, a])

    def build(self, key: Key) -> Subgrid | None:
        """The current Subgrid message for ``key`` (None when the map has nothing there)."""
        built = self._built(key)
        return None if built is None else built[0]

    def _built(self, key: Key) -> tuple[Subgrid, int] | None:
        """The current Subgrid for ``key`` and its encoded size, cached until its tile changes (a
        subgrid that did not fit one packet is not coded again for the next)."""
        level, ix, iy = key
        tile, _, _ = self.map.tile_of_subgrid(level, ix, iy)
        version = self.map.tile_version(tile)
        hit = self._cache.get(key)
        if hit is not None and hit[0] == version:
            return hit[1], hit[2]
        try:
            sg = self._build(key)
        except ValueError as exc:  # elevations outside the wire's range: skip, never crash
            self.unsendable.add(key)
            log.warning("subgrid %s cannot be sent: %s", key, exc)
            self._mark_sent(key, self.subgrid_time(key))
            return None
        if sg is None:
            return None
        size = (subgrid_bits(sg) + 7) // 8
        self._cache[key] = (version, sg, size)
        return sg, size

    def _build(self, key: Key) -> Subgrid | None:
        level, ix, iy = key
        blk = self.map.block(level, ix, iy)
        if blk is None or not (blk.count > 0).any():
            return None
        present = blk.count > 0
        q = np.zeros(blk.mean.shape, np.int64)
        q[present] = np.rint(blk.mean[present] / self.map.vertical_resolution).astype(np.int64)
        return encode_subgrid(
            q, present, level=level, ix=ix, iy=iy, stamp=to_stamp(blk.updated),
            resolution=self.map.resolution, vertical_resolution=self.map.vertical_resolution,
        )

    def _mark_sent(self, key: Key, updated: float, now: float | None = None) -> None:
        self._cache.pop(key, None)
        self._resend.pop(key, None)
        level, ix, iy = key
        tile, a, b = self.map.tile_of_subgrid(level, ix, iy)
        arr = self._sent_array(tile, level)
        arr[b, a] = max(arr[b, a], updated)
        if now is not None:
            self._sent_at[key] = now

    def _sent_time(self, key: Key) -> float:
        """The update time of the version of ``key`` last sent (``-inf``: never sent)."""
        level, ix, iy = key
        tile, a, b = self.map.tile_of_subgrid(level, ix, iy)
        if (tile, level) not in self._sent:
            return -math.inf
        return float(self._sent[(tile, level)][b, a])

    def last_transmitted(self, key: Key) -> float | None:
        """When subgrid ``key`` (level, ix, iy) was last handed to the link (None: never)."""
        return self._sent_at.get(key)

    def _background(self, now: float, limit: int = 64, quiet: bool = True) -> list[tuple[int, float, Key]]:
        """Up to about ``limit`` eligible background subgrids: coarsest level first, then the
        longest-quiet first (also counts every changed subgrid for ``pending``). With ``quiet``
        False, changed subgrids that are not quiet yet (provisional spare work) instead."""
        out: list[tuple[int, float, Key]] = []
        changed = 0
        for level in range(self.map.levels - 1, -1, -1):
            p = self.map.subgrids_per_tile(level)
            found: list[tuple[int, float, Key]] = []
            for tile in self.map.tiles:
                times = self.map.subgrid_times(tile, level)
                sent = self._sent_array(tile, level)
                dirty = np.isfinite(times) & (times > sent)
                changed += int(dirty.sum())
                if len(out) >= limit:
                    continue
                settled = now - times >= self.send_delay
                # provisional: quiet for a few seconds at least (a version sent in the middle of
                # a second of pings would go again with the same stamp)
                spare = ~settled & (now - times >= PROVISIONAL_QUIET)
                rows, cols = np.nonzero(dirty & (settled if quiet else spare))
                found.extend(
                    (-level, float(times[b, a]), (level, tile[0] * p + int(a), tile[1] * p + int(b)))
                    for b, a in zip(rows.tolist(), cols.tolist(), strict=True)
                )
            if found:
                found.sort()
                out.extend(found[: max(limit - len(out), 0)])
        self._pending = changed + len(self._queue)
        return out

    def inventory(self) -> dict[Key, int]:
        """Every subgrid holding data, with the stamp it would be sent with."""
        inv: dict[Key, int] = {}
        for level in range(self.map.levels):
            p = self.map.subgrids_per_tile(level)
            for tile in self.map.tiles:
                times = self.map.subgrid_times(tile, level)
                for b, a in zip(*np.nonzero(np.isfinite(times)), strict=True):
                    inv[(level, tile[0] * p + int(a), tile[1] * p + int(b))] = to_stamp(float(times[b, a]))
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
        )

    # ----------------------------------------------------------------------------- fill

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        out: list[Message] = []
        left = int(max_bytes)
        if left <= 0:
            return out
        # Soundings held back for lack of neighbours go in once the input has been quiet.
        self.map.flush(force=now - self.map.last_input >= self.send_delay)
        if not self.map.tiles:
            return out
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
        (a newer version stays queued)."""
        if not isinstance(message, Subgrid):
            return
        key = (message.level, message.ix, message.iy)
        self._confirmed[key] = hash(message)  # a copy of this version arrived
        if key not in self._queued and key not in self._resend:
            return
        built = self._built(key)
        if built is not None and built[0] == message:
            self._resend.pop(key, None)
            if key in self._queued:
                self._unqueue({key})

    def lost(self, message: Message, now: float) -> None:
        """No frame that carried a subgrid was acknowledged: if it is still the subgrid's
        current version (a newer one goes out with the background anyway), it becomes spare
        work."""
        if not isinstance(message, Subgrid):
            return
        key = (message.level, message.ix, message.iy)
        if self._confirmed.get(key) == hash(message):
            return  # another copy of this version arrived (its ack may come after this copy's loss)
        built = self._built(key)
        if built is not None and built[0] == message:
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
        if left >= MIN_SUBGRID_BYTES and misses < MAX_MISSES:
            self._pack(((k, u) for _, u, k in self._background(now, quiet=False)), left, misses, out, now)
        return out

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
            else:
                held = r.held[i]
                want = held is None or math.floor(updated) > unwrap(held, now)
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
