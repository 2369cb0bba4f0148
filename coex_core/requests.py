"""The one request tracker of CoEx receivers: a request goes out at once, again every ``retry``
seconds while it is unanswered, at most ``max_tries`` times; then it is given up.

A receiver adds each request under a key (its command id), tells the tracker when the answer
came (:meth:`RequestTracker.answered`, e.g. on the vehicle's CommandAck) or what counts as done
(``done`` of :meth:`RequestTracker.due`, e.g. the data arrived), and returns
:meth:`RequestTracker.due` from its ``poll``. Sans-I/O: time comes in as ``now``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Generic, TypeVar

from .errors import ConfigError
from .state import persistent

__all__ = ["Pending", "RequestTracker"]

M = TypeVar("M")


@persistent("core.Pending")
@dataclass
class Pending(Generic[M]):
    """One tracked request: the message, when it was last sent (None: not yet), how often."""

    message: M
    sent_at: float | None = None
    tries: int = 0


@persistent("core.RequestTracker")
class RequestTracker(Generic[M]):
    """Requests awaiting an answer, in the order they were added."""

    def __init__(self, retry: float, max_tries: int) -> None:
        if not (math.isfinite(retry) and retry > 0) or max_tries < 1:
            raise ConfigError("a request retry interval and try count must be positive")
        self.retry = float(retry)
        self.max_tries = int(max_tries)
        self._items: dict[Hashable, Pending[M]] = {}
        #: requests given up after ``max_tries`` sends without an answer
        self.given_up = 0

    def add(self, key: Hashable, message: M) -> M:
        """Track ``message`` (it goes out at the next :meth:`due`); a request under the same key
        is replaced."""
        self._items[key] = Pending(message)
        return message

    def answered(self, key: Hashable) -> Pending[M] | None:
        """Stop tracking the request under ``key``; returns it (None: not tracked)."""
        return self._items.pop(key, None)

    def due(self, now: float, done: Callable[[M], bool] | None = None) -> list[M]:
        """The requests to send now: new ones, and those unanswered ``retry`` s after their last
        send (or when the clock went back). ``done(message)`` true drops a request as answered;
        one sent ``max_tries`` times and unanswered ``retry`` s later is given up."""
        out: list[M] = []
        for key, p in list(self._items.items()):
            if done is not None and done(p.message):
                del self._items[key]
                continue
            if p.sent_at is not None and p.sent_at <= now < p.sent_at + self.retry:
                continue
            if p.tries >= self.max_tries:
                del self._items[key]
                self.given_up += 1
                continue
            p.sent_at = now
            p.tries += 1
            out.append(p.message)
        return out

    def pending(self, done: Callable[[M], bool] | None = None) -> list[M]:
        """The tracked requests (without those ``done`` says are answered), oldest first."""
        return [p.message for p in self._items.values() if done is None or not done(p.message)]

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, key: object) -> bool:
        return key in self._items
