"""One survey lifecycle for every autonomy output: what the vehicle daemon does between the
survey sender (which survey to fly now) and the ``[autonomy]`` output (``docs/autonomy.md``,
"The survey lifecycle").

:class:`SurveyLifecycle` hands the survey to fly now to the output (``submit``; after a restart of
the daemon the survey handed before is followed again with ``resume``, never handed anew), takes
the output's reports, and holds three rules for every output alike:

* **An ended survey is taken back.** When a survey ends (the output reports it completed,
  rejected or aborted, or the lifecycle aborts it for silence) the output's
  :meth:`~coex.Autonomy.end` replaces what it left behind with its ended form (the ``ros``
  output's empty path, the ``moos`` output's deactivation, the ``mavlink`` output's cleared
  mission, the ``lcm`` output's empty request), so that a planner, helm or autopilot that starts
  or restarts later is not handed it. After a restart of the daemon, a survey handed before the
  restart that ended meanwhile, whose end the output was not told, is ended then.
* **A late answer is recorded, not dropped.** A report about a survey that already ended (a
  planner's ``started`` after it was given up, an autopilot still flying an aborted mission) is
  logged, kept in the survey's record (the survey sender's :meth:`late`), and never changes its
  final state; one that shows the autonomy flying it (``STARTED``) ends it again (at most every
  :data:`REEND` seconds).
* **A silent autonomy aborts the survey.** From the survey's first ``STARTED`` (or its resumption
  after a restart) until it ends, the output's :meth:`~coex.Autonomy.heard` (its autopilot's
  heartbeat, the helm's postings, its planner's presence) may not be older than
  :meth:`~coex.Autonomy.silence` seconds: then the survey is reported ``ABORTED``,
  ``AUTONOMY_SILENT`` (``value`` the seconds of silence, ``detail`` what was not heard), told
  topside like any report, and ended.

The lifecycle keeps its own memory in the daemon's store (``get``/``put`` of two keys:
``vehicle.submitted``, the survey and plan version last handed over, and ``vehicle.ended``, the
last one whose end the output was told) and reads which surveys ended from the survey sender,
whose state the store keeps: so every rule holds across restarts of the daemon. Sans-I/O: time
comes from ``now``; nothing sleeps.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from coex import Autonomy
from coex.messages import SurveyReason, SurveyState

from ..options import LogOnce
from ..survey.plan import SurveyReport, cut_detail

__all__ = ["ENDED", "REEND", "SurveyLifecycle"]

log = logging.getLogger("coex.vehicle")

#: the final states
ENDED = (SurveyState.REJECTED, SurveyState.COMPLETED, SurveyState.ABORTED)
#: seconds between two ends of one survey on late answers that show it flown
REEND = 10.0
#: surveys this process saw end, remembered for late answers (beyond the survey sender's)
_REMEMBER = 256


@dataclass
class _Flight:
    """The survey the output has now: its id, the key it was handed under, and since when it
    flies (its first STARTED, or its resumption; None: not yet)."""

    survey_id: int
    key: str
    flying_since: float | None = None


class SurveyLifecycle:
    """Between the survey sender and an autonomy output (module docstring). ``survey``: the
    survey sender (``active_plan()``, ``plan_version``, ``state_of(id)``); ``get``/``put``: the
    daemon's store (None: nothing kept across restarts); ``name``: the output's type, for the
    log."""

    def __init__(self, output: Autonomy, survey: Any, *, get: Callable[[str], str | None] | None = None,
                 put: Callable[[str, str], None] | None = None, name: str = "autonomy") -> None:
        self.output = output
        self.survey = survey
        self._get = get
        self._put = put
        self.name = name
        self.submitted: str | None = get("vehicle.submitted") if get else None
        self.ended_key: str | None = get("vehicle.ended") if get else None
        self.flight: _Flight | None = None
        self._first = True
        self._ended: OrderedDict[int, str] = OrderedDict()  # ended in this process: id -> key
        self._reended: dict[int, float] = {}
        self._log_late = LogOnce(log)
        #: surveys handed over, resumed, ended (the output told), late answers, silences
        self.counts = {"submitted": 0, "resumed": 0, "ended": 0, "late": 0, "silent": 0}

    # ------------------------------------------------------------------ the store
    def _keep(self, key: str, value: str) -> None:
        if self._put is not None:
            self._put(key, value)

    def _sid(self, key: str | None) -> int | None:
        try:
            return int(str(key).split(":", 1)[0]) if key else None
        except ValueError:
            return None

    # ------------------------------------------------------------------ one step
    def step(self, now: float) -> list[SurveyReport]:
        """Hand over the survey to fly now, poll the output, apply the rules (module docstring);
        the reports for the survey sender. Raises what the output raises (the daemon guards it)."""
        plan = self.survey.active_plan()
        key = None if plan is None else f"{plan.survey_id}:{self.survey.plan_version}"
        if self._first:
            self._first = False
            self._restarted(plan, key, now)
        f = self.flight
        if f is not None and plan is None and self.survey.state_of(f.survey_id) in ENDED:
            self._end(f.survey_id, f.key, now)  # ended on the vehicle's side (a refused re-send of its id)
        if plan is not None and key != self.submitted:
            self._submit(plan, key, now)
        out: list[SurveyReport] = []
        for r in self.output.poll(now) or []:
            self._take(r, now, out)
        self._watch(now, out)
        return out

    def _restarted(self, plan: Any, key: str | None, now: float) -> None:
        """The first step of this process: follow the survey handed before the restart again, or
        end it if it ended meanwhile and the output was not told."""
        if plan is not None and key == self.submitted:
            assert key is not None
            if self.output.resume(plan, now):
                self.flight = _Flight(int(plan.survey_id), key, float(now))  # watched from now on
                self.counts["resumed"] += 1
                log.info("survey %d: following it again after the restart (%s)", plan.survey_id, self.name)
            else:
                log.warning("survey %d was given to the %s autonomy before the restart; that output cannot "
                            "follow it again, so its progress is no longer reported", plan.survey_id, self.name)
            return
        sid, submitted = self._sid(self.submitted), self.submitted
        if sid is None or submitted is None or submitted == self.ended_key or key is not None:
            return  # nothing handed, its end told, or a newer survey replaces it now
        state = self.survey.state_of(sid)
        if state in ENDED:
            log.info("survey %d ended (%s) while the %s output was not told: taking it back", sid,
                     state.name.lower(), self.name)
            self._end(sid, submitted, now)

    def _submit(self, plan: Any, key: str | None, now: float) -> None:
        assert key is not None
        old = self.flight
        log.info("survey %d to the autonomy (%s)", plan.survey_id, self.name)
        # the key first: a crash between the two never hands the same survey over twice
        self.submitted = key
        self._keep("vehicle.submitted", key)
        self.flight = _Flight(int(plan.survey_id), key)
        if old is not None and old.survey_id != int(plan.survey_id):
            self._remember(old.survey_id, old.key)  # replaced (SUPERSEDED): its late answers are late
        self.output.submit(plan, now)
        self.counts["submitted"] += 1

    # ------------------------------------------------------------------ reports
    def _remember(self, sid: int, key: str) -> None:
        self._ended[sid] = key
        self._ended.move_to_end(sid)
        while len(self._ended) > _REMEMBER:
            self._ended.popitem(last=False)

    def _is_ended(self, sid: int) -> bool:
        f = self.flight
        if f is not None and f.survey_id == sid:
            return False
        return sid in self._ended or self.survey.state_of(sid) in ENDED

    def _take(self, r: SurveyReport, now: float, out: list[SurveyReport]) -> None:
        sid = int(r.survey_id)
        state = SurveyState(r.state)
        if self._is_ended(sid):
            self._late(r, now)
            out.append(r)  # the survey sender keeps it in the survey's record
            return
        out.append(r)
        f = self.flight
        if f is None or f.survey_id != sid:
            return  # the vehicle's own mission, not one handed over
        if state == SurveyState.STARTED and f.flying_since is None:
            f.flying_since = float(now)
        if state in ENDED:
            self._end(sid, f.key, now)

    def _late(self, r: SurveyReport, now: float) -> None:
        sid, state = int(r.survey_id), SurveyState(r.state)
        self.counts["late"] += 1
        final = self.survey.state_of(sid)
        words = state.name.lower() + (f" {r.index}" if r.index is not None else "") + (
            f" {SurveyReason(r.reason).name}" if SurveyReason(r.reason) != SurveyReason.NONE else "") + (
            f": {r.detail}" if r.detail else "")
        # each distinct late answer once (a planner repeating its state every second)
        self._log_late(f"{sid}:{words}", "survey %d: a late answer from the %s autonomy after the survey "
                       "ended%s: %s (recorded in the survey's record; it stays %s)", sid, self.name,
                       f" ({final.name.lower()})" if final is not None else "", words,
                       final.name.lower() if final is not None else "ended")
        if state == SurveyState.STARTED and now - self._reended.get(sid, -1e18) >= REEND:
            key = self._ended.get(sid) or f"{sid}:?"
            log.warning("survey %d: the %s autonomy still flies it: taking it back again", sid, self.name)
            self._reended[sid] = float(now)
            self.output.end(sid, now)
            self._ended[sid] = key

    def _end(self, sid: int, key: str, now: float) -> None:
        """Tell the output the survey ended (its ended form), and remember it."""
        f = self.flight
        if f is not None and f.survey_id == sid:
            self.flight = None
        self._remember(sid, key)
        self._reended[sid] = float(now)
        self.output.end(sid, now)
        self.counts["ended"] += 1
        if key == self.submitted:
            self.ended_key = key
            self._keep("vehicle.ended", key)

    # ------------------------------------------------------------------ liveness
    def _watch(self, now: float, out: list[SurveyReport]) -> None:
        f = self.flight
        if f is None or f.flying_since is None:
            return
        bound = self.output.silence()
        if bound <= 0:
            return
        heard = self.output.heard(now)
        if heard is None:
            return
        quiet = float(now) - max(float(heard), f.flying_since)
        if quiet <= bound:
            return
        words = cut_detail(self.output.silent_detail())
        self.counts["silent"] += 1
        log.warning("survey %d aborted: the %s autonomy is silent (nothing heard for %.1f s, bound %g s%s)",
                    f.survey_id, self.name, quiet, bound, f": {words}" if words else "")
        report = SurveyReport(f.survey_id, SurveyState.ABORTED, float(now), SurveyReason.AUTONOMY_SILENT,
                              value=round(quiet, 1), detail=words)
        out.append(report)
        self._end(f.survey_id, f.key, now)

    def status(self) -> dict[str, Any]:
        """What the lifecycle holds (for logs and tests)."""
        f = self.flight
        return {"submitted": self.submitted, "ended": self.ended_key,
                "flying": None if f is None else f.survey_id, **self.counts}
