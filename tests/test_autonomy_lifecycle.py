"""The survey lifecycle every autonomy output shares (``coex_plugins.autonomy.lifecycle``): an
ended survey is taken back from the autonomy (``end``) and never handed to it again, across
restarts of the daemon; answers that come after a survey ended are recorded in its record and
logged, never applied; a survey whose autonomy falls silent while it flies is aborted
``AUTONOMY_SILENT`` within the output's ``silence``. Here with a scripted output and the real
survey sender; each built-in output's own ended form and liveness are tested with its real peer
(tests/test_ros.py, test_autonomy_mavlink.py, test_autonomy.py, test_moos_ivp.py)."""

from __future__ import annotations

import logging
from typing import Any

import pytest

from coex import Autonomy, InputContext
from coex_core.messages import AckStatus, SurveyCommand, SurveyKind, SurveyReason, SurveyState
from coex_core.state import dumps, loads
from coex_plugins.autonomy.lifecycle import REEND
from coex_plugins.survey.plan import SurveyReport

from ._lifecycle import Vehicle


class Scripted(Autonomy):
    """An output whose autonomy the test plays: what it was told, and the reports it gives."""

    name = "scripted"
    options = {"silence": (5.0, "seconds")}

    def __init__(self, options: Any = None, context: Any = None, *, resumes: bool = True) -> None:
        super().__init__(options or {}, context or InputContext())
        self.calls: list[tuple[str, int]] = []
        self.queue: list[SurveyReport] = []
        self.heard_at: float | None = None
        self.resumes = resumes

    def submit(self, plan: Any, now: float) -> None:
        self.calls.append(("submit", int(plan.survey_id)))

    def resume(self, plan: Any, now: float) -> bool:
        self.calls.append(("resume", int(plan.survey_id)))
        return self.resumes

    def end(self, survey_id: int, now: float) -> None:
        self.calls.append(("end", int(survey_id)))

    def poll(self, now: float) -> list[Any]:
        out, self.queue = self.queue, []
        return out

    def heard(self, now: float) -> float | None:
        return self.heard_at

    def silent_detail(self) -> str:
        return "no heartbeat"

    def says(self, sid: int, state: SurveyState, t: float, reason: SurveyReason = SurveyReason.NONE,
             index: int | None = None) -> None:
        self.queue.append(SurveyReport(sid, state, t, reason, index))


@pytest.mark.parametrize("final", [SurveyState.COMPLETED, SurveyState.REJECTED, SurveyState.ABORTED])
def test_an_ended_survey_is_taken_back_once_and_its_late_answers_recorded(
        final: SurveyState, caplog: pytest.LogCaptureFixture) -> None:
    v = Vehicle(Scripted())
    v.ask(1, 0.0)
    assert v.step(1.0) == [] and v.out.calls == [("submit", 1)]
    reason = {SurveyState.REJECTED: SurveyReason.AUTONOMY_REFUSED, SurveyState.ABORTED: SurveyReason.MANUAL_OVERRIDE}
    v.out.says(1, SurveyState.STARTED, 2.0, index=0)
    v.out.says(1, final, 3.0, reason.get(final, SurveyReason.NONE))
    assert [r[1] for r in v.step(3.0)] == [SurveyState.STARTED, final]
    assert v.out.calls == [("submit", 1), ("end", 1)]
    assert v.store["vehicle.ended"] == v.store["vehicle.submitted"]
    # a planner answering after the end (a respawned one flying it, its queue flushed late)
    caplog.set_level(logging.WARNING, "coex.vehicle")
    v.out.says(1, SurveyState.STARTED, 4.0, index=0)
    assert v.step(4.0) == [(1, SurveyState.STARTED, SurveyReason.NONE)]
    assert v.sender.state_of(1) == final  # never applied
    assert v.sender.late(1) == [(4.0, "STARTED", 0, "NONE", None)]
    assert v.out.calls[-1] == ("end", 1)  # it still flies it: taken back again
    assert any("late answer" in r.message and "started 0" in r.message for r in caplog.records)
    n = len(v.out.calls)
    v.out.says(1, SurveyState.STARTED, 5.0, index=0)
    v.step(5.0)
    assert len(v.out.calls) == n  # not again within REEND seconds
    v.out.says(1, SurveyState.STARTED, 5.0 + REEND, index=1)
    v.step(5.0 + REEND)
    assert v.out.calls[-1] == ("end", 1) and len(v.out.calls) == n + 1
    assert [c for c in v.out.calls if c[0] == "submit"] == [("submit", 1)]  # never handed again
    assert v.life.counts["late"] == 3


def test_a_silent_autonomy_aborts_the_survey_within_its_bound() -> None:
    v = Vehicle(Scripted())  # silence = 5 s
    v.ask(1, 0.0)
    v.out.heard_at = 0.0
    v.step(0.0)
    assert v.step(100.0) == []  # silent, but nothing flies yet (an upload's own retries answer that)
    v.out.says(1, SurveyState.STARTED, 101.0, index=0)
    v.out.heard_at = 101.0
    assert v.step(101.0) == [(1, SurveyState.STARTED, SurveyReason.NONE)]
    v.out.heard_at = 103.0
    assert v.step(106.0) == []  # 3 s since its last heartbeat
    v.out.heard_at = None  # cannot tell: not watched
    assert v.step(200.0) == []
    v.out.heard_at = 103.0
    [r] = v.life.step(108.5)
    assert (r.survey_id, r.state, r.reason, r.value, r.detail) == (
        1, SurveyState.ABORTED, SurveyReason.AUTONOMY_SILENT, 5.5, "no heartbeat")
    v.sender.ingest([r], 108.5)
    assert v.out.calls[-1] == ("end", 1) and v.sender.state_of(1) == SurveyState.ABORTED
    assert v.life.step(300.0) == [] and v.life.counts["silent"] == 1
    status = v.sender.fill(1000, 109.0)[-1]
    assert (status.reason, status.value, status.detail) == (SurveyReason.AUTONOMY_SILENT, 5.5, "no heartbeat")


