"""``MoosTransport``: each CoEx frame as one binary MOOS variable, through a MOOSDB.

URI: ``moos://HOST:PORT?name=pCoex&tx=COEX_TX&rx=COEX_RX`` (host ``localhost`` and port 9000,
MOOS's defaults, when left out). Options:

``name``     the MOOS client name (default ``pCoex``; unique per MOOSDB)
``tx``       the variable frames are written to (default ``COEX_TX``), as binary strings
``rx``       the variable frames are read from (default ``COEX_RX``)
``mtu``      largest frame :meth:`send` accepts (default 2048: a Micromodem-2 packet, 8 x 256 B)
``queue``    frames kept while MOOSDB is unreachable (default 10000; beyond it the oldest is
             dropped and counted)
``hold``     seconds frames wait after each (re)connect for a client to register for ``tx``
             (default 5; 0 sends at once)
``timeout``  seconds the constructor waits for the connection (default 5); if MOOSDB is not
             there yet the transport still opens, queues and keeps trying
``warp``     the community's ``MOOSTimeWarp`` (default 1): frames are stamped with the warped
             MOOS time, as MOOS applications stamp theirs

A vehicle whose modem is run by a MOOS application (a modem driver that subscribes to
``COEX_TX`` and publishes what it receives as ``COEX_RX``) is reached with the defaults.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any
from urllib.parse import urlsplit

from coex_core.errors import ConfigError, TransportError
from coex_core.transport import Transport, UriInfo, parse_query

from .client import MAX_TIME_WARP, MoosClient

__all__ = ["DEFAULT_PORT", "MoosConfig", "MoosTransport", "parse_moos_uri"]

log = logging.getLogger(__name__)

DEFAULT_PORT = 9000  # DEFAULT_MOOS_SERVER_PORT
_OPTIONS: dict[str, type] = {
    "name": str, "tx": str, "rx": str, "mtu": int, "queue": int, "hold": float, "timeout": float,
    "warp": float,
}


@dataclass(frozen=True)
class MoosConfig:
    """Configuration of one :class:`MoosTransport` end."""

    host: str = "localhost"
    port: int = DEFAULT_PORT
    #: MOOS client name (MOOSDB refuses a second client of the same name)
    name: str = "pCoex"
    #: variable frames are written to (binary)
    tx: str = "COEX_TX"
    #: variable frames are read from (binary)
    rx: str = "COEX_RX"
    mtu: int = 2048
    #: frames kept while MOOSDB is unreachable
    queue: int = 10000
    #: seconds frames wait after a (re)connect for a client registered for ``tx``
    hold: float = 5.0
    #: seconds the constructor waits for the connection
    timeout: float = 5.0
    #: the community's MOOSTimeWarp (values are stamped with the warped MOOS time)
    warp: float = 1.0

    def __post_init__(self) -> None:
        for key in ("name", "tx", "rx"):
            value = getattr(self, key)
            if not value or any(c.isspace() for c in value):
                raise ConfigError(f"{key} must be a non-empty MOOS name without spaces, got {value!r}")
        if not 0 < self.port < 65536:
            raise ConfigError(f"port must be 1..65535, got {self.port}")
        if self.mtu <= 0 or self.queue <= 0:
            raise ConfigError(f"mtu and queue must be positive, got {self.mtu} and {self.queue}")
        if self.hold < 0 or self.timeout < 0:
            raise ConfigError("hold and timeout must be >= 0")
        if not 0 < self.warp <= MAX_TIME_WARP:
            raise ConfigError(f"warp (MOOSTimeWarp) must be above 0 and at most {MAX_TIME_WARP:g}, "
                              f"got {self.warp:g}")

    @property
    def uri(self) -> str:
        return (f"moos://{self.host}:{self.port}?name={self.name}&tx={self.tx}&rx={self.rx}"
                f"&mtu={self.mtu}&queue={self.queue}&hold={self.hold:g}&timeout={self.timeout:g}"
                + (f"&warp={self.warp:g}" if self.warp != 1.0 else ""))

    def swapped(self, name: str) -> MoosConfig:
        """The other end: ``tx`` and ``rx`` exchanged, another client name."""
        return replace(self, name=name, tx=self.rx, rx=self.tx)


def parse_moos_uri(uri: str) -> MoosConfig:
    """Parse ``moos://HOST:PORT?options`` into a :class:`MoosConfig`."""
    parts = urlsplit(uri)
    if parts.scheme != "moos":
        raise ConfigError(f"not a moos URI: {uri!r}")
    if parts.path not in ("", "/"):
        raise ConfigError(f"{uri!r}: expected moos://HOST:PORT?options, not a path {parts.path!r}")
    try:
        port = parts.port
    except ValueError:
        raise ConfigError(f"{uri!r}: the port is not a number in 1..65535") from None
    options = parse_query(parts.query, _OPTIONS)
    return MoosConfig(host=parts.hostname or "localhost", port=port or DEFAULT_PORT, **options)


