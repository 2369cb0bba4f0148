"""Request to first answer, measured on the wire.

The demo's truth for "does an answer leave at the next vehicle slot": every modality request
topside transmits (its first transmission) and the first vehicle message that answers it as
topside decoded it (the ``CommandAck`` of an image or time-series request, the ``MapRoiReply`` of
a region request, to any of its retries), counted in vehicle TDMA slots started in between (1:
the next vehicle slot).
It reads the frames the topside node sends and receives; it changes nothing.
"""

from __future__ import annotations

import statistics
from collections.abc import Hashable
from typing import Any

from coex import CoexError, Node, Schedule
from coex.messages import (
    CommandAck,
    ImageByTimeRequest,
    ImageGoal,
    MapRoiReply,
    MapRoiRequest,
    Message,
    TimeSeriesRequest,
)
from coex.wire import unpack

__all__ = ["ResponseTimer"]

_COMMANDS = (ImageByTimeRequest, ImageGoal, TimeSeriesRequest)
_NEVER = 10**6  # an unanswered request


def _finite(v: float) -> float | None:
    return None if v >= _NEVER else v


class ResponseTimer:
    """Wraps ``node.poll`` and ``node.receive`` of the topside node (observes, changes nothing)."""

    def __init__(self, node: Node, schedule: Schedule, vehicle: int, epoch: float) -> None:
        self.schedule = schedule
        self.vehicle = vehicle
        self.epoch = epoch
        self._sent: dict[Hashable, tuple[str, float]] = {}
        #: request id -> the region it asked for (a region's retries carry new ids)
        self._regions: dict[int, Hashable] = {}
        self.answers: list[dict[str, Any]] = []
        poll, receive = node.poll, node.receive

        def tapped_poll(now: float) -> Any:
            txs = poll(now)
            for tx in txs:
                for frame in tx.frames:
                    for m in _messages(frame):
                        self._request(m, now)
            return txs

        def tapped_receive(link_id: int, frame: bytes, now: float) -> list[Message]:
            msgs = receive(link_id, frame, now)
            for m in msgs:
                self._answer(m, now)
            return msgs

        node.poll = tapped_poll  # type: ignore[method-assign]
        node.receive = tapped_receive  # type: ignore[method-assign]

    def _request(self, m: Message, now: float) -> None:
        if isinstance(m, _COMMANDS):
            self._sent.setdefault(("cmd", m.command_id), (type(m).__name__, now))
        elif isinstance(m, MapRoiRequest):
            region = ("roi", m.level, m.x0, m.y0, m.w, m.h, m.fill_gaps)
            self._regions[m.request_id] = region
            self._sent.setdefault(region, ("MapRoiRequest", now))

    def _answer(self, m: Message, now: float) -> None:
        key: Hashable
        if isinstance(m, CommandAck):
            key = ("cmd", m.command_id)
        elif isinstance(m, MapRoiReply):
            key = self._regions.get(m.request_id, ("roi-id", m.request_id))
        else:
            return
        sent = self._sent.pop(key, None)
        if sent is None:
            return
        kind, t0 = sent
        self.answers.append({"kind": kind, "sent_s": round(t0 - self.epoch, 1),
                             "answered_s": round(now - self.epoch, 1),
                             "vehicle_slots": self.vehicle_slots(t0, now)})

    def vehicle_slots(self, t0: float, t1: float) -> int:
        """Vehicle slots that started after ``t0`` and no later than ``t1``."""
        n = 0
        t = t0 + 1e-6
        while True:
            w = self.schedule.next_window(t, self.vehicle)
            if w is None or w.start > t1:
                return n
            if w.start > t0:
                n += 1
            t = w.end + 1e-6

    def summary(self) -> dict[str, Any]:
        """``requests`` sent, ``answered``, the median vehicle slots to the first answer and
        the share answered at the next vehicle slot (unanswered requests count as late)."""
        slots = [a["vehicle_slots"] for a in self.answers]
        total = len(self.answers) + len(self._sent)
        return {
            "requests": total,
            "answered": len(self.answers),
            "median_vehicle_slots": _finite(statistics.median(slots + [_NEVER] * len(self._sent))) if total else None,
            "at_next_vehicle_slot": round(sum(1 for s in slots if s <= 1) / total, 3) if total else None,
            "by_kind": {k: sum(1 for a in self.answers if a["kind"] == k)
                        for k in sorted({a["kind"] for a in self.answers})},
            "answers": self.answers,
            "unanswered": [{"kind": kind, "sent_s": round(t0 - self.epoch, 1)} for kind, t0 in self._sent.values()],
        }


def _messages(frame: bytes) -> list[Message]:
    try:
        return list(unpack(frame))
    except CoexError:
        return []
