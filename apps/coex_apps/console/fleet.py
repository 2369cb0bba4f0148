"""The console of a topside that talks to several vehicles (issue 43; ``[[vehicles]]`` in
``coex topside --config``, docs/console.md "A fleet").

One :class:`~.hub.ConsoleHub` per vehicle, each with its own :class:`~.state.ConsoleState` (the
vehicle's track, status, map, images, series, queues, commands, log) fed by that vehicle's
per-peer receivers (``Node.add_receiver(..., peer=id)``) and its messages, and with its own
:class:`~.node.NodeCommands` sending every command to that vehicle alone (``dst=id``; survey
and map requests go through the vehicle's own receivers, which send to it). The hubs share one
lock (the node is one). :class:`FleetHub` drains the node's events once per step and gives each
vehicle's state the events that are its own (a ``ProductUpdated`` of its receivers, a
``Received`` from it) and the network's (links, schedules, command results: a state only
follows the commands it sent); it keeps the fleet summary every page shows (``fleet``: each
vehicle's position, status age, link loss, queued bytes, open commands).

The server asks :meth:`FleetHub.view` for the vehicle a request names (``?vehicle=`` on the
page, the pictures and the event stream; the ``vehicle`` argument of ``POST /api/action``): an
unknown vehicle is refused with the reason, a fleet action without one too.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from coex import (
    CommandResult,
    CommandUnanswered,
    ConfigError,
    ProductUpdated,
    Received,
    RequestRejected,
)
from coex_plugins.bathymetry import BathymetryReceiver

from .hub import ConsoleHub, pump

__all__ = ["FleetHub", "VehicleView", "fleet_hub"]


def fleet_hub(node: Any, names: Mapping[int, str], clock: Callable[[], float], *,
              states: Mapping[int, Any] | None = None, stream_names: Mapping[int, str] | None = None,
              schedule: Any = None) -> FleetHub:
    """The console of a topside ``node`` that has per-peer receivers for the vehicles ``names``
    (id -> name, ``build_node`` of a ``[[vehicles]]`` configuration): one
    :class:`~.state.ConsoleState` per vehicle (``states``: the saved ones, by id) showing that
    vehicle's receivers, and one :class:`~.node.NodeCommands` per vehicle sending to it alone.
    The loop driving the node calls :meth:`FleetHub.pump` after each step."""
    from .node import NodeCommands
    from .state import ConsoleState

    hubs: dict[int, ConsoleHub] = {}
    for vid in names:
        own = {name: rx for name, rx in node.receivers() if _receiver_of(node, name, vid) is rx}
        state = (states or {}).get(vid)
        if not isinstance(state, ConsoleState):
            streams = {s.id: s.config.name for s in node.manager.streams}
            streams.update(stream_names or {})
            state = ConsoleState(node_id=node.node_id, vehicle_id=vid, stream_names=streams, receivers=own)
            for lid in node.manager.links:
                state.set_schedule(lid, schedule if schedule is not None else node.manager.schedule(lid))
        state.receivers = own  # the node's receivers are what the console shows
        state.own_receivers = False
        hub = ConsoleHub(state, NodeCommands(node, clock, dst=vid), clock)
        rx = own.get("bathymetry")
        if isinstance(rx, BathymetryReceiver):
            hub.actions.map_receiver = state.region_source = rx
        hubs[vid] = hub
    return FleetHub(hubs, names)


def _receiver_of(node: Any, name: str, peer: int) -> Any:
    """The node's receiver of modality ``name`` for vehicle ``peer`` (None: it has none)."""
    try:
        return node.receiver(name, peer)
    except ConfigError:
        return None


