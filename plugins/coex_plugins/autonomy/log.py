"""The ``log`` autonomy output (the default): every plan in words in the log, and optionally one
JSON line per plan appended to a file. It reports nothing: a vehicle whose own autonomy is
driven by hand (or by a script reading the file) still tells topside the survey was accepted."""

from __future__ import annotations

import json
import logging
import math
import os
from typing import Any

from coex import Autonomy

from ..options import Problems

__all__ = ["LogAutonomy", "describe_plan", "plan_record"]

log = logging.getLogger(__name__)


def _num(v: float | None) -> float | None:
    return None if v is None or not math.isfinite(v) else float(v)


def describe_plan(plan: Any, max_points: int = 6) -> str:
    """One line: ``survey 7 (LAWNMOWER): 12 waypoints (0, 0) (40, 0) ... at 5 m altitude, 1 m/s``."""
    pts = [f"({x:g}, {y:g})" for x, y in plan.waypoints]
    if len(pts) > max_points:
        pts = [*pts[: max_points - 2], "...", *pts[-2:]]
    n = len(plan.waypoints)
    kind = getattr(plan.kind, "name", str(plan.kind))
    text = f"survey {plan.survey_id} ({kind}): {n} waypoint{'s' if n != 1 else ''} {' '.join(pts)}"
    if plan.depth is not None:
        text += f" at {plan.depth:g} m depth"
    elif plan.altitude is not None:
        text += f" at {plan.altitude:g} m altitude"
    else:
        text += " at the present height"
    if plan.altitude is not None and plan.depth is not None:
        text += f" ({plan.altitude:g} m altitude)"
    text += f", {plan.speed:g} m/s" if plan.speed is not None else ", the vehicle's own speed"
    return text


def plan_record(plan: Any, now: float, context: Any = None) -> dict[str, Any]:
    """A plan as a JSON-ready dict (with each waypoint's latitude/longitude when a context is given)."""
    rec: dict[str, Any] = {
        "time": now,
        "survey_id": int(plan.survey_id),
        "kind": getattr(plan.kind, "name", str(plan.kind)),
        "waypoints": [[float(x), float(y)] for x, y in plan.waypoints],
    }
    if context is not None:
        rec["latlon"] = [list(context.geodetic(x, y)) for x, y in plan.waypoints]
    for key in ("altitude", "depth", "speed", "heading", "length", "width", "spacing"):
        rec[key] = _num(getattr(plan, key, None))
    centre = getattr(plan, "centre", None)
    rec["centre"] = None if centre is None else [float(centre[0]), float(centre[1])]
    return rec


class LogAutonomy(Autonomy):
    """Logs each plan (logger ``coex_plugins.autonomy.log``, level INFO)."""

    name = "log"
    options = {
        "file": (None, "also append one JSON line per plan to this file (relative to the "
                       "configuration's directory)"),
    }

    @classmethod
    def check(cls, options: Any) -> Problems:
        p = Problems()
        f = options.get("file")
        if f is not None and (not isinstance(f, str) or not f):
            p.said("file", f"autonomy 'log': file must be a path, got {f!r}")
        return p

    def __init__(self, options: Any, context: Any) -> None:
        super().__init__(options, context)
        f = self.config.get("file")
        self.path = None if f is None else os.path.join(getattr(context, "base_dir", "."), f)
        self.plans = 0

    def resume(self, plan: Any, now: float) -> bool:
        return True  # nothing to follow: a log reports nothing

    def submit(self, plan: Any, now: float) -> None:
        self.plans += 1
        log.info("autonomy: fly %s", describe_plan(plan))
        if self.path is not None:
            line = json.dumps(plan_record(plan, now, self.context), allow_nan=False)
            with open(self.path, "a", encoding="utf-8") as fh:
                fh.write(line + "\n")

    def end(self, survey_id: int, now: float) -> None:
        """The survey ended: said in the log, and as a JSON line ``{"time", "survey_id", "ended":
        true}`` in the file, so that a script following the file stops flying it."""
        log.info("autonomy: survey %d ended", survey_id)
        if self.path is not None:
            line = json.dumps({"time": now, "survey_id": int(survey_id), "ended": True})
            with open(self.path, "a", encoding="utf-8") as fh:
                fh.write(line + "\n")

    def poll(self, now: float) -> list[Any]:
        return []
