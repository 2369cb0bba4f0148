"""The event loops: the only place that drives sans-I/O :class:`~coex_core.node.Node` objects
with real time, real transports, or a simulated clock.

* :class:`Runner` drives one node over real :class:`~coex_core.transport.Transport` objects
  (one per link id) with a :class:`RealClock` (``time.time`` by default, since TDMA slots come
  from an epoch every node shares; pass ``time.monotonic`` for a free-running test) or a
  :class:`SimulatedClock`.
* :class:`SimNetwork` drives several nodes over simulated
  :class:`~coex_core.acoustic.AcousticChannel` links (one channel per link id) with a clock that
  jumps from event to event (packet ends, transmit opportunities, scheduled callbacks), so a
  two-hour dive replays in seconds. It writes the link log (JSON lines) if given a file.

Each packet goes to its transport whole (``Transport.send_packet``: a modem sends a packet's
frames together). A link that is down for now (:class:`~coex_core.errors.LinkDown`, from a
:class:`~coex_transports.recovery.ResilientTransport`) is counted in :attr:`Runner.not_sent`,
not logged, and given back to the node (``Node.not_sent``: not an acoustic loss, sent again); any other transport error is logged once and then counted while it repeats. With
``settings_path`` the runner loads the node's operator settings (stream settings, links,
schedules) at start and writes them whenever they change, so they survive a restart.

With a store, a write the store refuses (a full disk, a read-only or damaged file:
:class:`~coex_runtime.store.StoreError`) never stops the loop: a received frame is still given
to the node, a packet still goes out, the snapshot is tried again at the next transmission;
the problem is reported once when it starts (``on_error``) and once when the store writes
again, and :attr:`Runner.store_problem` holds it meanwhile. :meth:`Runner.ingest` raises it
(the input is not taken: the caller decides what to keep).

:class:`Runner` is the one loop for every program that drives a node over transports: ``coex
topside`` (the console) uses it with its hooks (``lock``: the console's lock held around each
step; ``after_step``: move events to the console; ``snapshot_due``: save the store after an
operator's command), and so can an integrator's program.
"""

from __future__ import annotations

import collections
import contextlib
import heapq
import itertools
import json
import os
import signal
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol, TextIO

from coex_core.acoustic import AcousticChannel
from coex_core.channel.linklog import to_json_line
from coex_core.channel.manager import Transmission
from coex_core.errors import CoexError, ConfigError, LinkDown, TransportError
from coex_core.loopback import SimClock
from coex_core.node import Node
from coex_core.transport import Transport

from .store import NodeStore, StoreError

__all__ = ["Clock", "RealClock", "Runner", "SimNetwork", "SimulatedClock", "next_wakeup", "sigterm_as_interrupt"]


class Clock(Protocol):
    def time(self) -> float: ...

    def wait_until(self, t: float) -> None: ...


class RealClock:
    """Wall-clock time (``time.time`` unless another source is given); waiting sleeps.

    With ``speed`` and ``at=(wall, reading)`` it is a faster clock (a dive replayed on real
    transports): it reads ``reading`` when the source reads ``wall`` and runs ``speed`` times
    as fast."""

    def __init__(self, source: Callable[[], float] = time.time, *, speed: float = 1.0,
                 at: tuple[float, float] | None = None) -> None:
        if speed <= 0:
            raise ConfigError("speed must be positive")
        self.source = source
        self.speed = float(speed)
        self.at = at

    def time(self) -> float:
        if self.at is None and self.speed == 1.0:
            return self.source()
        wall, reading = self.at or (0.0, 0.0)
        return reading + (self.source() - wall) * self.speed

    def wall_seconds(self, dt: float) -> float:
        """The wall-clock seconds ``dt`` seconds of this clock take."""
        return dt / self.speed

    def wait_until(self, t: float) -> None:
        dt = self.wall_seconds(t - self.time())
        if dt > 0:
            time.sleep(dt)


class SimulatedClock:
    """Simulated time: waiting jumps straight to the requested time (shares a
    :class:`~coex_core.loopback.SimClock` so loopback links and nodes agree)."""

    def __init__(self, start: float = 0.0, sim: SimClock | None = None) -> None:
        self.sim = sim or SimClock(start)

    def time(self) -> float:
        return self.sim.now

    def wait_until(self, t: float) -> None:
        self.sim.advance_to(t)


