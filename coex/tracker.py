"""The one table of states every request or command topside sends goes through (``queued``,
``sent``, ``pending``, then ``done``, ``refused``, ``no answer`` or ``aborted``) and its entries
(:class:`Tracked`).

The public face of :mod:`coex_core.tracker` (``from coex.tracker import ...``): a module of its own, so
that a plugin author's type checker finds it; the names are the core's (the same objects).
"""

from __future__ import annotations

from coex_core.tracker import (
    FINAL,
    OPEN,
    TRANSITIONS,
    Event,
    State,
    Tracked,
    answer_event,
)

__all__ = [
    "Event",
    "FINAL",
    "OPEN",
    "State",
    "TRANSITIONS",
    "Tracked",
    "answer_event",
]
