"""The ``moos`` autonomy output: accepted surveys flown by the MOOS-IvP helm's ``BHV_Waypoint``.

The behaviour is configured in the helm's ``.bhv`` file (``examples/moos/coex.bhv``)::

    Behavior = BHV_Waypoint
    {
      name      = coex_survey
      condition = COEX_SURVEY = true
      updates   = COEX_WPT_UPDATE
      endflag   = COEX_SURVEY = false
      perpetual = true
      ...
    }

:meth:`MoosAutonomy.submit` posts, in this order, through a
:class:`~coex_transports.moos.MoosClient`:

1. ``updates_var`` (``COEX_WPT_UPDATE``) = ``points=x1,y1:x2,y2:...#speed=1.5`` (a go-to:
   ``point=x,y``): the plan's own waypoints, in local metres, in order. Lawnmowers too are sent
   as their waypoints, not as the helm's ``format=lawnmower``: the helm's pattern
   (``XYPatternBlock``) has ``ceil(width / lane_width) + 1`` lanes, lanes past the edge when
   the width is not a multiple of the lane width, an entry corner chosen as the one nearest
   ``startx, starty`` and ignores ``degs`` below 1; the plan's rows are ``floor(width / spacing)
   + 1``, centred, first row on the port side. Points are always exactly what the geofence
   checked and topside shows, and ``WPT_INDEX`` k is then waypoint k of the plan.
2. ``depth_var`` = ``depth=NN`` when the plan gives a depth and the option is set (a
   ``BHV_ConstantDepth`` with ``updates``); ``altitude_var`` = ``altitude=NN`` likewise for a
   vehicle-specific altitude behaviour (moos-ivp has no constant-altitude behaviour).
3. ``activate`` (``COEX_SURVEY = true``): the behaviour's ``condition``.

What comes back (only after the submit, from the helm, never from this client):

* ``wpt_index_var`` (``WPT_INDEX``) = k -> STARTED, index k (once per index);
* ``wpt_status_var`` (``WPT_STAT``) naming the behaviour: ``...,index=k,...`` -> STARTED k;
  ``...,completed`` or ``...,cycled`` -> COMPLETED;
* ``BHV_WARNING`` = ``Faulty update for behavior: <behavior>. Bad parameter(s): ...`` ->
  REJECTED, AUTONOMY_REFUSED (other warnings naming the behaviour are logged);
* ``endflag`` (``VAR = value``, off by default) seen with that value -> COMPLETED;
* ``MOOS_MANUAL_OVERRIDE`` (or the helm's other spelling ``MOOS_MANUAL_OVERIDE``) true while
  a survey is flown -> ABORTED, AUTONOMY_STOPPED, and ``activate``'s variable is set to
  ``deactivate`` so the helm does not resume it when the override ends.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping
from typing import Any

from coex_core.messages import SurveyKind, SurveyReason, SurveyState

from ...survey.plan import SurveyReport
from ..inputs.moos import parse_server
from ..options import LogOnce, moos_client
from .base import Autonomy

__all__ = ["MoosAutonomy", "parse_flag", "update_of"]

log = logging.getLogger(__name__)

OVERRIDE_VARS = ("MOOS_MANUAL_OVERRIDE", "MOOS_MANUAL_OVERIDE")


def _n(v: float) -> str:
    """A number as the helm parses it: plain decimal, at most 2 decimals, no exponent."""
    text = f"{float(v):.2f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def update_of(plan: Any, extra: str = "") -> str:
    """The ``BHV_Waypoint`` update string of a plan."""
    pts = [(float(x), float(y)) for x, y in plan.waypoints]
    if SurveyKind(plan.kind) == SurveyKind.GOTO and len(pts) == 1:
        parts = [f"point={_n(pts[0][0])},{_n(pts[0][1])}"]
    else:
        parts = ["points=" + ":".join(f"{_n(x)},{_n(y)}" for x, y in pts)]
    if plan.speed is not None and plan.speed > 0:
        parts.append(f"speed={_n(plan.speed)}")
    if extra:
        parts.append(extra.strip("#"))
    return "#".join(parts)


def parse_flag(text: Any) -> tuple[str, str]:
    """``"VAR = value"`` -> ``("VAR", "value")``; ValueError if it is not one."""
    if isinstance(text, str):
        var, sep, value = text.partition("=")
        var, value = var.strip(), value.strip()
        if sep and var and value and not any(c.isspace() for c in var):
            return var, value
    raise ValueError(f"'VARIABLE = value' (e.g. 'COEX_SURVEY = true'), not {text!r}")


def _value(text: str) -> float | str:
    """A flag's value as MOOS posts it: a number as a double, else a string."""
    try:
        f = float(text)
    except ValueError:
        return text
    return f if math.isfinite(f) else text


