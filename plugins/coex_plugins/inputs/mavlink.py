"""The ``mavlink`` input: the vehicle's state from a MAVLink autopilot (ArduSub, PX4 ...), read
with a pymavlink connection (``udpin:0.0.0.0:14560``, ``tcp:host:port``, a serial device).

============================  ==================================================================
message                       item
============================  ==================================================================
GLOBAL_POSITION_INT           Nav lat, lon (degE7; 0, 0 = no fix), depth = -relative_alt / 1000
                              (0 at or above the surface), heading = hdg / 100 (65535 = unknown),
                              speed = |vx, vy| / 100
LOCAL_POSITION_NED            Nav x = y (east), y = x (north), depth = z, speed = |vx, vy|
ATTITUDE                      Nav heading = yaw (radians) in compass degrees
VFR_HUD                       Nav heading, speed = groundspeed
SCALED_PRESSURE2 (option)     Nav depth = (press_abs - surface_pressure) * 100 / (water_density
                              * g); temperature / 100 -> Samples ``temperature_channel``
DISTANCE_SENSOR (down)        Nav altitude = current_distance / 100 when the orientation is
                              ROTATION_PITCH_270 (25) and the reading within min..max
RANGEFINDER                   Nav altitude = distance
CAMERA_IMAGE_CAPTURED         Image from file_url (a local path or file:// URL; relative names
                              under ``image_dir``), read once the file has settled; time =
                              time_utc; x, y from lat, lon through the origin
============================  ==================================================================

Nav and Samples items are timed when they arrive (autopilot boot times are not epoch times).
The parser is pymavlink's, MAVLink 2 (which reads MAVLink 1 too), installed on the connection so
that nothing process-wide (``MAVLINK20``, the mavutil dialect) is changed after the import of
``mavutil``. A heartbeat is sent every ``heartbeat`` seconds (routers forward to an endpoint
only once it has been heard). ``poll`` never waits; a connection that fails is retried.
"""

from __future__ import annotations

import importlib
import logging
import math
import os
import time
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar
from urllib.parse import unquote, urlsplit

import numpy as np

from coex import Image, Input, InputContext, Item, Nav, Samples
from coex.options import REQUIRED, Option, flag, integer, number, text

from ..options import (
    LogOnce,
    Problems,
    check_mavlink_connection,
    need,
    serial_device,
)
from ._files import read_image

__all__ = ["MavlinkInput", "pressure_depth"]

log = logging.getLogger(__name__)

G = 9.80665
ROTATION_PITCH_270 = 25  # MAV_SENSOR_ORIENTATION: looking down
PRESSURE_MESSAGES = ("SCALED_PRESSURE", "SCALED_PRESSURE2", "SCALED_PRESSURE3", "")
RETRY = 5.0  # seconds between attempts to open a connection that failed


def pressure_depth(press_abs_hpa: float, surface_hpa: float, density: float) -> float:
    """Depth in metres below the surface from an absolute pressure (hPa)."""
    return (press_abs_hpa - surface_hpa) * 100.0 / (density * G)


@dataclass
class _Capture:
    path: Path
    time: float
    x: float | None
    y: float | None
    deadline: float
    stat: tuple[int, int] | None = None
    since: float = 0.0


