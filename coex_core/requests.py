"""The request tracker of CoEx receivers: a request goes out at once, again every ``retry``
seconds while it is unanswered, at most ``max_tries`` times; then it is given up.

A receiver adds each request under a key (its command id), tells the tracker when the answer
came (:meth:`RequestTracker.answered`, e.g. on the vehicle's CommandAck) or what counts as done
(``done`` of :meth:`RequestTracker.due`, e.g. the data arrived), and returns
:meth:`RequestTracker.due` from its ``poll``. Sans-I/O: time comes in as ``now``.

Each request is a :class:`~coex_core.tracker.Tracked` entry and moves through the states of
:data:`coex_core.tracker.TRANSITIONS` (queued, sent, done, no answer); a finished one leaves
the tracker.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Hashable
from typing import Any, Generic, TypeVar

from .errors import ConfigError
from .state import persistent
from .tracker import Event, Tracked, answer_event

__all__ = ["Pending", "RequestTracker"]

M = TypeVar("M")

#: a tracked request (the name of 0.1, kept for plugins that import it)
Pending = Tracked


def _upgrade_tracker(fields: dict[str, Any], saved: int) -> dict[str, Any]:
    """Version 1's entries knew when they were sent, not when they are due: again ``retry``
    seconds after that send."""
    if saved < 2:
        retry = float(fields.get("retry", 0.0))
        for p in dict(fields.get("_items") or {}).values():
            if isinstance(p, Tracked) and p.sent_at is not None:
                p.due_at = p.sent_at + retry
    return fields


@persistent("core.RequestTracker", version=2, upgrade=_upgrade_tracker)
class RequestTracker(Generic[M]):
    """Requests awaiting an answer, in the order they were added."""

    def __init__(self, retry: float, max_tries: int) -> None:
        if not (math.isfinite(retry) and retry > 0) or max_tries < 1:
            raise ConfigError("a request retry interval and try count must be positive")
        self.retry = float(retry)
        self.max_tries = int(max_tries)
        self._items: dict[Hashable, Tracked[M]] = {}
        #: requests given up after ``max_tries`` sends without an answer
        self.given_up = 0

    def add(self, key: Hashable, message: M) -> M:
        """Track ``message`` (it goes out at the next :meth:`due`); a request under the same key
        is replaced."""
        self._items[key] = Tracked(message)
        return message

    def answered(self, key: Hashable, now: float | None = None, status: str = "ACCEPTED") -> Tracked[M] | None:
        """Stop tracking the request under ``key``, answered (at ``now`` when given; ``status``:
        the vehicle's answer, an :class:`~coex_core.messages.AckStatus` name); returns it, in the
        state that answer leads to (None: not tracked)."""
        p = self._items.pop(key, None)
        if p is not None:
            p.apply(answer_event(status), math.nan if now is None else now, answer=status)
            if now is None:
                p.answered_at = None
        return p

    def due(self, now: float, done: Callable[[M], bool] | None = None) -> list[M]:
        """The requests to send now: new ones, and those unanswered ``retry`` s after their last
        send (or when the clock went back). ``done(message)`` true drops a request as answered;
        one sent ``max_tries`` times and unanswered ``retry`` s later is given up."""
        out: list[M] = []
        for key, p in list(self._items.items()):
            if done is not None and done(p.message):
                p.apply(Event.ACCEPT, now)
                del self._items[key]
                continue
            if not p.is_due(now):
                continue
            if p.tries >= self.max_tries:
                p.apply(Event.GIVE_UP, now)
                del self._items[key]
                self.given_up += 1
                continue
            p.send(now, self.retry)
            out.append(p.message)
        return out

    def pending(self, done: Callable[[M], bool] | None = None) -> list[M]:
        """The tracked requests (without those ``done`` says are answered), oldest first."""
        return [p.message for p in self._items.values() if done is None or not done(p.message)]

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, key: object) -> bool:
        return key in self._items
