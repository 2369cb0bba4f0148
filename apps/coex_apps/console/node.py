"""Glue between the console and a topside :class:`coex_core.node.Node`.

* :class:`NodeCommands` is the ``send`` of :class:`~.actions.ConsoleActions` for a node: command
  ids come from the node's channel manager (so its ``CommandResult`` events match), schedules go
  through ``propose_schedule`` (both ends switch on the announced cycle), everything else through
  ``node.request`` (control stream, acked, tracked until the vehicle's ``CommandAck``).
* :func:`attach` gives the console the node's receivers (what it shows comes from them and
  from the node's events: it decodes nothing itself).
* :func:`pump` moves what the node reported (``node.events()``, link state, schedules) into a
  :class:`~.state.ConsoleState`; the loop that drives the node calls it (via
  :meth:`ConsoleHub.pump <coex_apps.console.server.ConsoleHub.pump>`).

Not thread-safe by itself: call everything here with the hub's lock held (the node is not
thread-safe either).
"""

from __future__ import annotations

import warnings
from collections import deque
from collections.abc import Callable
from typing import Any

from coex import Event, ModalityReceiver
from coex.messages import Message, ScheduleUpdate
from coex_core.channel.schedule import Schedule, resolve_cycle
from coex_plugins.bathymetry import BathymetryReceiver

from .actions import CommandSink
from .hub import ConsoleHub, pump
from .state import ConsoleState

__all__ = ["NodeCommands", "attach", "drive_simulation", "pump", "tap_receiver"]


class NodeCommands(CommandSink):
    """Send console commands through a topside node (``clock()`` gives ``now``).

    With ``deferred``, a command is only queued when the page asks (from an HTTP thread) and
    reaches the node at the next :meth:`flush`, which the thread driving the node calls (through
    ``node.events()`` of an attached node, or :meth:`ConsoleHub.pump`): the node is never
    touched from two threads. ``on_sent(built, sent)`` hears when the node sent a different
    message than the one built (a schedule gets its command id from the channel manager)."""

    def __init__(self, node: Any, clock: Callable[[], float], *, deferred: bool = False,
                 on_sent: Callable[[Message, Message], Any] | None = None,
                 dst: int | None = None) -> None:
        self.node = node
        #: the node every command goes to (a fleet console: one vehicle's id); None: the
        #: link's peer
        self.dst = dst
        self.clock = clock
        self.deferred = deferred
        self.on_sent = on_sent
        self.sent: list[Message] = []
        self.pending: deque[Message] = deque()

    def next_command_id(self) -> int:
        return int(self.node.manager.next_command_id())

    def __call__(self, msg: Message) -> Message:
        if self.deferred:
            self.pending.append(msg)
            return msg
        return self._send(msg)

    def flush(self) -> int:
        """Send the queued commands (call it from the thread that drives the node)."""
        n = 0
        while self.pending:
            msg = self.pending.popleft()
            out = self._send(msg)
            n += 1
            if out is not msg and self.on_sent is not None:
                self.on_sent(msg, out)
        return n

    def _send(self, msg: Message) -> Message:
        now = self.clock()
        if isinstance(msg, ScheduleUpdate):
            current = self.node.manager.schedule(msg.link).cycle_at(now)
            cycle = resolve_cycle(msg.activate_cycle, current)
            out: Message = self.node.manager.propose_schedule(
                msg.link, Schedule.from_message(msg), now, cycle)
        elif self.dst is not None:
            self.node.request(msg, now, dst=self.dst)
            out = msg
        else:
            self.node.request(msg, now)
            out = msg
        self.sent.append(out)
        return out


def tap_receiver(receiver: ModalityReceiver, hub: Any = None) -> ModalityReceiver:
    """Deprecated (kept for one release): the console shows the node's receivers as they are
    (:func:`attach`, ``ConsoleState(receivers=...)``), so nothing needs wrapping. Returns
    ``receiver`` unchanged."""
    warnings.warn("tap_receiver is deprecated: the console shows the node's receivers as they "
                  "are (attach(node), ConsoleState(receivers=...))", DeprecationWarning,
                  stacklevel=2)
    return receiver


def attach(node: Any, clock: Callable[[], float] | None = None, *,
           map_receiver: BathymetryReceiver | None = None, stream_names: dict[int, str] | None = None) -> Any:
    """A :class:`~coex_apps.console.server.ConsoleHub` fed by a topside ``node``, whatever
    loop drives it.

    * The hub subscribes to the node's events (:meth:`Node.subscribe
      <coex_core.node.Node.subscribe>`): whoever drains them (a runner, the demo) also feeds the
      console.
    * Commands from the page are queued (:class:`NodeCommands` with ``deferred``) and sent
      during that same ``node.events()`` call, in the thread driving the node.
    * The console shows the node's receivers (products from ``ProductUpdated`` events, and what
      the receivers hold: subgrid stamps and ages, image bytes); the bathymetry receiver is the
      map-region path unless ``map_receiver`` is given. Modalities without a panel of their own
      go to the generic panel.

    ``clock`` (``now`` of commands) defaults to the newest event time the console has seen."""
    mgr = node.manager
    names = {q.id: q.config.name for q in mgr.streams}
    names.update(stream_names or {})
    receivers = dict(node.receivers())
    state = ConsoleState(node_id=node.node_id, stream_names=names,
                         schedules={link: mgr.schedule(link) for link in mgr.links},
                         receivers=receivers)
    now_of = clock or (lambda: state.now)
    commands = NodeCommands(node, now_of, deferred=True)
    hub = ConsoleHub(state, commands, now_of, map_receiver=map_receiver)
    commands.on_sent = lambda built, sent: hub.update(
        lambda st: st.replace_command(built, sent, now_of()))
    if map_receiver is None:
        bathymetry = receivers.get("bathymetry")
        hub.actions.map_receiver = bathymetry if isinstance(bathymetry, BathymetryReceiver) else None
    state.region_source = hub.actions.map_receiver

    def on_events(evs: list[Event]) -> None:
        commands.flush()  # the page's commands go out from the thread driving the node
        now = max((float(e.time) for e in evs), default=state.now)
        hub.update(lambda st: pump(st, node, now, evs))

    node.subscribe(on_events)
    hub.attached_to = node
    return hub


def drive_simulation(net: Any, node: Any, hub: Any, until: float, *, speed: float | None = None,
                     step: float = 1.0, stop: Callable[[], bool] | None = None,
                     on_events: Callable[[list[Any]], Any] | None = None) -> None:
    """Run a :class:`~coex.SimNetwork` to ``until`` with a live console.

    The network advances ``step`` simulated seconds at a time under ``hub.lock`` (operator
    actions from the page reach the node between steps); after each step the topside ``node``'s
    events go to the console (and to ``on_events`` when given, for a caller that also needs
    them). ``speed`` (simulated seconds per wall-clock second) paces the run; ``None`` runs as
    fast as possible. ``stop()`` ends it early."""
    import time

    wall0, sim0 = time.monotonic(), float(net.now)
    while net.now < until and not (stop is not None and stop()):
        with hub.lock:
            net.run(min(until, net.now + step))
            events = hub.pump(node, net.now)
            if on_events is not None:
                on_events(events)
        if speed:
            ahead = (net.now - sim0) / speed - (time.monotonic() - wall0)
            if ahead > 0:
                time.sleep(ahead)
