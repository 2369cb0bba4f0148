"""The ``mavlink`` autonomy output: each plan becomes a MAVLink mission (ArduSub, PX4), uploaded
with the standard mission protocol through pymavlink and then started.

Protocol (MAVLink devguide ``services/mission.md``; ``docs/autonomy.md``)::

    -> MISSION_COUNT{count, mission_type=0}
    <- MISSION_REQUEST_INT{seq}   (or the legacy MISSION_REQUEST)
    -> MISSION_ITEM_INT{seq, frame, MAV_CMD_NAV_WAYPOINT, x=lat*1e7, y=lon*1e7, z}
       ... every item, in order ...
    <- MISSION_ACK{type}          MAV_MISSION_ACCEPTED: start it;
                                  any other type: REJECTED AUTONOMY_REFUSED, value = the type,
                                  detail = its name (MAV_MISSION_DENIED ...); except
                                  MAV_MISSION_INVALID_SEQUENCE: ArduPilot's NACK of a duplicate
                                  item does not end the upload
    -> COMMAND_LONG MAV_CMD_MISSION_START (or MAV_CMD_DO_SET_MODE AUTO, or nothing)
    <- COMMAND_ACK                accepted: STARTED index 0 (with ``start = "none"``: at the
                                  upload's ack); refused: ABORTED AUTONOMY_STOPPED, value = the
                                  MAV_RESULT, detail = its name
    <- MISSION_ITEM_REACHED{seq}, MISSION_CURRENT{seq}: STARTED with the next waypoint, then
       COMPLETED when the last one is reached

MISSION_COUNT is sent again after ``timeout`` (1.5 s) without a request, the last item after
``item_timeout`` (0.25 s) without the next request or the ack, the start command after
``timeout`` without its COMMAND_ACK, at most ``retries`` (5) times in a row; then the survey is
REJECTED AUTONOMY_NO_ANSWER, value = the tries made (``retries`` + 1), detail = what went
unanswered: an autopilot that never answers is not one that refused. A new plan during an
upload restarts the upload with the new plan. With ``home_placeholder`` (ArduPilot: seq 0 is
home) a placeholder goes at seq 0, so waypoint ``k`` is seq ``k + 1`` (``k + 2`` when a
MAV_CMD_DO_CHANGE_SPEED item carries the plan's speed).

HEARTBEAT goes out about every ``heartbeat`` seconds (as ``MAV_TYPE_ONBOARD_CONTROLLER``,
``MAV_AUTOPILOT_INVALID``). The target system/component are the options', else those of the
first vehicle heartbeat heard, else 1/1. An ArduPilot vehicle seen in the AUTO mode
(``auto_mode``) that leaves it before the survey's end stops it: ABORTED, value = its new custom
mode, detail = "left AUTO for ALT_HOLD"; the reason is MANUAL_OVERRIDE when the new mode is one
of ``manual_modes`` (a pilot's mode: ArduSub MANUAL, STABILIZE, ACRO, ALT_HOLD, POSHOLD), else
AUTONOMY_STOPPED (SURFACE, a failsafe's mode, GUIDED ...).

Never blocking (``recv_match(blocking=False)``), never reading a clock: time is ``now``. Bad
input (garbage, a request out of range, a message for someone else) is logged and ignored.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from coex import Autonomy, ConfigError
from coex.messages import SurveyReason, SurveyState
from coex.options import REQUIRED, anything, flag, integer, number, text

from ..options import Problems, check_mavlink_connection
from ..survey.plan import SurveyReport, cut_detail

__all__ = ["MavlinkAutonomy", "MissionItem", "connect", "enum_name", "mission_items", "mode_name"]

log = logging.getLogger(__name__)

# MAVLink numbers (common.xml), so that building items needs no pymavlink import
MAV_CMD_NAV_WAYPOINT = 16
MAV_CMD_DO_CHANGE_SPEED = 178
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_MISSION_START = 300
MAV_FRAME_GLOBAL = 0
MAV_FRAME_GLOBAL_RELATIVE_ALT = 3
MAV_FRAME_GLOBAL_RELATIVE_ALT_INT = 6
MAV_FRAME_GLOBAL_TERRAIN_ALT = 10
MAV_FRAME_GLOBAL_TERRAIN_ALT_INT = 11
MAV_MISSION_ACCEPTED = 0
MAV_MISSION_INVALID_SEQUENCE = 13
MAV_RESULT_ACCEPTED = 0
MAV_RESULT_IN_PROGRESS = 5
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_INVALID = 8
MAV_TYPE_GCS = 6
MAV_TYPE_GIMBAL = 26
MAV_TYPE_ADSB = 27
MAV_TYPE_ONBOARD_CONTROLLER = 18
#: ArduSub's AUTO custom mode (ardupilotmega.xml SUB_MODE)
SUB_MODE_AUTO = 3
MAV_TYPE_SUBMARINE = 12
#: ArduSub's modes a pilot flies in (ardupilotmega.xml SUB_MODE): STABILIZE, ACRO, ALT_HOLD,
#: POSHOLD, MANUAL; leaving AUTO for one of them is a manual override
SUB_MANUAL_MODES = (0, 1, 2, 16, 19)

#: The names of the numbers this output reports, when pymavlink's dialect is not at hand
#: (common.xml MAV_MISSION_RESULT and MAV_RESULT, ardupilotmega.xml SUB_MODE)
_NAMES: dict[str, dict[int, str]] = {
    "MAV_MISSION_RESULT": {
        0: "MAV_MISSION_ACCEPTED", 1: "MAV_MISSION_ERROR", 2: "MAV_MISSION_UNSUPPORTED_FRAME",
        3: "MAV_MISSION_UNSUPPORTED", 4: "MAV_MISSION_NO_SPACE", 5: "MAV_MISSION_INVALID",
        6: "MAV_MISSION_INVALID_PARAM1", 7: "MAV_MISSION_INVALID_PARAM2", 8: "MAV_MISSION_INVALID_PARAM3",
        9: "MAV_MISSION_INVALID_PARAM4", 10: "MAV_MISSION_INVALID_PARAM5_X", 11: "MAV_MISSION_INVALID_PARAM6_Y",
        12: "MAV_MISSION_INVALID_PARAM7", 13: "MAV_MISSION_INVALID_SEQUENCE", 14: "MAV_MISSION_DENIED",
        15: "MAV_MISSION_OPERATION_CANCELLED"},
    "MAV_RESULT": {
        0: "MAV_RESULT_ACCEPTED", 1: "MAV_RESULT_TEMPORARILY_REJECTED", 2: "MAV_RESULT_DENIED",
        3: "MAV_RESULT_UNSUPPORTED", 4: "MAV_RESULT_FAILED", 5: "MAV_RESULT_IN_PROGRESS", 6: "MAV_RESULT_CANCELLED",
        7: "MAV_RESULT_COMMAND_LONG_ONLY", 8: "MAV_RESULT_COMMAND_INT_ONLY"},
    "SUB_MODE": {
        0: "SUB_MODE_STABILIZE", 1: "SUB_MODE_ACRO", 2: "SUB_MODE_ALT_HOLD", 3: "SUB_MODE_AUTO",
        4: "SUB_MODE_GUIDED", 7: "SUB_MODE_CIRCLE", 9: "SUB_MODE_SURFACE", 16: "SUB_MODE_POSHOLD",
        19: "SUB_MODE_MANUAL", 20: "SUB_MODE_MOTORDETECT", 21: "SUB_MODE_SURFTRAK"},
}
_COMMANDS = {MAV_CMD_MISSION_START: "MAV_CMD_MISSION_START", MAV_CMD_DO_SET_MODE: "MAV_CMD_DO_SET_MODE"}


def enum_name(enum: str, value: int) -> str:
    """The name of ``value`` in the MAVLink enum ``enum`` ("MAV_MISSION_RESULT", 14 ->
    "MAV_MISSION_DENIED"), from pymavlink's ardupilotmega dialect (which includes common.xml)
    when it is installed, else from a small table; "MAV_RESULT 42" for a value neither knows."""
    try:
        from pymavlink.dialects.v20 import ardupilotmega as dialect

        entry = dialect.enums.get(enum, {}).get(int(value))
        if entry is not None and not str(entry.name).endswith("_ENUM_END"):
            return str(entry.name)
    except ImportError:
        pass
    return _NAMES.get(enum, {}).get(int(value), f"{enum} {int(value)}")


def mode_name(mode: int, vehicle_type: int | None = MAV_TYPE_SUBMARINE) -> str:
    """An ArduPilot custom mode in words: ArduSub's name without its prefix ("ALT_HOLD") for a
    submarine (or a vehicle whose type is not known yet), else "mode 2" (other ArduPilot
    vehicles number their modes differently)."""
    if vehicle_type in (None, MAV_TYPE_SUBMARINE):
        name = enum_name("SUB_MODE", mode)
        if name.startswith("SUB_MODE_"):
            return name[len("SUB_MODE_"):]
    return f"mode {int(mode)}"

_FRAMES = {MAV_FRAME_GLOBAL, MAV_FRAME_GLOBAL_RELATIVE_ALT, MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
           MAV_FRAME_GLOBAL_TERRAIN_ALT, MAV_FRAME_GLOBAL_TERRAIN_ALT_INT}
_TERRAIN = {MAV_FRAME_GLOBAL_TERRAIN_ALT, MAV_FRAME_GLOBAL_TERRAIN_ALT_INT}
_STARTS = ("mission_start", "auto_mode", "none")
_NOT_VEHICLES = {MAV_TYPE_GCS, MAV_TYPE_GIMBAL, MAV_TYPE_ADSB, MAV_TYPE_ONBOARD_CONTROLLER}
#: most messages read in one poll (the rest wait for the next)
MAX_READ = 500


@dataclass(frozen=True)
class MissionItem:
    """One MISSION_ITEM_INT (``x``/``y`` in degE7). ``waypoint``: the plan's waypoint index it
    flies to (None: the home placeholder or a DO command)."""

    seq: int
    frame: int
    command: int
    param1: float
    param2: float
    param3: float
    param4: float
    x: int
    y: int
    z: float
    waypoint: int | None = None

    def fields(self) -> dict[str, Any]:
        return dict(seq=self.seq, frame=self.frame, command=self.command, current=0, autocontinue=1,
                    param1=self.param1, param2=self.param2, param3=self.param3, param4=self.param4,
                    x=self.x, y=self.y, z=self.z)


def _deg_e7(v: float) -> int:
    return round(v * 1e7)


def mission_items(plan: Any, context: Any, *, frame: int = MAV_FRAME_GLOBAL_RELATIVE_ALT,
                  altitude_frame: int = MAV_FRAME_GLOBAL_TERRAIN_ALT, home_placeholder: bool = True,
                  acceptance_radius: float = 2.0, hold: float = 0.0, speed_item: bool = True,
                  ) -> list[MissionItem]:
    """The mission of ``plan``: its waypoints as MAV_CMD_NAV_WAYPOINT items (lat/lon from
    ``context.geodetic``), after the home placeholder and a speed change when asked.

    Height: a depth gives ``z = -depth`` in ``frame`` (ArduSub: altitude above home, the
    surface); otherwise an altitude gives ``z = altitude`` in ``altitude_frame`` when that is a
    terrain frame (10, 11: height above the seafloor), else ``z = 0``; neither gives ``z = 0``
    in ``frame`` (ArduSub reads alt 0 as "keep the present depth")."""
    if plan.depth is not None:
        fr, z = frame, -float(plan.depth)
    elif plan.altitude is not None and altitude_frame in _TERRAIN:
        fr, z = altitude_frame, float(plan.altitude)
    else:
        fr, z = (altitude_frame if plan.altitude is not None else frame), 0.0
    items: list[MissionItem] = []
    if home_placeholder:
        lat, lon = context.geodetic(0.0, 0.0)
        items.append(MissionItem(0, MAV_FRAME_GLOBAL, MAV_CMD_NAV_WAYPOINT, 0.0, 0.0, 0.0, 0.0,
                                 _deg_e7(lat), _deg_e7(lon), 0.0))
    if speed_item and plan.speed is not None:
        # p1 speed type 1 = ground speed, p2 m/s, p3 throttle -1 = no change
        items.append(MissionItem(len(items), fr, MAV_CMD_DO_CHANGE_SPEED, 1.0, float(plan.speed), -1.0,
                                 0.0, 0, 0, 0.0))
    for k, (x, y) in enumerate(plan.waypoints):
        lat, lon = context.geodetic(float(x), float(y))
        items.append(MissionItem(len(items), fr, MAV_CMD_NAV_WAYPOINT, float(hold), float(acceptance_radius),
                                 0.0, math.nan, _deg_e7(lat), _deg_e7(lon), z, waypoint=k))
    return items


def connect(connection: str, source_system: int, source_component: int, *, baud: int = 115200,
            mavlink2: bool = True) -> Any:
    """A pymavlink connection (``mavutil.mavlink_connection``) that speaks MAVLink 2 from its
    first packet when ``mavlink2`` (pymavlink otherwise starts with MAVLink 1 and switches only
    when it hears a MAVLink 2 packet), without changing pymavlink's process-wide dialect."""
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(connection, baud=baud, source_system=source_system,
                                      source_component=source_component, autoreconnect=False)
    if mavlink2 and conn.WIRE_PROTOCOL_VERSION != "2.0":
        from pymavlink.dialects.v20 import ardupilotmega as v20

        conn.mav = v20.MAVLink(conn, srcSystem=source_system, srcComponent=source_component)
        conn.mav.robust_parsing = True
        conn.WIRE_PROTOCOL_VERSION = "2.0"
        conn.first_byte = False  # no auto-switch (it would change the global dialect)
    return conn


