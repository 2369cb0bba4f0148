"""The ``sim`` autonomy output: a simulated vehicle for examples and tests without a vehicle.

It flies each plan in straight legs at a constant speed (the plan's ``speed``, else the
``speed`` option), from where it is (at first the ``start`` option, default the origin). All
time comes from ``now`` (no clock is read, nothing sleeps): :meth:`SimAutonomy.poll` reports
what happened up to ``now``, each report stamped with the moment it happened:

* ``STARTED`` index 0 at the time of :meth:`~SimAutonomy.submit`;
* ``STARTED`` index ``k`` when it passes waypoint ``k - 1`` (one report per waypoint reached);
* ``COMPLETED`` when it reaches the last waypoint, where it then stays.

A newer plan aborts nothing by itself (the survey sender reports the old one SUPERSEDED): the
vehicle flies the new plan from where it is. :meth:`SimAutonomy.position` (and
:meth:`~SimAutonomy.heading`) let a daemon report a vehicle status from it.
"""

from __future__ import annotations

import math
from typing import Any

from coex import Autonomy
from coex.messages import SurveyState
from coex.options import number

from ..options import Problems
from ..survey.plan import SurveyReport

__all__ = ["SimAutonomy"]


def _pair(v: Any) -> tuple[float, float] | None:
    try:
        x, y = (float(a) for a in v)
    except (TypeError, ValueError):
        return None
    return (x, y) if math.isfinite(x) and math.isfinite(y) else None


class SimAutonomy(Autonomy):
    """A vehicle that flies plans at ``speed`` m/s (see the module docstring)."""

    name = "sim"
    options = {
        "speed": number(1.0, "metres per second when the plan gives no speed", unit="m/s", above=0),
        "start": ([0.0, 0.0], "where the vehicle is before the first plan: [x, y] metres east, north"),
    }

    @classmethod
    def check(cls, options: Any) -> Problems:
        p = Problems()
        if "start" in options and _pair(options["start"]) is None:
            p.said("start", f"autonomy 'sim': start must be [x, y] (metres), got {options['start']!r}")
        return p

    def __init__(self, options: Any, context: Any) -> None:
        super().__init__(options, context)
        start = _pair(self.config["start"])
        assert start is not None
        self._pos = start  # where the current route starts
        self._t0 = -math.inf  # when it started
        self._route: list[tuple[float, float]] = []  # the plan's waypoints
        self._arrive: list[float] = []  # time each waypoint is reached
        self._plan: Any = None
        self._reported = 0  # waypoints whose arrival was reported
        self._done = True
        self._out: list[SurveyReport] = []
        self.plans: list[Any] = []

    # ------------------------------------------------------------------ the autonomy
    def resume(self, plan: Any, now: float) -> bool:
        """A simulated vehicle keeps no state across a restart: it flies the plan again from
        its start position."""
        self.submit(plan, now)
        return True

    def submit(self, plan: Any, now: float) -> None:
        self._flush(now)
        here = self.position(now)
        speed = float(plan.speed) if plan.speed else float(self.config["speed"])
        self._pos, self._t0, self._plan = here, float(now), plan
        self._route = [(float(x), float(y)) for x, y in plan.waypoints]
        self._arrive, t, prev = [], float(now), here
        for p in self._route:
            t += math.hypot(p[0] - prev[0], p[1] - prev[1]) / speed
            self._arrive.append(t)
            prev = p
        self._reported = 0
        self._done = not self._route
        self.plans.append(plan)
        self._out.append(SurveyReport(plan.survey_id, SurveyState.STARTED, float(now), index=0))
        if not self._route:
            self._out.append(SurveyReport(plan.survey_id, SurveyState.COMPLETED, float(now)))

    def end(self, survey_id: int, now: float) -> None:
        """The survey ended: if it is the one flown, the vehicle stops where it is."""
        if self._plan is None or int(self._plan.survey_id) != int(survey_id) or self._done:
            return
        self._flush(now)
        here = self.position(now)
        self._pos, self._t0, self._route, self._arrive, self._done = here, float(now), [], [], True

    def poll(self, now: float) -> list[Any]:
        self._flush(now)
        out, self._out = self._out, []
        return out

    def _flush(self, now: float) -> None:
        """Queue a report for every waypoint reached by ``now``."""
        if self._done or self._plan is None:
            return
        n = len(self._route)
        while self._reported < n and self._arrive[self._reported] <= now:
            k, t = self._reported, self._arrive[self._reported]
            self._reported += 1
            if k + 1 < n:
                self._out.append(SurveyReport(self._plan.survey_id, SurveyState.STARTED, t, index=k + 1))
            else:
                self._out.append(SurveyReport(self._plan.survey_id, SurveyState.COMPLETED, t))
                self._done = True

    # ------------------------------------------------------------------ where it is
    def _leg(self, now: float) -> tuple[tuple[float, float], tuple[float, float], float]:
        """The leg flown at ``now`` (from, to, fraction done)."""
        if not self._route or now <= self._t0:
            return self._pos, self._pos, 0.0
        prev, t_prev = self._pos, self._t0
        for p, t in zip(self._route, self._arrive):
            if now < t:
                return prev, p, (now - t_prev) / (t - t_prev)
            prev, t_prev = p, t
        return prev, prev, 1.0

    def position(self, now: float) -> tuple[float, float]:
        """Where the vehicle is at ``now``: metres east, north of the origin."""
        a, b, f = self._leg(now)
        return a[0] + (b[0] - a[0]) * f, a[1] + (b[1] - a[1]) * f

    def heading(self, now: float) -> float | None:
        """Degrees clockwise from north of the leg flown at ``now`` (None: holding still)."""
        a, b, _ = self._leg(now)
        if a == b:
            return None
        return math.degrees(math.atan2(b[0] - a[0], b[1] - a[1])) % 360.0

    def active(self, now: float) -> int | None:
        """The survey being flown at ``now`` (None: none, or it is complete)."""
        if self._plan is None or not self._route or now >= self._arrive[-1]:
            return None
        return int(self._plan.survey_id)
