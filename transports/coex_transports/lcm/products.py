"""Decoded CoEx data as LCM types, for LCM tools (``lcm-spy``, ``lcm-logplayer``, consoles).

* ``coex.vehicle_status_t``: :func:`vehicle_status_to_lcm` / :func:`vehicle_status_from_lcm`
  convert a :class:`~coex_core.messages.VehicleStatus` both ways (lossless for values on the
  wire grid).
* ``coex.map_level_t``: :class:`MapLevelSummary` keeps the newest subgrid of each map cell block
  and summarises each level (subgrids, cells, extent, depth range, newest stamp).

Pure functions and objects: no LCM instance, no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from coex_core.messages import Subgrid, VehicleMode, VehicleStatus
from coex_core.subgrid import decode_subgrid

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


def _cells(sub: Subgrid) -> int:
    if sub.mask is None:
        return int(sub.side) * int(sub.side)
    return int(sub.mask).bit_count()


class MapLevelSummary:
    """Per-level summary of the received bathymetry map (``coex.map_level_t``).

    :meth:`add` keeps the newest subgrid per ``(level, ix, iy)`` (the last one added wins: the
    order of reception); :meth:`summary` / :meth:`summaries` describe the levels. Depths come
    from ``decoder(subgrid) -> array of elevations (NaN = empty)``, by default
    :func:`coex_core.subgrid.decode_subgrid` (the wire format's own decoding)."""

    def __init__(self, decoder: Callable[[Subgrid], Any] | None = None) -> None:
        self._decoder: Callable[[Subgrid], Any] = decoder if decoder is not None else decode_subgrid
        self._blocks: dict[int, dict[tuple[int, int], tuple[Subgrid, float, float]]] = {}

    def _z_range(self, sub: Subgrid) -> tuple[float, float]:
        try:
            z = np.asarray(self._decoder(sub), dtype=float)
        except Exception:
            return math.nan, math.nan
        finite = z[np.isfinite(z)]
        if finite.size == 0:
            return math.nan, math.nan
        return float(finite.min()), float(finite.max())

    def add(self, sub: Subgrid) -> int:
        """Take a received subgrid; return its level."""
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
        span = np.fromiter(
            (s.resolution * 2.0**s.level * s.side for s in subs), dtype=float, count=len(subs)
        )
        z = np.array([(entry[1], entry[2]) for entry in blocks.values()], dtype=float)
        out = map_level_t()
        out.utime = int(utime)
        out.level = int(level)
        out.resolution = float(subs[0].resolution * 2.0**level)
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
