"""The ``lcm`` autonomy output: each plan is published as a ``coex.survey_request_t`` for the
vehicle's own planner, whose ``coex.survey_state_t`` answers become survey reports.

* :meth:`LcmAutonomy.submit` publishes a request on ``channel`` (default
  ``COEX_SURVEY_REQUEST``): the waypoints in local metres and in degrees (from the configured
  origin), the altitude, depth and speed (NaN = not given). ``utime`` is ``now`` in microseconds.
* :meth:`LcmAutonomy.poll` handles what arrived on ``state_channel`` (default
  ``COEX_SURVEY_STATE``), never blocking: state 0 -> nothing (the planner has the request and
  flies it later), 1 -> REJECTED (AUTONOMY_REFUSED), 2 -> STARTED (``index``), 3 -> COMPLETED,
  4 -> ABORTED (AUTONOMY_STOPPED), 5 -> ABORTED (MANUAL_OVERRIDE), 6 -> ABORTED (ALL_STOP),
  7 -> ABORTED (AUTONOMY_RESTARTED). With 1 and 4..7 an ``index`` >= 0 is the planner's own
  code (the report's ``value``). Reports are stamped with ``now`` (the daemon's clock), not with
  the planner's ``utime``.
* A planner that does not answer a request (any state for its ``survey_id``) within
  ``answer_timeout`` seconds gets it again (the same message, the same ``utime``), at most
  ``retries`` times; then the survey is REJECTED AUTONOMY_NO_ANSWER (``value`` the tries made):
  the planner or the LCM network is down, which is not a refusal. ``answer_timeout = 0`` waits
  for nothing (a planner that only answers when it starts much later).

Anything else on the state channel (another type, an unknown state) is logged and dropped.
The types are defined in ``spec/bindings/coex.lcm``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from typing import Any

from coex import Autonomy, ConfigError
from coex.lcm import DEFAULT_URL, survey_request_t, survey_state_t
from coex.messages import SurveyReason, SurveyState
from coex.options import integer, number

from ..options import Problems, check_lcm_url
from ..survey.plan import SurveyReport, cut_detail

__all__ = ["LcmAutonomy", "ended_request", "report_of", "request_of"]

log = logging.getLogger(__name__)

#: survey_state_t.state -> (SurveyState, reason); 0 (RECEIVED) is an answer without a report
STATES = {
    1: (SurveyState.REJECTED, SurveyReason.AUTONOMY_REFUSED),
    2: (SurveyState.STARTED, SurveyReason.NONE),
    3: (SurveyState.COMPLETED, SurveyReason.NONE),
    4: (SurveyState.ABORTED, SurveyReason.AUTONOMY_STOPPED),
    5: (SurveyState.ABORTED, SurveyReason.MANUAL_OVERRIDE),
    6: (SurveyState.ABORTED, SurveyReason.ALL_STOP),
    7: (SurveyState.ABORTED, SurveyReason.AUTONOMY_RESTARTED),
}
#: survey_state_t.state of a planner that has the request and will fly it later
RECEIVED = 0
#: most messages handled in one poll
MAX_HANDLE = 1000


def _nan(v: float | None) -> float:
    return math.nan if v is None else float(v)


def request_of(plan: Any, context: Any, now: float) -> survey_request_t:
    """The ``survey_request_t`` of a plan."""
    msg = survey_request_t()
    msg.utime = round(now * 1e6)
    msg.survey_id = int(plan.survey_id)
    msg.kind = int(plan.kind)
    pts = [(float(x), float(y)) for x, y in plan.waypoints]
    msg.n = len(pts)
    msg.x = [p[0] for p in pts]
    msg.y = [p[1] for p in pts]
    geo = [context.geodetic(x, y) for x, y in pts]
    msg.lat = [g[0] for g in geo]
    msg.lon = [g[1] for g in geo]
    msg.altitude, msg.depth, msg.speed = _nan(plan.altitude), _nan(plan.depth), _nan(plan.speed)
    return msg


def ended_request(survey_id: int, now: float) -> survey_request_t:
    """The ended form of a survey: its ``survey_id``, ``n = 0`` (no waypoints), NaN heights and
    speed."""
    msg = survey_request_t()
    msg.utime = round(now * 1e6)
    msg.survey_id = int(survey_id)
    msg.kind = 0
    msg.n = 0
    msg.x, msg.y, msg.lat, msg.lon = [], [], [], []
    msg.altitude = msg.depth = msg.speed = math.nan
    return msg


def report_of(msg: survey_state_t, now: float) -> SurveyReport | None:
    """The SurveyReport of a planner's answer (None: a state it cannot be, or RECEIVED)."""
    state = STATES.get(int(msg.state))
    if state is None:
        return None
    if state[0] == SurveyState.STARTED:
        return SurveyReport(int(msg.survey_id), state[0], float(now), state[1], max(0, int(msg.index)))
    value = float(msg.index) if state[1] != SurveyReason.NONE and msg.index >= 0 else None
    return SurveyReport(int(msg.survey_id), state[0], float(now), state[1], None, value)