def next_wakeup(now: float, until: float, timer: float | None, sources: Iterable[float | None], *,
                started: bool) -> float:
    """When a hand-driven simulation loop (modems, drivers and nodes on one simulated clock)
    should step next: the earliest of ``until``, the next ``timer`` and every source's next
    event (None: none), never in the past; once the loop has ``started``, a millisecond later
    when nothing is due now, so that it always advances."""
    cands = [until, *(t for t in (timer, *sources) if t is not None)]
    t = max(min(cands), now)
    if t == now and started and not (timer is not None and timer <= now):
        t = now + 1e-3
    return t


def _write(sink: TextIO | Callable[[dict[str, Any]], None] | None, rec: dict[str, Any]) -> None:
    if sink is None:
        return
    if callable(sink):
        sink(rec)
    else:
        sink.write(to_json_line(rec))


def _send(transport: Transport, tx: Transmission) -> None:
    transport.send_packet(list(tx.frames), tx.rate)


#: an error repeated within this many seconds is counted, not reported again
REPEAT_WINDOW = 60.0
#: seconds (of the runner's clock) a store that refused a write must take every write before
#: :attr:`Runner.store_problem` clears and the runner says it writes again
STORE_RECOVERY = 30.0


class Runner:
    """Drives one node over real transports (``transports[link_id]``)."""

    def __init__(
        self,
        node: Node,
        transports: Mapping[int, Transport],
        clock: Clock | None = None,
        *,
        link_log: TextIO | Callable[[dict[str, Any]], None] | None = None,
        max_wait: float = 0.2,
        settings_path: str | Path | None = None,
        store: NodeStore | None = None,
        lock: contextlib.AbstractContextManager[Any] | None = None,
        after_step: Sequence[Callable[[float], Any]] = (),
        before_step: Sequence[Callable[[float], Any]] = (),
        snapshot_due: Callable[[], bool] | None = None,
        on_error: Callable[[str], Any] | None = None,
    ) -> None:
        unknown = set(transports) - set(node.manager.links)
        if unknown:
            raise ConfigError(f"transports for unknown links {sorted(unknown)}")
        self.settings_path = Path(settings_path) if settings_path is not None else None
        self._saved: dict[str, Any] | None = None
        if self.settings_path is not None and self.settings_path.exists():
            try:
                saved = json.loads(self.settings_path.read_text())
            except (OSError, ValueError) as exc:
                raise ConfigError(f"cannot read settings {self.settings_path}: {exc}") from exc
            node.manager.import_settings(saved)
            self._saved = saved
        self.node = node
        #: with a :class:`~coex_runtime.store.NodeStore`: every received frame and ingested
        #: input is journaled, the node's state is saved before every transmission (restore
        #: the node with ``store.restore(build)`` before making the runner)
        self.store = store
        self.transports = dict(transports)
        self.clock: Clock = clock or RealClock()
        self.link_log = link_log
        self.max_wait = max_wait
        #: held around each step and each received frame (a console's lock: nothing else
        #: touches the node meanwhile)
        self.lock: contextlib.AbstractContextManager[Any] = lock if lock is not None else contextlib.nullcontext()
        #: called with ``now`` at the end of every step, under :attr:`lock` (a hook that
        #: raises is recorded in :attr:`errors`; the loop goes on)
        self.after_step: list[Callable[[float], Any]] = list(after_step)
        #: called by :meth:`run` with ``now`` before every step, outside :attr:`lock` (a hook
        #: may :meth:`ingest` what is due: a sensor log replayed); one that raises is recorded
        #: in :attr:`errors` and the loop goes on
        self.before_step: list[Callable[[float], Any]] = list(before_step)
        #: with a store: ``snapshot_due()`` true saves the node at once (an operator command)
        self.snapshot_due = snapshot_due
        self.on_error = on_error
        #: The last 100 transport errors (the loop never stops for one); ``error_count`` counts all.
        self.errors: collections.deque[str] = collections.deque(maxlen=100)
        self.error_count = 0
        #: frames not sent because their link was down for now (per link id)
        self.not_sent: dict[int, int] = {}
        self._repeat: tuple[str, float, int] | None = None  # (text, first seen, repeats since)
        #: the store's problem as last reported (None: it keeps everything)
        self.store_problem: StoreError | None = None
        self._store_failed = self._store_failed_seen = 0
        self._store_ok_since: float | None = None

    def _error(self, text: str) -> None:
        """Record an error; the same text again within :data:`REPEAT_WINDOW` seconds is counted,
        and reported once as "(repeated N times)" when something else happens or the window ends."""
        self.error_count += 1
        now = time.monotonic()
        rep = self._repeat
        if rep is not None and rep[0] == text and now - rep[1] < REPEAT_WINDOW:
            self._repeat = (text, rep[1], rep[2] + 1)
            return
        if rep is not None and rep[2]:
            self._report(f"{rep[0]} (repeated {rep[2]} times in {now - rep[1]:.0f} s)")
        self._repeat = (text, now, 0)
        self._report(text)

    def _report(self, text: str) -> None:
        self.errors.append(text)
        if self.on_error is not None:
            try:
                self.on_error(text)
            except Exception:  # reporting an error must not become one
                pass

    def step(self) -> float:
        """Receive everything waiting, poll the node, send its packets, run the
        :attr:`after_step` hooks; returns the time the node next needs attention."""
        with self.lock:
            return self._step()

    def _snapshot(self, now: float, force: bool) -> None:
        assert self.store is not None
        if self.snapshot_due is not None and self.snapshot_due():
            force = True
        try:
            self.store.maybe_snapshot(self.node, now, force=force)
        except StoreError:
            pass  # a full disk must not stop the node: told once (_watch_store)
        except Exception as exc:
            self._error(f"store: {exc}")

    def _watch_store(self) -> None:
        """Report the store's problem when it starts or changes kind, and when it is over: after
        :data:`STORE_RECOVERY` seconds without a refused write (a nearly full disk that takes
        one snapshot in freed pages and refuses the next is not "writing again")."""
        if self.store is None:
            return
        p, was = self.store.problem, self.store_problem
        if p is not None:
            self._store_ok_since = None
            if was is None or p.kind != was.kind:
                self._store_failed = self.store.stats["failed"]
                self._report(f"store: {p}")
            self.store_problem = p
            return
        if was is None:
            return
        now = self.clock.time()
        if self._store_ok_since is None or self.store.stats["failed"] != self._store_failed_seen:
            self._store_ok_since, self._store_failed_seen = now, self.store.stats["failed"]
            return
        if now - self._store_ok_since < STORE_RECOVERY:
            return
        refused = self.store.stats["failed"] - self._store_failed + 1
        self._report(f"store {self.store.path}: writing again ({refused} write{'s' if refused != 1 else ''} "
                     "refused meanwhile; what comes from now on is kept)")
        self.store_problem = None
        self._store_ok_since = None

    def _step(self) -> float:
        now = self.clock.time()
        for link, tr in self.transports.items():
            while True:
                try:
                    frame = tr.recv(timeout=0)
                except TransportError as exc:
                    self._error(f"link {link} receive: {exc}")
                    break
                if frame is None:
                    break
                self._receive(link, frame)
        now = self.clock.time()
        txs = self.node.poll(now)
        if self.store is not None:
            for tx in txs:
                for f in tx.frames:
                    if self.store.journal_tx:
                        with contextlib.suppress(StoreError):  # a record: the packet goes anyway
                            self.store.record_tx(tx.link_id, f, now)
            # what leaves now is marked sent in the saved state before it leaves
            self._snapshot(now, bool(txs))
        for tx in txs:
            out = self.transports.get(tx.link_id)
            if out is None:
                continue
            try:
                _send(out, tx)
            except LinkDown:
                self.not_sent[tx.link_id] = self.not_sent.get(tx.link_id, 0) + len(tx.frames)
                self.node.not_sent(tx, now)  # sent again once the link is back, not after a timeout
            except CoexError as exc:
                self._error(f"link {tx.link_id} send: {exc}")
            _write(self.link_log, {
                "time": round(now, 6), "link": tx.link_id, "slot": tx.slot, "src": self.node.node_id,
                "dst": None, "rate": tx.rate, "frames": len(tx.frames), "capacity_bytes": tx.capacity,
                "used_bytes": tx.used, "delivered": None, "lost": None, "cause": "sent",
                "spare_bytes": tx.spare, "redundant_bytes": tx.redundant, "backlog_bytes": tx.backlog,
            })
        self.save_settings()
        for hook in self.after_step:
            try:
                hook(self.clock.time())
            except Exception as exc:
                self._error(f"after_step {getattr(hook, '__name__', hook)}: {exc}")
        if self.store is not None and self.snapshot_due is not None:
            self._snapshot(self.clock.time(), False)
        self._watch_store()
        nxt = self.node.next_event(self.clock.time())
        return nxt if nxt is not None else self.clock.time() + self.max_wait

    def _receive(self, link: int, frame: bytes) -> None:
        now = self.clock.time()
        if self.store is not None:
            try:
                self.store.record_rx(link, frame, now)  # committed before the node sees it
            except StoreError:
                pass  # not kept across a restart, but the node hears it (commands run)
        self.node.receive(link, frame, now)

    def receive(self, link: int, frame: bytes) -> None:
        """Give the node one frame that arrived on ``link`` now (journaled first with a
        store), under :attr:`lock`."""
        with self.lock:
            self._receive(link, frame)

    def ingest(self, name: str, data: Any, *, mark: str | None = None) -> None:
        """Give sensor data to the sender of modality ``name`` now (journaled first with a
        store, so a restart does not lose it). ``mark``: a key the store sets in the journal
        row's transaction (:meth:`NodeStore.record_input <coex_runtime.store.NodeStore.record_input>`:
        the application's record that it took this input). A
        :class:`~coex_runtime.store.StoreError` (the store cannot journal it) reaches the
        caller and the sender does not take the input."""
        with self.lock:
            now = self.clock.time()
            sender = self.node.sender(name)
            if self.store is not None:
                data = sender.journal_form(data)
                self.store.record_input(name, data, now, mark=mark)
            sender.ingest(data, now)

    def save_settings(self) -> bool:
        """Write the node's operator settings to ``settings_path`` when they changed (atomic
        replace), so they survive a restart. Returns whether a file was written."""
        if self.settings_path is None:
            return False
        current = json.loads(json.dumps(self.node.manager.export_settings()))
        if current == self._saved:
            return False
        tmp = self.settings_path.with_name(self.settings_path.name + ".tmp")
        try:
            tmp.write_text(json.dumps(current, indent=1, sort_keys=True))
            os.replace(tmp, self.settings_path)
        except OSError as exc:
            self._error(f"cannot save settings: {exc}")
            return False
        self._saved = current
        return True

    def run(self, *, until: float | None = None, duration: float | None = None,
            stop: Callable[[], bool] | None = None) -> None:
        """Loop until ``until`` (clock time), for ``duration`` seconds, or until ``stop()``."""
        end = until if until is not None else (
            self.clock.time() + duration if duration is not None else float("inf"))
        while self.clock.time() < end and not (stop is not None and stop()):
            for hook in self.before_step:
                try:
                    hook(self.clock.time())
                except Exception as exc:
                    self._error(f"before_step {getattr(hook, '__name__', hook)}: {exc}")
            nxt = self.step()
            wake = min(nxt, end, self.clock.time() + self.max_wait)
            if len(self.transports) == 1 and isinstance(self.clock, RealClock):
                # block in the transport's receive until a frame comes or it is time to poll
                (link, tr), = self.transports.items()
                left = self.clock.wall_seconds(wake - self.clock.time())
                if left > 0:
                    try:
                        frame = tr.recv(timeout=left)
                    except TransportError as exc:
                        self._error(f"link {link} receive: {exc}")
                        self.clock.wait_until(wake)  # do not spin on a broken transport
                        frame = None
                    if frame is not None:
                        self.receive(link, frame)
                        continue
                    if wake - self.clock.time() > 0:
                        # a transport that does not really block (a simulated link) must not
                        # make the loop spin
                        self.clock.wait_until(wake)
                continue
            self.clock.wait_until(wake)


