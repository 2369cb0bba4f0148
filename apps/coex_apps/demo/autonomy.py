"""The simulated vehicle's autonomy: it flies what the vehicle's survey sender says to fly now.

Topside's survey commands cross the acoustic link; the vehicle's
:class:`~coex_plugins.survey.SurveySender` checks each against the geofence and keeps the queue
of accepted surveys. Whenever its ``plan_version`` changes, :class:`Autonomy` flies the new
``active_plan()`` from where the vehicle is: a transit leg to the first waypoint (at
:data:`~.config.TRANSIT_ALTITUDE`, :data:`~.config.TRANSIT_SPEED`), then the waypoints at the
plan's altitude and speed with the camera on. It reports what it does back through the sender
(``SurveyReport``: STARTED index 0 when it sets off, STARTED index k + 1 on reaching waypoint k,
COMPLETED at the end) at those simulated times; the sender sends them topside. A replaced plan
stops where the vehicle is; with nothing queued the vehicle holds at
:data:`~.config.HOLD_ALTITUDE`. It takes over when the vehicle's own multibeam survey ends
(surveys accepted before then wait in the queue).
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable
from typing import Any

from coex.messages import SurveyState
from coex_plugins.survey import SurveyPlan, SurveyReport, SurveySender
from coex_plugins.survey.plan import describe

from .config import EPOCH, HOLD_ALTITUDE, TRANSIT_ALTITUDE, TRANSIT_SPEED
from .world import Leg, Track

__all__ = ["Autonomy"]


class Autonomy:
    """The vehicle's autonomy in the demo's world (see the module docstring). ``at(t, fn)``
    schedules ``fn(now)`` at simulated time ``t`` (the dive's events). ``mission``: waypoints
    the vehicle flies on its own (camera on) when its survey ends and nothing is queued (the
    ``--operator none`` dive's one transect through the centre), or ``None``."""

    def __init__(self, sender: SurveySender, track: Track, at: Callable[[float, Callable[[float], None]], None],
                 end: float, *, camera_altitude: float, camera_speed: float,
                 mission: tuple[tuple[float, float], ...] | None = None, nav: Any = None) -> None:
        self.sender = sender
        self.track = track
        self.at = at
        self.end = end
        self.camera_altitude = camera_altitude
        self.camera_speed = camera_speed
        self.mission = mission
        #: the vehicle's dead reckoning (:class:`~.navigation.DeadReckoning`): it flies waypoints of
        #: its own frame, so it truly goes where it believes they are, less its error (issue 56)
        self.nav = nav
        self.active = False
        self.version = sender.plan_version
        self._gen = 0
        self._flying: int | None = None
        #: the truth per survey id: when the command reached the vehicle and what it answered
        #: (``received``, ``answer``, ``reason``), and when the vehicle flew it (``set_off``,
        #: ``reached``: per waypoint, ``completed``, ``stopped``: replaced midway)
        self.truth: dict[int, dict[str, Any]] = {}

    # ------------------------------------------------------------------ the dive's hooks
    def start(self, now: float) -> None:
        """The vehicle's own survey is over: fly what is queued, or its own mission, or hold."""
        self.active = True
        self._note_commands()
        self._fly(now, mission=self.mission)

    def check(self, now: float) -> None:
        """After the vehicle took what arrived: a new plan to fly?"""
        self._note_commands()
        if self.active and self.sender.plan_version != self.version:
            self._fly(now)

    def camera_legs(self) -> list[Leg]:
        return [leg for leg in self.track.legs if leg.camera]

    # ------------------------------------------------------------------ flying
    def _note_commands(self) -> None:
        for sid, s in self.sender.surveys.items():
            if sid in self.truth or s.command is None:
                continue
            rejected = s.state == SurveyState.REJECTED
            self.truth[sid] = {"received": s.time, "answer": "rejected" if rejected else "accepted",
                               "reason": describe(s.reason, s.index, s.value) if rejected else None,
                               "set_off": None, "reached": [], "completed": None, "stopped": None}

    def _cut(self, now: float) -> tuple[float, float]:
        """Stop every leg planned beyond ``now`` where the vehicle is; its position."""
        legs = self.track.legs
        for leg in list(legs):
            if leg.t1 <= now:
                continue
            if leg.t0 >= now:
                legs.remove(leg)
            else:
                leg.p1, leg.t1 = leg.at(now), now
        x, y = self.track.position(now)[:2]
        return x, y

    def _fly(self, now: float, mission: tuple[tuple[float, float], ...] | None = None) -> None:
        self.version = self.sender.plan_version
        self._gen += 1
        gen = self._gen
        if self._flying is not None:
            flying = self.truth.get(self._flying)
            if flying is not None and flying["completed"] is None and flying["stopped"] is None:
                flying["stopped"] = now
            self._flying = None
        pos = self._cut(now)
        plan: SurveyPlan | None = self.sender.active_plan()
        if plan is None and mission is None:
            self.track.legs.append(Leg(now, max(self.end, now), pos, pos, HOLD_ALTITUDE))
            return
        if plan is not None:
            wps = [tuple(map(float, p)) for p in plan.waypoints]
            altitude = plan.altitude if plan.altitude is not None else TRANSIT_ALTITUDE
            speed = plan.speed or TRANSIT_SPEED
        else:
            assert mission is not None
            wps, altitude, speed = [tuple(map(float, p)) for p in mission], self.camera_altitude, self.camera_speed
        if self.nav is not None and self.nav.active:
            wps = self.nav.true_path(now, pos, wps, [TRANSIT_SPEED] + [speed] * (len(wps) - 1))
        t = now
        dist = math.hypot(wps[0][0] - pos[0], wps[0][1] - pos[1])
        self.track.legs.append(Leg(t, t + dist / TRANSIT_SPEED, pos, wps[0], TRANSIT_ALTITUDE))  # type: ignore[arg-type]
        t += dist / TRANSIT_SPEED
        reached = [t]
        for a, b in itertools.pairwise(wps):
            dt = math.hypot(b[0] - a[0], b[1] - a[1]) / speed
            self.track.legs.append(Leg(t, t + dt, a, b, altitude, camera=True))  # type: ignore[arg-type]
            t += dt
            reached.append(t)
        if plan is None:  # the vehicle's own mission: nobody to report to; hold after it
            self.track.legs.append(Leg(t, max(self.end, t), wps[-1], wps[-1], HOLD_ALTITUDE))  # type: ignore[arg-type]
            return
        sid = plan.survey_id
        self._flying = sid
        truth = self.truth.setdefault(sid, {"received": None, "answer": "accepted", "reason": None, "set_off": None,
                                            "reached": [], "completed": None, "stopped": None})
        truth["set_off"] = now
        self.sender.ingest(SurveyReport(sid, SurveyState.STARTED, now, index=0), now)
        for k, tk in enumerate(reached):
            self.at(tk, functools.partial(self._reach, gen, sid, k, tk, len(wps)))

    def _reach(self, gen: int, sid: int, k: int, tk: float, n: int, now: float) -> None:
        """The vehicle reached waypoint ``k`` of ``n`` of survey ``sid`` at ``tk``."""
        if gen != self._gen:
            return  # that plan was replaced
        truth = self.truth[sid]
        truth["reached"].append(tk)
        if k + 1 < n:
            self.sender.ingest(SurveyReport(sid, SurveyState.STARTED, tk, index=k + 1), tk)
            return
        truth["completed"] = tk
        self._flying = None
        self.sender.ingest(SurveyReport(sid, SurveyState.COMPLETED, tk), tk)
        self.check(tk)
        if self.version == self.sender.plan_version and self._gen == gen:
            self._fly(tk)  # the plan done and nothing changed: hold (or the next in the queue)

    def summary(self) -> dict[int, dict[str, Any]]:
        """The truth per survey id, in dive seconds."""

        def s(t: float | None) -> float | None:
            return None if t is None else round(t - EPOCH, 1)

        return {sid: {"received_by_vehicle_s": s(t["received"]), "vehicle_answer": t["answer"],
                      "vehicle_reason": t["reason"], "set_off_s": s(t["set_off"]),
                      "waypoints_reached_s": [s(x) for x in t["reached"]], "completed_s": s(t["completed"]),
                      "stopped_s": s(t["stopped"])}
                for sid, t in sorted(self.truth.items())}
