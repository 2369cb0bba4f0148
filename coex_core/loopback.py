"""A deterministic in-memory link for tests: seeded loss, MTU, bytes per second, delay.

No threads, no sockets, no wall clock: time is a :class:`SimClock` that only moves when a
receiver waits. ``LoopbackLink`` joins two :class:`LoopbackTransport` ends, ``a`` and ``b``.

Delivery guarantees (as python-can documents for its virtual bus):

* frames arrive whole and unaltered, in the order sent, or not at all;
* each frame is lost independently with probability ``loss``, drawn from ``random.Random(seed)``
  so that a seed always loses the same frames;
* a frame of n bytes sent at time t arrives at ``max(t, end of the previous frame from the same
  end) + n / bytes_per_s + delay``;
* :meth:`LoopbackTransport.recv` with a timeout advances the shared clock to the arrival time,
  or by the timeout if nothing arrives in time; with ``timeout=None`` and nothing in flight it
  returns ``None`` at once (nothing else could ever send in a single-threaded simulation).

URI form: ``loopback://NAME?mtu=256&rate=100&loss=0.1&seed=1&delay=0``; the first
``open_transport`` of a name gets end ``a``, the second end ``b``.
"""

from __future__ import annotations

import heapq
import random
from typing import Any
from urllib.parse import urlsplit

from .errors import ConfigError
from .transport import Transport, UriInfo, parse_query

__all__ = ["LoopbackLink", "LoopbackTransport", "SimClock"]


class SimClock:
    """Simulated time in seconds; it moves only when told to."""

    def __init__(self, start: float = 0.0) -> None:
        self.now = float(start)

    def advance_to(self, t: float) -> None:
        if t > self.now:
            self.now = float(t)

    def advance(self, dt: float) -> None:
        if dt > 0:
            self.now += float(dt)


class LoopbackLink:
    """Two transport ends joined in memory."""

    def __init__(
        self,
        *,
        mtu: int = 256,
        bytes_per_s: float = 100.0,
        loss: float = 0.0,
        seed: int = 0,
        delay: float = 0.0,
        clock: SimClock | None = None,
    ) -> None:
        if not 0.0 <= loss <= 1.0:
            raise ConfigError(f"loss must be in [0, 1], got {loss}")
        if bytes_per_s <= 0:
            raise ConfigError(f"bytes_per_s must be positive, got {bytes_per_s}")
        if delay < 0:
            raise ConfigError(f"delay must not be negative, got {delay}")
        self.mtu = mtu
        self.bytes_per_s = float(bytes_per_s)
        self.loss = float(loss)
        self.delay = float(delay)
        self.clock = clock or SimClock()
        self._rng = random.Random(seed)
        self._queue: list[tuple[float, int, int, bytes]] = []
        self._counter = 0
        self._busy_until = [0.0, 0.0]
        self.sent = [0, 0]
        self.lost = [0, 0]
        self.a = LoopbackTransport(self, 0)
        self.b = LoopbackTransport(self, 1)

    @property
    def now(self) -> float:
        return self.clock.now

    def _transmit(self, side: int, frame: bytes) -> None:
        start = max(self.clock.now, self._busy_until[side])
        end = start + len(frame) / self.bytes_per_s
        self._busy_until[side] = end
        self.sent[side] += 1
        if self._rng.random() < self.loss:
            self.lost[side] += 1
            return
        self._counter += 1
        heapq.heappush(self._queue, (end + self.delay, self._counter, 1 - side, frame))

    def _receive(self, side: int, timeout: float | None) -> bytes | None:
        mine = [item for item in self._queue if item[2] == side]
        if not mine:
            if timeout is not None:
                self.clock.advance(timeout)
            return None
        first = min(mine)
        deadline = None if timeout is None else self.clock.now + timeout
        if deadline is not None and first[0] > deadline:
            self.clock.advance_to(deadline)
            return None
        self._queue.remove(first)
        heapq.heapify(self._queue)
        self.clock.advance_to(first[0])
        return first[3]

    def in_flight(self) -> int:
        return len(self._queue)


class LoopbackTransport(Transport):
    """One end of a :class:`LoopbackLink`."""

    scheme = "loopback"
    _named: dict[str, LoopbackLink] = {}
    _opened: dict[str, int] = {}

    def __init__(self, link: LoopbackLink, side: int) -> None:
        super().__init__(link.mtu)
        self.link = link
        self.side = side

    def _send_internal(self, frame: bytes) -> None:
        self.link._transmit(self.side, frame)

    def _recv_internal(self, timeout: float | None) -> bytes | None:
        return self.link._receive(self.side, timeout)

    def stats(self) -> dict[str, Any]:
        return {"sent": self.link.sent[self.side], "lost": self.link.lost[self.side]}

    @staticmethod
    def _parse(uri: str) -> tuple[str, dict[str, Any]]:
        parts = urlsplit(uri)
        if parts.scheme != "loopback":
            raise ConfigError(f"not a loopback URI: {uri!r}")
        name = parts.netloc or parts.path or "default"
        opts = parse_query(
            parts.query, {"mtu": int, "rate": float, "loss": float, "seed": int, "delay": float}
        )
        if opts.get("mtu", 256) <= 0:
            raise ConfigError(f"{uri!r}: mtu must be positive")
        return name, opts

    @classmethod
    def check_uri(cls, uri: str) -> UriInfo:
        _, opts = cls._parse(uri)
        return UriInfo(uri, int(opts.get("mtu", 256)))

    @classmethod
    def from_uri(cls, uri: str) -> LoopbackTransport:
        name, opts = cls._parse(uri)
        link = cls._named.get(name)
        if link is None or cls._opened.get(name, 0) >= 2:
            link = LoopbackLink(
                mtu=opts.get("mtu", 256),
                bytes_per_s=opts.get("rate", 100.0),
                loss=opts.get("loss", 0.0),
                seed=opts.get("seed", 0),
                delay=opts.get("delay", 0.0),
            )
            cls._named[name] = link
            cls._opened[name] = 0
        side = cls._opened[name]
        cls._opened[name] = side + 1
        return link.a if side == 0 else link.b
