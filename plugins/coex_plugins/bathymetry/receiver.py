"""The topside side: level mosaics, per-subgrid holdings and ages, region requests and retries."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from coex_core.config import merged_config
from coex_core.errors import ConfigError, RequestRejected
from coex_core.messages import MapMetadata, MapRoiReply, MapRoiRequest, Message, Subgrid
from coex_core.modality import ModalityReceiver, Product
from coex_core.state import persistent
from coex_core.timefmt import to_stamp, unwrap

from .codec import decode_subgrid

__all__ = ["BathymetryReceiver", "RECEIVER_DEFAULTS", "Region"]

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
}

#: Largest region of one request with stamps (8 x 8 = 64 subgrids) and of one gap-filling request.
ROI_CHUNK = 8
GAP_CHUNK = 16
#: subgrid indices a MapRoiRequest can carry (14-bit two's complement, spec: MapRoiRequest x0/y0)
SUBGRID_INDEX_MIN, SUBGRID_INDEX_MAX = -8192, 8191


@persistent("bathymetry.Region", version=3,
            upgrade=lambda fields, saved: {"queued": None, "answered": None, "waiting": 0, **fields})
@dataclass
class Region:
    """An active region request: re-sent (with fresh stamps) until the vehicle answers "nothing newer"."""

    level: int
    x0: int
    y0: int
    w: int
    h: int
    fill_gaps: bool
    auto: bool = False
    next_send: float = -math.inf
    request_id: int | None = None
    sends: int = 0
    done: bool = False
    #: what the vehicle last answered: subgrids it queued for the region, and when
    queued: int | None = None
    answered: float | None = None
    #: subgrids of the region the vehicle has not surveyed yet: its request stands for them
    waiting: int = 0


@persistent("bathymetry.Held")
@dataclass
class _Held:
    stamp: float
    values: npt.NDArray[np.float64]
    received: float


@persistent("bathymetry.Mosaic")
@dataclass
class _Mosaic:
    """One level assembled from subgrids, grown by doubling as subgrids arrive."""

    side: int
    ix0: int = 0
    iy0: int = 0
    nx: int = 0
    ny: int = 0
    array: npt.NDArray[np.float64] = field(default_factory=lambda: np.full((0, 0), np.nan))

    def fits(self, ix: int, iy: int, max_cells: int) -> bool:
        """Whether pasting subgrid (ix, iy) keeps the mosaic's bounding box within ``max_cells``."""
        if self.nx == 0:
            return True
        w = max(self.ix0 + self.nx, ix + 1) - min(self.ix0, ix)
        h = max(self.iy0 + self.ny, iy + 1) - min(self.iy0, iy)
        return w * h * self.side * self.side <= max_cells

    def paste(self, ix: int, iy: int, values: npt.NDArray[np.float64]) -> None:
        if self.nx == 0:
            self.ix0, self.iy0, self.nx, self.ny = ix, iy, 1, 1
            self.array = np.full((self.side, self.side), np.nan)
        if not (self.ix0 <= ix < self.ix0 + self.nx and self.iy0 <= iy < self.iy0 + self.ny):
            x0 = min(self.ix0, ix)
            y0 = min(self.iy0, iy)
            x1 = max(self.ix0 + self.nx, ix + 1)
            y1 = max(self.iy0 + self.ny, iy + 1)
            # grow with slack so a survey's steady growth costs amortised O(1) per subgrid
            gx = max(x1 - x0, 2 * self.nx) if (x1 - x0) > self.nx else self.nx
            gy = max(y1 - y0, 2 * self.ny) if (y1 - y0) > self.ny else self.ny
            if ix < self.ix0:
                x0 = self.ix0 + self.nx - gx
            if iy < self.iy0:
                y0 = self.iy0 + self.ny - gy
            new = np.full((gy * self.side, gx * self.side), np.nan)
            s = self.side
            new[(self.iy0 - y0) * s:(self.iy0 - y0 + self.ny) * s, (self.ix0 - x0) * s:(self.ix0 - x0 + self.nx) * s] = self.array
            self.array, self.ix0, self.iy0, self.nx, self.ny = new, x0, y0, gx, gy
        s = self.side
        r, c = (iy - self.iy0) * s, (ix - self.ix0) * s
        self.array[r:r + s, c:c + s] = values


