"""The console's shared state between the thread driving a topside node and the HTTP threads:
:class:`ConsoleHub` (a :class:`~.state.ConsoleState`, its actions and one lock) and
:func:`pump`, which moves a node's events into the state.

Module order (no cycles): ``render``, ``words`` <- ``state`` <- ``actions`` <- ``hub`` <- ``node``
(attach a node) <- ``server``.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

from coex import Message
from coex_plugins.bathymetry import BathymetryReceiver

from .actions import CommandSink, ConsoleActions
from .state import SECTIONS, ConsoleState

__all__ = ["ConsoleHub", "pump"]


def pump(state: ConsoleState, node: Any, now: float, events: list[Any] | None = None) -> int:
    """Apply the node's events (``node.events()``, or ``events`` when the caller drains the
    node itself) and refresh link/schedule state; returns the events applied."""
    if events is None:
        events = node.events()
    for e in events:
        try:
            state.apply_event(e)
        except Exception as exc:  # a display problem must never stop the node's loop
            state._log(now, f"console could not show {type(e).__name__}: {exc}", "warn",
                       key=f"could not show|{type(e).__name__}|{exc}")
    mgr = node.manager
    for link in mgr.links:
        info = mgr.link_state(link)
        lk = state._link(link)
        local = (info["enabled"], info["muted"], info["packets"], info["frames_rx"],
                 info["last_heard"])
        if lk.get("_local") != local:
            lk["_local"] = local
            lk.update(enabled=info["enabled"], muted=info["muted"], sent_packets=info["packets"],
                      frames_rx=info["frames_rx"], last_heard=info["last_heard"])
            state._touch("link")
        sch = mgr.schedule(link)
        known = state.schedules.get(link)
        key = (sch.version, sch.epoch, sch.first_cycle, len(sch.slots))
        if known is None or known.get("_key") != key:
            proposed = known.get("proposed") if known else None
            state.set_schedule(link, sch)
            state.schedules[link]["_key"] = key
            state.schedules[link]["proposed"] = proposed
    # regions asked of the bathymetry receiver by others (a script): show them too
    source = state.region_source
    if source is not None:
        others = [r for r in list(source.regions) if not r.auto and id(r) not in state._region_ids]
        if others:
            state.record_regions(others, now, "map level "
                                 + ",".join(sorted({str(r.level) for r in others}))
                                 + " (by the node)")
    # regions a bathymetry receiver sends for us: show when they go out (ids, retries)
    for r in state.roi.values():  # what the vehicle queued for it: filled, or nothing to send
        if r.region.queued:
            r.got = max(int(r.got or 0), int(r.region.queued))
    sig = tuple((k, r.region.request_id, r.region.sends, r.region.done, r.region.queued,
                 r.region.waiting) for k, r in state.roi.items())
    if sig != state._region_sig:
        state._region_sig = sig
        state._touch("map", "commands")
    # surveys the survey receiver follows: a new state, one given up, one asked by a script
    state.refresh_surveys()
    if now > state.now:
        state.now = float(now)
    return len(events)



class ConsoleHub:
    """A :class:`ConsoleState` and its :class:`ConsoleActions` shared by the runner thread and
    the HTTP threads: every change goes through :meth:`update` (under one lock) and wakes the
    event streams.

    ``send`` takes each command message (the topside node's send path); ``clock`` gives ``now``.
    """

    def __init__(self, state: ConsoleState, send: CommandSink | Callable[[Message], Any],
                 clock: Callable[[], float], *, map_receiver: BathymetryReceiver | None = None) -> None:
        self.state = state
        self.clock = clock
        self.lock = threading.RLock()
        self.changed = threading.Condition(self.lock)
        self.actions = ConsoleActions(state, send, clock, map_receiver=map_receiver)
        self.closed = False
        #: the topside node this hub watches (set by :func:`~.node.attach`), or None
        self.attached_to: Any = None

    # ------------------------------------------------------------------ from the runner
    def update(self, fn: Callable[[ConsoleState], Any]) -> Any:
        """Run ``fn(state)`` under the lock and wake every event stream."""
        with self.changed:
            result = fn(self.state)
            self.changed.notify_all()
            return result

    def messages(self, msgs: Iterable[Message], now: float, link: int | None = None) -> None:
        msgs = list(msgs)
        self.update(lambda s: s.apply_messages(msgs, now, link))

    def events(self, events: Iterable[Any]) -> None:
        events = list(events)
        self.update(lambda s: [s.apply_event(e) for e in events])

    def pump(self, node: Any, now: float, events: list[Any] | None = None) -> list[Any]:
        """Call it from the loop that drives a topside node, after each step: sends commands
        the page queued, applies the node's events (``node.events()``, or ``events`` drained by
        the caller) and refreshes link and schedule state. Returns the events."""
        with self.changed:
            self.actions.send.flush()
            before = dict(self.state.versions)
            wrapped = self.attached_to is node  # it feeds the hub itself
            if events is None:
                events = list(node.events())  # an attached node feeds the console itself
                if not wrapped:
                    pump(self.state, node, now, events)
            elif not wrapped:
                pump(self.state, node, now, events)
            pump(self.state, node, now, [])
            if before != self.state.versions:
                self.changed.notify_all()
            return events

    def tick(self, now: float) -> None:
        """Move the console's clock (ages, TDMA position)."""
        def go(s: ConsoleState) -> None:
            if now > s.now:
                s.now = float(now)
        with self.lock:
            go(self.state)

    # ---------------------------------------------------------------- from the browser
    def act(self, action: str, args: dict[str, Any], operator: str = "") -> list[Any]:
        """Run a page action; ``operator`` (the signed-in name) is recorded with its commands."""
        with self.changed:
            sent = self.actions.dispatch(action, args, operator)
            self.changed.notify_all()
            return sent

    def snapshot(self) -> dict[str, Any]:
        with self.lock:
            return self.state.snapshot()

    def seen(self) -> dict[str, Any]:
        """The section versions of a client that has just taken :meth:`snapshot`."""
        with self.lock:
            return dict(self.state.versions)

    def wait_changes(self, seen: dict[str, int], timeout: float,
                     coalesce: float = 0.0) -> dict[str, Any]:
        """Sections changed since ``seen`` (waits up to ``timeout`` s, then ``coalesce`` s more
        so that a burst of changes goes out as one update); updates ``seen``."""
        with self.changed:
            if not self._dirty(seen):
                self.changed.wait(timeout)
            if not self._dirty(seen):
                return {}
        if coalesce > 0:
            time.sleep(coalesce)
        return self.changes_since(seen)

    def changes_since(self, seen: dict[str, Any]) -> dict[str, Any]:
        """The sections changed since ``seen`` (no waiting); updates ``seen``."""
        with self.lock:
            out = self.state.changes(seen)
            seen.update({k: self.state.versions[k] for k in out})
            return out

    def _dirty(self, seen: dict[str, int]) -> bool:
        return any(seen.get(s) != self.state.versions[s] for s in SECTIONS)

    def close(self) -> None:
        with self.changed:
            self.closed = True
            self.changed.notify_all()
