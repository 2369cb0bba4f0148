"""The ``ros`` input: live ROS 1 topics of the vehicle (rospy, through
:class:`~coex_transports.ros.RosNode`), with the same choices as the ``rosbag`` input
(:mod:`.rosmsg`: frames mapped to the local grid, image encodings, navigation):

* ``points_topic``: ``sensor_msgs/PointCloud2`` -> :class:`~coex.Points` (in the local grid
  through ``frames``; rows with a NaN dropped);
* ``image_topic``: ``sensor_msgs/Image`` or ``CompressedImage`` -> :class:`~coex.Image`;
* ``nav_topic``: ``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped`` (``WithCovariance``) or
  ``sensor_msgs/NavSatFix`` -> :class:`~coex.Nav`;
* ``series``: numeric fields of any message -> :class:`~coex.Samples`, a field path per
  channel (``{ topic = "/ctd", channels = { temperature = "temperature" } }``);
* ``altitude_topic``: the vehicle's height above the seafloor (an altimeter's or DVL's
  ``sensor_msgs/Range``, a ``std_msgs/Float32``/``Float64``, or a field of any message:
  ``altitude_field``) -> :class:`~coex.Nav` with only ``altitude`` (merged into the vehicle status).

Subscriptions take any type and check it against the role when a message arrives (a topic of
another type is logged once and skipped). Messages wait in a queue per topic (``queue``, the
oldest dropped beyond it, counted) until :meth:`RosInput.poll`, which deserializes and converts
them, never blocking. An item's time is its ``header.stamp`` (``stamps = "header"``, when it is
not zero), else when the daemon polled it. The ROS master may start after CoEx, go away and come
back: :class:`~coex_transports.ros.RosNode` waits, and registers again (``docs/inputs.md``).
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

import numpy as np

from coex import Input, InputContext, Item, Nav, Samples
from coex.options import Option, flag, integer, text

from ..options import LogOnce, Problems, check_scale, compile_path, finite
from .rosmsg import ROLES, FrameMap, canonical, check_frames, item_of, stamp_of

__all__ = ["RosInput", "check_series"]

log = logging.getLogger(__name__)

SERIES_KEYS = ("topic", "channels", "scale")


def check_series(p: Problems, who: str, options: Mapping[str, Any]) -> None:
    """Problems of the option ``series``: a list of ``{topic, channels, scale}`` tables."""
    tables = p.option_tables(who, options, "series", SERIES_KEYS, hint="[[inputs.series]]",
                             entry_hint=" {topic, channels, scale}")
    for key, entry in tables:
        topic = entry.get("topic")
        if not isinstance(topic, str) or not topic.strip():
            p.said("series", f"{who}: option '{key}.topic' is required (a topic name)")
        channels = entry.get("channels")
        if not isinstance(channels, Mapping) or not channels:
            p.said("series", f"{who}: option '{key}.channels' is required (a table of "
                            "channel = \"field path\")")
            channels = {}
        for channel, path in channels.items():
            try:
                compile_path(path)
            except ValueError as exc:
                p.said("series", f"{who}: option '{key}.channels.{channel}': {exc}")
        check_scale(p, who, "series", key, entry, channels, "channels", "channel")


class _Topic:
    """One subscription: its role, the messages waiting for the next poll."""

    def __init__(self, role: str, topic: str, queue: int, series: Mapping[str, Any] | None = None) -> None:
        self.role = role
        self.topic = topic
        self.waiting: deque[tuple[str, bytes]] = deque(maxlen=queue)
        self.dropped = 0
        self.sub: Any = None
        self.getters: dict[str, tuple[Callable[[Any], Any], float]] = {}
        if series is not None:
            scale = series.get("scale", {})
            self.getters = {ch: (compile_path(path)[0], float(scale.get(ch, 1.0)))
                            for ch, path in series["channels"].items()}


class RosInput(Input):
    """Live ROS topics (see the module docstring)."""

    name = "ros"
    feeds = ("bathymetry", "imagery", "status", "timeseries")
    options: ClassVar[Mapping[str, tuple[Any, str] | Option]] = {
        "master": ("", "the ROS master URI; empty: $ROS_MASTER_URI, else http://localhost:11311"),
        "node": ("coex_vehicle", "the name of CoEx's ROS node (one per process)"),
        "points_topic": ("", "sensor_msgs/PointCloud2 topic: soundings for the bathymetry map"),
        "image_topic": ("", "sensor_msgs/Image or CompressedImage topic: camera images"),
        "nav_topic": ("", "nav_msgs/Odometry, geometry_msgs/PoseStamped (WithCovariance) or "
                          "sensor_msgs/NavSatFix topic: the vehicle's position"),
        "nav_frame": ("enu", "frame of nav_topic poses when 'frames' is empty: 'enu' or 'ned'"),
        "frames": ({}, "frame id -> 'enu' | 'ned' | {axes, x, y, z, yaw}: how each header.frame_id "
                       "maps to the local grid (empty: points ENU, poses nav_frame, any frame id)"),
        "series": ([], "numeric fields as time series: a list of {topic, channels = {channel = "
                       "\"field path\"}, scale} tables"),
        "queue": integer(10, "messages kept per topic between two polls (the oldest dropped beyond)",
                         lo=1, hi=10000),
        "stamps": text("header", "'header': an item's time is its header.stamp (when not zero); "
                                 "'arrival': when the daemon took it", choices=("header", "arrival")),
        "nav_images": flag(True, "images get the newest vehicle position (a camera image has none of its own)"),
        "altitude_topic": ("", "the vehicle's altitude above the seafloor: sensor_msgs/Range, std_msgs/Float32 "
                               "or Float64, or any message with altitude_field"),
        "altitude_field": ("", "field path of the altitude in altitude_topic's messages (default: range for "
                               "sensor_msgs/Range, data for std_msgs/Float32 and Float64)"),
    }

    @classmethod
    def check(cls, options: Mapping[str, Any]) -> Problems:
        p, who = Problems(), f"input {cls.name!r}"
        for key in ("master", "node", "points_topic", "image_topic", "nav_topic", "altitude_topic", "altitude_field"):
            p.option_str(who, options, key, nonempty=key == "node")
        field = options.get("altitude_field", "")
        if isinstance(field, str) and field:
            try:
                compile_path(field)
            except ValueError as exc:
                p.said("altitude_field", f"{who}: option 'altitude_field': {exc}")
        master = options.get("master", "")
        if isinstance(master, str) and master and not master.startswith(("http://", "https://")):
            p.said("master", f"{who}: option 'master' must be an http:// URI (http://localhost:11311), not {master!r}")
        if not any(options.get(k) for k in ("points_topic", "image_topic", "nav_topic", "series", "altitude_topic")):
            p.said("", f"{who} needs at least one of the options 'points_topic', 'image_topic', 'nav_topic', "
                       "'series', 'altitude_topic'")
        check_frames(p, cls.name, options)
        if "series" in options:
            check_series(p, who, options)
        return p

    def __init__(self, options: Mapping[str, Any], context: InputContext) -> None:
        super().__init__(options, context)
        self._frames = FrameMap(self.config["frames"], self.config["nav_frame"])
        q = int(self.config["queue"])
        # navigation first: an image taken in the same poll gets the position of its time
        roles = sorted(ROLES.items(), key=lambda kv: kv[0] != "nav")
        self.topics = [_Topic(role, self.config[key], q) for role, (key, _) in roles if self.config[key]]
        self.topics += [_Topic("series", s["topic"], q, s) for s in self.config["series"]]
        if self.config["altitude_topic"]:
            self.topics.insert(0, _Topic("altitude", self.config["altitude_topic"], q))
        field = self.config["altitude_field"]
        self._altitude_field = compile_path(field)[0] if field else None
        self._node: Any = None
        self._lock = threading.Lock()
        self._problem = LogOnce(log)
        #: messages turned into items, skipped (wrong type, not convertible), dropped (queue full)
        #: and altitudes (``no_altitude``: a message without one: out of the altimeter's range)
        self.counts = {"points": 0, "image": 0, "nav": 0, "series": 0, "altitude": 0, "no_altitude": 0,
                       "skipped": 0, "dropped": 0}

    @property
    def stamp_images(self) -> bool:
        """Whether the daemon gives images the newest vehicle position (option ``nav_images``)."""
        return bool(self.config["nav_images"])

    @property
    def state(self) -> str:
        """The ROS node's state (``waiting``, ``up``, ``master lost`` ...), or ``closed``."""
        return str(self._node.state) if self._node is not None else "closed"

    def open(self) -> None:
        if self._node is not None:
            return
        from coex.ros import RosNode

        node = RosNode.get(self.config["master"], self.config["node"])
        for t in self.topics:
            t.sub = node.subscribe(t.topic, self._receiver(t), queue=int(self.config["queue"]))
        self._node = node

    def _receiver(self, t: _Topic) -> Callable[[str, bytes], None]:
        def receive(msgtype: str, data: bytes) -> None:  # in a rospy thread
            with self._lock:
                if len(t.waiting) == t.waiting.maxlen:
                    t.dropped += 1
                    self.counts["dropped"] += 1
                t.waiting.append((msgtype, data))
        return receive

    def poll(self, now: float) -> list[Item]:
        if self._node is None:
            self.open()
        with self._lock:
            batches = [(t, list(t.waiting)) for t in self.topics]
            for t in self.topics:
                t.waiting.clear()
        items: list[Item] = []
        samples: dict[str, list[tuple[float, float]]] = {}
        for t, waiting in batches:
            for msgtype, data in waiting:
                try:
                    item = self._convert(t, msgtype, data, now, samples)
                except Exception as exc:  # one bad message is skipped, the input goes on
                    self.counts["skipped"] += 1
                    self._problem(f"{t.topic}:{type(exc).__name__}", "input ros: a %s message on %s skipped (%s: %s)",
                                  msgtype or "?", t.topic, type(exc).__name__, exc)
                    continue
                if item is not None:
                    self.counts[t.role] += 1
                    items.append(item)
        for channel, pairs in samples.items():
            arr = np.asarray(pairs, np.float64)
            arr = arr[np.argsort(arr[:, 0], kind="stable")]
            items.append(Samples(channel, arr[:, 0].copy(), arr[:, 1].copy()))
        return items

    def _convert(self, t: _Topic, msgtype: str, data: bytes, now: float,
                 samples: dict[str, list[tuple[float, float]]]) -> Item | None:
        kind = canonical(msgtype)
        if t.role == "altitude":
            return self._altitude(msgtype, data, now)
        if t.role != "series":
            types = ROLES[t.role][1]
            if kind not in types:
                raise ValueError(f"{t.topic} carries {msgtype}, not {' or '.join(types)}")
        msg = self._node.deserialize(msgtype, data)
        when = now if self.config["stamps"] == "arrival" else (stamp_of(msg) or now)
        if t.role != "series":
            return item_of(t.role, kind, msg, when, self._frames)
        got = False
        for channel, (get, factor) in t.getters.items():
            v = get(msg)
            if isinstance(v, list | tuple | np.ndarray | bytes):
                raise ValueError(f"{channel!r} is {len(v)} values (index it: name[i])")
            f = finite(v)
            if f is not None:
                samples.setdefault(channel, []).append((when, f * factor))
                got = True
        if got:
            self.counts["series"] += 1
        return None

    def _altitude(self, msgtype: str, data: bytes, now: float) -> Item | None:
        """A Nav of the altitude one message gives (None: it gives none: NaN, infinite, or a
        Range outside its min_range..max_range, which is how a Range says "no bottom")."""
        kind = canonical(msgtype)
        msg = self._node.deserialize(msgtype, data)
        when = now if self.config["stamps"] == "arrival" else (stamp_of(msg) or now)
        get = self._altitude_field
        if get is None:
            if kind == "sensor_msgs/msg/Range":
                get = compile_path("range")[0]
            elif kind in ("std_msgs/msg/Float32", "std_msgs/msg/Float64"):
                get = compile_path("data")[0]
            else:
                raise ValueError(f"{msgtype} is not sensor_msgs/Range or std_msgs/Float32/64: give altitude_field")
        v = finite(get(msg))
        lo, hi = finite(getattr(msg, "min_range", None)), finite(getattr(msg, "max_range", None))
        if v is None or v < 0 or (kind == "sensor_msgs/msg/Range" and (
                (lo is not None and v < lo) or (hi is not None and hi > 0 and v > hi))):
            self.counts["no_altitude"] += 1
            return None
        return Nav(when, altitude=v)

    def close(self) -> None:
        if self._node is not None:
            for t in self.topics:
                if t.sub is not None:
                    self._node.unsubscribe(t.sub)
                    t.sub = None
            self._node = None
