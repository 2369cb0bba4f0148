"""What reached topside, on ROS 1 topics, so that rviz, rqt and rosbag on the ship show and keep
it: the ``[ros]`` table of a topside configuration (``docs/deploy.md`` section 8).

:class:`RosProducts` watches the topside node's events (:meth:`Node.subscribe
<coex_core.node.Node.subscribe>`: the receivers' products and the vehicle status, whoever drains
the events) and publishes, from a thread of its own, at most once per ``interval`` seconds per
topic, only what changed since:

| topic (``prefix`` = ``/coex``) | type | what |
|---|---|---|
| ``/coex/map/level_K`` | ``sensor_msgs/PointCloud2`` | map level K (0 = finest): one point per cell held, at its elevation (z up) |
| ``/coex/map/level_K/grid`` | ``nav_msgs/OccupancyGrid`` | the same level as a grid: -1 nothing held, else the elevation on one fixed scale, 0 = ``grid_min`` .. 100 = ``grid_max`` metres (z up) |
| ``/coex/map/grid_range`` | ``std_msgs/String`` | that scale as JSON: ``{"min": -40.0, "max": -20.0, "unknown": -1, "frame": ...}`` |
| ``/coex/image`` | ``sensor_msgs/Image`` | the newest image (by capture time), refined as more of it comes; an older image refined later does not replace it |
| ``/coex/image/compressed`` | ``sensor_msgs/CompressedImage`` | the same, PNG (``image_transport``'s ``compressed`` form) |
| ``/coex/vehicle/odometry`` | ``nav_msgs/Odometry`` | the vehicle status: x, y, -depth, heading, speed |
| ``/coex/vehicle/track`` | ``nav_msgs/Path`` | the statuses received (the newest ``track`` of them) |
| ``/tf`` | ``tf2_msgs/TFMessage`` | ``vehicle_frame`` in ``frame`` at each status (not latched, as tf wants) |
| ``/coex/series/NAME`` | ``std_msgs/Float64MultiArray`` | each time-series channel: 3 rows (times, values, error bounds) by its newest ``series_samples`` samples |
| ``/coex/surveys`` | ``std_msgs/String`` | every survey topside follows, as JSON: ``{"surveys": [{"survey_id", "state", "reason", "text", "index", "time", "kind", "waypoints", ...}]}`` |

Every topic but ``/tf`` is latched (rviz started later shows the newest) and everything is in
``frame`` (``coex_local``: x east, y north of ``node.origin``, z up). ``grid_min`` / ``grid_max``
fix the grids' scale; without them it is fixed from the first level published (its deepest and
shallowest, widened to whole 10 m) for the rest of the run, logged and published on
``/coex/map/grid_range``. The node's own loop only records which product changed (a dictionary
write per event); the publisher copies a changed map level or image under the console's lock
(``lock``) and converts and publishes it outside it, so the topside node never waits for ROS,
and a ROS master that is down or slow costs it nothing.
"""

from __future__ import annotations

import json
import logging
import math
import re
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from contextlib import AbstractContextManager, nullcontext
from typing import Any

import numpy as np

from coex import Problems

__all__ = ["RosProducts", "grid_scale", "topic_name"]

log = logging.getLogger(__name__)


