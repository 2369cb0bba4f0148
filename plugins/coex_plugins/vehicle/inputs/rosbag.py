"""The ``rosbag`` input: replays a ROS 1 ``.bag`` or a ROS 2 bag (directory with
``metadata.yaml``, or a ``.db3`` / ``.mcap`` file) with its original timing, read with
``rosbags`` (no ROS install).

Topics (at least one):

* ``points_topic``: ``sensor_msgs/PointCloud2`` -> :class:`~.base.Points` (x east, y north,
  z up; rows with a NaN are dropped);
* ``image_topic``: ``sensor_msgs/Image`` (mono8, mono16, rgb8, bgr8, rgba8, bgra8, 8UC1,
  16UC1, 8UC3 as bgr) or ``sensor_msgs/CompressedImage`` (JPEG, PNG) -> :class:`~.base.Image`;
* ``nav_topic``: ``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped`` or
  ``PoseWithCovarianceStamped`` -> :class:`~.base.Nav` x, y, depth (-z), heading (from the
  yaw), speed (Odometry's twist); ``sensor_msgs/NavSatFix`` -> Nav lat, lon.

Timing: the first replayed message is due at the daemon's time when the input opens (the
context's clock, else the first poll), each later one ``(its bag time - the first's) / speed``
after it. An item's time is its message's header stamp (the bag's record time when the stamp is
zero); with ``start = "now"`` it is shifted (and scaled by ``speed``) onto the daemon's clock
like the message's due time, with ``start = "original"`` it is kept as recorded.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from coex_core.errors import ConfigError

from ..options import (
    LogOnce,
    compass_from_enu_yaw,
    finite,
    need,
    want_choice,
    want_number,
    want_str,
    yaw_of_quaternion,
)
from ._files import as_pixels, decode_image
from .base import Image, Input, InputContext, Item, Nav, Points

__all__ = ["IMAGE_TYPES", "NAV_TYPES", "POINTS_TYPES", "RosbagInput", "ros_image_pixels"]

log = logging.getLogger(__name__)

POINTS_TYPES = ("sensor_msgs/msg/PointCloud2",)
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
NAV_TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped",
             "geometry_msgs/msg/PoseWithCovarianceStamped", "sensor_msgs/msg/NavSatFix")

#: sensor_msgs/Image encodings: channels, bytes per channel, channel order reversed (BGR)
_ENCODINGS = {
    "mono8": (1, 1, False), "8uc1": (1, 1, False), "mono16": (1, 2, False), "16uc1": (1, 2, False),
    "rgb8": (3, 1, False), "bgr8": (3, 1, True), "8uc3": (3, 1, True),
    "rgba8": (4, 1, False), "bgra8": (4, 1, True), "8uc4": (4, 1, True),
    "rgb16": (3, 2, False), "bgr16": (3, 2, True), "16uc3": (3, 2, True),
}


def ros_image_pixels(msg: Any) -> np.ndarray:
    """The pixels of a ``sensor_msgs/Image`` (rows padded to ``step`` are cut); ValueError for an
    encoding it does not know or data shorter than height x step."""
    enc = str(msg.encoding).lower()
    if enc not in _ENCODINGS:
        raise ValueError(f"image encoding {msg.encoding!r} not supported "
                         f"(known: {', '.join(sorted(_ENCODINGS))})")
    channels, size, reverse = _ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row = w * channels * size
    data = np.asarray(msg.data, dtype=np.uint8).ravel()
    if h <= 0 or w <= 0 or step < row or data.size < h * step:
        raise ValueError(f"image {w} x {h} {enc} with step {step} and {data.size} bytes of data")
    rows = np.ascontiguousarray(data[: h * step].reshape(h, step)[:, :row])
    dtype = np.dtype(np.uint8) if size == 1 else np.dtype(">u2" if msg.is_bigendian else "<u2")
    a = rows.view(dtype).reshape((h, w, channels) if channels > 1 else (h, w))
    if reverse:
        a = a[..., ::-1]
    if channels == 4:
        a = a[..., 1:] if reverse else a[..., :3]  # after reversing BGRA is ARGB
    return as_pixels(a.astype(np.uint16) if size == 2 else a)


def _stamp(msg: Any) -> float | None:
    header = getattr(msg, "header", None)
    stamp = getattr(header, "stamp", None)
    if stamp is None:
        return None
    t = float(stamp.sec) + float(stamp.nanosec) * 1e-9
    return t if t > 0 else None


class RosbagInput(Input):
    """A bag replayed with its timing (see the module docstring)."""

    name = "rosbag"
    feeds = ("bathymetry", "imagery", "status")
    options: ClassVar[Mapping[str, tuple[Any, str]]] = {
        "path": (..., "a ROS 1 .bag, or a ROS 2 bag directory (metadata.yaml), .db3 or .mcap"),
        "points_topic": ("", "sensor_msgs/PointCloud2 topic: soundings for the bathymetry map"),
        "image_topic": ("", "sensor_msgs/Image or CompressedImage topic: camera images"),
        "nav_topic": ("", "nav_msgs/Odometry, geometry_msgs/PoseStamped (WithCovariance) or "
                          "sensor_msgs/NavSatFix topic: the vehicle's position"),
        "start": ("now", "'now': item times shifted so the bag starts when the input opens; "
                         "'original': item times as recorded"),
        "speed": (1.0, "replay speed (2.0 = twice as fast)"),
        "nav_frame": ("enu", "frame of nav_topic poses: 'enu' (ROS REP 103: x east, y north, "
                             "z up, yaw from east) or 'ned' (x north, y east, z down, yaw from north)"),
    }

    @classmethod
    def check(cls, options: Mapping[str, Any]) -> list[str]:
        problems = want_str(cls.name, options, "path", nonempty=True)
        for key in ("points_topic", "image_topic", "nav_topic"):
            problems += want_str(cls.name, options, key)
        if not any(options.get(k) for k in ("points_topic", "image_topic", "nav_topic")):
            problems.append(f"input {cls.name!r} needs at least one of the options 'points_topic', "
                            "'image_topic', 'nav_topic'")
        problems += want_choice(cls.name, options, "start", ("now", "original"))
        problems += want_number(cls.name, options, "speed", positive=True)
        problems += want_choice(cls.name, options, "nav_frame", ("enu", "ned"))
        return problems

    @classmethod
    def paths(cls, options: Mapping[str, Any]) -> list[tuple[str, str, str]]:
        return [("path", str(options["path"]), "file or folder")] if isinstance(options.get("path"), str) else []

    def __init__(self, options: Mapping[str, Any], context: InputContext) -> None:
        super().__init__(options, context)
        path = Path(self.config["path"]).expanduser()
        self.path = path if path.is_absolute() else Path(context.base_dir) / path
        self.speed = float(self.config["speed"])
        self._reader: Any = None
        self._messages: Iterator[tuple[Any, int, bytes]] | None = None
        self._next: tuple[Any, int, bytes] | None = None
        self._roles: dict[str, str] = {}  # topic -> "points" | "image" | "nav"
        self._t0: int | None = None  # bag time (ns) of the first replayed message
        self._anchor: float | None = None  # daemon time the first message is due
        self._opened = False
        self._problem = LogOnce(log)
        #: messages replayed per role (and, as every input, ``skipped``: undecodable ones)
        self.counts.update(points=0, image=0, nav=0)

    # ----------------------------------------------------------------- opening
    def open(self) -> None:
        if self._opened:
            return
        highlevel = need("rosbags.highlevel", "bathymetry")
        typesys = need("rosbags.typesys", "bathymetry")
        if not self.path.exists():
            raise ConfigError(f"input 'rosbag': option 'path': {self.path} does not exist")
        try:
            reader = highlevel.AnyReader(
                [self.path], default_typestore=typesys.get_typestore(typesys.Stores.ROS2_HUMBLE))
            reader.open()
        except Exception as exc:
            raise ConfigError(f"input 'rosbag': option 'path': cannot read {self.path} as a bag "
                              f"({type(exc).__name__}: {exc})") from exc
        try:
            conns = self._select(reader)
            self._messages = iter(reader.messages(connections=conns))
            self._reader = reader
            self._opened = True
            self._advance()
        except Exception:
            reader.close()
            raise
        if self._next is not None:
            self._t0 = self._next[1]
        clock = self.context.clock
        if clock is not None and callable(getattr(clock, "time", None)):
            self._anchor = float(clock.time())

    def _select(self, reader: Any) -> list[Any]:
        topics = sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections})
        chosen: list[Any] = []
        for role, key, types in (("points", "points_topic", POINTS_TYPES),
                                 ("image", "image_topic", IMAGE_TYPES),
                                 ("nav", "nav_topic", NAV_TYPES)):
            topic = self.config[key]
            if not topic:
                continue
            conns = [c for c in reader.connections if c.topic == topic]
            if not conns:
                raise ConfigError(f"input 'rosbag': option {key!r}: no topic {topic!r} in "
                                  f"{self.path} (topics: {', '.join(topics) or 'none'})")
            for c in conns:
                if c.msgtype not in types:
                    raise ConfigError(f"input 'rosbag': option {key!r}: topic {topic!r} holds "
                                      f"{c.msgtype}, not {' or '.join(types)}")
                self._roles[c.topic] = role
                chosen.append(c)
        return chosen

    def _advance(self) -> None:
        self._next = None
        if self._messages is None:
            return
        try:
            self._next = next(self._messages)
        except StopIteration:
            log.info("input rosbag: %s replayed (%s)", self.path, self.counts)
            self._messages = None
        except Exception as exc:  # a damaged chunk: stop this replay, keep the daemon alive
            log.warning("input rosbag: %s unreadable from here on, replay stopped (%s: %s)",
                        self.path, type(exc).__name__, exc)
            self._messages = None

    # ----------------------------------------------------------------- timing
    def _due(self, bag_ns: int) -> float:
        assert self._anchor is not None and self._t0 is not None
        return self._anchor + (bag_ns - self._t0) * 1e-9 / self.speed

    def _item_time(self, t: float) -> float:
        if self.config["start"] == "original":
            return t
        assert self._anchor is not None and self._t0 is not None
        return self._anchor + (t - self._t0 * 1e-9) / self.speed

    def next_event(self, now: float) -> float | None:
        if self._next is None:
            return None
        if self._anchor is None:
            self._anchor = now
        return self._due(self._next[1])

    def poll(self, now: float, limit: int = 1000) -> list[Item]:
        """Messages due by ``now`` (at most ``limit``: the rest come at the next call)."""
        if not self._opened:
            self.open()
        if self._anchor is None:
            self._anchor = now
        items: list[Item] = []
        while self._next is not None and len(items) < limit and self._due(self._next[1]) <= now:
            conn, bag_ns, raw = self._next
            self._advance()
            role = self._roles.get(conn.topic, "")
            try:
                msg = self._reader.deserialize(raw, conn.msgtype)
                t = self._item_time(_stamp(msg) or bag_ns * 1e-9)
                item = self._convert(role, conn.msgtype, msg, t)
            except Exception as exc:  # one bad message is skipped, the replay goes on
                self.skip()
                self._problem(f"{conn.topic}:{type(exc).__name__}",
                              "input rosbag: a %s message on %s skipped (%s: %s)",
                              conn.msgtype, conn.topic, type(exc).__name__, exc)
                continue
            if item is not None:
                self.counts[role] += 1
                items.append(item)
        return items

    # ----------------------------------------------------------------- messages
    def _convert(self, role: str, msgtype: str, msg: Any, t: float) -> Item | None:
        if role == "points":
            from coex_plugins.bathymetry.points import pointcloud2_xyz

            xyz = pointcloud2_xyz(msg)
            xyz = xyz[np.isfinite(xyz).all(axis=1)]
            return Points(t, xyz) if len(xyz) else None
        if role == "image":
            if msgtype.endswith("CompressedImage"):
                pixels = decode_image(bytes(np.asarray(msg.data, np.uint8)))
            else:
                pixels = ros_image_pixels(msg)
            return Image(t, pixels=pixels)
        return self._nav(msgtype, msg, t)

    def _nav(self, msgtype: str, msg: Any, t: float) -> Nav | None:
        if msgtype == "sensor_msgs/msg/NavSatFix":
            lat, lon = finite(msg.latitude), finite(msg.longitude)
            if int(msg.status.status) < 0 or lat is None or lon is None:
                return None  # no fix
            return Nav(t, lat=lat, lon=lon)
        speed = None
        if msgtype == "nav_msgs/msg/Odometry":
            pose = msg.pose.pose
            lin = msg.twist.twist.linear
            speed = finite(math.hypot(lin.x, lin.y))
        elif msgtype == "geometry_msgs/msg/PoseWithCovarianceStamped":
            pose = msg.pose.pose
        else:
            pose = msg.pose
        p, q = pose.position, pose.orientation
        yaw = yaw_of_quaternion(q.x, q.y, q.z, q.w)
        if self.config["nav_frame"] == "ned":
            x, y, depth = finite(p.y), finite(p.x), finite(p.z)
            heading = None if yaw is None else math.degrees(yaw) % 360.0
        else:
            x, y, depth = finite(p.x), finite(p.y), finite(-p.z)
            heading = None if yaw is None else compass_from_enu_yaw(yaw)
        return Nav(t, x=x, y=y, depth=depth, heading=heading, speed=speed)

    def close(self) -> None:
        if self._reader is not None:
            try:
                self._reader.close()
            finally:
                self._reader = None
                self._messages = None
                self._next = None