class SimNetwork:
    """Several nodes over simulated acoustic channels, on a jumping simulated clock."""

    def __init__(
        self,
        channels: Mapping[int, AcousticChannel],
        clock: SimulatedClock | None = None,
        *,
        link_log: TextIO | Callable[[dict[str, Any]], None] | None = None,
        keep_transmissions: int | None = None,
    ) -> None:
        self.channels = dict(channels)
        for link, ch in self.channels.items():
            ch.link = link
        self.clock = clock or SimulatedClock()
        self.link_log = link_log
        self.nodes: dict[int, Node] = {}
        self._timers: list[tuple[float, int, Callable[[float], None]]] = []
        self._count = itertools.count()
        #: ``(node id, Transmission)`` of every packet sent, oldest first (for tests and
        #: reports); with ``keep_transmissions`` only that many of the newest (long runs).
        self.transmissions: collections.deque[tuple[int, Transmission]] = collections.deque(
            maxlen=keep_transmissions)
        self.on_transmit: Callable[[int, Transmission], None] | None = None
        self._last_step = float("-inf")

    @property
    def now(self) -> float:
        return self.clock.time()

    def add_node(self, node: Node, position: Sequence[float] = (0.0, 0.0, 0.0)) -> None:
        if node.node_id in self.nodes:
            raise ConfigError(f"node {node.node_id} added twice")
        self.nodes[node.node_id] = node
        for ch in self.channels.values():
            ch.set_position(node.node_id, position)

    def move(self, node_id: int, position: Sequence[float]) -> None:
        for ch in self.channels.values():
            ch.set_position(node_id, position)

    def at(self, t: float, fn: Callable[[float], None]) -> None:
        """Call ``fn(now)`` at simulated time ``t`` (sensor data, operator actions ...)."""
        heapq.heappush(self._timers, (t, next(self._count), fn))

    def every(self, period: float, fn: Callable[[float], None], start: float | None = None) -> None:
        """Call ``fn(now)`` every ``period`` seconds from ``start`` (default: now)."""
        if period <= 0:
            raise ConfigError("period must be positive")

        def tick(now: float) -> None:
            fn(now)
            self.at(now + period, tick)

        self.at(self.now if start is None else start, tick)

    def _next_time(self) -> float | None:
        times: list[float] = []
        if self._timers:
            times.append(self._timers[0][0])
        for ch in self.channels.values():
            t = ch.next_arrival()
            if t is not None:
                times.append(t)
        now = self.now
        for node in self.nodes.values():
            t = node.next_event(now)
            if t is not None:
                # a node already polled at this instant gets its next look a moment later
                times.append(t if t > self._last_step else self._last_step + 1e-3)
        return min(times) if times else None

    def step(self, until: float) -> bool:
        """Advance to the next event (not past ``until``) and handle it. Returns False when
        ``until`` is reached."""
        t = self._next_time()
        if t is None or t > until:
            self.clock.wait_until(until)
            return False
        self.clock.wait_until(max(t, self.now))
        now = self.now
        self._last_step = now
        while self._timers and self._timers[0][0] <= now:
            _, _, fn = heapq.heappop(self._timers)
            fn(now)
        for link, ch in self.channels.items():
            for arrival in ch.poll(now):
                node = self.nodes.get(arrival.dst)
                if node is None:
                    continue
                for frame in arrival.frames:
                    if frame is not None:
                        node.receive(link, frame, now)
            for rec in ch.log():
                _write(self.link_log, rec)
        for node_id in sorted(self.nodes):
            node = self.nodes[node_id]
            for tx in node.poll(now):
                target = self.channels.get(tx.link_id)
                if target is None:
                    continue
                target.transmit(node_id, list(tx.frames), tx.rate, now, slot=tx.slot)
                self.transmissions.append((node_id, tx))
                if self.on_transmit is not None:
                    self.on_transmit(node_id, tx)
        return True

    def run(self, until: float, *, max_steps: int | None = None) -> int:
        """Run until simulated time ``until``; returns the number of steps taken."""
        steps = 0
        while self.step(until):
            steps += 1
            if max_steps is not None and steps >= max_steps:
                break
        return steps


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Inside the block SIGTERM raises :class:`KeyboardInterrupt`, so a daemon stopped by its
    service manager stops as on Ctrl-C: cleanly, its store saved. The previous handler is put back
    on leaving (main thread only, as for any signal handler)."""
    def terminate(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
