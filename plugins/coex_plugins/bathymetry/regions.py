"""A region request of the topside receiver, as it is tracked until the vehicle answers."""

from __future__ import annotations

import math
from dataclasses import dataclass

from coex_core.state import persistent

__all__ = ["Region"]


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