class LcmAutonomy(Autonomy):
    """Publishes survey requests on LCM, reads the planner's answers (module docstring)."""

    name = "lcm"
    options = {
        "url": (DEFAULT_URL, "LCM provider URL (udpm://239.255.76.67:7667?ttl=0, memq:// ...)"),
        "channel": ("COEX_SURVEY_REQUEST", "channel of the survey_request_t it publishes"),
        "state_channel": ("COEX_SURVEY_STATE", "channel of the planner's survey_state_t answers"),
        "answer_timeout": number(5.0, "seconds to wait for the planner's first answer to a request before it "
                                      "is published again (0: do not wait for one)", unit="s", lo=0),
        "retries": integer(2, "times a request is published again before the survey is given up as "
                              "REJECTED AUTONOMY_NO_ANSWER", lo=0, hi=100),
        "silence": number(10.0, "seconds without a survey_state_t from the planner while a survey flies before "
                                "it is aborted AUTONOMY_SILENT (0: not watched; a planner repeats its state "
                                "while it flies)", unit="s", lo=0),
    }

    @classmethod
    def check(cls, options: Mapping[str, Any]) -> Problems:
        p = Problems()
        for key in ("url", "channel", "state_channel"):
            v = options.get(key, "x")
            if not isinstance(v, str) or not v:
                p.said(key, f"autonomy 'lcm': {key} must be a non-empty string, got {v!r}")
            elif key != "url" and len(v) > 63:
                p.said(key, f"autonomy 'lcm': {key} is longer than LCM's 63 characters")
        check_lcm_url(p, "autonomy 'lcm'", options)
        return p

    def __init__(self, options: Mapping[str, Any], context: Any, instance: Any = None) -> None:
        super().__init__(options, context)
        self.lc: Any = instance
        self._own = instance is None
        self._sub: Any = None
        self._received: list[bytes] = []
        #: the request waiting for the planner's first answer: survey id, the encoded request,
        #: when to publish it again, tries made (None: none waits)
        self._waiting: tuple[int, bytes, float, int] | None = None
        #: when the planner's last survey_state_t came (None: never)
        self.heard_at: float | None = None
        self.stats = {"published": 0, "received": 0, "bad": 0, "resent": 0, "ended": 0}

    def open(self) -> None:
        if self._sub is not None:
            return
        if self.lc is None:
            import lcm

            try:
                self.lc = lcm.LCM(self.config["url"])
            except Exception as exc:
                raise ConfigError(f"autonomy 'lcm': cannot open {self.config['url']!r}: {exc}") from exc
        # LCM subscribes by regular expression: match the channel name exactly
        import re

        self._sub = self.lc.subscribe(re.escape(self.config["state_channel"]),
                                      lambda _channel, data: self._received.append(data))

    def close(self) -> None:
        if self.lc is not None and self._sub is not None:
            try:
                self.lc.unsubscribe(self._sub)
            except Exception:  # already gone
                pass
        self._sub = None
        if self._own:
            self.lc = None

    def submit(self, plan: Any, now: float) -> None:
        if self._sub is None:
            self.open()
        msg = request_of(plan, self.context, now)
        data = bytes(msg.encode())
        self.lc.publish(self.config["channel"], data)
        self.stats["published"] += 1
        wait = float(self.config["answer_timeout"])
        self._waiting = (int(plan.survey_id), data, now + wait, 1) if wait > 0 else None
        log.info("lcm: survey %s (%d waypoints) published on %s", plan.survey_id, msg.n, self.config["channel"])

    def resume(self, plan: Any, now: float) -> bool:
        """The planner reports by survey id: its answers are followed again, nothing published."""
        if self._sub is None:
            self.open()
        self._waiting = None
        return True

    def end(self, survey_id: int, now: float) -> None:
        """The survey ended: it is not published again (no resend), and its ended form goes out: a
        ``survey_request_t`` with its ``survey_id`` and ``n = 0`` (no waypoints: fly nothing of
        it, stop flying it)."""
        if self._sub is None:
            self.open()
        sid = int(survey_id)
        if self._waiting is not None and self._waiting[0] == sid:
            self._waiting = None
        msg = ended_request(sid, now)
        try:
            self.lc.publish(self.config["channel"], bytes(msg.encode()))
        except OSError as exc:
            log.warning("lcm: survey %d: publishing its end failed: %s", sid, exc)
            return
        self.stats["ended"] += 1
        log.info("lcm: survey %d ended: an empty request (n = 0) published on %s", sid, self.config["channel"])

    def heard(self, now: float) -> float | None:
        """When the planner's last ``survey_state_t`` came (-inf: none since this output opened)."""
        if self._sub is None:
            return None
        return -math.inf if self.heard_at is None else self.heard_at

    def silent_detail(self) -> str:
        return f"no survey_state_t on {self.config['state_channel']}"

    def poll(self, now: float) -> list[Any]:
        if self._sub is None:
            return []
        for _ in range(MAX_HANDLE):
            try:
                if self.lc.handle_timeout(0) <= 0:
                    break
            except OSError as exc:
                log.warning("lcm: receive failed: %s", exc)
                break
        data, self._received = self._received, []
        out = []
        for raw in data:
            try:
                msg = survey_state_t.decode(raw)
            except Exception as exc:  # another type on the channel, a truncated message
                self.stats["bad"] += 1
                log.warning("lcm: not a survey_state_t on %s (%d bytes): %s", self.config["state_channel"],
                            len(raw), exc)
                continue
            if int(msg.state) != RECEIVED and int(msg.state) not in STATES:
                self.stats["bad"] += 1
                log.warning("lcm: survey %d: unknown state %d", msg.survey_id, msg.state)
                continue
            self.stats["received"] += 1
            self.heard_at = float(now)
            if self._waiting is not None and self._waiting[0] == int(msg.survey_id):
                self._waiting = None  # the planner answers
            report = report_of(msg, now)
            if report is not None:
                out.append(report)
        return out + self._timeout(now)

    def _timeout(self, now: float) -> list[SurveyReport]:
        """Publish the waiting request again, or give it up."""
        if self._waiting is None or now < self._waiting[2]:
            return []
        sid, data, _, tries = self._waiting
        if tries > int(self.config["retries"]):
            self._waiting = None
            channel = self.config["state_channel"]
            log.warning("lcm: survey %d: no survey_state_t on %s after %d tries; given up", sid, channel, tries)
            return [SurveyReport(sid, SurveyState.REJECTED, float(now), SurveyReason.AUTONOMY_NO_ANSWER,
                                 value=float(tries), detail=cut_detail(f"no survey_state_t on {channel}"))]
        try:
            self.lc.publish(self.config["channel"], data)
        except OSError as exc:  # a network down: the next try or the give-up tells
            log.warning("lcm: survey %d: publishing again failed: %s", sid, exc)
        self.stats["resent"] += 1
        self._waiting = (sid, data, now + float(self.config["answer_timeout"]), tries + 1)
        return []
