"""The ``moos`` autonomy output: accepted surveys flown by the MOOS-IvP helm's ``BHV_Waypoint``.

The behaviour is configured in the helm's ``.bhv`` file (``examples/moos/coex.bhv``)::

    initialize COEX_SURVEY = false
    Behavior = BHV_Waypoint
    {
      name      = coex_survey
      condition = COEX_SURVEY = true
      updates   = COEX_WPT_UPDATE
      endflag   = COEX_SURVEY = false
      perpetual = true
      ...
    }

What the helm does with what it is sent was read from pHelmIvP (``HelmIvP.cpp``,
``IvPBehavior::checkUpdates``, ``BehaviorSet::produceOF``, ``BHV_Waypoint.cpp``) and checked
against a running helm (``tests/test_moos_ivp.py``):

* Updates are applied to a behaviour in every state, idle too, each one checked: the helm
  posts ``IVPHELM_UPDATE_RESULT = "bhv=B,var=V,time=T,result=R,val=UPDATE"`` with R
  ``success``, ``param_error`` (then ``BHV_WARNING = "Faulty update for behavior: B. Bad
  parameter(s): ..."``; the valid parameters *are* applied), ``duplicate`` (equal to the last
  successful update: dropped; unless it contains ``toggle``, ``engage`` or ``mod``) or
  ``name_mismatch``. A parked helm (``MOOS_MANUAL_OVERRIDE``) discards updates unread.
* Behaviour posts are sent only when they change (``detectChangeOnKey``): a second identical
  ``BHV_WARNING`` or ``WPT_STAT`` never comes.
* A restarted helm posts ``PHELMIVP_PID`` and its ``initialize`` values (source_aux
  ``HELM_VAR_INIT``); ``RESTART_HELM`` gives ``IVPHELM_RESTARTED``. ``IVPHELM_STATE`` (DRIVE,
  PARK ...) comes every iteration; ``IVPHELM_ALLSTOP`` (``clear``, ``ManualOverride``,
  ``NothingToDo``, ``MissingDecVars:depth`` ...) and ``IVPHELM_BHV_ACTIVE`` / ``_RUNNING`` /
  ``_IDLE`` (behaviour names) when they change.

So :meth:`MoosAutonomy.submit` posts, in this order:

1. ``activate``'s variable = ``deactivate`` (``COEX_SURVEY = false``): whatever the behaviour
   flew stops before anything of the new survey is applied;
2. ``updates_var`` = ``name=coex_survey``: a successful update that no survey update equals,
   so the helm's last successful update is never the survey's and never drops it as a duplicate
   (the same survey twice is flown twice);
3. ``updates_var`` = ``name=coex_survey#points=x1,y1:x2,y2:...#speed=1.5`` (a go-to:
   ``point=x,y``): the plan's own waypoints in order (``update_of``). Lawnmowers too are sent as
   their waypoints, not as the helm's ``format=lawnmower`` (its ``XYPatternBlock`` has other
   rows), so ``WPT_INDEX`` k is waypoint k of the plan. ``name=`` makes a helm whose behaviour
   has another name answer ``name_mismatch`` instead of flying it with another behaviour;
4. ``depth_var`` = ``depth=NN`` / ``altitude_var`` = ``altitude=NN`` when the plan gives one.

It then waits for the helm's answer to each update (never posting the activation before):
every one ``success`` (``duplicate`` is fine for depth and altitude) -> ``activate``
(``COEX_SURVEY = true``); a ``param_error`` -> REJECTED, AUTONOMY_REFUSED, ``detail`` the
helm's words (``coex_survey: Bad parameter(s): speed``), and the behaviour stays deactivated,
so nothing of a refused survey is flown. Then, from what the helm posts after the activation:

* ``WPT_INDEX`` = k or ``WPT_STAT`` ``...,index=k,...`` -> STARTED, index k (once per index);
* ``WPT_STAT`` ``behavior-name=coex_survey,completed`` (or ``cycled``), or the behaviour's
  endflag (``COEX_SURVEY = false`` posted by the helm for ``coex_survey``), or the ``endflag``
  option -> COMPLETED;
* ``MOOS_MANUAL_OVERRIDE`` (or ``MOOS_MANUAL_OVERIDE``) = true, ``IVPHELM_STATE = PARK``,
  ``IVPHELM_ALLSTOP = ManualOverride`` -> MANUAL_OVERRIDE;
* ``PHELMIVP_PID``, ``IVPHELM_RESTARTED``, ``COEX_SURVEY`` re-initialised -> AUTONOMY_RESTARTED;
* once the behaviour ran, ``IVPHELM_ALLSTOP`` other than ``clear`` -> ALL_STOP, ``detail`` the
  all-stop (``MissingDecVars:depth``);
* ``COEX_SURVEY`` set to anything else by someone else, the behaviour idle again before its end,
  ``IVPHELM_STATE`` neither DRIVE nor PARK (DISABLED, MALCONFIG), or the behaviour not running
  ``timeout`` seconds after its activation -> AUTONOMY_STOPPED, ``detail`` what was seen.

These end a survey REJECTED when the helm had not taken its updates yet (no answer within
``timeout``: AUTONOMY_NO_ANSWER), ABORTED after; every end but COMPLETED posts ``deactivate``
again so the helm does not resume the survey by itself. Every end is followed by the daemon's
:meth:`MoosAutonomy.end`: the ended form (``deactivate``, and ``updates_var`` = ``name=<behavior>``,
no points) stays in MOOSDB for a helm that starts later. The helm's ``IVPHELM_STATE`` is the sign
of life (:meth:`MoosAutonomy.heard`): the daemon aborts a survey flown while the helm is silent
for ``silence`` seconds (AUTONOMY_SILENT).

**Time.** ``now`` (reports, timeouts) is CoEx's clock, real seconds. What is posted carries the
community's MOOS time (``time_warp``, pCoex: the mission's ``MOOSTimeWarp``), so a warped helm
does not drop it as skewed (``ok_skew``, 60 MOOS seconds by default). Helm posts are taken in the
order MOOSDB delivers them, never by their time: mail waiting when a survey is submitted is read
first, for the state it tells, and what matters of the new survey comes after the helm's answer
to its update.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from typing import Any

from coex import Autonomy
from coex.messages import SurveyKind, SurveyReason, SurveyState
from coex.options import number

from ..inputs.moos import parse_server
from ..options import LogOnce, Problems, moos_client, time_warp
from ..survey.plan import SurveyReport, cut_detail

__all__ = ["MoosAutonomy", "parse_flag", "parse_update_result", "update_of"]

log = logging.getLogger(__name__)

OVERRIDE_VARS = ("MOOS_MANUAL_OVERRIDE", "MOOS_MANUAL_OVERIDE")
#: the helm's own variables read (HelmIvP.cpp)
HELM_VARS = ("IVPHELM_UPDATE_RESULT", "IVPHELM_STATE", "IVPHELM_ALLSTOP", "IVPHELM_BHV_ACTIVE",
             "IVPHELM_BHV_RUNNING", "IVPHELM_BHV_IDLE", "PHELMIVP_PID", "IVPHELM_RESTARTED")
FAULTY = "Faulty update for behavior: "

# phases of the survey being handed over
_UPDATE = "update"  # updates posted, waiting for the helm's answer to each
_REFUSED = "refused"  # the helm refused an update; waiting for its BHV_WARNING (the words)
_ACTIVATED = "activated"  # activation posted; the behaviour has not been seen running yet
_FLYING = "flying"  # the behaviour ran after the activation


def _n(v: float) -> str:
    """A number as the helm parses it: plain decimal, at most 2 decimals, no exponent."""
    text = f"{float(v):.2f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def update_of(plan: Any, extra: str = "") -> str:
    """The ``BHV_Waypoint`` parameters of a plan (the update :class:`MoosAutonomy` posts puts
    ``name=<behavior>#`` in front)."""
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


def parse_update_result(text: str) -> dict[str, str]:
    """``IVPHELM_UPDATE_RESULT`` (``bhv=B,var=V,time=T,result=R,val=UPDATE``) -> its fields;
    ``val`` is everything after ``,val=`` (an update holds commas)."""
    head, sep, val = text.partition(",val=")
    out: dict[str, str] = {}
    for part in head.split(","):
        k, eq, v = part.partition("=")
        if eq:
            out[k.strip()] = v.strip()
    if sep:
        out["val"] = val
    return out


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


def _names(text: Any) -> set[str]:
    return {p.strip() for p in str(text).split(",") if p.strip()}


class MoosAutonomy(Autonomy):
    """Surveys to the IvP helm's waypoint behaviour (module docstring)."""

    name = "moos"
    options = {
        "server": ("localhost:9000", "the MOOSDB, host:port (pCoex: the mission's ServerHost:ServerPort)"),
        "name": ("pCoex_helm", "MOOS client name (unique on the MOOSDB)"),
        "behavior": ("coex_survey", "the BHV_Waypoint's name (WPT_STAT behavior-name, BHV_WARNING)"),
        "updates_var": ("COEX_WPT_UPDATE", "the behaviour's `updates` variable"),
        "activate": ("COEX_SURVEY = true", "posted once the helm took the updates: the behaviour's condition"),
        "deactivate": ("false", "value of activate's variable posted before each survey and when one ends early"),
        "depth_var": ("", "`updates` variable of a depth behaviour (depth=NN); '' = none"),
        "altitude_var": ("", "`updates` variable of an altitude behaviour (altitude=NN); '' = none"),
        "update_extra": ("", "more BHV_Waypoint parameters appended to every update, e.g. 'capture_radius=5'"),
        "wpt_status_var": ("WPT_STAT", "the behaviour's wpt_status_var"),
        "wpt_index_var": ("WPT_INDEX", "the behaviour's wpt_index_var"),
        "endflag": ("", "another 'VAR = value' the behaviour posts at its end (COMPLETED); '' = none"),
        "time_warp": time_warp("the community's MOOSTimeWarp (pCoex: the mission's): posts carry the warped MOOS time"),
        "timeout": number(10.0, "seconds (real) to wait for the helm's answer and for the behaviour to run",
                          unit="s", above=0),
        "position_fix_var": ("USM_RESET", "variable topside's position fixes are posted to as 'x=X,y=Y' "
                                          "(uSimMarine's USM_RESET moves the simulated vehicle there; a vehicle's "
                                          "navigation names its own); '' = refuse them"),
        "position_fix_full_var": ("COEX_POSITION_FIX", "also posted: 'x=X,y=Y,time=T,sigma=S,depth=D,source=...' "
                                                       "for a navigation that fuses fixes; '' = none"),
        "silence": number(10.0, "seconds (real) without IVPHELM_STATE while a survey flies before it is aborted "
                                "AUTONOMY_SILENT (0: not watched)", unit="s", lo=0),
    }

    @classmethod
    def check(cls, options: Mapping[str, Any]) -> Problems:
        p, who = Problems(), "autonomy 'moos'"
        if "server" in options:
            try:
                parse_server(options["server"])
            except ValueError as exc:
                p.said("server", f"{who}: option 'server' must be {exc}")
        for key in ("activate", "endflag"):
            if key in options and not (key == "endflag" and options[key] == ""):
                try:
                    parse_flag(options[key])
                except ValueError as exc:
                    p.said(key, f"{who}: option {key!r} must be {exc}")
        for key in ("name", "behavior", "updates_var", "wpt_status_var", "wpt_index_var", "depth_var",
                    "altitude_var", "deactivate", "update_extra", "position_fix_var", "position_fix_full_var"):
            v = options.get(key, "x")
            must = key in ("name", "behavior", "updates_var", "wpt_status_var", "wpt_index_var", "deactivate")
            if not isinstance(v, str) or (must and not v) or (
                    key not in ("deactivate", "update_extra") and any(c.isspace() for c in v)):
                p.said(key, f"{who}: option {key!r} must be a "
                            f"{'non-empty ' if must else ''}MOOS name without spaces, not {v!r}")
        if isinstance(options.get("update_extra"), str) and "name=" in options["update_extra"].lower():
            p.said("update_extra", f"{who}: option 'update_extra' must not set name= (the output sends "
                                   "the behaviour's name itself)")
        return p

    def __init__(self, options: Mapping[str, Any], context: Any, client: Any = None) -> None:
        super().__init__(options, context)
        c = self.config
        self.host, self.port = parse_server(c["server"])
        self.behavior: str = c["behavior"]
        self.activate_var, activate = parse_flag(c["activate"])
        self.activate_value = _value(activate)
        self.deactivate_value = _value(c["deactivate"])
        self.endflag = None if not c["endflag"] else parse_flag(c["endflag"])
        self.time_warp = float(c["time_warp"])
        self.timeout = float(c["timeout"])
        self.client = client
        self.plan: Any = None
        self._phase: str | None = None  # None: no survey in hand
        self._since = 0.0  # `now` of the submit or of the phase's start (timeouts)
        self._pending: dict[str, str] = {}  # updates variable -> the update the helm must answer
        self._refusal = ""  # the helm's words on a refused update
        self._refused_bhv = ""  # the behaviour that refused it
        self._index: int | None = None
        self._out: list[SurveyReport] = []
        self._problem = LogOnce(log)
        #: what the helm last said: IVPHELM_STATE, IVPHELM_ALLSTOP, and `now` when each came
        self.helm_state: str | None = None
        self.helm_state_at: float | None = None
        self.allstop: str | None = None
        self.stats = {"submitted": 0, "received": 0, "ignored": 0}

    @property
    def variables(self) -> list[str]:
        c = self.config
        out = [c["wpt_index_var"], c["wpt_status_var"], "BHV_WARNING", "BHV_ERROR", *OVERRIDE_VARS, *HELM_VARS,
               self.activate_var]
        if self.endflag is not None:
            out.append(self.endflag[0])
        return list(dict.fromkeys(out))

    def open(self) -> None:
        self.client = moos_client(self.client, self.host, self.port, self.config["name"], self.variables,
                                  self.time_warp)

    def close(self) -> None:
        if self.client is not None:
            self.client.flush(timeout=2.0)  # what was posted reaches MOOSDB
            self.client.close()
            self.client = None

    def aid(self, fix: Any, now: float) -> bool:
        """A position fix posted to ``position_fix_var`` as ``x=X,y=Y`` (local metres: the MOOS
        community's NAV frame at ``node.origin``) and to ``position_fix_full_var`` with its time,
        sigma, depth and source."""
        var, full = self.config["position_fix_var"], self.config["position_fix_full_var"]
        if not var:
            return False
        if self.client is None:
            self.open()
        self.client.notify(var, f"x={_n(fix.x)},y={_n(fix.y)}")
        if full:
            depth = "" if fix.depth is None else f",depth={_n(fix.depth)}"
            self.client.notify(full, f"x={_n(fix.x)},y={_n(fix.y)},time={fix.time:.1f},sigma={_n(fix.sigma)}"
                                     f"{depth},source={fix.source}")
        return True

    # ------------------------------------------------------------------ submit
    def submit(self, plan: Any, now: float) -> None:
        if self.client is None:
            self.open()
        self._read(now)  # mail that came before this survey: the helm's state, nothing of it
        c = self.config
        wpt = f"name={self.behavior}#" + update_of(plan, c["update_extra"])
        self._pending = {c["updates_var"]: wpt}
        if c["depth_var"] and plan.depth is not None:
            self._pending[c["depth_var"]] = f"depth={_n(plan.depth)}"
        if c["altitude_var"] and plan.altitude is not None:
            self._pending[c["altitude_var"]] = f"altitude={_n(plan.altitude)}"
        self.client.notify(self.activate_var, self.deactivate_value)
        self.client.notify(c["updates_var"], f"name={self.behavior}")
        for var, update in self._pending.items():
            self.client.notify(var, update)
        self.plan, self._phase, self._since, self._index, self._refusal = plan, _UPDATE, now, None, ""
        self._out = [r for r in self._out if r.survey_id != int(plan.survey_id)]
        self.stats["submitted"] += 1
        log.info("moos: survey %s to the helm: %s = %s%s", plan.survey_id, c["updates_var"],
                 wpt if len(wpt) < 200 else wpt[:200] + "...",
                 "".join(f"; {k} = {v}" for k, v in list(self._pending.items())[1:]))

    def resume(self, plan: Any, now: float) -> bool:
        """The helm may still fly it: follow WPT_INDEX / WPT_STAT again, post nothing."""
        if self.client is None:
            self.open()
        self.plan, self._phase, self._since, self._index, self._refusal = plan, _FLYING, now, None, ""
        self._pending = {}
        log.info("moos: following survey %s again after a restart (nothing posted to the helm)", plan.survey_id)
        return True

    def end(self, survey_id: int, now: float) -> None:
        """The survey ended: stop following it and, unless a newer survey was handed over since,
        post the ended form: ``activate``'s variable = ``deactivate`` (the behaviour off) and
        ``updates_var`` = ``name=<behavior>`` (no points: MOOSDB keeps the newest value of a
        variable, and a helm that starts later reads it, so what it reads is no survey)."""
        if self.client is None:
            self.open()
        sid = int(survey_id)
        if self.plan is not None and int(self.plan.survey_id) != sid:
            return  # a newer survey is the helm's now
        self._phase = None
        self.client.notify(self.activate_var, self.deactivate_value)
        self.client.notify(self.config["updates_var"], f"name={self.behavior}")
        log.info("moos: survey %s ended: %s = %s, %s holds no survey", sid, self.activate_var,
                 self.deactivate_value, self.config["updates_var"])

    def heard(self, now: float) -> float | None:
        """When the helm last posted IVPHELM_STATE (it does every iteration; -inf: never); while
        the MOOSDB itself is out of reach, now (no helm can be heard, nor be called silent)."""
        if self.client is None:
            return None
        if not self.client.connected:
            return float(now)
        return -math.inf if self.helm_state_at is None else self.helm_state_at

    def silent_detail(self) -> str:
        return "no IVPHELM_STATE from the helm"

    # ------------------------------------------------------------------ reports
    def _report(self, state: SurveyState, now: float, reason: SurveyReason = SurveyReason.NONE,
                index: int | None = None, detail: str | None = None) -> None:
        self._out.append(SurveyReport(int(self.plan.survey_id), state, float(now), reason, index,
                                      detail=cut_detail(detail)))

    def _started(self, index: int, now: float) -> None:
        if self._phase == _ACTIVATED:
            self._phase = _FLYING
        n = len(self.plan.waypoints)
        if not 0 <= index < n:
            self._problem(f"index:{index}", "moos: waypoint index %d of a %d-waypoint survey ignored", index, n)
            return
        if index != self._index:
            self._index = index
            self._report(SurveyState.STARTED, now, index=index)
            log.info("moos: survey %s heading for waypoint %d of %d", self.plan.survey_id, index, n)

    def _completed(self, now: float) -> None:
        if self._index is None:  # too short for the helm to post an index: it did set off
            self._report(SurveyState.STARTED, now, index=0)
        self._report(SurveyState.COMPLETED, now)
        log.info("moos: survey %s completed", self.plan.survey_id)
        self._phase = None

    def _end(self, reason: SurveyReason, now: float, detail: str) -> None:
        """The survey ends before its last waypoint: REJECTED while the helm had not taken its
        updates, ABORTED after; the behaviour is deactivated so the helm never resumes it."""
        state = SurveyState.REJECTED if self._phase in (_UPDATE, _REFUSED) else SurveyState.ABORTED
        log.warning("moos: survey %s %s (%s): %s", self.plan.survey_id, state.name.lower(), reason.name, detail)
        self._report(state, now, reason, detail=detail)
        self.client.notify(self.activate_var, self.deactivate_value)
        self._phase = None

    # ------------------------------------------------------------------ poll
    def poll(self, now: float) -> list[Any]:
        if self.client is None:
            return []
        self._read(now)
        if self._phase is not None:
            self._timeouts(now)
        out, self._out = self._out, []
        return out

    def _read(self, now: float) -> None:
        if not self.client.connected:  # no mail can come: no timeout runs meanwhile
            self._since = max(self._since, now) if self._phase is not None else self._since
            self.helm_state_at = None if self.helm_state_at is None else max(self.helm_state_at, now)
        for m in self.client.fetch():
            self.stats["received"] += 1
            if m.source == self.config["name"]:
                self.stats["ignored"] += 1
                continue
            try:
                self._mail(m, now)
            except Exception as exc:  # bad mail from the vehicle is logged, never raised
                self._problem(f"bad:{m.key}", "moos: %s = %r not understood: %s", m.key, m.value, exc)

    def _timeouts(self, now: float) -> None:
        waited = now - self._since
        if self._phase == _REFUSED and waited > self.timeout:
            self._end(SurveyReason.AUTONOMY_REFUSED, now, self._refusal)
        elif self._phase == _UPDATE and waited > self.timeout:
            var = next(iter(self._pending), self.config["updates_var"])
            self._end(SurveyReason.AUTONOMY_NO_ANSWER, now, self._no_helm(now) or
                      f"no answer to {var} (helm {self.helm_state})")
        elif self._phase == _ACTIVATED and waited > self.timeout:
            stop = self.allstop if self.allstop and self.allstop.lower() != "clear" else f"helm {self.helm_state}"
            self._end(SurveyReason.AUTONOMY_STOPPED, now, self._no_helm(now) or f"{self.behavior} did not run ({stop})")

    def _no_helm(self, now: float) -> str:
        """Why no helm answers, or "" when one is heard."""
        if self.helm_state is None or self.helm_state_at is None or now - self.helm_state_at > self.timeout:
            return "no helm (no IVPHELM_STATE)"
        return ""

    def _mail(self, m: Any, now: float) -> None:
        key = m.key
        text = m.value if m.is_string else None
        # the helm's state, kept whatever the phase
        if key == "IVPHELM_STATE" and text is not None:
            self.helm_state, self.helm_state_at = text.strip(), now
        elif key == "IVPHELM_ALLSTOP" and text is not None:
            self.allstop = text.strip()
        phase = self._phase
        if phase is None or self.plan is None:
            self.stats["ignored"] += 1
            return
        # a helm (re)start loses the survey, whatever its phase
        if key == "PHELMIVP_PID" or (key == "IVPHELM_RESTARTED" and text is not None and text.lower() == "true"):
            self._end(SurveyReason.AUTONOMY_RESTARTED, now, f"{m.source or 'the helm'} restarted ({key})")
            return
        if key == self.activate_var and m.source_aux == "HELM_VAR_INIT":
            self._end(SurveyReason.AUTONOMY_RESTARTED, now, f"{m.source or 'the helm'} restarted "
                                                            f"({key} = {m.value} initialized)")
            return
        if key in OVERRIDE_VARS:
            if text is not None and text.strip().lower() == "true":
                self._end(SurveyReason.MANUAL_OVERRIDE, now, f"{key} = true ({m.source})")
            return
        if key == "IVPHELM_STATE" and text is not None:
            state = text.strip().upper()
            if state == "PARK":
                self._end(SurveyReason.MANUAL_OVERRIDE, now, "helm PARK" + (f": {self.allstop}" if self.allstop
                                                                          and self.allstop.lower() != "clear" else ""))
            elif not state.startswith(("DRIVE", "STANDBY")):
                self._end(SurveyReason.AUTONOMY_STOPPED, now, f"helm {text.strip()}")
            elif phase == _REFUSED:  # the helm's next iteration: its warning (if any) came before
                self._end(SurveyReason.AUTONOMY_REFUSED, now, self._refusal)
            return
        if phase in (_UPDATE, _REFUSED):
            self._handing_over(m, now)
        else:
            self._flying(m, now)
        if self._phase is not None and self.endflag is not None and key == self.endflag[0] \
                and self._phase in (_ACTIVATED, _FLYING) and _same(m.value, _value(self.endflag[1])):
            self._completed(now)

    def _handing_over(self, m: Any, now: float) -> None:
        """The helm's answers to the updates, until the activation."""
        c = self.config
        if m.key == "IVPHELM_UPDATE_RESULT" and m.is_string:
            r = parse_update_result(str(m.value))
            var, result = r.get("var", ""), r.get("result", "")
            if self._pending.get(var) != r.get("val") or self._phase != _UPDATE:
                return  # another behaviour's, the separator's, or an answer after a refusal
            bhv = r.get("bhv", "?")
            if result == "success" or (result == "duplicate" and var != c["updates_var"]):
                del self._pending[var]
                if not self._pending:
                    self.client.notify(self.activate_var, self.activate_value)
                    self._phase, self._since = _ACTIVATED, now
                    log.info("moos: the helm took survey %s; %s = %s", self.plan.survey_id, self.activate_var,
                             self.activate_value)
            elif result == "param_error":
                self.client.notify(self.activate_var, self.deactivate_value)  # nothing of it is flown
                self._phase, self._since = _REFUSED, now
                self._refusal, self._refused_bhv = f"{bhv} refused {var}", bhv
            elif result == "name_mismatch":
                self._end(SurveyReason.AUTONOMY_REFUSED, now, f"{var} is {bhv}'s, not {self.behavior}")
            else:
                self._end(SurveyReason.AUTONOMY_REFUSED, now, f"{bhv}: {result or 'no result'} ({var})")
        elif m.key == "BHV_WARNING" and m.is_string and self._phase == _REFUSED \
                and str(m.value).startswith(f"{FAULTY}{self._refused_bhv}."):
            bhv, _, rest = str(m.value)[len(FAULTY):].partition(". ")
            self._end(SurveyReason.AUTONOMY_REFUSED, now, f"{bhv}: {rest}")

    def _flying(self, m: Any, now: float) -> None:
        """What the helm does with the activated survey."""
        c = self.config
        key, behavior = m.key, self.behavior
        if key == c["wpt_index_var"] and m.is_double:
            self._started(round(float(m.value)), now)
        elif key == c["wpt_status_var"] and m.is_string:
            fields, words = {}, set()
            for part in str(m.value).split(","):
                k, sep, v = part.partition("=")
                if sep:
                    fields[k.strip().lower()] = v.strip()
                else:
                    words.add(part.strip().lower())
            if fields.get("behavior-name", behavior) != behavior:
                return  # another waypoint behaviour
            if "completed" in words or "cycled" in words:
                self._completed(now)
            elif "index" in fields:
                self._started(int(fields["index"]), now)
        elif key in ("IVPHELM_BHV_ACTIVE", "IVPHELM_BHV_RUNNING") and behavior in _names(m.value):
            if self._phase == _ACTIVATED:
                self._phase = _FLYING
                if self._index is None:
                    self._started(0, now)
        elif key == "IVPHELM_BHV_IDLE" and behavior in _names(m.value) and self._phase == _FLYING:
            self._end(SurveyReason.AUTONOMY_STOPPED, now, f"{behavior} idle before its last waypoint")
        elif key == "IVPHELM_ALLSTOP" and m.is_string and self._phase == _FLYING:
            stop = str(m.value).strip()
            if stop.lower() == "manualoverride":
                self._end(SurveyReason.MANUAL_OVERRIDE, now, "helm all-stop ManualOverride")
            elif stop.lower() != "clear":
                self._end(SurveyReason.ALL_STOP, now, stop)
        elif key == self.activate_var:
            if _same(m.value, self.activate_value):
                return  # someone activated it too
            if m.source_aux.endswith(f":{behavior}"):
                self._completed(now)  # the behaviour's own endflag: it reached its last waypoint
            else:
                who = m.source + (f" ({m.source_aux})" if m.source_aux else "")
                self._end(SurveyReason.AUTONOMY_STOPPED, now, f"{key} = {m.value} by {who}")
        elif key == "BHV_WARNING" and m.is_string and behavior in str(m.value):
            self._problem(f"warn:{m.value}", "moos: helm warning: %s", m.value)
        elif key == "BHV_ERROR" and m.is_string and behavior in str(m.value):
            self._problem(f"err:{m.value}", "moos: helm error: %s", m.value)
