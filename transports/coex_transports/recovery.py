"""Links that come back: a transport that reopens its device or stream when it goes away.

Real modems go away. A USB-serial adapter is unplugged, a modem is power-cycled, a serial-over-IP
server restarts, a MOOSDB is restarted: pyserial raises ``SerialException`` on every read and the
port object stays dead until it is closed and opened again (``../shared/reference/field.md``).
:class:`ResilientTransport` wraps any transport chosen by URI and makes that a passing state,
never the end of the dive:

* **Lost.** A :class:`~coex_core.errors.TransportError` from the inner transport's ``recv``,
  ``send`` or ``send_packet`` (anything but a frame too large, or a
  :class:`~coex_core.errors.LinkDown` of its own: a server with no client yet) marks the link down: the inner
  transport is closed and reopened with :func:`~coex_core.registry.open_transport`, first after
  ``first_retry`` seconds, then at doubling intervals up to ``max_retry`` (0.5 s to 30 s by
  default). A transport that reconnects by itself (MOOS) is never reopened; its
  :meth:`~coex_core.transport.Transport.link_up` only counts the outage.
* **Quiet.** One log line per change of state: lost (with the error), still down (after the
  retries reach their longest interval, then at most once an hour), back (with how long it was
  down and the attempts). A down link's ``recv`` waits (it never spins) and its ``send`` raises
  :class:`~coex_core.errors.LinkDown`, which the runner counts without logging: what was not sent
  is recovered by the protocol's acks once the link is back.
* **Absent at start.** A device missing when the daemon starts is waited for the same way
  (``required=True`` makes it an error at once instead). The MTU comes from the URI
  (:meth:`~coex_core.transport.Transport.check_uri`), so the node is built before the modem is
  there; a URI that does not check is a :class:`~coex_core.errors.ConfigError` at once.
* **Counted.** :meth:`ResilientTransport.health` gives the outages, the time down in all and
  the last outage's length (the vehicle sends it topside as ``LinkHealth``).

The clock and the sleep are injectable (tests and time-compressed benchmarks).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from coex_core.errors import ConfigError, FrameTooLarge, LinkDown, PluginLoadError, TransportError
from coex_core.registry import check_transport_uri, open_transport
from coex_core.transport import Transport

__all__ = ["Health", "ResilientTransport", "describe_seconds"]

log = logging.getLogger("coex.link")

#: after the retries reach their longest interval, "still down" is logged at most this often
REMIND_EVERY = 3600.0


def describe_seconds(seconds: float) -> str:
    """``42 s``, ``3 min 12 s``, ``2 h 5 min``: a duration as an operator reads it."""
    s = round(max(0.0, seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60} s" if s % 60 else f"{s // 60} min"
    return f"{s // 3600} h {s % 3600 // 60} min"


@dataclass(frozen=True)
class Health:
    """A link's outages so far (:meth:`ResilientTransport.health`). Seconds on the transport's
    clock; ``down_total`` and ``last_down`` include the present outage while it lasts."""

    up: bool
    outages: int
    down_total: float
    last_down: float
    attempts: int
    last_error: str
    #: frames offered while the link was down (not sent; the protocol recovers them)
    not_sent: int


class ResilientTransport(Transport):
    """A transport (by URI) that reopens itself when its device or stream goes away (module
    docstring). ``name`` is how the log calls it (``link 0``)."""

    def __init__(self, uri: str, *, name: str = "", required: bool = False,
                 first_retry: float = 0.5, max_retry: float = 30.0,
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], Any] = time.sleep,
                 opener: Callable[[str], Transport] = open_transport) -> None:
        if not 0 < first_retry <= max_retry:
            raise ConfigError(f"retry intervals must satisfy 0 < first ({first_retry}) <= longest ({max_retry})")
        info = check_transport_uri(uri)
        self.uri = uri
        self.name = name or uri
        self.first_retry, self.max_retry = float(first_retry), float(max_retry)
        self._clock, self._sleep, self._opener = clock, sleep, opener
        self._lock = threading.RLock()
        self.inner: Transport | None = None
        self._outages = 0
        self._down_total = 0.0  # finished outages
        self._last_down = 0.0
        self._down_since: float | None = None
        self._attempts = 0
        self._delay = self.first_retry
        self._next_try = 0.0
        self._last_error = ""
        self._not_sent = 0
        self._reminded: float | None = None
        self._self_down = False  # the inner transport says it is away (it reconnects by itself)
        if info is None:
            # a transport that cannot tell its MTU without opening: it must open now
            self.inner = self._opener(uri)
            mtu = int(self.inner.mtu)
        else:
            mtu = int(info.mtu)
            try:
                self.inner = self._opener(uri)
            except ConfigError:
                raise
            except (TransportError, OSError, PluginLoadError) as exc:
                if required:
                    raise TransportError(f"{self.name}: cannot open {uri}: {exc}") from exc
                self._went_down(f"not there at start: {exc}", start=True)
        super().__init__(mtu)

    # ------------------------------------------------------------------ states
    def _went_down(self, why: str, *, start: bool = False) -> None:
        now = self._clock()
        self._down_since = now
        self._outages += 1
        self._attempts = 0
        self._delay = self.first_retry
        self._next_try = now + self._delay
        self._last_error = why
        self._reminded = None
        log.warning("%s (%s): %s; %s", self.name, self.uri, why,
                    f"waiting for it (retrying from {self.first_retry:g} s, backing off to {self.max_retry:g} s)"
                    if start else f"reopening it (from {self.first_retry:g} s, backing off to {self.max_retry:g} s)")

    def _came_back(self, how: str) -> None:
        now = self._clock()
        assert self._down_since is not None
        length = now - self._down_since
        self._down_total += length
        self._last_down = length
        self._down_since = None
        extra = f"; {self._not_sent} frames not sent meanwhile" if self._not_sent else ""
        log.warning("%s: back after %s (%s; outage %d, %d attempts%s)", self.name, describe_seconds(length),
                    how, self._outages, self._attempts, extra)
        self._not_sent = 0

    def _lost(self, exc: BaseException) -> None:
        inner, self.inner = self.inner, None
        if inner is not None:
            try:
                inner.close()
            except Exception:  # closing a dead port may fail too: it is gone either way
                pass
        self._went_down(f"lost: {exc}")

    def _maintain(self) -> None:
        """Reopen when due; follow a self-reconnecting transport's own state."""
        now = self._clock()
        inner = self.inner
        if inner is not None:
            up = inner.link_up()
            if not up and not self._self_down:
                self._self_down = True
                self._went_down("stream away (the transport reconnects by itself)")
            elif up and self._self_down:
                self._self_down = False
                self._came_back("reconnected")
            return
        if now < self._next_try:
            return
        self._attempts += 1
        try:
            self.inner = self._opener(self.uri)
        except Exception as exc:  # still gone (or failing to open): back off
            self._last_error = f"{type(exc).__name__}: {exc}" if not isinstance(exc, TransportError) else str(exc)
            self._delay = min(self._delay * 2.0, self.max_retry)
            self._next_try = now + self._delay
            self._remind(now)
            return
        self._came_back("reopened")

    def _remind(self, now: float) -> None:
        if self._delay < self.max_retry or self._down_since is None:
            return
        if self._reminded is None or now - self._reminded >= REMIND_EVERY:
            self._reminded = now
            log.warning("%s: still down after %s (%d attempts; last: %s); retrying every %g s", self.name,
                        describe_seconds(now - self._down_since), self._attempts, self._last_error, self.max_retry)

    # ------------------------------------------------------------------ transport
    def _send_internal(self, frame: bytes) -> None:
        self.send_packet([frame])

    def send_packet(self, frames: Sequence[bytes], rate: int | None = None) -> None:
        if self.closed:
            raise TransportError("transport is closed")
        with self._lock:
            self._maintain()
            inner = self.inner
            if inner is None:
                self._not_sent += len(frames)
                raise LinkDown(f"{self.name} is down ({self._last_error})")
            try:
                inner.send_packet(frames, rate)
            except FrameTooLarge:
                raise
            except LinkDown:  # the transport is there and waiting for a peer (a server with no client)
                self._not_sent += len(frames)
                raise
            except TransportError as exc:
                self._lost(exc)
                self._not_sent += len(frames)
                raise LinkDown(f"{self.name} went down: {exc}") from exc

    def _recv_internal(self, timeout: float | None) -> bytes | None:
        deadline = None if timeout is None else self._clock() + max(0.0, timeout)
        while True:
            with self._lock:
                self._maintain()
                inner = self.inner
                wait_until = self._next_try
            now = self._clock()
            if inner is not None:
                left = None if deadline is None else max(0.0, deadline - now)
                try:
                    return inner.recv(timeout=left)
                except TransportError as exc:
                    with self._lock:
                        if self.inner is inner:
                            self._lost(exc)
                    continue
            # down: wait for the next attempt or the caller's deadline, never spinning
            until = wait_until if deadline is None else min(wait_until, deadline)
            if until > now:
                self._sleep(until - now)
            if deadline is not None and self._clock() >= deadline:
                with self._lock:
                    self._maintain()
                return None

    def _close_internal(self) -> None:
        with self._lock:
            inner, self.inner = self.inner, None
        if inner is not None:
            inner.close()

    # ------------------------------------------------------------------ what it tells
    @property
    def up(self) -> bool:
        return self.inner is not None and not self._self_down

    def link_up(self) -> bool:
        return self.up

    def link_status(self) -> Any:
        inner = self.inner
        return None if inner is None else inner.link_status()

    def health(self) -> Health:
        with self._lock:
            now = self._clock()
            current = 0.0 if self._down_since is None else now - self._down_since
            return Health(self.up, self._outages, self._down_total + current,
                          current if self._down_since is not None else self._last_down,
                          self._attempts, self._last_error, self._not_sent)

    def stats(self) -> Mapping[str, Any]:
        inner = self.inner
        out: dict[str, Any] = dict(inner.stats()) if inner is not None else {}
        h = self.health()
        out.update(up=h.up, outages=h.outages, down_seconds=round(h.down_total, 3),
                   last_down_seconds=round(h.last_down, 3), reopen_attempts=h.attempts, last_error=h.last_error)
        return out

    def __repr__(self) -> str:
        return f"<ResilientTransport {self.name} {self.uri} {'up' if self.up else 'down'}>"