class FleetHub:
    """The consoles of the vehicles of one topside node (``hubs``: vehicle id -> its hub, in the
    order the page lists them; ``names``: vehicle id -> name)."""

    def __init__(self, hubs: Mapping[int, ConsoleHub], names: Mapping[int, str]) -> None:
        if not hubs:
            raise ValueError("a fleet console needs at least one vehicle")
        self.hubs = dict(hubs)
        self.names = {vid: str(names.get(vid, f"vehicle{vid}")) for vid in self.hubs}
        self.lock = threading.RLock()
        self.changed = threading.Condition(self.lock)
        for hub in self.hubs.values():  # one node, one lock: every vehicle's hub shares it
            hub.lock, hub.changed = self.lock, self.changed
        self.closed = False
        #: changes whenever the fleet summary does (the page's ``fleet`` section)
        self.version = 0
        self._summary: list[dict[str, Any]] = []
        self._peers: dict[int, dict[str, Any]] = {}
        self.attached_to: Any = None

    # ------------------------------------------------------------------ vehicles
    @property
    def first(self) -> int:
        return next(iter(self.hubs))

    def resolve(self, vehicle: Any) -> int:
        """The id of the vehicle ``vehicle`` names (its id, as a number or digits, or its
        name); :class:`RequestRejected` naming the fleet's vehicles otherwise."""
        known = ", ".join(f"{n} ({v})" for v, n in self.names.items())
        if isinstance(vehicle, bool) or not isinstance(vehicle, int | str):
            raise RequestRejected(f"vehicle is a vehicle's name or id (one of {known}), not {vehicle!r}")
        text = str(vehicle).strip()
        for vid, name in self.names.items():
            if text == name or text == str(vid):
                return vid
        raise RequestRejected(f"no vehicle {str(vehicle)[:40]!r} in this fleet (one of {known})")

    def view(self, vehicle: Any = None) -> VehicleView:
        """What the page of one vehicle shows (None: the first vehicle's)."""
        return VehicleView(self, self.first if vehicle is None else self.resolve(vehicle))

    @property
    def state(self) -> Any:
        """The first vehicle's state (what a caller that knows one vehicle sees)."""
        return self.hubs[self.first].state

    def states(self) -> dict[int, Any]:
        return {vid: hub.state for vid, hub in self.hubs.items()}

    # ------------------------------------------------------------------ from the runner
    def pump(self, node: Any, now: float, events: list[Any] | None = None) -> list[Any]:
        """As :meth:`ConsoleHub.pump`, for every vehicle: send the commands the pages queued,
        drain the node's events once (or take ``events``) and give each vehicle's console its
        own and the network's; refresh the fleet summary. Returns the events."""
        with self.changed:
            for hub in self.hubs.values():
                hub.actions.send.flush()
            if events is None:
                events = list(node.events())
            for vid, hub in self.hubs.items():
                pump(hub.state, node, now, [e for e in events if _concerns(e, vid)])
            self._refresh(node)
            self.changed.notify_all()
            return events

    def messages(self, msgs: Sequence[Any], now: float, link: int | None = None) -> None:
        """Messages about the topside's own modem (its receive statistics): every vehicle's."""
        for hub in self.hubs.values():
            hub.messages(msgs, now, link)

    def tick(self, now: float) -> None:
        for hub in self.hubs.values():
            hub.tick(now)

    def _refresh(self, node: Any) -> None:
        mgr = node.manager
        peers: dict[int, dict[int, Any]] = {}
        for link in mgr.links:
            for peer, info in (mgr.link_state(link).get("peers") or {}).items():
                peers.setdefault(int(peer), {})[int(link)] = info
        rows = []
        for vid, hub in self.hubs.items():
            st = hub.state
            s = st.status
            queued = sum(int(r.get("queued_bytes") or 0) for r in st.streams.values())
            open_cmds = sum(1 for c in st.commands.values() if c.status in ("sent", "queued", "pending"))
            links = {str(link): {"loss": _round(info.get("loss")), "last_heard": _round(info.get("last_heard"))}
                     for link, info in sorted(peers.get(vid, {}).items())}
            rows.append({
                "id": vid, "name": self.names[vid],
                "x": _round(s.x) if s else None, "y": _round(s.y) if s else None,
                "depth": _round(s.depth) if s else None, "mode": s.mode.name if s else None,
                "status_t": _round(st.status_t), "track": _track(st.track),
                "links": links, "queued_bytes": queued, "open_commands": open_cmds,
                "images": len(st.images), "ended": st.ended})
        if rows != self._summary:
            self._summary = rows
            self.version += 1

    def summary(self) -> list[dict[str, Any]]:
        """Every vehicle's line of the fleet strip (id, name, position, mode, status time, link
        loss and last heard per link, queued bytes, open commands, images) and its track
        (``[x, y]`` points, for the other vehicles' maps)."""
        with self.lock:
            return [dict(r) for r in self._summary] or [{"id": v, "name": n} for v, n in self.names.items()]

    # ---------------------------------------------------------------- from the browser
    def act(self, action: str, args: Mapping[str, Any], operator: str = "") -> list[Any]:
        """Run a page action for the vehicle its ``vehicle`` argument names (required)."""
        rest = dict(args)
        if "vehicle" not in rest:
            raise RequestRejected(f"{action} needs vehicle: this console has several "
                                  f"({', '.join(self.names.values())})")
        vid = self.resolve(rest.pop("vehicle"))
        return self.hubs[vid].act(action, rest, operator)

    def snapshot(self) -> dict[str, Any]:
        return self.view().snapshot()

    def close(self) -> None:
        with self.changed:
            self.closed = True
            for hub in self.hubs.values():
                hub.closed = True
            self.changed.notify_all()


