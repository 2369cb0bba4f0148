"""Survey messages: a topside command asking the vehicle to survey somewhere, and the vehicle's
report of where that survey is (accepted, rejected with a reason, started, completed)."""

from __future__ import annotations

import construct as cs

from ..messages import (
    SURVEY_DETAIL_MAX,
    SurveyCommand,
    SurveyKind,
    SurveyPoint,
    SurveyReason,
    SurveyState,
    SurveyStatus,
)
from ._primitives import Body, Bool, Bounded, Count, Enum, Given, Rule, Stamp, Text, When
from ._registry import MessageSpec, register

#: Further waypoints of a WAYPOINTS survey (the first is ``x``, ``y``).
MAX_SURVEY_POINTS = 31
SURVEY_ID = Bounded(0, 1023) * "Survey id (chosen topside; wraps at 1024)"
XY = dict(lo=-50000, hi=50000, res=0.1, unit="m")

SURVEY_POINT = cs.Struct(
    "x" / Bounded(**XY) * "Waypoint east of the origin",  # type: ignore[arg-type]
    "y" / Bounded(**XY) * "Waypoint north of the origin",  # type: ignore[arg-type]
)


#: the optional fields each kind needs (the others may be given; a kind that does not use them
#: ignores them)
NEEDS = {SurveyKind.LINE: ("heading", "length"), SurveyKind.LAWNMOWER: ("heading", "length", "width", "spacing")}


def _complete(ctx: cs.Container) -> bool:
    return all(ctx[f] is not None for f in NEEDS.get(SurveyKind(int(ctx.kind)), ()))


SURVEY_COMMAND = Body(
    "command_id" / Bounded(0, 255) * "Command id, echoed in the CommandAck",
    "survey_id" / SURVEY_ID,
    "kind" / Enum(SurveyKind, bits=3) * "What to fly",
    "x" / Bounded(**XY) * "Goal point, line start, lawnmower centre or first waypoint, east",  # type: ignore[arg-type]
    "y" / Bounded(**XY) * "The same, north",  # type: ignore[arg-type]
    "heading" / Bounded(0, 359.9, 0.1, optional=True, unit="deg")
    * "Direction of the line or of the lawnmower's rows, clockwise from north",
    "length" / Bounded(0, 10000, 0.5, optional=True, unit="m") * "Line length, or lawnmower row length",
    "width" / Bounded(0, 10000, 0.5, optional=True, unit="m") * "Lawnmower width (across the rows)",
    "spacing" / Bounded(0, 500, 0.5, optional=True, unit="m") * "Lawnmower row spacing",
    "altitude" / Bounded(0, 500, 0.1, optional=True, unit="m") * "Altitude above the seafloor to fly at",
    "depth" / Bounded(0, 6000, 0.1, optional=True, unit="m") * "Depth to fly at (instead of altitude)",
    "speed" / Bounded(0, 5, 0.05, optional=True, unit="m/s") * "Speed through the water",
    "append" / Bool() * "Queue after the surveys already accepted (0: replace them)",
    "n_points" / Count(0, MAX_SURVEY_POINTS, "points"),
    "points" / cs.Array(cs.this.n_points, SURVEY_POINT) * "Further waypoints of a WAYPOINTS survey, in order",
    Rule(_complete, "`kind` is LINE and `heading` or `length` is absent, or `kind` is LAWNMOWER and one of "
                    "`heading`, `length`, `width`, `spacing` is absent", "incomplete survey"),
    Rule(lambda ctx: int(ctx.kind) == SurveyKind.WAYPOINTS or len(ctx.points) == 0,
         "`points` has entries and `kind` is not WAYPOINTS", "points without WAYPOINTS"),
    Rule(lambda ctx: ctx.altitude is None or ctx.depth is None, "`altitude` and `depth` are both given",
         "altitude and depth"),
)