def read(conn: Any, limit: int = MAX_READ) -> list[Any]:
    """Every message waiting on ``conn`` (at most ``limit``), never blocking. A receive error
    is logged and ends the read."""
    out = []
    for _ in range(limit):
        try:
            msg = conn.recv_match(blocking=False)
        except Exception as exc:  # garbage pymavlink cannot parse, a socket error
            log.warning("mavlink: receive failed: %s", exc)
            break
        if msg is None:
            break
        out.append(msg)
    return out


#: GPS_INPUT's ignore flags (MAVLink common GPS_INPUT_IGNORE_FLAGS)
GPS_INPUT_IGNORE_ALT = 1
GPS_INPUT_IGNORE_VEL_HORIZ = 8
GPS_INPUT_IGNORE_VEL_VERT = 16
GPS_INPUT_IGNORE_SPEED_ACCURACY = 32
GPS_INPUT_IGNORE_VERTICAL_ACCURACY = 128
#: the GPS epoch (1980-01-06) in Unix seconds, and GPS less UTC (s)
GPS_EPOCH = 315964800.0
GPS_LEAP_SECONDS = 18.0


class MavlinkAutonomy(Autonomy):
    """Uploads each plan as a MAVLink mission and follows its progress (module docstring)."""

    name = "mavlink"
    options = {
        "connection": text(REQUIRED, "pymavlink connection string: udpout:HOST:PORT, udpin:HOST:PORT, "
                                     "tcp:HOST:PORT or a serial device such as /dev/ttyACM0"),
        "baud": integer(115200, "serial baud rate", unit="baud", lo=1, hi=10_000_000),
        "source_system": integer(1, "our MAVLink system id (a companion computer shares the vehicle's)", lo=1, hi=255),
        "source_component": integer(191, "our component id (191 = MAV_COMP_ID_ONBOARD_COMPUTER)", lo=0, hi=255),
        "target_system": integer(None, "the autopilot's system id (default: from its first heartbeat, else 1)",
                                 lo=0, hi=255, none=True),
        "target_component": integer(None, "the autopilot's component id (default: from its first heartbeat, "
                                          "else 1)", lo=0, hi=255, none=True),
        "frame": integer(MAV_FRAME_GLOBAL_RELATIVE_ALT, "MAV_FRAME of depth items (3 = GLOBAL_RELATIVE_ALT, "
                                                        "z = -depth above home = the surface)",
                         choices=tuple(sorted(_FRAMES))),
        "altitude_frame": integer(MAV_FRAME_GLOBAL_TERRAIN_ALT, "MAV_FRAME of altitude items (10 = "
                                                                "GLOBAL_TERRAIN_ALT, z = altitude above the "
                                                                "seafloor; any other: z = 0, the present depth)",
                                  choices=tuple(sorted(_FRAMES))),
        "home_placeholder": flag(True, "send a placeholder at seq 0 (ArduPilot: seq 0 is home)"),
        "acceptance_radius": number(2.0, "param2 of each waypoint", unit="m", lo=0),
        "hold": number(0.0, "param1 of each waypoint: seconds to hold there", unit="s", lo=0),
        "speed_item": flag(True, "when the plan gives a speed, a MAV_CMD_DO_CHANGE_SPEED item before the waypoints"),
        "start": text("mission_start", "how to start an accepted mission: mission_start (MAV_CMD_MISSION_START), "
                                       "auto_mode (MAV_CMD_DO_SET_MODE to auto_mode) or none", choices=_STARTS),
        "auto_mode": integer(SUB_MODE_AUTO, "the autopilot's custom mode that flies missions (ArduSub AUTO = 3)",
                             lo=0, hi=2**32 - 1),
        "manual_modes": anything(list(SUB_MANUAL_MODES), "custom modes a pilot flies in: leaving AUTO for one of "
                                                         "them is a manual override (ArduSub STABILIZE 0, ACRO 1, "
                                                         "ALT_HOLD 2, POSHOLD 16, MANUAL 19)"),
        "timeout": number(1.5, "seconds without a request before MISSION_COUNT (or a command) is sent again",
                          unit="s", above=0),
        "item_timeout": number(0.25, "seconds without the next request before the last item is sent again",
                               unit="s", above=0),
        "retries": integer(5, "resends in a row without an answer before the upload (or the start) is given up "
                              "(REJECTED AUTONOMY_NO_ANSWER)", lo=0, hi=100),
        "heartbeat": number(1.0, "seconds between our HEARTBEATs (0 = none)", unit="s", lo=0),
        "mavlink2": flag(True, "speak MAVLink 2 from the first packet"),
        "position_fix": flag(True, "pass topside's position fixes (PositionFix) to the autopilot as GPS_INPUT "
                                   "(ArduSub: GPS_TYPE = 14, MAV); false: refuse them"),
        "gps_id": integer(0, "GPS_INPUT gps_id of the fixes (which GPS instance of the autopilot they feed)",
                          lo=0, hi=255),
        "silence": number(5.0, "seconds without the autopilot's HEARTBEAT while a survey flies before it is "
                               "aborted AUTONOMY_SILENT (0: not watched)", unit="s", lo=0),
        "clear": flag(True, "clear the autopilot's mission (MISSION_CLEAR_ALL) once a survey ended, so that "
                            "AUTO does not fly it again"),
    }

    @classmethod
    def check(cls, options: Mapping[str, Any]) -> Problems:
        p = Problems()
        c = options.get("connection")
        if not isinstance(c, str) or not c:
            p.said("connection", f"autonomy 'mavlink': connection must be a pymavlink connection string, got {c!r}")
        check_mavlink_connection(p, "autonomy 'mavlink'", options)
        modes = options.get("manual_modes", [])
        if not isinstance(modes, list | tuple) or any(
                isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < 2**32 for v in modes):
            p.said("manual_modes", f"autonomy 'mavlink': manual_modes must be a list of custom modes (integers), "
                                   f"got {modes!r}")
        return p

    @classmethod
    def paths(cls, options: Mapping[str, Any]) -> list[tuple[str, str, str]]:
        from ..options import serial_device

        return serial_device(options.get("connection"))

    def __init__(self, options: Mapping[str, Any], context: Any) -> None:
        super().__init__(options, context)
        cfg = self.config
        self.conn: Any = None
        self.target_system: int | None = cfg["target_system"]
        self.target_component: int | None = cfg["target_component"]
        self._heard_vehicle = False
        self._next_heartbeat = -math.inf
        self._out: list[SurveyReport] = []
        # the mission being uploaded or flown
        self.plan: Any = None
        self.items: list[MissionItem] = []
        #: idle, upload, starting (the start command sent, not acknowledged yet), flying, done
        self.phase = "idle"
        self._sent: int | None = None  # the last item sent (None: only MISSION_COUNT)
        self._deadline = math.inf
        self._tries = 0
        self._heading_for = -1  # the waypoint last reported in STARTED
        # the start command
        self._command: tuple[int, tuple[float, ...]] | None = None
        self._command_deadline = math.inf
        self._command_tries = 0
        self._vehicle_mode: int | None = None
        self._vehicle_type: int | None = None
        self._seen_auto = False
        #: when the target vehicle's HEARTBEAT was last heard (None: never)
        self.heard_at: float | None = None
        #: the clearing of an ended survey's mission: survey id, deadline of the answer, tries
        #: made (None: nothing to clear); ``_clear_later``: given up for now, sent again when the
        #: autopilot is heard again after a silence or leaves AUTO
        self._clear: tuple[int, float, int] | None = None
        self._clear_later: int | None = None
        #: the survey whose mission may still be on the autopilot (None: cleared, or none)
        self.on_autopilot: int | None = None
        #: counters for tests and status pages
        self.stats = {"bad": 0, "ignored": 0, "resent": 0, "uploads": 0, "items_sent": 0, "cleared": 0}

    # ------------------------------------------------------------------ connection
    def open(self) -> None:
        if self.conn is not None:
            return
        cfg = self.config
        try:
            self.conn = connect(cfg["connection"], cfg["source_system"], cfg["source_component"],
                                baud=cfg["baud"], mavlink2=cfg["mavlink2"])
        except Exception as exc:
            raise ConfigError(f"autonomy 'mavlink': cannot open {cfg['connection']!r}: {exc}") from exc

    def close(self) -> None:
        if self.conn is not None:
            try:
                self.conn.close()
            finally:
                self.conn = None

    def aid(self, fix: Any, now: float) -> bool:
        """A position fix as ``GPS_INPUT`` (latitude and longitude from ``node.origin``, horizontal
        accuracy ``sigma``, altitude ``-depth``; velocities ignored): ArduSub and PX4 take it as a
        GPS (ArduSub ``GPS_TYPE = 14``), the way a USBL feeds them."""
        if not self.config["position_fix"]:
            return False
        if self.conn is None:
            self.open()
        lat, lon = self.context.geodetic(float(fix.x), float(fix.y))
        gps = float(fix.time) - GPS_EPOCH + GPS_LEAP_SECONDS
        week, ms = int(gps // 604800), round((gps % 604800) * 1000)
        ignore = GPS_INPUT_IGNORE_VEL_HORIZ | GPS_INPUT_IGNORE_VEL_VERT | GPS_INPUT_IGNORE_SPEED_ACCURACY \
            | GPS_INPUT_IGNORE_VERTICAL_ACCURACY | (GPS_INPUT_IGNORE_ALT if fix.depth is None else 0)
        sigma = max(float(fix.sigma), 0.1)
        self._send("gps_input", time_usec=int(float(fix.time) * 1e6), gps_id=int(self.config["gps_id"]),
                   ignore_flags=ignore, time_week_ms=ms, time_week=week, fix_type=3, lat=_deg_e7(lat),
                   lon=_deg_e7(lon), alt=0.0 if fix.depth is None else -float(fix.depth), hdop=sigma, vdop=sigma,
                   vn=0.0, ve=0.0, vd=0.0, speed_accuracy=0.0, horiz_accuracy=sigma, vert_accuracy=0.0,
                   satellites_visible=0)
        return True

    @property
    def _targets(self) -> tuple[int, int]:
        ts = 1 if self.target_system is None else self.target_system
        tc = 1 if self.target_component is None else self.target_component
        return ts, tc

    def _send(self, name: str, **fields: Any) -> None:
        if self.conn is None:
            raise RuntimeError("autonomy 'mavlink' is not open")
        try:
            getattr(self.conn.mav, f"{name}_send")(**fields)
        except OSError as exc:  # a serial port gone, a network down: the retries deal with it
            log.warning("mavlink: sending %s failed: %s", name.upper(), exc)

    # ------------------------------------------------------------------ the autonomy
    def _adopt(self, plan: Any) -> dict[str, Any]:
        """Make ``plan`` the one flown: the connection open, its mission items built; returns the
        configuration."""
        if self.conn is None:
            self.open()
        cfg = self.config
        self.plan = plan
        self.items = mission_items(plan, self.context, frame=cfg["frame"], altitude_frame=cfg["altitude_frame"],
                                   home_placeholder=cfg["home_placeholder"],
                                   acceptance_radius=cfg["acceptance_radius"], hold=cfg["hold"],
                                   speed_item=cfg["speed_item"])
        return cfg

    def submit(self, plan: Any, now: float) -> None:
        cfg = self._adopt(plan)
        if plan.altitude is not None and plan.depth is None and cfg["altitude_frame"] not in _TERRAIN:
            log.warning("mavlink: survey %s asks for %g m altitude, but altitude_frame %s is not a terrain "
                        "frame: its waypoints keep the present depth (z = 0)", plan.survey_id, plan.altitude,
                        cfg["altitude_frame"])
        self.phase, self._sent, self._tries = "upload", None, 0
        self._heading_for, self._seen_auto = -1, False
        self._command = None
        self._command_deadline = math.inf
        self._clear, self._clear_later = None, None  # the new mission replaces whatever is there
        self.on_autopilot = int(plan.survey_id)
        self.stats["uploads"] += 1
        log.info("mavlink: uploading survey %s as %d mission items", plan.survey_id, len(self.items))
        self._send_count(now)

    def resume(self, plan: Any, now: float) -> bool:
        """The autopilot may still fly the uploaded mission: follow MISSION_CURRENT /
        MISSION_ITEM_REACHED again, upload nothing."""
        self._adopt(plan)
        self.phase, self._sent, self._tries, self._heading_for, self._seen_auto = "flying", None, 0, -1, False
        self._command, self._command_deadline = None, math.inf
        self._deadline = math.inf
        self.on_autopilot = int(plan.survey_id)
        log.info("mavlink: following survey %s again after a restart (nothing uploaded)", plan.survey_id)
        return True

    def end(self, survey_id: int, now: float) -> None:
        """The survey ended: stop following it (an upload or a start under way is abandoned) and,
        with ``clear``, clear the autopilot's mission (``MISSION_CLEAR_ALL``), answered by a
        ``MISSION_ACK``: sent again after ``timeout``, at most ``retries`` times, then again when
        the autopilot is heard after a silence, or leaves AUTO after refusing (ArduPilot does not
        clear the mission it flies)."""
        if self.conn is None:
            self.open()
        sid = int(survey_id)
        if self.plan is not None and int(self.plan.survey_id) == sid and self.phase != "done":
            self.phase = "done"
            self._deadline = math.inf
            self._command, self._command_deadline = None, math.inf
        if self.on_autopilot is None:
            self.on_autopilot = sid  # after a restart: whatever it holds may be that survey's
        if not self.config["clear"] or self.on_autopilot != sid:
            return  # nothing of it there, or a newer survey's mission replaced it
        self._clear_later = None
        self._send_clear(sid, 0, now)

    def _send_clear(self, sid: int, tries: int, now: float) -> None:
        ts, tc = self._targets
        self._send("mission_clear_all", target_system=ts, target_component=tc, mission_type=0)
        self._clear = (sid, now + float(self.config["timeout"]), tries)

    def _clear_answered(self, result: int, now: float) -> None:
        assert self._clear is not None
        sid = self._clear[0]
        self._clear = None
        if result == MAV_MISSION_ACCEPTED:
            self.on_autopilot = None
            self.stats["cleared"] += 1
            log.info("mavlink: survey %s ended: the autopilot's mission cleared", sid)
            return
        name = enum_name("MAV_MISSION_RESULT", result)
        log.warning("mavlink: survey %s ended, but the autopilot refused to clear its mission (%s)%s", sid, name,
                    ": cleared once it leaves AUTO" if self._vehicle_mode == int(self.config["auto_mode"]) else "")
        self._clear_later = sid

    def heard(self, now: float) -> float | None:
        """When the autopilot's HEARTBEAT was last heard (-inf: never, since this output opened)."""
        if self.conn is None:
            return None
        return -math.inf if self.heard_at is None else self.heard_at

    def silent_detail(self) -> str:
        ts, tc = self._targets
        return f"no HEARTBEAT from {ts}/{tc}"

    def poll(self, now: float) -> list[Any]:
        if self.conn is None:
            return self._take()
        every = float(self.config["heartbeat"])
        if every > 0 and now >= self._next_heartbeat:
            self._send("heartbeat", type=MAV_TYPE_ONBOARD_CONTROLLER, autopilot=MAV_AUTOPILOT_INVALID,
                       base_mode=0, custom_mode=0, system_status=4)  # MAV_STATE_ACTIVE
            self._next_heartbeat = now + every
        for msg in read(self.conn):
            try:
                self._handle(msg, now)
            except Exception as exc:  # a message with fields we did not expect
                self.stats["bad"] += 1
                log.warning("mavlink: ignored %s: %s", _type(msg), exc)
        self._timeouts(now)
        return self._take()

    def _take(self) -> list[SurveyReport]:
        out, self._out = self._out, []
        return out

    def _report(self, state: SurveyState, now: float, reason: SurveyReason = SurveyReason.NONE,
                index: int | None = None, value: float | None = None, detail: str | None = None) -> None:
        self._out.append(SurveyReport(self.plan.survey_id, state, float(now), reason, index, value,
                                      cut_detail(detail)))

    def _no_answer(self, now: float, what: str, tries: int) -> None:
        """Give the survey up: the autopilot did not answer ``what`` in ``tries`` tries."""
        heard = "" if self._heard_vehicle else ", no heartbeat heard"
        log.warning("mavlink: survey %s: no answer from the autopilot to %s after %d tries%s; given up",
                    self.plan.survey_id, what, tries, heard)
        self.phase = "idle"
        self._command, self._command_deadline = None, math.inf
        self._deadline = math.inf
        self._report(SurveyState.REJECTED, now, SurveyReason.AUTONOMY_NO_ANSWER, value=float(tries),
                     detail=f"{what} unanswered{heard}")

    # ------------------------------------------------------------------ upload
    def _send_count(self, now: float) -> None:
        ts, tc = self._targets
        self._send("mission_count", target_system=ts, target_component=tc, count=len(self.items), mission_type=0)
        self._deadline = now + float(self.config["timeout"])

    def _send_item(self, seq: int, now: float) -> None:
        ts, tc = self._targets
        self._send("mission_item_int", target_system=ts, target_component=tc, mission_type=0,
                   **self.items[seq].fields())
        self._sent = seq
        self.stats["items_sent"] += 1
        self._deadline = now + float(self.config["item_timeout"])

    def _timeouts(self, now: float) -> None:
        if self.phase == "upload" and now >= self._deadline:
            if self._tries >= int(self.config["retries"]):
                what = "MISSION_COUNT" if self._sent is None else f"item {self._sent} of {len(self.items)}"
                self._no_answer(now, what, self._tries + 1)
                return
            self._tries += 1
            self.stats["resent"] += 1
            if self._sent is None:
                self._send_count(now)
            else:
                self._send_item(self._sent, now)
        if self._clear is not None and now >= self._clear[1]:
            sid, _, tries = self._clear
            if tries >= int(self.config["retries"]):
                log.warning("mavlink: survey %s ended; the autopilot did not answer MISSION_CLEAR_ALL (%d tries): "
                            "its mission may still be on the autopilot (sent again when it is heard)", sid, tries + 1)
                self._clear, self._clear_later = None, sid
            else:
                self._send_clear(sid, tries + 1, now)
        if self._command is not None and now >= self._command_deadline:
            if self._command_tries >= int(self.config["retries"]):
                self._no_answer(now, _COMMANDS.get(self._command[0], f"command {self._command[0]}"),
                                self._command_tries + 1)
                return
            self._command_tries += 1
            self._send_command(now)

    def _mine(self, msg: Any) -> bool:
        """Whether a message addressed to a system/component is for us (0 = broadcast)."""
        ts = getattr(msg, "target_system", 0)
        tc = getattr(msg, "target_component", 0)
        return ts in (0, self.config["source_system"]) and tc in (0, self.config["source_component"])

    def _from_vehicle(self, msg: Any) -> bool:
        return self.target_system is None or msg.get_srcSystem() == self.target_system

    def _handle(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            self.stats["bad"] += 1
            log.debug("mavlink: bad data (%d bytes)", len(getattr(msg, "data", b"") or b""))
            return
        if kind == "HEARTBEAT":
            self._heartbeat(msg, now)
            return
        if kind in ("MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"):
            if not (self._mine(msg) and self._from_vehicle(msg)) or getattr(msg, "mission_type", 0) != 0:
                self.stats["ignored"] += 1
                return
            if kind == "MISSION_ACK":
                if self._clear is not None and self.phase != "upload":
                    self._clear_answered(int(msg.type), now)
                else:
                    self._ack(msg, now)
            else:
                self._request(msg, now)
        elif kind in ("MISSION_ITEM_REACHED", "MISSION_CURRENT"):
            if self._from_vehicle(msg):
                self._progress(kind, int(msg.seq), now)
        elif kind == "COMMAND_ACK":
            if self._mine(msg) and self._from_vehicle(msg):
                self._command_ack(msg, now)

    def _heartbeat(self, msg: Any, now: float) -> None:
        if msg.type in _NOT_VEHICLES or msg.autopilot == MAV_AUTOPILOT_INVALID:
            return
        self._vehicle_type = int(msg.type)
        if not self._heard_vehicle:
            self._heard_vehicle = True
            if self.target_system is None:
                self.target_system = msg.get_srcSystem()
            if self.target_component is None:
                self.target_component = msg.get_srcComponent()
            log.info("mavlink: vehicle %d/%d (type %d, autopilot %d)", msg.get_srcSystem(),
                     msg.get_srcComponent(), msg.type, msg.autopilot)
        if msg.get_srcSystem() != self.target_system:
            return
        silence = float(self.config["silence"]) or float(self.config["timeout"])
        back = self.heard_at is None or now - self.heard_at > silence
        self.heard_at = float(now)
        if back and self._clear_later is not None and self._clear is None:
            sid, self._clear_later = self._clear_later, None
            log.info("mavlink: the autopilot is heard again: clearing survey %s's mission", sid)
            self._send_clear(sid, 0, now)
        if msg.autopilot != MAV_AUTOPILOT_ARDUPILOTMEGA:
            return
        mode = int(msg.custom_mode)
        previous, self._vehicle_mode = self._vehicle_mode, mode
        if (previous == int(self.config["auto_mode"]) and mode != previous and self._clear_later is not None
                and self._clear is None):
            sid, self._clear_later = self._clear_later, None
            self._send_clear(sid, 0, now)  # it refused while flying it: now it does not
        if self.phase != "flying" or self.config["start"] == "none":
            return
        auto = int(self.config["auto_mode"])
        if mode == auto:
            self._seen_auto = True
        elif self._seen_auto and previous == auto:
            manual = mode in self.config["manual_modes"]
            words = f"left {mode_name(auto, self._vehicle_type)} for {mode_name(mode, self._vehicle_type)}"
            log.warning("mavlink: survey %s stopped: the vehicle %s (%s)", self.plan.survey_id, words,
                        "a pilot's mode: manual override" if manual else "not a pilot's mode")
            self.phase = "done"
            self._report(SurveyState.ABORTED, now,
                         SurveyReason.MANUAL_OVERRIDE if manual else SurveyReason.AUTONOMY_STOPPED,
                         value=float(mode), detail=words)

    def _request(self, msg: Any, now: float) -> None:
        seq = int(msg.seq)
        if self.phase != "upload":
            self.stats["ignored"] += 1
            log.debug("mavlink: request for item %d outside an upload", seq)
            return
        if not 0 <= seq < len(self.items):
            self.stats["bad"] += 1
            log.warning("mavlink: the autopilot asked for item %d (the mission has %d); ignored", seq, len(self.items))
            return
        expected = 0 if self._sent is None else self._sent + 1
        if seq > expected:
            log.warning("mavlink: the autopilot skipped to item %d (expected %d)", seq, expected)
        if seq >= expected:
            self._tries = 0  # progress
        self._send_item(seq, now)

    def _ack(self, msg: Any, now: float) -> None:
        result = int(msg.type)
        if self.phase != "upload":
            self.stats["ignored"] += 1
            return
        if result == MAV_MISSION_INVALID_SEQUENCE:  # ArduPilot: a NACK that does not end the upload
            log.info("mavlink: the autopilot NACKed an item out of sequence; the upload goes on")
            return
        if result != MAV_MISSION_ACCEPTED:
            name = enum_name("MAV_MISSION_RESULT", result)
            log.warning("mavlink: survey %s refused by the autopilot (MAV_MISSION_RESULT %d %s)",
                        self.plan.survey_id, result, name)
            self.phase = "idle"
            self._deadline = math.inf
            self._report(SurveyState.REJECTED, now, SurveyReason.AUTONOMY_REFUSED, value=float(result), detail=name)
            return
        if self._sent != len(self.items) - 1:
            # the vehicle accepts after the last item: this ack is an earlier upload's
            self.stats["ignored"] += 1
            log.info("mavlink: ignored an ack before the last item of survey %s was sent", self.plan.survey_id)
            return
        log.info("mavlink: survey %s uploaded", self.plan.survey_id)
        self._deadline = math.inf
        start = self.config["start"]
        if start == "mission_start":
            # p1 first item, p2 last item: 0, 0 = the whole mission (as pymavlink's set_mode_auto sends it)
            self._command = (MAV_CMD_MISSION_START, (0, 0, 0, 0, 0, 0, 0))
        elif start == "auto_mode":
            self._command = (MAV_CMD_DO_SET_MODE, (MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                                                   float(self.config["auto_mode"]), 0, 0, 0, 0, 0))
        else:
            self._flying(now)  # the vehicle starts it itself
            return
        self.phase = "starting"
        self._command_tries = 0
        self._send_command(now)

    def _flying(self, now: float) -> None:
        """The mission runs: STARTED, heading for waypoint 0."""
        self.phase = "flying"
        self._heading_for = 0
        self._report(SurveyState.STARTED, now, index=0)

    def _send_command(self, now: float) -> None:
        assert self._command is not None
        ts, tc = self._targets
        cmd, params = self._command
        self._send("command_long", target_system=ts, target_component=tc, command=cmd,
                   confirmation=self._command_tries, **{f"param{i + 1}": float(p) for i, p in enumerate(params)})
        self._command_deadline = now + float(self.config["timeout"])

    def _command_ack(self, msg: Any, now: float) -> None:
        if self._command is None or int(msg.command) != self._command[0]:
            return
        result = int(msg.result)
        if result == MAV_RESULT_IN_PROGRESS:
            self._command_deadline = now + float(self.config["timeout"])
            return
        self._command, self._command_deadline = None, math.inf
        if self.phase != "starting":
            return
        if result == MAV_RESULT_ACCEPTED:
            self._flying(now)
            return
        name = enum_name("MAV_RESULT", result)
        log.warning("mavlink: survey %s uploaded, but the autopilot refused to start it (MAV_RESULT %d %s)",
                    self.plan.survey_id, result, name)
        self.phase = "done"
        self._report(SurveyState.ABORTED, now, SurveyReason.AUTONOMY_STOPPED, value=float(result), detail=name)

    # ------------------------------------------------------------------ progress
    def _waypoint_of(self, seq: int) -> int | None:
        if 0 <= seq < len(self.items):
            return self.items[seq].waypoint
        return None

    def _progress(self, kind: str, seq: int, now: float) -> None:
        if (self.phase == "done" and kind == "MISSION_ITEM_REACHED" and self.plan is not None
                and self.on_autopilot == int(self.plan.survey_id) and self._waypoint_of(seq) is not None):
            # the autopilot flies the mission of a survey that ended: a late answer (the daemon's
            # lifecycle records it and ends the survey again)
            k = self._waypoint_of(seq)
            assert k is not None
            last = k == len(self.plan.waypoints) - 1
            self._report(SurveyState.COMPLETED if last else SurveyState.STARTED, now, index=None if last else k + 1)
            return
        if self.phase == "starting" and kind == "MISSION_ITEM_REACHED" and self._waypoint_of(seq) is not None:
            # it flies the new mission, though the start command's ack was lost
            self._command, self._command_deadline = None, math.inf
            self._flying(now)
        if self.phase != "flying":
            return
        if kind == "MISSION_CURRENT":
            # (before the start is acknowledged, MISSION_CURRENT may still name the old mission:
            # it is not read in the phase "starting")
            k = self._waypoint_of(seq)
            if k is not None and k > self._heading_for:
                self._heading_for = k
                self._report(SurveyState.STARTED, now, index=k)
            return
        k = self._waypoint_of(seq)
        if k is None:
            return
        n = len(self.plan.waypoints)
        if k == n - 1:
            log.info("mavlink: survey %s completed", self.plan.survey_id)
            self.phase = "done"
            self._report(SurveyState.COMPLETED, now)
        elif k + 1 > self._heading_for:
            self._heading_for = k + 1
            self._report(SurveyState.STARTED, now, index=k + 1)


def _type(msg: Any) -> str:
    try:
        return str(msg.get_type())
    except Exception:
        return type(msg).__name__