class RosProducts:
    """Topside products on ROS topics (module docstring). ``lock``: held while a product's data
    is copied (the console's lock, which the loop driving the node holds around each step)."""

    #: name -> (default, description)
    options: Mapping[str, tuple[Any, str]] = {
        "master": ("", "the ROS master URI; empty: $ROS_MASTER_URI, else http://localhost:11311"),
        "node": ("coex_topside", "the name of CoEx's ROS node on the ship"),
        "prefix": ("/coex", "the topics' namespace"),
        "frame": ("coex_local", "frame_id of everything published: the local grid (x east, y north, z up)"),
        "interval": (1.0, "seconds between two publications of one topic, at least"),
        "track": (1000, "statuses kept in the track (nav_msgs/Path)"),
        "vehicle_frame": ("coex_vehicle", "the vehicle's frame on /tf (and the odometry's child frame)"),
        "grid_min": (None, "elevation (m, z up) of OccupancyGrid value 0 (absent: fixed from the first level)"),
        "grid_max": (None, "elevation (m, z up) of OccupancyGrid value 100 (absent: fixed from the first level)"),
        "series_samples": (10000, "newest samples of each time series published"),
    }

    @classmethod
    def check(cls, options: Mapping[str, Any]) -> Problems:
        """Problems of a ``[ros]`` table (keys ``ros.master`` ...), one sentence each naming
        the key."""
        p = Problems()
        p.unknown(options, tuple(cls.options), "ros")
        for key in ("master", "node", "prefix", "frame", "vehicle_frame"):
            v = options.get(key, "x")
            if not isinstance(v, str) or (key != "master" and not v.strip()):
                p.add(f"ros.{key}", f"a {'non-empty ' if key != 'master' else ''}string, got {v!r}")
        master = options.get("master", "")
        if isinstance(master, str) and master and not master.startswith(("http://", "https://")):
            p.add("ros.master", f"an http:// URI (http://localhost:11311), got {master!r}")
        prefix = options.get("prefix", "/coex")
        if isinstance(prefix, str) and prefix and not prefix.startswith("/"):
            p.add("ros.prefix", f"a global namespace starting with '/', got {prefix!r}")
        v = options.get("interval", 1.0)
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or not 0.05 <= v <= 3600:
            p.add("ros.interval", f"seconds from 0.05 to 3600, got {v!r}")
        v = options.get("track", 1000)
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= 100000:
            p.add("ros.track", f"an integer from 0 to 100000, got {v!r}")
        v = options.get("series_samples", 10000)
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 1_000_000:
            p.add("ros.series_samples", f"an integer from 1 to 1000000, got {v!r}")
        grid = [options.get(k) for k in ("grid_min", "grid_max")]
        for key, v in zip(("grid_min", "grid_max"), grid, strict=True):
            if v is not None and (isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v)):
                p.add(f"ros.{key}", f"an elevation in metres (z up, negative below the surface), got {v!r}")
        if (grid[0] is None) != (grid[1] is None):
            p.add("ros.grid_min" if grid[0] is None else "ros.grid_max", "give grid_min and grid_max together")
        else:
            lo, hi = grid
            if isinstance(lo, int | float) and isinstance(hi, int | float) and not float(lo) < float(hi):
                p.add("ros.grid_max", f"above grid_min ({lo!r}), got {hi!r}")
        return p

    def __init__(self, options: Mapping[str, Any] | None = None, *,
                 lock: AbstractContextManager[Any] | None = None,
                 clock: Callable[[], float] = time.time) -> None:
        options = dict(options or {})
        self.check(options).check()
        self.config = {k: v[0] for k, v in self.options.items()}
        self.config.update(options)
        self.prefix = str(self.config["prefix"]).rstrip("/")
        self.frame = str(self.config["frame"])
        self.interval = float(self.config["interval"])
        self.lock: AbstractContextManager[Any] = lock if lock is not None else nullcontext()
        self.clock = clock
        self.node: Any = None
        self._mu = threading.Lock()
        self._levels: dict[int, Any] = {}  # level -> newest map-level product not yet published
        self._image: Any = None
        #: (capture time, image id) of the newest image seen: only it goes on the image topics
        self._newest: tuple[float, int] | None = None
        self._status: Any = None
        self._series: dict[str, Any] = {}  # channel name -> newest series product not yet published
        self._surveys: dict[int, dict[str, Any]] = {}  # survey id -> its newest product's meta
        self._surveys_changed = False
        lo, hi = self.config["grid_min"], self.config["grid_max"]
        #: the OccupancyGrid scale (elevations of 0 and 100), None until fixed
        self.grid_range: tuple[float, float] | None = None if lo is None else (float(lo), float(hi))
        self._track: deque[tuple[float, float, float, float]] = deque(maxlen=max(1, int(self.config["track"])))
        self._pubs: dict[str, Any] = {}
        self._no_tf: str | None = None  # why /tf is not published (tf2_msgs missing)
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread: threading.Thread | None = None
        self._unsubscribe: Callable[[], None] | None = None
        #: messages published per kind, and conversions that failed
        self.counts = {"map": 0, "image": 0, "status": 0, "series": 0, "surveys": 0, "tf": 0, "failed": 0}

    # ------------------------------------------------------------------ wiring
    def attach(self, coex_node: Any) -> RosProducts:
        """Watch ``coex_node``'s events, start the ROS node and the publishing thread."""
        from coex.ros import RosNode

        self.node = RosNode.get(self.config["master"], self.config["node"])
        self._unsubscribe = coex_node.subscribe(self.on_events)
        self._thread = threading.Thread(target=self._run, name="coex-ros-products", daemon=True)
        self._thread.start()
        return self

    def on_events(self, events: list[Any]) -> None:
        """The node's events (in the thread driving the node): only remembers what changed."""
        from coex import ProductUpdated, Received
        from coex.messages import VehicleStatus

        changed = False
        with self._mu:
            for e in events:
                if isinstance(e, ProductUpdated):
                    p = e.product
                    if p.kind == "map-level" and "level" in p.meta:
                        self._levels[int(p.meta["level"])] = p
                        changed = True
                    elif p.kind == "image" and p.data is not None:
                        changed = self._take_image(p) or changed
                    elif p.kind == "series" and p.data is not None:
                        self._series[str(p.key)] = p
                        changed = True
                    elif p.kind == "survey":
                        try:
                            self._surveys[int(p.meta.get("survey_id", p.key))] = dict(p.meta)
                        except (TypeError, ValueError):
                            continue
                        self._surveys_changed = changed = True
                elif isinstance(e, Received) and isinstance(e.message, VehicleStatus):
                    self._status = (e.message, float(e.time))
                    changed = True
        if changed:
            self._wake.set()

    def _take_image(self, p: Any) -> bool:
        """Keep an image product for the image topics if it is the newest image (by capture time,
        then id) or a refinement of it."""
        try:
            key = (float(p.meta.get("time") or 0.0), int(p.meta.get("image_id", p.key)))
        except (TypeError, ValueError):
            return False
        if self._newest is not None and key < self._newest and key[1] != self._newest[1]:
            return False  # an older image refined: the topics keep showing the newest
        self._newest = key
        self._image = p
        return True

    def close(self) -> None:
        if self._unsubscribe is not None:
            self._unsubscribe()
            self._unsubscribe = None
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        for pub in self._pubs.values():
            pub.close()
        self._pubs.clear()

    # ------------------------------------------------------------------ publishing
    def _pub(self, topic: str, msgtype: str, latch: bool = True) -> Any:
        pub = self._pubs.get(topic)
        if pub is None:
            pub = self._pubs[topic] = self.node.publisher(topic, msgtype, latch=latch, queue=2 if latch else 10)
        return pub

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait()
            self._wake.clear()
            if self._stop.is_set():
                return
            started = time.monotonic()
            try:
                self.publish_pending()
            except Exception as exc:  # never let the thread die: the next change tries again
                self.counts["failed"] += 1
                log.warning("ROS products: %s: %s", type(exc).__name__, exc)
            self._stop.wait(max(0.0, self.interval - (time.monotonic() - started)))

    def publish_pending(self) -> None:
        """Publish what changed since the last call (the thread does it, at most every
        ``interval`` s; a test may call it)."""
        with self._mu:
            levels, self._levels = self._levels, {}
            image, self._image = self._image, None
            status, self._status = self._status, None
            series, self._series = self._series, {}
            surveys = [self._surveys[k] for k in sorted(self._surveys)] if self._surveys_changed else None
            self._surveys_changed = False
        now = self.clock()
        for level, product in sorted(levels.items()):
            self._publish_level(level, product, now)
        if image is not None:
            self._publish_image(image, now)
        if status is not None:
            self._publish_status(*status)
        for name, product in sorted(series.items()):
            self._publish_series(name, product)
        if surveys is not None:
            self._publish_surveys(surveys, now)

    def _publish_level(self, level: int, product: Any, now: float) -> None:
        from coex.ros import msgs

        cls = self.node.message_class
        with self.lock:  # the receiver may be writing the level's array in the node's thread
            grid = np.array(product.data, dtype=np.float64, copy=True)
            meta = dict(product.meta)
        t = float(meta.get("newest") or now)
        if self.grid_range is None and np.isfinite(grid).any():
            self.grid_range = grid_scale(grid)
            log.info("ROS products: OccupancyGrid values 0..100 are elevations %g..%g m from now on (fixed for "
                     "this run from the first level; [ros] grid_min, grid_max fix them)", *self.grid_range)
        try:
            self._pub(f"{self.prefix}/map/level_{level}", "sensor_msgs/PointCloud2").publish(
                msgs.level_cloud(grid, meta, cls, t, self.frame))
            if self.grid_range is not None:
                lo, hi = self.grid_range
                if f"{self.prefix}/map/grid_range" not in self._pubs:
                    self._pub(f"{self.prefix}/map/grid_range", "std_msgs/String").publish(self.node.message(
                        "std_msgs/String", data=json.dumps({"min": lo, "max": hi, "unknown": -1, "frame": self.frame})))
                self._pub(f"{self.prefix}/map/level_{level}/grid", "nav_msgs/OccupancyGrid").publish(
                    msgs.level_grid(grid, meta, cls, t, self.frame, lo=lo, hi=hi))
            self.counts["map"] += 1
        except (KeyError, ValueError) as exc:
            self.counts["failed"] += 1
            log.warning("ROS products: map level %d not published: %s", level, exc)

    def _publish_image(self, image: Any, now: float) -> None:
        from coex.ros import msgs

        cls = self.node.message_class
        with self.lock:
            pixels = np.array(image.data, copy=True)
            meta = dict(image.meta)
        t = float(meta.get("time") or now)
        try:
            self._pub(f"{self.prefix}/image", "sensor_msgs/Image").publish(msgs.image(pixels, cls, t, self.frame))
            self._pub(f"{self.prefix}/image/compressed", "sensor_msgs/CompressedImage").publish(
                msgs.compressed_image(pixels, cls, t, self.frame))
            self.counts["image"] += 1
        except (ValueError, OSError) as exc:
            self.counts["failed"] += 1
            log.warning("ROS products: image %s not published: %s", meta.get("image_id"), exc)

    def _publish_status(self, st: Any, received: float) -> None:
        from coex import unwrap
        from coex.ros import msgs

        cls = self.node.message_class
        t = unwrap(int(st.stamp), received)
        child = str(self.config["vehicle_frame"])
        self._pub(f"{self.prefix}/vehicle/odometry", "nav_msgs/Odometry").publish(
            msgs.odometry(st, cls, t, self.frame, child))
        self._track.append((t, float(st.x), float(st.y), -float(st.depth)))
        if int(self.config["track"]) > 0:
            track = msgs.path([(x, y) for _, x, y, _ in self._track], cls, t, self.frame)
            for pose, (when, _, _, z) in zip(track.poses, self._track, strict=True):
                pose.pose.position.z = z
                msgs.set_stamp(pose.header, when)
            self._pub(f"{self.prefix}/vehicle/track", "nav_msgs/Path").publish(track)
        self.counts["status"] += 1
        if self._no_tf is None:
            try:
                tf = msgs.transform(st, cls, t, self.frame, child)
            except ValueError as exc:  # tf2_msgs not installed
                self._no_tf = str(exc)
                log.warning("ROS products: no /tf (%s); the odometry still carries the pose", exc)
                return
            self._pub("/tf", "tf2_msgs/TFMessage", latch=False).publish(tf)
            self.counts["tf"] += 1

    def _publish_series(self, name: str, product: Any) -> None:
        from coex.ros import msgs

        n = int(self.config["series_samples"])
        with self.lock:
            s = product.data
            times = np.array(s.times[-n:], dtype=np.float64, copy=True)
            values = np.array(s.values[-n:], dtype=np.float64, copy=True)
            bounds = np.array(s.bounds[-n:], dtype=np.float64, copy=True)
        try:
            self._pub(f"{self.prefix}/series/{topic_name(name)}", "std_msgs/Float64MultiArray").publish(
                msgs.series(times, values, bounds, self.node.message_class))
            self.counts["series"] += 1
        except ValueError as exc:
            self.counts["failed"] += 1
            log.warning("ROS products: series %r not published: %s", name, exc)

    def _publish_surveys(self, surveys: list[dict[str, Any]], now: float) -> None:
        text = json.dumps({"surveys": surveys, "frame": self.frame, "stamp": round(now, 3)}, default=_plain)
        self._pub(f"{self.prefix}/surveys", "std_msgs/String").publish(self.node.message("std_msgs/String", data=text))
        self.counts["surveys"] += 1


def grid_scale(grid: np.ndarray) -> tuple[float, float]:
    """The OccupancyGrid scale fixed from a first map level: its deepest and shallowest
    elevations held, widened to whole 10 m (at least 10 m apart)."""
    a = np.asarray(grid, dtype=np.float64)
    held = a[np.isfinite(a)]
    if not held.size:
        raise ValueError("no cell held")
    lo, hi = math.floor(float(held.min()) / 10.0) * 10.0, math.ceil(float(held.max()) / 10.0) * 10.0
    return lo, hi if hi > lo else lo + 10.0


def topic_name(name: str) -> str:
    """A channel name as a ROS graph name: letters, digits and ``_`` (others become ``_``),
    starting with a letter (``ch_`` put in front otherwise)."""
    out = re.sub(r"[^A-Za-z0-9_]", "_", str(name)) or "ch"
    return out if out[0].isalpha() else f"ch_{out}"


def _plain(v: Any) -> Any:
    """JSON for what a product's meta may hold besides JSON types (numpy numbers, tuples)."""
    if isinstance(v, np.generic):
        f = v.item()
        return None if isinstance(f, float) and not math.isfinite(f) else f
    if isinstance(v, tuple | set):
        return list(v)
    return str(v)
