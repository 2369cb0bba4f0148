"""A region request of the topside receiver, as it is tracked until the vehicle answers."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from coex import RequestRejected, persistent
from coex.tracker import State, Tracked

__all__ = ["GAP_CHUNK", "ROI_CHUNK", "SUBGRID_INDEX_MAX", "SUBGRID_INDEX_MIN", "Region", "plan"]

#: Largest region of one request with stamps (8 x 8 = 64 subgrids) and of one gap-filling request.
ROI_CHUNK = 8
GAP_CHUNK = 16
#: subgrid indices a MapRoiRequest can carry (14-bit two's complement, spec: MapRoiRequest x0/y0)
SUBGRID_INDEX_MIN, SUBGRID_INDEX_MAX = -8192, 8191


def _upgrade_region(fields: dict[str, Any], saved: int) -> dict[str, Any]:
    """Version 3 (and older) kept its own ``next_send``, ``sends``, ``done`` and ``answered``:
    now the core tracker's entry (:class:`~coex_core.tracker.Tracked`) holds them."""
    fields = {"queued": None, "waiting": 0, **fields}
    if saved < 4:
        sends = int(fields.pop("sends", 0) or 0)
        answered = fields.pop("answered", None)
        if fields.pop("done", False):
            state = State.DONE
        elif answered is not None:
            state = State.PENDING
        else:
            state = State.SENT if sends else State.QUEUED
        fields["track"] = Tracked(None, state, None, sends, float(fields.pop("next_send", -math.inf)),
                                  answered)
    return fields


@persistent("bathymetry.Region", version=4, upgrade=_upgrade_region)
@dataclass
class Region:
    """An active region request: re-sent (with fresh stamps) until the vehicle answers "nothing newer".

    Its state is the core tracker's (:mod:`coex_core.tracker`): ``queued`` (not sent yet),
    ``sent``, ``pending`` (the vehicle queued subgrids for it, or it stands there for subgrids
    not surveyed yet) and ``done`` (nothing newer)."""

    level: int
    x0: int
    y0: int
    w: int
    h: int
    fill_gaps: bool
    auto: bool = False
    #: the id of the copy sent last
    request_id: int | None = None
    #: what the vehicle last answered: subgrids it queued for the region
    queued: int | None = None
    #: subgrids of the region the vehicle has not surveyed yet: its request stands for them
    waiting: int = 0
    #: its state, sends and answers, and when it goes out again
    track: Tracked[None] = field(default_factory=lambda: Tracked(None))

    @property
    def done(self) -> bool:
        """The vehicle answered that it has nothing newer."""
        return self.track.state is State.DONE

    @property
    def sends(self) -> int:
        return self.track.tries

    @property
    def next_send(self) -> float:
        return self.track.due_at

    @property
    def answered(self) -> float | None:
        """When the vehicle last answered (None: not yet)."""
        return self.track.answered_at


def plan(level: int, x0: int, y0: int, w: int, h: int, *, levels: int, fill_gaps: bool, auto: bool,
         max_regions: int) -> list[Region]:
    """The requests that ask for subgrids ``[x0, x0+w) x [y0, y0+h)`` at ``level``: chunks of at
    most :data:`ROI_CHUNK` (with stamps) or :data:`GAP_CHUNK` (gap filling) subgrids a side.
    :class:`RequestRejected` for a level outside ``0..levels-1``, an empty region, one beyond
    the wire's subgrid indices or one that needs more than ``max_regions`` requests."""
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
    if n > max_regions:
        raise RequestRejected(f"region of {w} x {h} subgrids needs {n} requests (max {max_regions})")
    return [Region(level, cx, cy, min(chunk, x0 + w - cx), min(chunk, y0 + h - cy), fill_gaps, auto)
            for cy in range(y0, y0 + h, chunk) for cx in range(x0, x0 + w, chunk)]
