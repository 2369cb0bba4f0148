"""The process's ROS 1 node, through rospy, for the ``ros`` input, the ``ros`` autonomy output and
the topside's ROS products.

rospy allows one node per process (``rospy.init_node`` once), so everything ROS in a CoEx process
goes through one :class:`RosNode` (:meth:`RosNode.get`). Nothing here ever blocks its caller:

* ``rospy.init_node`` and every subscription and publisher are made in the node's own thread
  (rospy waits there, retrying, while the master is not up: a vehicle whose roscore starts after
  CoEx is waited for).
* Subscriptions take any type (``rospy.AnyMsg``): the callback gets the publisher's type name and
  the serialized bytes, and :meth:`RosNode.deserialize` turns them into a message of that type
  (the consumer decides what it takes, and a wrong type is its log line, not rospy's error).
* A publisher handle queues the newest message until its publisher exists.

**A roscore that goes away and comes back.** Connections between nodes are peer to peer: while
the master is down, the topics already connected go on flowing. A restarted master knows nobody
(ROS 1 nodes do not register again by themselves; rospy does not either). The node's thread asks
the master for its PID every ``watch`` seconds; when a master answers again with another PID it
registers every subscription, publisher and service of this node again and connects to the
publishers the master names (as rospy does at start), so nodes started after the restart reach
CoEx and CoEx reaches them. Nodes that kept running through the restart stay connected to CoEx
only through their existing connections (ROS 1's own limit: restart them with the roscore).

:attr:`RosNode.state` and :meth:`RosNode.status` say where it is (``waiting for the ROS master``,
``up``, ``master lost``), and each change is logged once.
"""

from __future__ import annotations

import logging
import os
import threading
import time
import xmlrpc.client
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

from coex_core.errors import ConfigError, PluginLoadError

__all__ = ["ROSPY_HINT", "RosNode", "RosPublisher", "import_rospy"]

log = logging.getLogger(__name__)

#: how to get rospy into CoEx's Python (docs/deploy.md)
ROSPY_HINT = ("Debian's ROS 1: apt-get install python3-rospy python3-rosmaster python3-roslaunch "
              "python3-sensor-msgs python3-nav-msgs python3-geometry-msgs python3-std-msgs python3-tf2-msgs "
              "python3-rostopic python3-rosnode python3-rosbag, then "
              "`make ros` (scripts/ros.sh) so the venv imports it (docs/deploy.md)")


def import_rospy() -> Any:
    """rospy, or :class:`PluginLoadError` saying how to install it."""
    try:
        import rospy
    except ImportError as exc:
        raise PluginLoadError(f"ROS 1 (rospy) is not importable ({exc}): {ROSPY_HINT}") from exc
    return rospy


class _TimeoutTransport(xmlrpc.client.Transport):
    """XML-RPC with a socket timeout: a master host that does not answer never hangs the watch."""

    def __init__(self, timeout: float) -> None:
        super().__init__()
        self.timeout = timeout

    def make_connection(self, host: Any) -> Any:
        conn = super().make_connection(host)
        conn.timeout = self.timeout
        return conn


@dataclass
class _Sub:
    topic: str
    callback: Callable[[str, bytes], None]
    queue: int
    handle: Any = None
    closed: bool = False

    def connections(self) -> int:
        """How many publishers it is connected to now (0 before it exists)."""
        try:
            return int(self.handle.get_num_connections()) if self.handle is not None else 0
        except Exception:  # shut down
            return 0


class RosPublisher:
    """A publisher of one topic, made in the node's thread; :meth:`publish` never waits (before
    the publisher exists the newest message is kept and published once it does)."""

    def __init__(self, node: RosNode, topic: str, msgtype: str, latch: bool, queue: int) -> None:
        self.node = node
        self.topic = topic
        self.msgtype = msgtype
        self.latch = latch
        self.queue = queue
        self.handle: Any = None
        self.closed = False
        self._pending: Any = None
        self._lock = threading.Lock()
        #: messages published, and messages replaced while waiting for the publisher
        self.counts = {"published": 0, "waiting": 0}

    @property
    def ready(self) -> bool:
        return self.handle is not None

    def publish(self, msg: Any) -> bool:
        """Publish ``msg`` (True), or keep it until the publisher exists (False)."""
        with self._lock:
            if self.handle is None:
                if self._pending is not None:
                    self.counts["waiting"] += 1
                self._pending = msg
                return False
        try:
            self.handle.publish(msg)
        except Exception as exc:  # rospy raises when shut down or a connection fails
            self.node._problem(f"publish {self.topic}", f"publishing on {self.topic} failed: {exc}")
            return False
        self.counts["published"] += 1
        return True

    def connections(self) -> int:
        """How many subscribers are connected to it now (0 before it exists)."""
        try:
            return int(self.handle.get_num_connections()) if self.handle is not None else 0
        except Exception:  # shut down
            return 0

    def _made(self, handle: Any) -> None:
        with self._lock:
            self.handle = handle
            pending, self._pending = self._pending, None
        if pending is not None:
            self.publish(pending)

    def close(self) -> None:
        self.node._close(self)