class MoosTransport(Transport):
    """One end of a CoEx link through a MOOSDB (see the module documentation for the URI).

    Frames are written to ``tx`` with :meth:`MoosClient.notify` as binary strings and read from
    ``rx``. The client keeps every frame until MOOSDB has processed it, across disconnects and
    MOOSDB restarts, and drops duplicates and the value MOOSDB replays on registration, so a
    restart loses nothing and delivers nothing twice. Frames the end wrote itself (``tx`` equal
    to ``rx``) and values that are not binary are counted in :meth:`stats`, never returned.
    """

    scheme = "moos"
    options = _OPTIONS  # its URI query options (parse_query)

    def __init__(self, config: MoosConfig | None = None) -> None:
        self.config = config or MoosConfig()
        super().__init__(self.config.mtu)
        cfg = self.config
        self._queue: deque[bytes] = deque()
        self._counts = {"sent": 0, "received": 0, "own": 0, "bad": 0}
        self.client = MoosClient(
            cfg.host, cfg.port, cfg.name,
            await_subscribers=(cfg.tx,) if cfg.hold > 0 else (),
            await_timeout=cfg.hold, max_pending=cfg.queue, time_warp=cfg.warp,
        )
        self.client.register(cfg.rx, 0.0)
        if not self.client.connect(cfg.timeout):
            log.warning("MOOS transport %s: MOOSDB at %s:%d not reachable yet (%s); frames wait until it is",
                        cfg.name, cfg.host, cfg.port, self.client.stats()["last_error"] or "no answer")

    @classmethod
    def from_uri(cls, uri: str) -> MoosTransport:
        return cls(parse_moos_uri(uri))

    @classmethod
    def check_uri(cls, uri: str) -> UriInfo:
        """The URI through :func:`parse_moos_uri` (every option by name), connecting to nothing."""
        return UriInfo(uri, parse_moos_uri(uri).mtu)

    def link_up(self) -> bool:
        """Whether the client is connected to MOOSDB now (it reconnects by itself)."""
        return bool(self.client.connected)

    # ------------------------------------------------------------------ transport
    def _send_internal(self, frame: bytes) -> None:
        self.client.notify(self.config.tx, frame)
        self._counts["sent"] += 1

    def _pull(self) -> None:
        for msg in self.client.fetch():
            if msg.key != self.config.rx:
                continue
            if msg.source == self.config.name:
                self._counts["own"] += 1
                continue
            if not isinstance(msg.value, bytes):
                self._counts["bad"] += 1
                log.warning("MOOS transport %s: ignoring a %s value on %s from %s (frames are binary)",
                            self.config.name, msg.kind, msg.key, msg.source)
                continue
            self._queue.append(msg.value)
            self._counts["received"] += 1

    def _recv_internal(self, timeout: float | None) -> bytes | None:
        deadline = None if timeout is None else time.monotonic() + max(0.0, timeout)
        while True:
            if not self._queue:
                self._pull()
            if self._queue:
                return self._queue.popleft()
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                return None
            self.client.wait_for_mail(1.0 if left is None else min(left, 1.0))

    def flush(self, timeout: float | None = 30.0) -> None:
        """Wait until MOOSDB has processed every frame sent; :class:`TransportError` if it has not
        within ``timeout`` seconds (they stay queued)."""
        if not self.client.flush(timeout):
            raise TransportError(
                f"MOOS transport {self.config.name}: {self.client.pending()} frames not taken by MOOSDB at "
                f"{self.config.host}:{self.config.port} within {timeout} s ({self.client.stats()['last_error']})")

    def _close_internal(self) -> None:
        if self.client.connected:
            self.client.flush(1.0)  # best effort: what was sent just before close
        self.client.close()
        self._queue.clear()

    # ------------------------------------------------------------------ extras
    @property
    def connected(self) -> bool:
        return self.client.connected

    def pending(self) -> int:
        """Frames received and not yet returned by :meth:`recv`."""
        return len(self._queue)

    def stats(self) -> Mapping[str, Any]:
        """``sent``, ``received``, ``own``, ``bad`` and the client's counters (``connects``,
        ``duplicates``, ``replays_ignored``, ``resent``, ``dropped_pending``, ``pending`` ...)."""
        client = self.client.stats()
        return {**client, **self._counts, "client_sent": client["sent"], "client_received": client["received"],
                "tx": self.config.tx, "rx": self.config.rx, "uri": self.config.uri}