@persistent("bathymetry.Receiver")
class BathymetryReceiver(ModalityReceiver):
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
        self.held: dict[int, dict[tuple[int, int], _Held]] = {}
        self._mosaics: dict[int, _Mosaic] = {}
        self._versions: dict[int, int] = {}
        self._geometry: dict[int, tuple[float, int]] = {}
        self.regions: list[Region] = []
        self._by_id: dict[int, Region] = {}
        self._next_id = 0
        self._next_auto = -math.inf
        self._auto_stamp: int | None = None
        self._auto_found = False
        self.duplicates = 0
        self.max_mosaic_cells = int(cfg["max_mosaic_cells"])
        #: Subgrids held but left out of the level mosaics (they would make them too large).
        self.off_mosaic: set[tuple[int, int, int]] = set()

    # ---------------------------------------------------------------------------- receive

    def receive(self, message: Message, now: float) -> list[Product]:
        if isinstance(message, Subgrid):
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
                region.answered = now
                region.waiting = message.waiting
                if message.queued == 0 and message.waiting == 0:
                    region.done = True
                elif message.queued == 0:  # it stands on the vehicle: the data follows when surveyed
                    region.next_send = now + self.standing_recheck
                else:
                    self._auto_found |= region.auto
                    region.next_send = now + self.request_timeout + self.subgrid_wait * message.queued
            return []
        return []

    def _subgrid(self, sg: Subgrid, now: float) -> list[Product]:
        level = sg.level
        stamp = unwrap(sg.stamp, now)
        cells = self.held.setdefault(level, {})
        old = cells.get((sg.ix, sg.iy))
        if old is not None and old.stamp >= stamp:
            self.duplicates += 1
            return []
        values = decode_subgrid(sg)
        cells[(sg.ix, sg.iy)] = _Held(stamp, values, now)
        self._geometry[level] = (sg.resolution * (1 << level), sg.side)
        mosaic = self._mosaics.get(level)
        if mosaic is None or mosaic.side != sg.side:
            mosaic = self._mosaics[level] = _Mosaic(sg.side)
        if not mosaic.fits(sg.ix, sg.iy, self.max_mosaic_cells // 4):  # growth may double a side
            # Held and requestable, but too far from the rest to draw without a huge array.
            self.off_mosaic.add((level, sg.ix, sg.iy))
            return []
        mosaic.paste(sg.ix, sg.iy, values)
        self._versions[level] = self._versions.get(level, 0) + 1
        return [self.level_product(level, now)]

    # ---------------------------------------------------------------------------- products

    def level_product(self, level: int, now: float | None = None) -> Product:
        """Level ``level`` as one array (row 0 = south, NaN where nothing is held)."""
        mosaic = self._mosaics[level]
        cell, side = self._geometry[level]
        held = self.held.get(level, {})
        newest = max((h.stamp for h in held.values()), default=0.0)
        meta: dict[str, Any] = {
            "level": level,
            "cell_size": cell,
            "x0": mosaic.ix0 * side * cell,
            "y0": mosaic.iy0 * side * cell,
            "subgrids": len(held),
            "newest": newest,
            "origin_lat": self.origin()[0],
            "origin_lon": self.origin()[1],
        }
        if now is not None:
            meta["oldest_age"] = now - min((h.received for h in held.values()), default=now)
        return Product("map-level", f"level-{level}", self._versions.get(level, 0), mosaic.array, meta)

    def products(self) -> list[Product]:
        return [self.level_product(k) for k in sorted(self._mosaics)]

    def levels(self) -> list[int]:
        """The levels of which something is held, finest first."""
        return sorted(k for k, held in self.held.items() if held)

    def geometry(self, level: int) -> tuple[float, int] | None:
        """``(cell size in m, subgrid side in cells)`` of a level, once a subgrid of it came."""
        return self._geometry.get(level)

    def level_version(self, level: int) -> int:
        """Changes whenever the level's mosaic does (the version of its product)."""
        return self._versions.get(level, 0)

    def origin(self) -> tuple[float, float]:
        lat, lon = self.config["origin_lat"], self.config["origin_lon"]
        if lat is None and self.metadata is not None:
            lat = self.metadata.origin_lat
        if lon is None and self.metadata is not None:
            lon = self.metadata.origin_lon
        return float(lat or 0.0), float(lon or 0.0)

    def holdings(self, level: int) -> dict[tuple[int, int], int]:
        """``(ix, iy) -> stamp`` of every subgrid held at ``level``."""
        return {k: to_stamp(h.stamp) for k, h in self.held.get(level, {}).items()}

    def age(self, level: int, ix: int, iy: int, now: float) -> float | None:
        """Seconds since the newest data in a held subgrid was measured (None if not held)."""
        h = self.held.get(level, {}).get((ix, iy))
        return None if h is None else now - h.stamp

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
        if not 0 <= level < levels:
            raise RequestRejected(f"level {level} outside 0..{levels - 1}")
        if w < 1 or h < 1:
            raise RequestRejected("empty region")
        if not (SUBGRID_INDEX_MIN <= x0 and x0 + w - 1 <= SUBGRID_INDEX_MAX
                and SUBGRID_INDEX_MIN <= y0 and y0 + h - 1 <= SUBGRID_INDEX_MAX):
            raise RequestRejected(f"region outside the map's subgrid index range "
                                  f"({SUBGRID_INDEX_MIN}..{SUBGRID_INDEX_MAX}, the wire's limit)")
        chunk = GAP_CHUNK if fill_gaps else ROI_CHUNK
        n = math.ceil(w / chunk) * math.ceil(h / chunk)
        if n > self.max_regions:
            raise RequestRejected(f"region of {w} x {h} subgrids needs {n} requests (max {self.max_regions})")
        out = []
        for cy in range(y0, y0 + h, chunk):
            for cx in range(x0, x0 + w, chunk):
                r = Region(level, cx, cy, min(chunk, x0 + w - cx), min(chunk, y0 + h - cy), fill_gaps, auto)
                self._add(r)
                out.append(r)
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
        held = self.held.get(r.level, {})
        keys = [(r.x0 + i % r.w, r.y0 + i // r.w) for i in range(r.w * r.h)]
        if r.fill_gaps:
            have = 0
            for k in keys:
                have = (have << 1) | (k in held)
            return MapRoiRequest(rid, r.level, r.x0, r.y0, r.w, r.h, True, (), have)
        stamps = tuple(to_stamp(held[k].stamp) if k in held else None for k in keys)
        return MapRoiRequest(rid, r.level, r.x0, r.y0, r.w, r.h, False, stamps)

    def poll(self, now: float) -> list[Message]:
        out: list[Message] = []
        self.regions = [r for r in self.regions if not r.done]
        # Coarse levels first, then in the order asked; a few requests per poll (the uplink is
        # slow), the rest on the next polls.
        for r in sorted(self.regions, key=lambda r: -r.level):
            if len(out) >= self.max_requests_per_poll:
                break
            if now >= r.next_send:
                out.append(self._message(r))
                r.sends += 1
                r.next_send = now + self.request_timeout
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
