"""Decoded CoEx data as LCM types, for LCM tools (``lcm-spy``, ``lcm-logplayer``, consoles).

* ``coex.vehicle_status_t``: :func:`vehicle_status_to_lcm` / :func:`vehicle_status_from_lcm`
  convert a :class:`~coex_core.messages.VehicleStatus` both ways (lossless for values on the
  wire grid).
* ``coex.map_level_t``: :class:`MapLevelSummary` keeps the newest subgrid of each map cell block
  and summarises each level (subgrids, cells, extent, depth range, newest stamp). A subgrid
  predicted from its parent (``PredictedSubgrid``) is rebuilt with the parent's cells the
  summary holds; without them its depth range is unknown (NaN) until it comes again.

Pure functions and objects: no LCM instance, no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from coex_core.messages import (
    PredictedSubgrid,
    Subgrid,
    SubgridContext,
    SubgridMessage,
    VehicleMode,
    VehicleStatus,
)
from coex_core.predicted import ABSENT, ContextMismatch, SubgridParent, decode_predicted_units
from coex_core.subgrid import decode_subgrid, decode_subgrid_units

from ._types import map_level_t, vehicle_status_t

__all__ = [
    "MAP_LEVEL_CHANNEL",
    "VEHICLE_STATUS_CHANNEL",
    "MapLevelSummary",
    "vehicle_status_from_lcm",
    "vehicle_status_to_lcm",
]

#: Default channel names for the decoded types.
VEHICLE_STATUS_CHANNEL = "COEX_VEHICLE_STATUS"
MAP_LEVEL_CHANNEL = "COEX_MAP_LEVEL"


def vehicle_status_to_lcm(status: VehicleStatus, utime: int = 0) -> vehicle_status_t:
    """A ``coex.vehicle_status_t`` for a received VehicleStatus (``utime``: µs since 1970)."""
    out = vehicle_status_t()
    out.utime = int(utime)
    out.stamp = int(status.stamp)
    out.x = float(status.x)
    out.y = float(status.y)
    out.depth = float(status.depth)
    out.has_altitude = status.altitude is not None
    out.altitude = float(status.altitude) if status.altitude is not None else math.nan
    out.heading = float(status.heading)
    out.speed = float(status.speed)
    out.battery = int(status.battery)
    mode = VehicleMode(int(status.mode))
    out.mode = int(mode)
    out.mode_name = mode.name
    out.faults = int(status.faults)
    return out


def vehicle_status_from_lcm(msg: vehicle_status_t) -> VehicleStatus:
    """The VehicleStatus a ``coex.vehicle_status_t`` describes."""
    return VehicleStatus(
        stamp=int(msg.stamp),
        x=float(msg.x),
        y=float(msg.y),
        depth=float(msg.depth),
        altitude=float(msg.altitude) if msg.has_altitude else None,
        heading=float(msg.heading),
        speed=float(msg.speed),
        battery=int(msg.battery),
        mode=VehicleMode(int(msg.mode)),
        faults=int(msg.faults),
    )


def _cells(sub: SubgridMessage) -> int:
    mask = sub.cells.mask if isinstance(sub, PredictedSubgrid) else sub.mask
    if mask is None:
        return int(sub.side) * int(sub.side)
    return int(mask).bit_count()


class MapLevelSummary:
    """Per-level summary of the received bathymetry map (``coex.map_level_t``).

    :meth:`add` keeps the newest subgrid per ``(level, ix, iy)`` (the last one added wins: the
    order of reception); :meth:`summary` / :meth:`summaries` describe the levels. Depths come
    from ``decoder(subgrid) -> array of elevations (NaN = empty)``, by default
    :func:`coex_core.subgrid.decode_subgrid` (the wire format's own decoding)."""

    def __init__(self, decoder: Callable[[Subgrid], Any] | None = None) -> None:
        self._decoder: Callable[[Subgrid], Any] = decoder if decoder is not None else decode_subgrid
        self._blocks: dict[int, dict[tuple[int, int], tuple[SubgridMessage, float, float]]] = {}
        #: cells (vertical units) of the subgrids of the levels above the finest, for their
        #: children predicted from them; each level's vertical resolution and level-0 cell size
        self._units: dict[tuple[int, int, int], np.ndarray] = {}
        self._vres: dict[int, float] = {}
        self._resolution: float | None = None

    def _predicted(self, sub: PredictedSubgrid) -> Any:
        """Elevations (m) of a predicted subgrid, from the parent cells held (NaN: not held)."""
        if sub.context == SubgridContext.NONE:
            assert sub.vertical_resolution is not None
            units, vres = decode_predicted_units(sub), sub.vertical_resolution
        else:
            held = self._units.get((sub.level + 1, sub.ix >> 1, sub.iy >> 1))
            vres_up = self._vres.get(sub.level + 1)
            if held is None or vres_up is None:
                return np.full((sub.side, sub.side), np.nan)
            try:
                units = decode_predicted_units(sub, SubgridParent(held, held != ABSENT))
            except ContextMismatch:
                return np.full((sub.side, sub.side), np.nan)
            vres = vres_up
        self._keep(sub.level, sub.ix, sub.iy, units, vres)
        return np.where(units != ABSENT, units * vres, np.nan)

    def _keep(self, level: int, ix: int, iy: int, units: Any, vres: float) -> None:
        self._vres[level] = vres
        if level > 0:  # the finest level's cells are nobody's parent
            self._units[(level, ix, iy)] = np.asarray(units, np.int64)

    def _z_range(self, sub: SubgridMessage) -> tuple[float, float]:
        try:
            if isinstance(sub, PredictedSubgrid):
                z = np.asarray(self._predicted(sub), dtype=float)
            else:
                self._resolution = sub.resolution
                z = np.asarray(self._decoder(sub), dtype=float)
                if sub.level > 0:  # a parent of predicted subgrids: its cells as the wire says
                    self._keep(sub.level, sub.ix, sub.iy, decode_subgrid_units(sub), sub.vertical_resolution)
        except Exception:
            return math.nan, math.nan
        finite = z[np.isfinite(z)]
        if finite.size == 0:
            return math.nan, math.nan
        return float(finite.min()), float(finite.max())

    def add(self, sub: SubgridMessage) -> int:
        """Take a received subgrid; return its level."""
        if isinstance(sub, PredictedSubgrid) and sub.resolution is not None:
            self._resolution = sub.resolution
        lo, hi = self._z_range(sub)
        self._blocks.setdefault(int(sub.level), {})[(int(sub.ix), int(sub.iy))] = (sub, lo, hi)
        return int(sub.level)

    def levels(self) -> list[int]:
        return sorted(self._blocks)

    def summary(self, level: int, utime: int = 0) -> map_level_t:
        """The ``coex.map_level_t`` of one level (``KeyError`` if nothing arrived for it)."""
        blocks = self._blocks[level]
        subs = [entry[0] for entry in blocks.values()]
        ix = np.fromiter((s.ix for s in subs), dtype=np.int64, count=len(subs))
        iy = np.fromiter((s.iy for s in subs), dtype=np.int64, count=len(subs))
        res0 = self._resolution if self._resolution is not None else math.nan
        span = np.fromiter(
            ((res0 if s.resolution is None else s.resolution) * 2.0**s.level * s.side for s in subs),
            dtype=float, count=len(subs))
        z = np.array([(entry[1], entry[2]) for entry in blocks.values()], dtype=float)
        out = map_level_t()
        out.utime = int(utime)
        out.level = int(level)
        out.resolution = float(res0 * 2.0**level)
        out.subgrids = len(subs)
        out.cells = int(sum(_cells(s) for s in subs))
        out.x_min = float((ix * span).min())
        out.y_min = float((iy * span).min())
        out.x_max = float(((ix + 1) * span).max())
        out.y_max = float(((iy + 1) * span).max())
        out.z_min = float(np.nanmin(z[:, 0])) if np.isfinite(z[:, 0]).any() else math.nan
        out.z_max = float(np.nanmax(z[:, 1])) if np.isfinite(z[:, 1]).any() else math.nan
        out.newest_stamp = int(max(s.stamp for s in subs))
        return out

    def summaries(self, utime: int = 0) -> list[map_level_t]:
        return [self.summary(level, utime) for level in self.levels()]