def _same(got: Any, want: float | str) -> bool:
    if isinstance(want, float):
        return isinstance(got, float) and got == want
    return isinstance(got, str) and got.strip().lower() == want.lower()


class MoosAutonomy(Autonomy):
    """Surveys to the IvP helm's waypoint behaviour (module docstring)."""

    name = "moos"
    options = {
        "server": ("localhost:9000", "the MOOSDB, host:port (pCoex: the mission's ServerHost:ServerPort)"),
        "name": ("pCoex_helm", "MOOS client name (unique on the MOOSDB)"),
        "behavior": ("coex_survey", "the BHV_Waypoint's name (WPT_STAT behavior-name, BHV_WARNING)"),
        "updates_var": ("COEX_WPT_UPDATE", "the behaviour's `updates` variable"),
        "activate": ("COEX_SURVEY = true", "posted after the update: the behaviour's condition"),
        "deactivate": ("false", "value of activate's variable posted when a survey is aborted"),
        "depth_var": ("", "`updates` variable of a depth behaviour (depth=NN); '' = none"),
        "altitude_var": ("", "`updates` variable of an altitude behaviour (altitude=NN); '' = none"),
        "update_extra": ("", "more BHV_Waypoint parameters appended to every update, e.g. 'capture_radius=5'"),
        "wpt_status_var": ("WPT_STAT", "the behaviour's wpt_status_var"),
        "wpt_index_var": ("WPT_INDEX", "the behaviour's wpt_index_var"),
        "endflag": ("", "'VAR = value' the behaviour posts at its end (COMPLETED); '' = WPT_STAT only"),
    }

    @classmethod
    def check(cls, options: Mapping[str, Any]) -> list[str]:
        problems: list[str] = []
        if "server" in options:
            try:
                parse_server(options["server"])
            except ValueError as exc:
                problems.append(f"autonomy 'moos': option 'server' must be {exc}")
        for key in ("activate", "endflag"):
            if key in options and not (key == "endflag" and options[key] == ""):
                try:
                    parse_flag(options[key])
                except ValueError as exc:
                    problems.append(f"autonomy 'moos': option {key!r} must be {exc}")
        for key in ("name", "behavior", "updates_var", "wpt_status_var", "wpt_index_var", "depth_var",
                    "altitude_var", "deactivate", "update_extra"):
            v = options.get(key, "x")
            must = key in ("name", "behavior", "updates_var", "wpt_status_var", "wpt_index_var", "deactivate")
            if not isinstance(v, str) or (must and not v) or (
                    key not in ("deactivate", "update_extra") and any(c.isspace() for c in v)):
                problems.append(f"autonomy 'moos': option {key!r} must be a "
                                f"{'non-empty ' if must else ''}MOOS name without spaces, not {v!r}")
        return problems

    def __init__(self, options: Mapping[str, Any], context: Any, client: Any = None) -> None:
        super().__init__(options, context)
        c = self.config
        self.host, self.port = parse_server(c["server"])
        self.activate_var, activate = parse_flag(c["activate"])
        self.activate_value = _value(activate)
        self.endflag = None if not c["endflag"] else parse_flag(c["endflag"])
        self.client = client
        self.plan: Any = None
        self._since = 0.0  # MOOS time of the submit: older helm posts are about the previous plan
        self._index: int | None = None
        self._done = True
        self._out: list[SurveyReport] = []
        self._problem = LogOnce(log)
        self.stats = {"submitted": 0, "received": 0, "ignored": 0}

    @property
    def variables(self) -> list[str]:
        c = self.config
        out = [c["wpt_index_var"], c["wpt_status_var"], "BHV_WARNING", "BHV_ERROR", *OVERRIDE_VARS]
        if self.endflag is not None:
            out.append(self.endflag[0])
        return list(dict.fromkeys(out))

    def open(self) -> None:
        self.client = moos_client(self.client, self.host, self.port, self.config["name"], self.variables)

    def close(self) -> None:
        if self.client is not None:
            self.client.flush(timeout=2.0)  # what was posted reaches MOOSDB
            self.client.close()
            self.client = None

    def submit(self, plan: Any, now: float) -> None:
        if self.client is None:
            self.open()
        c = self.config
        update = update_of(plan, c["update_extra"])
        self._since = time.time()
        self.client.notify(c["updates_var"], update)
        if c["depth_var"] and plan.depth is not None:
            self.client.notify(c["depth_var"], f"depth={_n(plan.depth)}")
        if c["altitude_var"] and plan.altitude is not None:
            self.client.notify(c["altitude_var"], f"altitude={_n(plan.altitude)}")
        self.client.notify(self.activate_var, self.activate_value)
        self.plan, self._index, self._done = plan, None, False
        self.stats["submitted"] += 1
        log.info("moos: survey %s to the helm: %s = %s; %s = %s", plan.survey_id, c["updates_var"],
                 update if len(update) < 200 else update[:200] + "...", self.activate_var, self.activate_value)

    # ------------------------------------------------------------------ reports
    def _report(self, state: SurveyState, now: float, reason: SurveyReason = SurveyReason.NONE,
                index: int | None = None) -> None:
        self._out.append(SurveyReport(int(self.plan.survey_id), state, float(now), reason, index))
        if state != SurveyState.STARTED:
            self._done = True

    def _started(self, index: int, now: float) -> None:
        n = len(self.plan.waypoints)
        if not 0 <= index < n:
            self._problem(f"index:{index}", "moos: waypoint index %d of a %d-waypoint survey ignored", index, n)
            return
        if index != self._index:
            self._index = index
            self._report(SurveyState.STARTED, now, index=index)

    def _completed(self, now: float) -> None:
        if self._index is None:  # too short for the helm to post an index: it did set off
            self._report(SurveyState.STARTED, now, index=0)
        self._report(SurveyState.COMPLETED, now)

    def poll(self, now: float) -> list[Any]:
        if self.client is None:
            return []
        c = self.config
        for m in self.client.fetch():
            self.stats["received"] += 1
            if m.source == c["name"] or self.plan is None or self._done or m.time < self._since:
                self.stats["ignored"] += 1
                continue
            try:
                self._mail(m, now)
            except Exception as exc:  # bad mail from the vehicle is logged, never raised
                self._problem(f"bad:{m.key}", "moos: %s = %r not understood: %s", m.key, m.value, exc)
            if self._done:
                break
        out, self._out = self._out, []
        return out

    def _mail(self, m: Any, now: float) -> None:
        c = self.config
        behavior = c["behavior"]
        if m.key == c["wpt_index_var"] and m.is_double:
            self._started(round(float(m.value)), now)
        elif m.key == c["wpt_status_var"] and m.is_string:
            fields = {}
            words = set()
            for part in str(m.value).split(","):
                k, sep, v = part.partition("=")
                if sep:
                    fields[k.strip().lower()] = v.strip()
                else:
                    words.add(part.strip().lower())
            if "behavior-name" in fields and fields["behavior-name"] != behavior:
                return  # another waypoint behaviour
            if "completed" in words or "cycled" in words:
                self._completed(now)
            elif "index" in fields:
                self._started(int(fields["index"]), now)
        elif m.key == "BHV_WARNING" and m.is_string:
            text = str(m.value)
            if f"Faulty update for behavior: {behavior}." in text or text.endswith(f"Faulty update for behavior: {behavior}"):
                log.warning("moos: the helm refused survey %s: %s", self.plan.survey_id, text)
                self._report(SurveyState.REJECTED, now, SurveyReason.AUTONOMY_REFUSED)
            elif behavior in text:
                self._problem(f"warn:{text}", "moos: helm warning: %s", text)
        elif m.key == "BHV_ERROR" and m.is_string and behavior in str(m.value):
            self._problem(f"err:{m.value}", "moos: helm error: %s", m.value)
        elif m.key in OVERRIDE_VARS:
            on = (str(m.value).strip().lower() == "true") if m.is_string else (m.is_double and float(m.value) != 0)
            if on:
                log.warning("moos: %s = %s while survey %s was flown: aborted", m.key, m.value, self.plan.survey_id)
                self._report(SurveyState.ABORTED, now, SurveyReason.AUTONOMY_STOPPED)
                self.client.notify(self.activate_var, _value(c["deactivate"]))
        if self.endflag is not None and m.key == self.endflag[0] and not self._done \
                and _same(m.value, _value(self.endflag[1])):
            self._completed(now)
