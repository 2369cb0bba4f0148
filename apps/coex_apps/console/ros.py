"""What reached topside, on ROS 1 topics, so that rviz (or any ROS tool on the ship) shows it:
the ``[ros]`` table of a topside configuration (``docs/deploy.md``).

:class:`RosProducts` watches the topside node's events (:meth:`Node.subscribe
<coex_core.node.Node.subscribe>`: the receivers' products and the vehicle status, whoever drains
the events) and publishes, from a thread of its own, at most once per ``interval`` seconds per
topic, only what changed since:

| topic (``prefix`` = ``/coex``) | type | what |
|---|---|---|
| ``/coex/map/level_K`` | ``sensor_msgs/PointCloud2`` | map level K (0 = finest): one point per cell held, at its elevation (z up) |
| ``/coex/map/level_K/grid`` | ``nav_msgs/OccupancyGrid`` | the same level as a grid: -1 nothing held, 0 its deepest .. 100 its shallowest |
| ``/coex/image`` | ``sensor_msgs/Image`` | the newest image received or improved (mono8/16, rgb8/16), stamped with its capture time |
| ``/coex/vehicle/odometry`` | ``nav_msgs/Odometry`` | the vehicle status: x, y, -depth, heading, speed |
| ``/coex/vehicle/track`` | ``nav_msgs/Path`` | the statuses received (the newest ``track`` of them) |

Every topic is latched (rviz started later shows the newest) and in ``frame`` (``coex_local``: x
east, y north of ``node.origin``, z up). The node's own loop only records which product changed
(a dictionary write per event); the publisher copies a changed map level or image under the
console's lock (``lock``) and converts and publishes it outside it, so the topside node never
waits for ROS, and a ROS master that is down or slow costs it nothing.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from contextlib import AbstractContextManager, nullcontext
from typing import Any

import numpy as np

from coex import ConfigError, Problems

__all__ = ["RosProducts"]

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
    }

    @classmethod
    def check(cls, options: Mapping[str, Any]) -> Problems:
        """Problems of a ``[ros]`` table (keys ``ros.master`` ...), one sentence each naming
        the key."""
        p = Problems()
        p.unknown(options, tuple(cls.options), "ros")
        for key in ("master", "node", "prefix", "frame"):
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
        self._status: Any = None
        self._track: deque[tuple[float, float, float, float]] = deque(maxlen=max(1, int(self.config["track"])))
        self._pubs: dict[str, Any] = {}
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread: threading.Thread | None = None
        self._unsubscribe: Callable[[], None] | None = None
        #: messages published per kind, and conversions that failed
        self.counts = {"map": 0, "image": 0, "status": 0, "failed": 0}

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
                        self._image = p
                        changed = True
                elif isinstance(e, Received) and isinstance(e.message, VehicleStatus):
                    self._status = (e.message, float(e.time))
                    changed = True
        if changed:
            self._wake.set()

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
    def _pub(self, topic: str, msgtype: str) -> Any:
        pub = self._pubs.get(topic)
        if pub is None:
            pub = self._pubs[topic] = self.node.publisher(topic, msgtype, latch=True, queue=2)
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
        from coex import unwrap
        from coex.ros import msgs

        with self._mu:
            levels, self._levels = self._levels, {}
            image, self._image = self._image, None
            status, self._status = self._status, None
        cls = self.node.message_class
        now = self.clock()
        for level, product in sorted(levels.items()):
            with self.lock:  # the receiver may be writing the level's array in the node's thread
                grid = np.array(product.data, dtype=np.float64, copy=True)
                meta = dict(product.meta)
            t = float(meta.get("newest") or now)
            try:
                self._pub(f"{self.prefix}/map/level_{level}", "sensor_msgs/PointCloud2").publish(
                    msgs.level_cloud(grid, meta, cls, t, self.frame))
                self._pub(f"{self.prefix}/map/level_{level}/grid", "nav_msgs/OccupancyGrid").publish(
                    msgs.level_grid(grid, meta, cls, t, self.frame))
                self.counts["map"] += 1
            except (KeyError, ValueError) as exc:
                self.counts["failed"] += 1
                log.warning("ROS products: map level %d not published: %s", level, exc)
        if image is not None:
            with self.lock:
                pixels = np.array(image.data, copy=True)
                meta = dict(image.meta)
            try:
                self._pub(f"{self.prefix}/image", "sensor_msgs/Image").publish(
                    msgs.image(pixels, cls, float(meta.get("time") or now), "coex_camera"))
                self.counts["image"] += 1
            except ValueError as exc:
                self.counts["failed"] += 1
                log.warning("ROS products: image %s not published: %s", meta.get("image_id"), exc)
        if status is not None:
            st, received = status
            t = unwrap(int(st.stamp), received)
            self._pub(f"{self.prefix}/vehicle/odometry", "nav_msgs/Odometry").publish(
                msgs.odometry(st, cls, t, self.frame))
            self._track.append((t, float(st.x), float(st.y), -float(st.depth)))
            if int(self.config["track"]) > 0:
                track = msgs.path([(x, y) for _, x, y, _ in self._track], cls, t, self.frame)
                for pose, (when, _, _, z) in zip(track.poses, self._track, strict=True):
                    pose.pose.position.z = z
                    msgs.set_stamp(pose.header, when)
                self._pub(f"{self.prefix}/vehicle/track", "nav_msgs/Path").publish(track)
            self.counts["status"] += 1
