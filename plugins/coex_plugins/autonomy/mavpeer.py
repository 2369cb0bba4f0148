"""A MAVLink mission-protocol peer built from stock pymavlink: the vehicle's side of a mission
upload, for tests and examples without an autopilot (or SITL).

It sends HEARTBEAT as an ArduPilot submarine (``MAV_TYPE_SUBMARINE``,
``MAV_AUTOPILOT_ARDUPILOTMEGA``, custom mode ALT_HOLD), answers ``MISSION_COUNT`` by requesting
every item with ``MISSION_REQUEST_INT`` (or the legacy ``MISSION_REQUEST``), checks each item
(sequence, frame, command) and ends with ``MISSION_ACK`` (accepted, or the error it was told to
give, or the error an item earned). It answers ``MAV_CMD_MISSION_START`` and
``MAV_CMD_DO_SET_MODE`` with ``COMMAND_ACK``, switches to AUTO, and, when told to fly, sends
``MISSION_CURRENT`` and then ``MISSION_ITEM_REACHED`` for each item at a fixed interval (switching
to ALT_HOLD at the end, as ArduSub does). ``MISSION_CLEAR_ALL`` clears the mission it holds
(acked accepted; refused with ``MAV_MISSION_ERROR`` while it flies it, as ArduPilot does). It
keeps what it received: :attr:`MissionPeer.missions`
(each a list of received items), :attr:`~MissionPeer.items` (the last one),
:attr:`~MissionPeer.acks_sent`, :attr:`~MissionPeer.counts` and :attr:`~MissionPeer.commands`.

As a program it prints one JSON line per received mission (and ``{"clear": true, ...}`` per
mission cleared)::

    python -m coex_plugins.autonomy.mavpeer --listen udpin:127.0.0.1:14551 [--fly 1.0]

In a test (a thread reading the socket; :meth:`MissionPeer.step` to drive it by hand)::

    with MissionPeer("udpin:127.0.0.1:14551", fly_interval=0.1) as peer:
        ...
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any

from .mavlink import (
    MAV_AUTOPILOT_ARDUPILOTMEGA,
    MAV_CMD_DO_CHANGE_SPEED,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_MISSION_START,
    MAV_CMD_NAV_WAYPOINT,
    MAV_MISSION_ACCEPTED,
    MAV_MISSION_INVALID_SEQUENCE,
    MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
    SUB_MODE_AUTO,
    connect,
    read,
)

__all__ = ["MissionPeer", "main"]

log = logging.getLogger(__name__)

MAV_TYPE_SUBMARINE = 12
MAV_STATE_ACTIVE = 4
MAV_MISSION_ERROR = 1
MAV_MISSION_UNSUPPORTED_FRAME = 2  # common.xml
MAV_MISSION_UNSUPPORTED = 3
MAV_RESULT_UNSUPPORTED = 3
SUB_MODE_ALT_HOLD = 2
MISSION_STATE_NOT_STARTED, MISSION_STATE_ACTIVE, MISSION_STATE_COMPLETE = 2, 3, 5


class MissionPeer:
    """The vehicle's side of the MAVLink mission protocol (module docstring).

    ``result``: the MISSION_ACK type for every upload (0 = accepted; e.g. 4 =
    ``MAV_MISSION_NO_SPACE`` refuses it at once); ``legacy``: request items with
    ``MISSION_REQUEST``; ``silent``: never answer (only count what arrives); ``frames`` /
    ``commands``: what an item may carry (otherwise ``MAV_MISSION_UNSUPPORTED_FRAME`` /
    ``MAV_MISSION_UNSUPPORTED``); ``start_result``: the COMMAND_ACK result of a start command
    (None: the start command is never answered nor obeyed); ``ack_start``: False starts the
    mission without sending the COMMAND_ACK (an ack lost on the way);
    ``fly_interval``: seconds between MISSION_ITEM_REACHED messages once started (None: stays at
    the first item); ``stop_after``: leave AUTO for ``stop_mode`` (ALT_HOLD: a pilot took over;
    SURFACE 9: a failsafe) after reaching this many items;
    ``drop_items``: how many received items to pretend were lost (the first ones), to exercise
    the sender's resends."""

    def __init__(self, listen: str, *, system: int = 1, component: int = 1, result: int = MAV_MISSION_ACCEPTED,
                 legacy: bool = False, silent: bool = False, frames: Sequence[int] = (0, 3, 6, 10, 11),
                 commands: Sequence[int] = (MAV_CMD_NAV_WAYPOINT, MAV_CMD_DO_CHANGE_SPEED),
                 start_result: int | None = 0, ack_start: bool = True,
                 fly_interval: float | None = None, stop_after: int | None = None,
                 stop_mode: int = 2, drop_items: int = 0,
                 heartbeat: float = 1.0, request_timeout: float = 1.0, on_mission: Any = None) -> None:
        self.conn = connect(listen, system, component)
        self.result, self.legacy, self.silent = int(result), bool(legacy), bool(silent)
        self.frames, self.commands = set(frames), set(commands)
        self.start_result = None if start_result is None else int(start_result)
        self.ack_start = bool(ack_start)
        self.fly_interval, self.stop_after, self.stop_mode = fly_interval, stop_after, int(stop_mode)
        self.drop_items = int(drop_items)
        self.heartbeat, self.request_timeout = float(heartbeat), float(request_timeout)
        self.on_mission = on_mission
        self.custom_mode = SUB_MODE_ALT_HOLD
        #: every mission received in full (a list of item dicts each)
        self.missions: list[list[dict[str, Any]]] = []
        #: the items of the mission received last (or being received)
        self.items: list[dict[str, Any]] = []
        #: (MISSION_ACK type) sent, in order
        self.acks_sent: list[int] = []
        #: MISSION_COUNT counts received, in order
        self.counts: list[int] = []
        #: (command, param1, param2) of every COMMAND_LONG received
        self.commands_received: list[tuple[int, float, float]] = []
        #: the request message type used (MISSION_REQUEST_INT or MISSION_REQUEST), one per request sent
        self.requests_sent: list[tuple[str, int]] = []
        self.reached: list[int] = []
        #: MISSION_CLEAR_ALL answers sent (0 cleared; 1 refused: it was flying the mission)
        self.clears: list[int] = []
        #: whether it holds a mission (received in full and not cleared since)
        self.mission_held = False
        self._count = 0
        self._peer: tuple[int, int] = (255, 0)
        self._receiving = False
        self._request_at = math.inf
        self._next_heartbeat = -math.inf
        self._flying = False
        self._next_reach = math.inf
        self._current = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ running it
    def __enter__(self) -> MissionPeer:
        self.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def start(self) -> None:
        """Run :meth:`step` in a background thread (the socket is polled every 5 ms)."""
        self._thread = threading.Thread(target=self._run, name="mavpeer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            self.step(time.monotonic())
            self._stop.wait(0.005)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
            self._thread = None
        self.conn.close()

    # ------------------------------------------------------------------ the protocol
    def step(self, now: float) -> None:
        """Handle what arrived, send what is due at ``now``."""
        with self._lock:
            if now >= self._next_heartbeat:
                self._next_heartbeat = now + self.heartbeat
                self._send("heartbeat", type=MAV_TYPE_SUBMARINE, autopilot=MAV_AUTOPILOT_ARDUPILOTMEGA,
                           base_mode=MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, custom_mode=self.custom_mode,
                           system_status=MAV_STATE_ACTIVE)
                if self.missions and self.mission_held:
                    state = (MISSION_STATE_ACTIVE if self._flying else
                             MISSION_STATE_COMPLETE if self.reached else MISSION_STATE_NOT_STARTED)
                    self._send("mission_current", seq=self._current, total=len(self.missions[-1]),
                               mission_state=state)
            for msg in read(self.conn):
                try:
                    self._handle(msg, now)
                except Exception as exc:
                    log.warning("mavpeer: ignored %s: %s", msg.get_type(), exc)
            if self._receiving and now >= self._request_at:
                self._request(len(self.items), now)  # the item did not come: ask again
            if self._flying and now >= self._next_reach:
                self._reach(now)

    def _send(self, name: str, **fields: Any) -> None:
        getattr(self.conn.mav, f"{name}_send")(**fields)

    def _handle(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        if kind in ("BAD_DATA", "HEARTBEAT"):
            return
        if getattr(msg, "target_system", None) not in (None, 0, self.conn.source_system):
            return
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if kind == "MISSION_COUNT":
            self.counts.append(int(msg.count))
            if self.silent:
                return
            self._peer, self._flying = src, False
            self.items, self._count = [], int(msg.count)
            if self.result != MAV_MISSION_ACCEPTED:
                self._ack(self.result)
                self._tell(self.result)
                return
            if self._count == 0:
                self._ack(MAV_MISSION_ACCEPTED)
                return
            self._receiving = True
            self._request(0, now)
        elif kind in ("MISSION_ITEM_INT", "MISSION_ITEM") and not self.silent:
            self._item(msg, now)
        elif kind == "COMMAND_LONG" and not self.silent:
            self._command(msg, src, now)
        elif kind == "MISSION_CLEAR_ALL" and not self.silent and getattr(msg, "mission_type", 0) == 0:
            self._peer = src
            if self._flying:  # ArduPilot does not clear the mission it flies
                self.clears.append(MAV_MISSION_ERROR)
                self._ack(MAV_MISSION_ERROR)
                return
            self.clears.append(MAV_MISSION_ACCEPTED)
            self.items, self._receiving, self._count = [], False, 0
            self.mission_held = False
            self._ack(MAV_MISSION_ACCEPTED)
            if self.on_mission is not None:
                self.on_mission({"clear": True, "result": MAV_MISSION_ACCEPTED, "count": 0, "items": []})

    def _request(self, seq: int, now: float) -> None:
        name = "mission_request" if self.legacy else "mission_request_int"
        self.requests_sent.append((name.upper(), seq))
        self._send(name, target_system=self._peer[0], target_component=self._peer[1], seq=seq, mission_type=0)
        self._request_at = now + self.request_timeout

    def _ack(self, result: int) -> None:
        self.acks_sent.append(result)
        self._send("mission_ack", target_system=self._peer[0], target_component=self._peer[1], type=result,
                   mission_type=0)

    def _item(self, msg: Any, now: float) -> None:
        if not self._receiving:
            return
        seq = int(msg.seq)
        if seq != len(self.items):  # ArduPilot: a NACK that does not end the upload
            self._ack(MAV_MISSION_INVALID_SEQUENCE)
            return
        if self.drop_items > 0:
            self.drop_items -= 1
            return
        item = {k: getattr(msg, k) for k in ("seq", "frame", "command", "current", "autocontinue", "param1",
                                             "param2", "param3", "param4", "x", "y", "z")}
        item["type"] = msg.get_type()
        problem = (MAV_MISSION_UNSUPPORTED_FRAME if item["frame"] not in self.frames else
                   MAV_MISSION_UNSUPPORTED if item["command"] not in self.commands else None)
        if problem is not None and seq > 0:  # the home item (seq 0) is not checked, as ArduPilot
            self._receiving = False
            self._ack(problem)
            self._tell(problem)
            return
        self.items.append(item)
        if len(self.items) < self._count:
            self._request(len(self.items), now)
            return
        self._receiving = False
        self._request_at = math.inf
        self.missions.append(list(self.items))
        self.mission_held = True
        self._current = self._first_nav(self.items)
        self.reached = []
        self._ack(MAV_MISSION_ACCEPTED)
        self._tell(MAV_MISSION_ACCEPTED)

    def _tell(self, result: int) -> None:
        if self.on_mission is not None:
            self.on_mission({"count": self._count, "result": result, "items": list(self.items)})

    def _command(self, msg: Any, src: tuple[int, int], now: float) -> None:
        cmd = int(msg.command)
        self.commands_received.append((cmd, float(msg.param1), float(msg.param2)))
        start = cmd == MAV_CMD_MISSION_START or (cmd == MAV_CMD_DO_SET_MODE and int(msg.param2) == SUB_MODE_AUTO)
        if start and self.start_result is None:
            return  # an autopilot that has stopped listening
        result = self.start_result if start and self.start_result is not None else MAV_RESULT_UNSUPPORTED
        if self.ack_start or not start:
            self._send("command_ack", command=cmd, result=result, target_system=src[0], target_component=src[1])
        if result == 0 and self.missions and self.mission_held:
            self.custom_mode = SUB_MODE_AUTO
            self._next_heartbeat = -math.inf  # tell the new mode at once
            if self.fly_interval is not None:
                self._flying = True
                self._current = self._first_nav(self.missions[-1])
                self._send("mission_current", seq=self._current, total=len(self.missions[-1]),
                           mission_state=MISSION_STATE_ACTIVE)
                self._next_reach = now + self.fly_interval

    @staticmethod
    def _first_nav(mission: list[dict[str, Any]]) -> int:
        """The first item flown to: the first NAV_WAYPOINT after home (seq 0)."""
        navs = [i for i, item in enumerate(mission) if i > 0 and item["command"] == MAV_CMD_NAV_WAYPOINT]
        return navs[0] if navs else 0

    def _reach(self, now: float) -> None:
        mission = self.missions[-1]
        seq = self._current
        self.reached.append(seq)
        self._send("mission_item_reached", seq=seq)
        # skip DO commands: the next item it flies to is the next NAV_WAYPOINT
        nxt = seq + 1
        while nxt < len(mission) and mission[nxt]["command"] != MAV_CMD_NAV_WAYPOINT:
            nxt += 1
        if nxt >= len(mission) or (self.stop_after is not None and len(self.reached) >= self.stop_after):
            self._flying = False
            self._next_reach = math.inf
            self.custom_mode = SUB_MODE_ALT_HOLD if nxt >= len(mission) else self.stop_mode
            self._next_heartbeat = -math.inf
            return
        self._current = nxt
        self._send("mission_current", seq=nxt, total=len(mission), mission_state=MISSION_STATE_ACTIVE)
        self._next_reach = now + (self.fly_interval or 0.0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="A MAVLink mission-protocol peer (the vehicle's side) "
                                                 "built from stock pymavlink.")
    parser.add_argument("--listen", required=True, help="pymavlink connection string, e.g. udpin:127.0.0.1:14551")
    parser.add_argument("--system", type=int, default=1)
    parser.add_argument("--component", type=int, default=1)
    parser.add_argument("--result", type=int, default=0, help="MISSION_ACK type to give (0 = accepted)")
    parser.add_argument("--legacy", action="store_true", help="request items with MISSION_REQUEST")
    parser.add_argument("--silent", action="store_true", help="never answer (an autopilot that is down)")
    parser.add_argument("--fly", type=float, default=None, metavar="SECONDS",
                        help="once started, reach one item every SECONDS")
    parser.add_argument("--heartbeat", type=float, default=1.0, help="seconds between HEARTBEATs")
    parser.add_argument("--duration", type=float, default=None, help="exit after this many seconds")
    args = parser.parse_args(argv)

    def printed(mission: dict[str, Any]) -> None:
        items = [{k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in item.items()}
                 for item in mission["items"]]
        print(json.dumps({**mission, "items": items}), flush=True)

    peer = MissionPeer(args.listen, system=args.system, component=args.component, result=args.result,
                       legacy=args.legacy, silent=args.silent, fly_interval=args.fly, heartbeat=args.heartbeat,
                       on_mission=printed)
    peer.start()
    try:
        if args.duration is None:
            while True:
                time.sleep(3600)
        time.sleep(args.duration)
    except KeyboardInterrupt:
        pass
    finally:
        peer.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