def test_silence_zero_is_not_watched() -> None:
    v = Vehicle(Scripted({"silence": 0}))
    v.ask(1, 0.0)
    v.step(0.0)
    v.out.says(1, SurveyState.STARTED, 1.0, index=0)
    v.out.heard_at = 1.0
    v.step(1.0)
    assert v.step(10_000.0) == []


def test_across_restarts_an_ended_survey_is_never_handed_again() -> None:
    store: dict[str, str] = {}
    v = Vehicle(Scripted(), store)
    v.ask(1, 0.0)
    v.step(0.0)
    saved = dumps(v.sender)  # the store's snapshot, taken while it flies

    # the daemon restarts while it flies: followed again, not handed anew
    again = Vehicle(Scripted(), store, loads(saved))
    assert again.step(10.0) == [] and again.out.calls == [("resume", 1)]
    again.out.heard_at = -float("inf")  # nothing heard since the restart
    assert [r[2] for r in again.step(16.0)] == [SurveyReason.AUTONOMY_SILENT]  # watched from the resumption
    assert again.out.calls == [("resume", 1), ("end", 1)]
    saved = dumps(again.sender)

    # and restarts again once it ended: neither resumed nor handed, nor ended twice
    third = Vehicle(Scripted(), store, loads(saved))
    assert third.step(20.0) == [] and third.out.calls == []

    # the end reached the survey sender (journaled) but not the output: it is ended at start
    store["vehicle.ended"] = "0:0"
    fourth = Vehicle(Scripted(), store, loads(saved))
    fourth.step(30.0)
    assert fourth.out.calls == [("end", 1)] and store["vehicle.ended"] == store["vehicle.submitted"]
    # a late answer after the restart is still the ended survey's
    fourth.out.says(1, SurveyState.COMPLETED, 31.0)
    assert fourth.step(31.0) == [(1, SurveyState.COMPLETED, SurveyReason.NONE)]
    assert fourth.sender.state_of(1) == SurveyState.ABORTED and fourth.sender.late(1)[-1][1] == "COMPLETED"


def test_an_output_that_cannot_resume_is_not_watched() -> None:
    store: dict[str, str] = {}
    v = Vehicle(Scripted(), store)
    v.ask(1, 0.0)
    v.step(0.0)
    again = Vehicle(Scripted(resumes=False), store, loads(dumps(v.sender)))
    again.out.heard_at = -float("inf")
    assert again.step(1.0) == [] and again.step(1000.0) == []


def test_a_newer_survey_replaces_the_old_whose_answers_are_then_late() -> None:
    v = Vehicle(Scripted())
    v.ask(1, 0.0)
    v.step(0.0)
    v.out.says(1, SurveyState.STARTED, 1.0, index=0)
    v.step(1.0)
    v.ask(2, 2.0, x=20.0)  # replaces 1 (SUPERSEDED, the sender's)
    v.out.says(1, SurveyState.STARTED, 2.5, index=1)  # the older one's, read with the handing over
    assert v.step(3.0) == [(1, SurveyState.STARTED, SurveyReason.NONE)]
    assert v.out.calls == [("submit", 1), ("submit", 2), ("end", 1)]  # no end of the newer one
    assert v.sender.state_of(1) == SurveyState.ABORTED and v.sender.late(1)[0][1:3] == ("STARTED", 1)
    v.out.says(2, SurveyState.STARTED, 4.0, index=0)
    v.out.says(2, SurveyState.COMPLETED, 5.0)
    v.step(5.0)
    assert v.out.calls[-1] == ("end", 2) and v.sender.state_of(2) == SurveyState.COMPLETED


def test_a_survey_the_vehicle_itself_ends_is_taken_back() -> None:
    v = Vehicle(Scripted())
    v.ask(1, 0.0)
    v.step(0.0)
    # topside re-uses the id for a command the vehicle refuses: survey 1 is no longer to be flown
    [ack] = v.sender.handle(SurveyCommand(9, 1, SurveyKind.GOTO, 5000.0, 0.0), 1.0)
    assert ack.status == AckStatus.REJECTED and v.sender.active_plan() is None
    v.step(1.0)
    assert v.out.calls == [("submit", 1), ("end", 1)]


def test_reports_about_a_mission_never_handed_over_pass_as_they_are() -> None:
    v = Vehicle(Scripted())
    v.out.says(900, SurveyState.STARTED, 1.0, index=0)
    assert v.step(1.0) == [(900, SurveyState.STARTED, SurveyReason.NONE)]
    assert v.out.calls == [] and v.sender.state_of(900) == SurveyState.STARTED


def test_the_base_class_defaults_watch_nothing() -> None:
    class Bare(Autonomy):
        name = "bare"
        options: dict[str, Any] = {}

        def submit(self, plan: Any, now: float) -> None:
            pass

        def poll(self, now: float) -> list[Any]:
            return []

    b = Bare({}, InputContext())
    assert (b.heard(0.0), b.silence(), b.silent_detail(), b.end(1, 0.0)) == (None, 0.0, "", None)