class MavlinkInput(Input):
    """A MAVLink connection (see the module docstring)."""

    name = "mavlink"
    feeds = ("status", "imagery", "timeseries")
    options: ClassVar[Mapping[str, Option]] = {
        "connection": text(REQUIRED, "pymavlink connection: udpin:0.0.0.0:14560, udpout:host:port, "
                                     "tcp:host:port, /dev/ttyACM0 ..."),
        "baud": integer(115200, "baud rate of a serial connection", unit="baud", lo=1, hi=10_000_000),
        "source_system": integer(255, "our MAVLink system id (heartbeats)", lo=1, hi=255),
        "source_component": integer(191, "our MAVLink component id (191: onboard computer)", lo=0, hi=255),
        "system": integer(0, "only read messages from this system id (0: any)", lo=0, hi=255),
        "dialect": text("ardupilotmega", "pymavlink MAVLink 2 dialect that parses the messages"),
        "heartbeat": number(1.0, "seconds between our heartbeats (0: send none)", unit="s", lo=0),
        "pressure_message": text("SCALED_PRESSURE2", "message of the depth sensor: SCALED_PRESSURE, "
                                                     "SCALED_PRESSURE2, SCALED_PRESSURE3, or '' for none",
                                 choices=PRESSURE_MESSAGES),
        "surface_pressure": number(1013.25, "absolute pressure at the surface", unit="hPa", above=0),
        "water_density": number(1025.0, "water density for depth from pressure", unit="kg/m^3", above=0),
        "temperature_channel": text("temperature", "time-series channel of the pressure sensor's "
                                                   "temperature ('' for none)"),
        "images": flag(True, "turn CAMERA_IMAGE_CAPTURED into images"),
        "image_dir": text("", "directory of relative image file names (default: the configuration's)"),
        "settle": number(1.0, "seconds a captured image file must stay unchanged before it is read", unit="s", lo=0),
        "image_timeout": number(60.0, "seconds to wait for a captured image file to appear", unit="s", lo=0),
    }

    @classmethod
    def check(cls, options: Mapping[str, Any]) -> Problems:
        p, who = Problems(), f"input {cls.name!r}"
        p.option_str(who, options, "connection", nonempty=True)
        check_mavlink_connection(p, who, options)
        p.option_str(who, options, "dialect", nonempty=True)
        dialect = options.get("dialect")
        if isinstance(dialect, str) and dialect and not dialect.isidentifier():
            p.said("dialect", f"{who}: option 'dialect' must be a pymavlink dialect name, not {dialect!r}")
        return p

    @classmethod
    def paths(cls, options: Mapping[str, Any]) -> list[tuple[str, str, str]]:
        return serial_device(options.get("connection"))

    def __init__(self, options: Mapping[str, Any], context: InputContext) -> None:
        super().__init__(options, context)
        image_dir = Path(self.config["image_dir"] or context.base_dir).expanduser()
        self.image_dir = image_dir if image_dir.is_absolute() else Path(context.base_dir) / image_dir
        self._conn: Any = None
        self._retry_at = -math.inf
        self._last_heartbeat = -math.inf
        self._captures: list[_Capture] = []
        self._recent_captures: deque[tuple[str, int]] = deque(maxlen=256)
        self._problem = LogOnce(log)
        #: messages read and used, bytes pymavlink could not parse (``bad``), and, as every input,
        #: ``skipped``: items not used (garbage, a message whose values make no sense, a capture
        #: that cannot be read)
        self.counts.update(messages=0, used=0, bad=0)

    # ----------------------------------------------------------------- connection
    def open(self) -> None:
        self._connect(-math.inf)

    def _connect(self, now: float) -> bool:
        if self._conn is not None:
            return True
        if now < self._retry_at:
            return False
        mavutil = need("pymavlink.mavutil", "mavlink")
        try:
            dialect = importlib.import_module(f"pymavlink.dialects.v20.{self.config['dialect']}")
        except ImportError as exc:
            from coex import ConfigError

            raise ConfigError(f"input 'mavlink': option 'dialect': no pymavlink dialect "
                              f"{self.config['dialect']!r} ({exc})") from exc
        try:
            conn = mavutil.mavlink_connection(
                self.config["connection"], baud=self.config["baud"],
                source_system=self.config["source_system"],
                source_component=self.config["source_component"],
                autoreconnect=False, retries=0)  # one attempt, never sleeping; poll retries
        except Exception as exc:  # a missing device, a port in use: try again later
            self._retry_at = now + RETRY
            self._problem(f"open:{type(exc).__name__}", "input mavlink: cannot open %r (%s: %s); "
                          "retrying every %.0f s", self.config["connection"], type(exc).__name__, exc, RETRY)
            return False
        # our own MAVLink 2 parser: nothing process-wide changes when a MAVLink 2 packet arrives
        conn.mav = dialect.MAVLink(conn, srcSystem=self.config["source_system"],
                                   srcComponent=self.config["source_component"])
        conn.mav.robust_parsing = True
        conn.robust_parsing = True
        conn.first_byte = False
        conn.WIRE_PROTOCOL_VERSION = "2.0"
        self._conn = conn
        self._retry_at = -math.inf
        log.info("input mavlink: %s open", self.config["connection"])
        return True

    def close(self) -> None:
        if self._conn is not None:
            try:
                self._conn.close()
            except Exception:  # closing must not fail
                pass
            self._conn = None

    def _heartbeat(self, now: float) -> None:
        period = float(self.config["heartbeat"])
        if period <= 0 or now - self._last_heartbeat < period:
            return
        conn = self._conn
        if getattr(conn, "udp_server", False) and not (getattr(conn, "clients", None)
                                                      or getattr(conn, "last_address", None)):
            return  # udpin: nobody heard yet, so nobody to send to
        self._last_heartbeat = now
        try:
            # MAV_TYPE_ONBOARD_CONTROLLER (18), MAV_AUTOPILOT_INVALID (8), MAV_STATE_ACTIVE (4)
            self._conn.mav.heartbeat_send(18, 8, 0, 0, 4)
        except Exception as exc:  # udpin before anything was heard: no peer yet
            self._problem(f"heartbeat:{type(exc).__name__}", "input mavlink: heartbeat not sent (%s)",
                          exc, level=logging.DEBUG)

    # ----------------------------------------------------------------- the loop
    def poll(self, now: float, limit: int = 10000) -> list[Item]:
        """Every message received since the last call (at most ``limit``), and captured images
        whose files have settled."""
        if not self._connect(now):
            return []
        items: list[Item] = []
        temps: list[tuple[float, float]] = []
        for _ in range(limit):
            try:
                msg = self._conn.recv_match(blocking=False)
            except Exception as exc:  # a closed port, a parser surprise: reopen later
                self._problem(f"recv:{type(exc).__name__}", "input mavlink: receive failed (%s: %s)",
                              type(exc).__name__, exc)
                self.close()
                self._retry_at = now + RETRY
                break
            if msg is None:
                break
            kind = msg.get_type()
            if kind == "BAD_DATA":
                self.counts["bad"] += 1
                self.skip()
                continue
            self.counts["messages"] += 1
            system = int(self.config["system"])
            if system and msg.get_srcSystem() != system:
                continue
            try:
                item = self._convert(kind, msg, now, temps)
            except Exception as exc:  # a value pymavlink let through that makes no sense
                self._problem(f"{kind}:{type(exc).__name__}", "input mavlink: a %s skipped (%s: %s)",
                              kind, type(exc).__name__, exc)
                self.skip()
                continue
            if item is not None:
                self.counts["used"] += 1
                items.append(item)
        if self._conn is not None:
            self._heartbeat(now)
        if temps:
            arr = np.asarray(temps, np.float64)
            items.append(Samples(self.config["temperature_channel"], arr[:, 0].copy(), arr[:, 1].copy()))
        items += self._settled_captures(now)
        return items

    def next_event(self, now: float) -> float | None:
        if self._captures:
            return now + min(0.5, float(self.config["settle"]) or 0.5)
        return None

    # ----------------------------------------------------------------- messages
    def _convert(self, kind: str, msg: Any, now: float, temps: list[tuple[float, float]]) -> Item | None:
        if kind == "GLOBAL_POSITION_INT":
            lat, lon = msg.lat * 1e-7, msg.lon * 1e-7
            fix = not (msg.lat == 0 and msg.lon == 0)
            return Nav(now, lat=lat if fix else None, lon=lon if fix else None,
                       depth=max(0.0, -msg.relative_alt / 1000.0),
                       heading=None if msg.hdg == 65535 else msg.hdg / 100.0,
                       speed=math.hypot(msg.vx, msg.vy) / 100.0)
        if kind == "LOCAL_POSITION_NED":
            return Nav(now, x=float(msg.y), y=float(msg.x), depth=float(msg.z),
                       speed=math.hypot(msg.vx, msg.vy))
        if kind == "ATTITUDE":
            return Nav(now, heading=math.degrees(msg.yaw) % 360.0)
        if kind == "VFR_HUD":
            return Nav(now, heading=float(msg.heading) % 360.0, speed=float(msg.groundspeed))
        if kind == self.config["pressure_message"]:
            if self.config["temperature_channel"]:
                temps.append((now, msg.temperature / 100.0))
            depth = pressure_depth(float(msg.press_abs), float(self.config["surface_pressure"]),
                                   float(self.config["water_density"]))
            return Nav(now, depth=depth) if math.isfinite(depth) else None
        if kind == "DISTANCE_SENSOR":
            if msg.orientation != ROTATION_PITCH_270:
                return None
            if not msg.min_distance <= msg.current_distance <= msg.max_distance:
                return None  # out of range: no bottom lock
            return Nav(now, altitude=msg.current_distance / 100.0)
        if kind == "RANGEFINDER":
            d = float(msg.distance)
            return Nav(now, altitude=d) if math.isfinite(d) and d > 0 else None
        if kind == "CAMERA_IMAGE_CAPTURED" and self.config["images"]:
            self._capture(msg, now)
        return None

    def _capture(self, msg: Any, now: float) -> None:
        url = str(msg.file_url).rstrip("\0").strip()
        if msg.capture_result == 0:
            return  # the camera says it failed
        key = (url, int(msg.image_index))
        if key in self._recent_captures:
            return  # repeated (cameras re-send on request)
        self._recent_captures.append(key)
        if not url:
            self._problem("capture:nourl", "input mavlink: CAMERA_IMAGE_CAPTURED without file_url skipped")
            self.skip()
            return
        parts = urlsplit(url)
        if parts.scheme == "file":
            path = Path(unquote(parts.path))
        elif parts.scheme and len(parts.scheme) > 1:  # http:// ...; a one-letter scheme is a drive
            self._problem(f"capture:{parts.scheme}", "input mavlink: image %s is not a local file, "
                          "skipped", url)
            self.skip()
            return
        else:
            path = Path(url)
        if not path.is_absolute():
            path = self.image_dir / path
        t = msg.time_utc / 1e6 if msg.time_utc > 0 else now
        x = y = None
        if msg.lat != 0 or msg.lon != 0:
            x, y = self.context.local(msg.lat * 1e-7, msg.lon * 1e-7)
        self._captures.append(_Capture(path, t, x, y, now + float(self.config["image_timeout"])))

    def _settled_captures(self, now: float) -> list[Item]:
        out: list[Item] = []
        keep: list[_Capture] = []
        wall = time.time()
        settle = float(self.config["settle"])
        for cap in self._captures:
            try:
                st = os.stat(cap.path)
            except OSError:
                if now >= cap.deadline:
                    self._problem(f"missing:{cap.path}", "input mavlink: captured image %s never "
                                  "appeared, skipped", cap.path)
                    self.skip()
                else:
                    keep.append(cap)
                continue
            stat = (st.st_size, st.st_mtime_ns)
            if stat != cap.stat:
                cap.stat, cap.since = stat, now
            if not (now - cap.since >= settle or wall - st.st_mtime >= settle):
                keep.append(cap)
                continue
            try:
                pixels = read_image(cap.path)
            except Exception as exc:  # a damaged or unknown file
                self._problem(f"read:{cap.path}", "input mavlink: cannot read %s, skipped (%s: %s)",
                              cap.path, type(exc).__name__, exc)
                self.skip()
                continue
            out.append(Image(cap.time, pixels=pixels, path=str(cap.path), x=cap.x, y=cap.y))
        self._captures = keep
        return out
