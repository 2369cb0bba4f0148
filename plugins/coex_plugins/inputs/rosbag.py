"""The ``rosbag`` input: replays a ROS 1 ``.bag`` or a ROS 2 bag (directory with
``metadata.yaml``, or a ``.db3`` / ``.mcap`` file) with its original timing, read with
``rosbags`` (no ROS install).

Topics (at least one):

* ``points_topic``: ``sensor_msgs/PointCloud2`` -> :class:`~coex.Points` (x east, y north,
  z up; rows with a NaN are dropped);
* ``image_topic``: ``sensor_msgs/Image`` (mono8, mono16, rgb8, bgr8, rgba8, bgra8, 8UC1,
  16UC1, 8UC3 as bgr) or ``sensor_msgs/CompressedImage`` (JPEG, PNG) -> :class:`~coex.Image`;
* ``nav_topic``: ``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped`` or
  ``PoseWithCovarianceStamped`` -> :class:`~coex.Nav` x, y, depth (-z), heading (from the
  yaw), speed (Odometry's twist); ``sensor_msgs/NavSatFix`` -> Nav lat, lon.

What a message means (frames mapped to the local grid: ``frames``, ``nav_frame``; image
encodings; navigation) is :mod:`.rosmsg`, shared with the live ``ros`` input.

Timing: the first replayed message is due at the daemon's time when the input opens (the
context's clock, else the first poll), each later one ``(its bag time - the first's) / speed``
after it. An item's time is its message's header stamp (the bag's record time when the stamp is
zero); with ``start = "now"`` it is shifted (and scaled by ``speed``) onto the daemon's clock
like the message's due time, with ``start = "original"`` it is kept as recorded.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any, ClassVar

from coex import ConfigError, Input, InputContext, Item
from coex.options import Option, number, text

from ..options import LogOnce, Problems, need
from .rosmsg import (
    IMAGE_TYPES,
    NAV_TYPES,
    POINTS_TYPES,
    ROLES,
    FrameMap,
    check_frames,
    item_of,
    stamp_of,
)
from .rosmsg import ros_image_pixels as ros_image_pixels  # where it was before rosmsg

__all__ = ["IMAGE_TYPES", "NAV_TYPES", "POINTS_TYPES", "RosbagInput", "ros_image_pixels"]

log = logging.getLogger(__name__)

class RosbagInput(Input):
    """A bag replayed with its timing (see the module docstring)."""

    name = "rosbag"
    feeds = ("bathymetry", "imagery", "status")
    options: ClassVar[Mapping[str, tuple[Any, str] | Option]] = {
        "path": (..., "a ROS 1 .bag, or a ROS 2 bag directory (metadata.yaml), .db3 or .mcap"),
        "points_topic": ("", "sensor_msgs/PointCloud2 topic: soundings for the bathymetry map"),
        "image_topic": ("", "sensor_msgs/Image or CompressedImage topic: camera images"),
        "nav_topic": ("", "nav_msgs/Odometry, geometry_msgs/PoseStamped (WithCovariance) or "
                          "sensor_msgs/NavSatFix topic: the vehicle's position"),
        "start": text("now", "'now': item times shifted so the bag starts when the input opens; "
                             "'original': item times as recorded", choices=("now", "original")),
        "speed": number(1.0, "replay speed (2.0 = twice as fast)", above=0),
        "nav_frame": ("enu", "frame of nav_topic poses: 'enu' (ROS REP 103: x east, y north, "
                             "z up, yaw from east) or 'ned' (x north, y east, z down, yaw from north)"),
        "frames": ({}, "frame id -> 'enu' | 'ned' | {axes, x, y, z, yaw}: how each header.frame_id "
                       "maps to the local grid (empty: points ENU, poses nav_frame, any frame id)"),
    }

    @classmethod
    def check(cls, options: Mapping[str, Any]) -> Problems:
        p, who = Problems(), f"input {cls.name!r}"
        p.option_str(who, options, "path", nonempty=True)
        for key in ("points_topic", "image_topic", "nav_topic"):
            p.option_str(who, options, key)
        if not any(options.get(k) for k in ("points_topic", "image_topic", "nav_topic")):
            p.said("", f"{who} needs at least one of the options 'points_topic', 'image_topic', 'nav_topic'")
        check_frames(p, cls.name, options)
        return p

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
        self._frames = FrameMap(self.config["frames"], self.config["nav_frame"])
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
        if clock is not None:
            self._anchor = float(clock())

    def _select(self, reader: Any) -> list[Any]:
        topics = sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections})
        chosen: list[Any] = []
        for role, (key, types) in ROLES.items():
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
                t = self._item_time(stamp_of(msg) or bag_ns * 1e-9)
                item = item_of(role, conn.msgtype, msg, t, self._frames)
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

    def close(self) -> None:
        if self._reader is not None:
            try:
                self._reader.close()
            finally:
                self._reader = None
                self._messages = None
                self._next = None