class VehicleView:
    """One vehicle's page of a fleet console: its hub's state and actions, plus the ``fleet``
    section (every vehicle's summary, ``vehicle``: whose page this is). Has what the server
    uses of a :class:`ConsoleHub`."""

    def __init__(self, fleet: FleetHub, vehicle: int) -> None:
        self.fleet = fleet
        self.vehicle = vehicle
        self.hub = fleet.hubs[vehicle]
        self.lock = fleet.lock
        self.state = self.hub.state

    @property
    def closed(self) -> bool:
        return self.fleet.closed

    def _fleet(self) -> dict[str, Any]:
        return {"vehicle": self.vehicle, "name": self.fleet.names[self.vehicle],
                "vehicles": self.fleet.summary()}

    def snapshot(self) -> dict[str, Any]:
        with self.lock:
            out = self.hub.snapshot()
            out["fleet"] = self._fleet()
            return out

    def seen(self) -> dict[str, Any]:
        with self.lock:
            return {**self.hub.seen(), "_fleet": self.fleet.version}

    def changes_since(self, seen: dict[str, Any]) -> dict[str, Any]:
        with self.lock:
            out = self.hub.changes_since(seen)
            if seen.get("_fleet") != self.fleet.version:
                out["fleet"] = self._fleet()
                seen["_fleet"] = self.fleet.version
            return out

    def _dirty(self, seen: dict[str, Any]) -> bool:
        return self.hub._dirty(seen) or seen.get("_fleet") != self.fleet.version

    def act(self, action: str, args: Mapping[str, Any], operator: str = "") -> list[Any]:
        return self.fleet.act(action, args, operator)


def _concerns(event: Any, vehicle: int) -> bool:
    """Whether a node event belongs on ``vehicle``'s console: a product of another vehicle's
    receiver, a message from another node, or the answer of another vehicle (or the lack of
    one) does not; the network's events (links, schedules) do."""
    if isinstance(event, Received):
        return int(event.src) == vehicle
    if isinstance(event, ProductUpdated | CommandResult | CommandUnanswered):
        return event.peer in (None, 0, vehicle)
    return True


def _track(track: Any, most: int = 200) -> list[list[float]]:
    """A vehicle's track for the other vehicles' maps: at most ``most`` ``[x, y]`` points (every
    k-th and the newest)."""
    pts = [[round(float(x), 1), round(float(y), 1)] for _t, x, y, _d in list(track)]
    if len(pts) > most:
        k = -(-len(pts) // most)
        pts = [*pts[::k], pts[-1]]
    return pts


def _round(v: Any) -> Any:
    return None if v is None else round(float(v), 3)
