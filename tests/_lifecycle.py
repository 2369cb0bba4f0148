"""The vehicle daemon's composition around an autonomy output, for the outputs' lifecycle
tests: the survey sender, the survey lifecycle between it and the output
(``coex_plugins.autonomy.lifecycle``), a store (a dict), and every report ingested as the daemon
ingests them."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from coex_core.messages import AckStatus, SurveyCommand, SurveyKind, SurveyReason, SurveyState
from coex_plugins.autonomy.lifecycle import SurveyLifecycle
from coex_plugins.survey import SurveySender

__all__ = ["Vehicle"]


class Vehicle:
    """``out`` between a survey sender and the lifecycle; ``clock`` gives ``now`` (the wall
    clock unless told)."""

    def __init__(self, out: Any, store: dict[str, str] | None = None, sender: SurveySender | None = None, *,
                 clock: Callable[[], float] = time.time, name: str = "test") -> None:
        self.out = out
        self.clock = clock
        self.store = {} if store is None else store
        self.sender = sender or SurveySender({"geofence": {"radius": 1000.0}})
        self.life = SurveyLifecycle(out, self.sender, get=self.store.get, put=self.store.__setitem__, name=name)
        self.reports: list[Any] = []
        self.cid = 0

    def ask(self, sid: int, now: float | None = None, x: float = 10.0, y: float = 0.0, *,
            kind: SurveyKind = SurveyKind.GOTO, **fields: Any) -> None:
        """Topside asks for survey ``sid`` (a go-to by default); the vehicle accepts it."""
        self.cid += 1
        if kind == SurveyKind.LINE:
            fields = {"heading": 90.0, "length": 20.0, **fields}
        [ack] = self.sender.handle(SurveyCommand(self.cid, sid, kind, x, y, **fields),
                                   self.clock() if now is None else now)
        assert ack.status == AckStatus.ACCEPTED, ack

    def step(self, now: float | None = None) -> list[tuple[int, SurveyState, SurveyReason]]:
        """One step of the daemon: the lifecycle, its reports ingested."""
        t = self.clock() if now is None else now
        got = self.life.step(t)
        self.sender.ingest(got, t)
        self.reports += got
        return [(r.survey_id, SurveyState(r.state), SurveyReason(r.reason)) for r in got]

    def until(self, what: str, cond: Callable[[], Any], timeout: float = 30.0, every: float = 0.01,
              also: Callable[[], Any] | None = None) -> Any:
        """Step (and ``also()``) until ``cond()`` holds, at most ``timeout`` real seconds."""
        end = time.monotonic() + timeout
        while True:
            if also is not None:
                also()
            self.step()
            got = cond()
            if got:
                return got
            if time.monotonic() > end:
                raise AssertionError(f"timed out after {timeout:g} s waiting for {what}; reports: {self.reports}")
            time.sleep(every)

    def state(self, sid: int) -> SurveyState | None:
        return self.sender.state_of(sid)

    def final(self, sid: int) -> Any:
        """The report that ended survey ``sid``."""
        ended = [r for r in self.reports if r.survey_id == sid
                 and SurveyState(r.state) in (SurveyState.COMPLETED, SurveyState.REJECTED, SurveyState.ABORTED)]
        return ended[0] if ended else None