SURVEY_STATUS = Body(
    "survey_id" / SURVEY_ID,
    "state" / Enum(SurveyState, bits=3) * "Where the survey is",
    "reason" / Enum(SurveyReason, bits=4) * "Why it was rejected or aborted (NONE otherwise)",
    "stamp" / Stamp() * "When it got to this state",
    "index" / Bounded(0, 255, optional=True)
    * "STARTED: the waypoint it heads for; REJECTED: the first waypoint that broke the rule",
    "value" / Bounded(0, 10000, 0.1, optional=True, unit="m, or m/s")
    * "REJECTED: how far outside the geofence, the limit that was broken, or the autonomy's code; "
    "AUTONOMY_NO_ANSWER: the tries made; AUTONOMY_SILENT: the seconds of silence",
    "has_detail" / Given("detail"),
    "detail" / When("`has_detail` = 1", cs.this.has_detail, Text(SURVEY_DETAIL_MAX))
    * "REJECTED, ABORTED: the autonomy's own words (e.g. the helm's bad parameters)",
    Rule(lambda ctx: ctx.detail is None or len(ctx.detail) > 0,
         "`has_detail` is 1 and `detail` has no bytes (no detail is `has_detail` = 0)", "empty detail"),
)

_FAR = 50000.0
_BIG = SurveyCommand(255, 1023, SurveyKind.WAYPOINTS, -_FAR, _FAR, None, None, None, None, 500.0, None,
                     5.0, True, tuple(SurveyPoint(_FAR, -_FAR) for _ in range(MAX_SURVEY_POINTS)))

register(MessageSpec(
    11, SurveyCommand, SURVEY_COMMAND, False, "survey",
    "Topside command: survey somewhere (go to a point, a line, a lawnmower or waypoints); "
    "answered by a CommandAck and SurveyStatus reports.",
    largest=lambda: _BIG,
    cases=lambda: [
        ("goto", SurveyCommand(0, 0, SurveyKind.GOTO, 12.3, -45.6)),
        ("line", SurveyCommand(7, 3, SurveyKind.LINE, 100.0, -20.0, 0.0, 60.0, None, None, 5.0, None, 0.5,
                               True)),
        ("lawnmower", SurveyCommand(21, 17, SurveyKind.LAWNMOWER, 150.0, 150.0, 45.0, 120.0, 80.0, 20.0,
                                    None, 35.5, 1.0)),
        ("waypoints_max", _BIG),
    ],
))
register(MessageSpec(
    12, SurveyStatus, SURVEY_STATUS, False, "survey",
    "Vehicle report: the newest state of one survey (re-sent until acknowledged).",
    largest=lambda: SurveyStatus(1023, SurveyState.ABORTED, SurveyReason.ALL_STOP, 2**18 - 1, 255, 10000.0,
                                 "x" * SURVEY_DETAIL_MAX),
    cases=lambda: [
        ("accepted", SurveyStatus(0, SurveyState.ACCEPTED, SurveyReason.NONE, 0)),
        ("outside_fence", SurveyStatus(17, SurveyState.REJECTED, SurveyReason.OUTSIDE_GEOFENCE, 5123, 3, 212.5)),
        ("started", SurveyStatus(3, SurveyState.STARTED, SurveyReason.NONE, 7200, 1)),
        ("helm_refused", SurveyStatus(5, SurveyState.REJECTED, SurveyReason.AUTONOMY_REFUSED, 812, None, None,
                                      "Bad parameter(s): speed")),
        ("autopilot_refused", SurveyStatus(6, SurveyState.REJECTED, SurveyReason.AUTONOMY_REFUSED, 900, None, 14.0,
                                           "MAV_MISSION_DENIED")),
        ("no_answer", SurveyStatus(7, SurveyState.REJECTED, SurveyReason.AUTONOMY_NO_ANSWER, 950, None, 6.0)),
        ("override", SurveyStatus(8, SurveyState.ABORTED, SurveyReason.MANUAL_OVERRIDE, 1000, 3)),
        ("silent", SurveyStatus(9, SurveyState.ABORTED, SurveyReason.AUTONOMY_SILENT, 1100, 2, 12.5,
                                "no HEARTBEAT from 1/1")),
        ("largest", SurveyStatus(1023, SurveyState.ABORTED, SurveyReason.ALL_STOP, 2**18 - 1, 255, 10000.0,
                                 "x" * SURVEY_DETAIL_MAX)),
    ],
))
