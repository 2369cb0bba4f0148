"""Simulated modems on one acoustic channel in simulated time (:class:`ModemNetwork`, its
:class:`NetworkClock`) and the loop that drives real runners over them (:class:`SimLoop`); see
:mod:`.simulator`."""

from __future__ import annotations

import contextlib
import functools
import heapq
import itertools
import os
import select
import time
import tty
from collections.abc import Callable, Sequence
from typing import Any

from coex_core.acoustic import RATES as AIR_RATES
from coex_core.acoustic import AcousticChannel, Arrival
from coex_core.errors import ConfigError, TransportError
from coex_core.loopback import SimClock

from .simmodem import SimulatedModem, _Meta

__all__ = ['ModemNetwork', 'NetworkClock', 'SimLoop']

class _Host:
    """An in-process host (driver) wired to a simulated modem's serial port: directly, or through
    a real pseudo-terminal pair (``pty=True``: the driver's bytes are written to the terminal
    side and read by the modem from the master side, and back, in the caller's thread)."""

    def __init__(self, driver: Any, modem: SimulatedModem, pty: bool = False) -> None:
        self.driver = driver
        self.modem = modem
        self.master: int | None = None
        self.slave: int | None = None
        self.path = ""
        if pty:
            self.master, self.slave = os.openpty()
            tty.setraw(self.slave)
            os.set_blocking(self.master, False)
            os.set_blocking(self.slave, False)
            self.path = os.ttyname(self.slave)

    @staticmethod
    def _pipe(src: int, dst: int, data: bytes, timeout: float = 10.0) -> bytes:
        """Write ``data`` into ``src`` and return it as it comes out at ``dst``: all of it (a raw
        terminal passes bytes one for one), however late the kernel moves it across: a read that
        finds the terminal empty waits for the rest instead of leaving it for a later call, so a
        loaded machine runs the same dive as an idle one. OSError when it does not come out."""
        got = bytearray()
        view = memoryview(data)
        poller = select.poll()
        poller.register(dst, select.POLLIN)
        deadline = time.monotonic() + timeout
        while len(got) < len(data):
            if view:
                try:
                    n = os.write(src, view[:1024])
                    view = view[n:]
                except BlockingIOError:
                    pass
            try:
                got += os.read(dst, 4096)
                continue
            except BlockingIOError:
                pass
            left = deadline - time.monotonic()
            if left <= 0:
                raise OSError(f"pseudo-terminal: {len(got)} of {len(data)} bytes came through in {timeout:g} s")
            poller.poll(min(left, 0.05 if view else left) * 1000.0)
        return bytes(got)

    def to_modem(self, data: bytes) -> bytes:
        if self.master is None or self.slave is None:
            return data
        return self._pipe(self.slave, self.master, data)

    def to_host(self, data: bytes) -> bytes:
        if self.master is None or self.slave is None:
            return data
        return self._pipe(self.master, self.slave, data)

    def close(self) -> None:
        for fd in (self.master, self.slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.master = self.slave = None


class ModemNetwork:
    """Simulated modems on one acoustic channel, run on a simulated clock.

    ``positions`` maps node id → (x, y, z) metres; each node gets a :class:`SimulatedModem`
    whose SRC is the node id. Time is POSIX seconds on ``clock`` (default start: 2025-01-01).
    """

    def __init__(
        self,
        positions: dict[int, Sequence[float]] | None = None,
        *,
        channel: AcousticChannel | None = None,
        clock: SimClock | None = None,
        snr: float = 15.0,
        doppler: float = 0.0,
        ptys: bool = False,
    ) -> None:
        #: with ``ptys``, every in-process host talks to its modem through a real pseudo-terminal
        self.ptys = ptys
        self.channel = channel or AcousticChannel()
        self.clock = clock or SimClock(1735689600.0)
        self.modems: dict[int, SimulatedModem] = {}
        #: modems whose serial cable is pulled (:meth:`unplug`)
        self.unplugged: set[int] = set()
        self._hosts: list[_Host] = []
        self._meta: list[tuple[int, float, _Meta]] = []
        positions = positions if positions is not None else {1: (0.0, 0.0, 0.0), 2: (1000.0, 0.0, 0.0)}
        for node, xyz in positions.items():
            self.add_modem(node, xyz, snr=snr, doppler=doppler)

    @property
    def now(self) -> float:
        return self.clock.now

    def add_modem(self, node: int, xyz: Sequence[float], *, snr: float = 15.0, doppler: float = 0.0) -> SimulatedModem:
        if node in self.modems:
            raise ConfigError(f"node {node} already has a modem")
        if not 1 <= node <= 127:
            raise ConfigError(f"node ids are 1..127, got {node}")
        self.channel.set_position(node, xyz)
        modem = SimulatedModem(node, self, snr=snr, doppler=doppler)
        self.modems[node] = modem
        return modem

    def attach(self, node: int, driver: Any) -> None:
        """Wire an in-process host driver (``feed``/``poll``/``data_to_send``/``next_deadline``) to
        ``node``'s modem. :class:`TransportError` while that modem is unplugged (:meth:`unplug`)."""
        if node in self.unplugged:
            raise TransportError(f"cannot open simulated modem {node}: its cable is unplugged")
        if any(h.modem.node == node for h in self._hosts):
            raise ConfigError(f"modem {node} already has a host")
        self._hosts.append(_Host(driver, self.modems[node], pty=self.ptys))
        self.modems[node].orphan = False

    def detach(self, driver: Any) -> None:
        """Unwire a host driver (its modem's output is then discarded)."""
        for h in list(self._hosts):
            if h.driver is driver:
                self._hosts.remove(h)
                h.modem.orphan = True

    def attached(self, driver: Any) -> bool:
        """Whether ``driver`` is wired to its modem (not detached, its cable not pulled)."""
        return any(h.driver is driver for h in self._hosts)

    def unplug(self, node: int) -> None:
        """Pull the serial cable of ``node``'s modem (a USB adapter unplugged, a serial-over-IP
        server gone): the host's transport raises :class:`TransportError` at its next use and
        stays dead, like a real port, and a new one cannot be opened until :meth:`plug`. The
        modem itself keeps its power and settings; what it receives meanwhile is lost."""
        self.unplugged.add(node)
        for h in list(self._hosts):
            if h.modem.node == node:
                self._hosts.remove(h)
                h.close()
                h.modem.orphan = True

    def plug(self, node: int) -> None:
        """Put ``node``'s serial cable back: a transport can be opened on its modem again."""
        self.unplugged.discard(node)

    def open_uri(self, uri: str) -> Any:
        """A ``micromodem:`` URI opened on this network instead of a serial port: the driver, with
        the URI's options, on the simulated modem of its ``src`` (the device path is only a
        name). An opener for :class:`~coex_transports.recovery.ResilientTransport`."""
        import dataclasses

        from .transport import MicromodemTransport, parse_uri

        _, _, config = parse_uri(uri)
        if config.src not in self.modems:
            raise TransportError(f"cannot open {uri}: no simulated modem {config.src}")
        return MicromodemTransport.simulated(self, config.src, **dataclasses.asdict(config))

    def transport(self, node: int, **options: Any) -> Any:
        """A :class:`~.transport.MicromodemTransport` on ``node``'s simulated modem, driven by this
        network's clock (options: those of :class:`~.driver.DriverConfig`; ``src`` defaults to
        ``node``)."""
        from .transport import MicromodemTransport

        return MicromodemTransport.simulated(self, node, **options)

    # ------------------------------------------------------------------------ simulation
    def _transmit(self, modem: SimulatedModem, meta: _Meta, frames: list[bytes], rate: int, now: float) -> float:
        end = self.channel.transmit(modem.node, frames, rate, now)
        start = end - AIR_RATES[rate].packet_airtime(len(frames))
        self._meta.append((modem.node, start, meta))
        for other in self.modems.values():
            if other is not modem:
                t = start + self.channel.delay(modem.node, other.node)
                other._at(t, functools.partial(other.detect, meta))
        return end

    def _lookup(self, a: Arrival) -> _Meta | None:
        tx_start = a.start - self.channel.delay(a.src, a.dst)
        best = None
        for node, start, meta in self._meta:
            if node == a.src and abs(start - tx_start) < 1e-6:
                best = meta
        return best

    def next_event(self) -> float | None:
        times = [self.channel.next_arrival()]
        times += [m.next_deadline() for m in self.modems.values()]
        times += [h.driver.next_deadline() for h in self._hosts]
        found = [t for t in times if t is not None]
        return min(found) if found else None

    def busy(self) -> bool:
        """Anything in flight: a packet on the channel, a modem cycle, a host transmission."""
        if self.channel.next_arrival() is not None:
            return True
        if any(m.busy() for m in self.modems.values()):
            return True
        return any(not h.driver.idle or not h.driver.ready for h in self._hosts)

    def step(self) -> None:
        """Process everything due at the current time."""
        now = self.clock.now
        for _ in range(1000):
            moved = self._exchange(now)
            for a in self.channel.poll(now):
                meta = self._lookup(a)
                modem = self.modems.get(a.dst)
                if meta is not None and modem is not None:
                    modem.on_arrival(a, meta, now)
                    moved = True
            for m in self.modems.values():
                m.poll(now)
            for h in self._hosts:
                h.driver.poll(now)
            moved = self._exchange(now) or moved
            if not moved:
                break
        for m in self.modems.values():
            if m.orphan:
                m.data_to_send()  # nobody listens on this modem's serial port any more
        self._prune(now)

    def _exchange(self, now: float) -> bool:
        moved = False
        for _ in range(1000):
            any_bytes = False
            for h in self._hosts:
                out = h.driver.data_to_send()
                if out:
                    h.modem.feed(h.to_modem(out), now)
                    any_bytes = True
                back = h.modem.data_to_send()
                if back:
                    h.driver.feed(h.to_host(back), now)
                    any_bytes = True
            if not any_bytes:
                break
            moved = True
        return moved

    def pty_paths(self) -> dict[int, str]:
        """The pseudo-terminal of each in-process host's modem (``ptys=True``)."""
        return {h.modem.node: h.path for h in self._hosts if h.path}

    def close(self) -> None:
        """Close the hosts' pseudo-terminals."""
        for h in self._hosts:
            h.close()

    def _prune(self, now: float) -> None:
        if len(self._meta) > 256:
            self._meta = [m for m in self._meta if m[1] > now - 600.0]

    def run_until(self, t: float) -> None:
        """Advance the clock to ``t``, processing every event on the way."""
        self.step()
        while True:
            nxt = self.next_event()
            if nxt is None or nxt > t:
                break
            if nxt <= self.clock.now:
                # something due now that did not clear itself: move on a hair to avoid spinning
                nxt = self.clock.now + 1e-6
                if nxt > t:
                    break
            self.clock.advance_to(nxt)
            self.step()
        self.clock.advance_to(t)
        self.step()

    def as_clock(self) -> NetworkClock:
        """A clock for :class:`coex.Runner` (``time()``/``wait_until(t)``):
        waiting runs this network, returning early when a host driver receives a frame."""
        return NetworkClock(self)

    def received_count(self) -> int:
        """Frames delivered so far to all in-process host drivers."""
        return sum(int(h.driver.received_count) for h in self._hosts)

    def run_for(self, dt: float) -> None:
        self.run_until(self.clock.now + dt)

    def run_while(self, condition: Callable[[], bool], timeout: float) -> bool:
        """Run until ``condition()`` is false or ``timeout`` simulated seconds pass; returns
        whether the condition became false."""
        deadline = self.clock.now + timeout
        self.step()
        while condition():
            nxt = self.next_event()
            if nxt is None or nxt > deadline:
                self.clock.advance_to(deadline)
                self.step()
                return not condition()
            self.clock.advance_to(max(nxt, self.clock.now + 1e-6) if nxt <= self.clock.now else nxt)
            self.step()
        return True


class NetworkClock:
    """``time()`` and ``wait_until(t)`` over a :class:`ModemNetwork` (the runner's Clock protocol)."""

    def __init__(self, network: ModemNetwork) -> None:
        self.network = network

    def time(self) -> float:
        return self.network.now

    def wait_until(self, t: float) -> None:
        net = self.network
        if t <= net.now:
            net.step()
            return
        start = net.received_count()
        net.run_while(lambda: net.received_count() == start, t - net.now)


class SimLoop:
    """:class:`~coex_runtime.runner.Runner` objects over a :class:`ModemNetwork`, with timed
    callbacks, on the network's clock (each runner's clock must read that clock): the one paced
    loop of a simulated dive (``coex demo``, the fault suite, ``bench/soak_faults.py``).

    Each pass advances the network to the next thing due (a modem or driver deadline, a node's
    next slot, a callback; at most ``max_step`` seconds on), calls the callbacks due, steps every
    runner in :attr:`runners` (a list the caller may change: a node restarted), calls each of
    :attr:`after` with the time, lets the network take what the runners wrote, and calls each
    of :attr:`settled`. ``max_step``
    bounds the jumps for parts the loop cannot see (an autonomy's protocol timers). With
    ``speed`` the simulated clock runs at most that many times as fast as the wall clock (a
    person at a console can follow the dive); ``lock`` is held around each pass (the console's
    lock: nothing else touches the nodes meanwhile)."""

    def __init__(self, network: ModemNetwork, runners: Sequence[Any] = (), *,
                 max_step: float | None = None, speed: float | None = None,
                 lock: contextlib.AbstractContextManager[Any] | None = None) -> None:
        if speed is not None and speed <= 0:
            raise ConfigError("speed must be positive")
        self.network = network
        self.runners: list[Any] = list(runners)
        self.max_step = max_step
        self.speed = speed
        self.lock: contextlib.AbstractContextManager[Any] = lock if lock is not None else contextlib.nullcontext()
        #: called with the time after the runners, every pass
        self.after: list[Callable[[float], Any]] = []
        #: called with the time at the end of every pass, once the network took what the
        #: runners wrote (what a node heard, the channel's log)
        self.settled: list[Callable[[float], Any]] = []
        self._events: list[tuple[float, int, Callable[[float], Any]]] = []
        self._count = itertools.count()
        self.steps = 0

    @property
    def now(self) -> float:
        return self.network.now

    def at(self, t: float, fn: Callable[[float], Any]) -> None:
        """Call ``fn(now)`` at time ``t`` (in the order given, for equal times)."""
        heapq.heappush(self._events, (float(t), next(self._count), fn))

    def every(self, period: float, fn: Callable[[float], Any], start: float | None = None,
              until: float | None = None) -> None:
        """Call ``fn(now)`` every ``period`` seconds from ``start`` (default: now), before ``until``."""
        if period <= 0:
            raise ConfigError("period must be positive")

        def tick(now: float) -> None:
            fn(now)
            if until is None or now + period < until:
                self.at(now + period, tick)

        self.at(self.now if start is None else start, tick)

    def run(self, until: float) -> None:
        """Run to time ``until``."""
        from coex_runtime.runner import next_wakeup

        net = self.network
        wall_start, sim_start = time.monotonic(), net.now
        while net.now < until:
            t = next_wakeup(net.now, until, self._events[0][0] if self._events else None,
                            [net.next_event(), *(r.node.next_event(net.now) for r in self.runners)],
                            started=bool(self.steps))
            if self.max_step is not None:
                t = min(t, net.now + self.max_step)
            if self.speed is not None:  # no faster than the wall clock allows
                ahead = (t - sim_start) / self.speed - (time.monotonic() - wall_start)
                if ahead > 0:
                    time.sleep(ahead)
            with self.lock:
                self.step(t)

    def step(self, t: float) -> None:
        """One pass: the network to ``t``, the callbacks due, every runner, :attr:`after`, the
        network, :attr:`settled`."""
        net = self.network
        net.run_until(t)
        while self._events and self._events[0][0] <= net.now:
            _, _, fn = heapq.heappop(self._events)
            fn(net.now)
        for r in list(self.runners):
            r.step()
        for fn in self.after:
            fn(net.now)
        net.step()
        for fn in self.settled:
            fn(net.now)
        self.steps += 1