class RosNode:
    """The process's ROS 1 node (module docstring). Build it with :meth:`get`."""

    _instance: ClassVar[RosNode | None] = None
    _instance_lock: ClassVar[threading.Lock] = threading.Lock()

    def __init__(self, master: str, name: str, watch: float = 1.0) -> None:
        self.rospy = import_rospy()
        self.master = master or os.environ.get("ROS_MASTER_URI", "") or "http://localhost:11311"
        self.name = name
        self.watch = watch
        self.state = "starting"
        #: master outages seen, registrations made again after a master restart
        self.counts = {"outages": 0, "reregistered": 0}
        self._lock = threading.Lock()
        self._todo: list[_Sub | RosPublisher] = []
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._pid: int | None = None
        self._logged: dict[str, float] = {}
        self._classes: dict[str, Any] = {}
        self._thread = threading.Thread(target=self._run, name="coex-ros", daemon=True)
        self._thread.start()

    @classmethod
    def get(cls, master: str = "", name: str = "coex", watch: float = 1.0) -> RosNode:
        """The process's node, started on first use (``master``: the ROS master URI, default
        ``$ROS_MASTER_URI``; ``name``: the node's name). ConfigError when another part of the
        process asked for another master (one master per process: rospy's limit)."""
        with cls._instance_lock:
            inst = cls._instance
            if inst is None:
                inst = cls._instance = cls(master, name, watch)
            elif master and master.rstrip("/") != inst.master.rstrip("/"):
                raise ConfigError(f"ROS master {master!r}: this process already uses {inst.master!r} "
                                  "(rospy allows one master per process)")
            elif name != inst.name:
                log.info("ROS node %r also serves what asked for node %r (one node per process)",
                         inst.name, name)
            return inst

    # ---------------------------------------------------------------- what users ask
    def subscribe(self, topic: str, callback: Callable[[str, bytes], None], queue: int = 10) -> _Sub:
        """Call ``callback(type_name, data)`` (in a rospy thread) for each message on ``topic``,
        whatever its type: ``type_name`` as the publisher gives it (``sensor_msgs/Image``)."""
        sub = _Sub(topic, callback, queue)
        self._ask(sub)
        return sub

    def publisher(self, topic: str, msgtype: str, *, latch: bool = False, queue: int = 2) -> RosPublisher:
        """A publisher of ``msgtype`` (``nav_msgs/Path``) on ``topic``, made in the node's thread."""
        self.message_class(msgtype)  # an unknown type is an error now, not in the thread
        pub = RosPublisher(self, topic, msgtype, latch, queue)
        self._ask(pub)
        return pub

    def unsubscribe(self, sub: _Sub) -> None:
        self._close(sub)

    def message_class(self, msgtype: str) -> Any:
        """The Python class of a message type (``sensor_msgs/Image`` or ``sensor_msgs/msg/Image``);
        ValueError when no installed package defines it."""
        parts = msgtype.split("/")
        name = f"{parts[0]}/{parts[-1]}" if len(parts) == 3 and parts[1] == "msg" else msgtype
        cls = self._classes.get(name)
        if cls is None:
            import roslib.message

            try:
                cls = roslib.message.get_message_class(name)
            except Exception as exc:  # a malformed name
                raise ValueError(f"message type {msgtype!r}: {exc}") from exc
            if cls is None:
                raise ValueError(f"message type {msgtype!r} is not installed (its Python package, e.g. "
                                 f"python3-{parts[0].replace('_', '-')}, or the workspace that builds it)")
            self._classes[name] = cls
        return cls

    def message(self, msgtype: str, **fields: Any) -> Any:
        return self.message_class(msgtype)(**fields)

    def deserialize(self, msgtype: str, data: bytes) -> Any:
        """A message of ``msgtype`` from its serialized bytes (ValueError when they do not fit)."""
        msg = self.message_class(msgtype)()
        try:
            msg.deserialize(data)
        except Exception as exc:  # genpy raises struct.error, DeserializationError ...
            raise ValueError(f"{msgtype}: {type(exc).__name__}: {exc}") from exc
        return msg

    def time(self, t: float) -> Any:
        return self.rospy.Time.from_sec(float(t))

    def status(self) -> dict[str, Any]:
        return {"state": self.state, "master": self.master, "node": self.name, **self.counts}

    # ---------------------------------------------------------------- the node's thread
    def _ask(self, item: _Sub | RosPublisher) -> None:
        with self._lock:
            self._todo.append(item)
        self._wake.set()

    def _close(self, item: Any) -> None:
        item.closed = True
        self._ask(item)

    def _problem(self, key: str, text: str, level: int = logging.WARNING) -> None:
        now = time.monotonic()
        if now - self._logged.get(key, -1e9) > 60.0:
            self._logged[key] = now
            log.log(level, "ROS: %s", text)

    def _set_state(self, state: str, text: str, level: int = logging.INFO) -> None:
        if state != self.state:
            self.state = state
            log.log(level, "ROS node %s (master %s): %s", self.name, self.master, text)

    def _run(self) -> None:
        rospy = self.rospy
        os.environ["ROS_MASTER_URI"] = self.master  # rospy reads it at init_node
        self._set_state("waiting", "waiting for the ROS master")
        root = logging.getLogger()
        handlers, level = list(root.handlers), root.level
        try:
            rospy.init_node(self.name, anonymous=False, disable_signals=True)
        except Exception as exc:
            self._set_state("failed", f"rospy.init_node failed: {exc}", logging.ERROR)
            return
        finally:
            # rospy's logging configuration sends the root logger to a file under ROS_HOME: the
            # process keeps its own (its log stays where its operators read it); rospy's chatter
            # (each connection made) only from warnings up
            root.handlers[:] = handlers
            root.setLevel(level)
            if logging.getLogger("rospy").level < logging.WARNING:
                logging.getLogger("rospy").setLevel(logging.WARNING)
        self._pid = self._master_pid()
        self._set_state("up", "up")
        while not self._stop.is_set():
            self._do_todo()
            if rospy.is_shutdown():
                self._set_state("shut down", "rospy was shut down (another node named "
                                f"{self.name!r} on this master?); restart this process", logging.ERROR)
                return
            self._watch_master()
            self._wake.wait(self.watch)
            self._wake.clear()

    def _do_todo(self) -> None:
        rospy = self.rospy
        with self._lock:
            todo, self._todo = self._todo, []
        for item in todo:
            try:
                if isinstance(item, _Sub):
                    if item.closed:
                        if item.handle is not None:
                            item.handle.unregister()
                        continue
                    if item.handle is not None:
                        continue
                    cb = item.callback

                    def deliver(msg: Any, cb: Callable[[str, bytes], None] = cb) -> None:
                        header = getattr(msg, "_connection_header", None) or {}
                        cb(str(header.get("type", "")), bytes(msg._buff))

                    item.handle = rospy.Subscriber(item.topic, rospy.AnyMsg, deliver, queue_size=item.queue)
                elif isinstance(item, RosPublisher):
                    if item.closed:
                        if item.handle is not None:
                            item.handle.unregister()
                        continue
                    if item.handle is None:
                        item._made(rospy.Publisher(item.topic, self.message_class(item.msgtype),
                                                   latch=item.latch, queue_size=item.queue))
            except Exception as exc:  # one bad topic never stops the others
                self._problem(f"make {item.topic}", f"cannot subscribe or publish {item.topic}: {exc}")

    def _proxy(self, uri: str) -> Any:
        return xmlrpc.client.ServerProxy(uri, transport=_TimeoutTransport(2.0), allow_none=True)

    def _master_pid(self) -> int | None:
        try:
            code, _msg, pid = self._proxy(self.master).getPid(f"/{self.name}")
            return int(pid) if code == 1 else None
        except Exception:  # refused, timed out, not an XML-RPC server
            return None

    def _watch_master(self) -> None:
        pid = self._master_pid()
        if pid is None:
            if self.state == "up":
                self.counts["outages"] += 1
                self._set_state("master lost", "the ROS master does not answer; connected topics go on, "
                                "registering again when it is back", logging.WARNING)
            return
        if pid != self._pid:
            n = self._reregister()
            self.counts["reregistered"] += 1
            self._pid = pid
            self.state = "up"
            log.info("ROS node %s (master %s): a new ROS master (pid %d): %d registrations made again",
                     self.name, self.master, pid, n)
        elif self.state != "up":
            self._set_state("up", "the ROS master answers again (the same one)")

    def _reregister(self) -> int:
        """Register every subscription, publisher and service of this node with the (new) master,
        and connect the subscriptions to the publishers it names."""
        from rospy.impl.registration import get_service_manager, get_topic_manager

        rospy = self.rospy
        caller = rospy.get_caller_id()
        uri = rospy.get_node_uri()
        master = self._proxy(self.master)
        me = self._proxy(uri)
        n = 0
        for topic, msgtype in get_topic_manager().get_publications():
            master.registerPublisher(caller, topic, msgtype, uri)
            n += 1
        for topic, msgtype in get_topic_manager().get_subscriptions():
            code, _msg, pubs = master.registerSubscriber(caller, topic, msgtype, uri)
            if code == 1 and pubs:
                me.publisherUpdate("/master", topic, pubs)  # what the master tells a subscriber
            n += 1
        for service, service_uri in get_service_manager().get_services():
            master.registerService(caller, service, service_uri, uri)
            n += 1
        return n

    def close(self) -> None:
        """Stop the node's thread (rospy itself stays initialised: it cannot start twice)."""
        self._stop.set()
        self._wake.set()
