"""Abstract base of a transport: something that sends and receives whole frames.

Modelled on python-can's ``BusABC``: subclasses implement :meth:`Transport.send_frame` and
:meth:`Transport._recv_internal`; the base class adds the MTU check, the timeout loop, the
context manager and an idempotent :meth:`Transport.close`.

Transports are chosen by URI (``micromodem:///dev/ttyUSB0?rate=5``,
``mavlink:udpout:127.0.0.1:14550``, ``lcm:udpm://239.255.76.67:7667``, ``loopback://name``);
see :func:`coex_core.registry.open_transport`.
"""

from __future__ import annotations

import abc
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import Any, ClassVar
from urllib.parse import parse_qsl

from .errors import ConfigError, FrameTooLarge, TransportError

__all__ = ["Transport", "UriInfo", "parse_query"]


@dataclass(frozen=True)
class UriInfo:
    """What a transport URI says, found without opening anything (:meth:`Transport.check_uri`):
    the largest frame the transport will accept (``mtu``), the local device nodes or files it
    will open (``paths``: a missing one is a warning, the device may be plugged in later), the
    modem's packet ``rate`` when the URI sets one (the channel manager must plan for it), and,
    for a modem that addresses its packets, its own address (``src``) and the one it sends to
    (``dest``, 0: every node): ``coex config check`` refuses a ``src`` that is not the node's
    id and a ``dest`` that is the node's own or not its peer's (a link that carries nothing)."""

    uri: str
    mtu: int
    paths: tuple[str, ...] = ()
    rate: int | None = None
    src: int | None = None
    dest: int | None = None


class Transport(abc.ABC):
    """Sends and receives whole frames of at most :attr:`mtu` bytes.

    Contract: a frame given to :meth:`send` either goes out whole or raises
    :class:`~coex_core.errors.TransportError`; a frame above the MTU raises
    :class:`~coex_core.errors.FrameTooLarge` and nothing is sent. :meth:`recv` returns one whole
    frame exactly as sent, or ``None`` on timeout; it never returns part of a frame. Transports
    may lose frames (acoustic links do); they never alter one without detection.
    """

    #: URI scheme this transport answers to (``micromodem``, ``mavlink`` ...).
    scheme: ClassVar[str] = ""

    def __init__(self, mtu: int) -> None:
        if mtu <= 0:
            raise ConfigError(f"MTU must be positive, got {mtu}")
        self.mtu = mtu
        self._closed = False

    # ----------------------------------------------------------------- to implement
    @abc.abstractmethod
    def _send_internal(self, frame: bytes) -> None:
        """Send one frame (already checked against the MTU)."""

    @abc.abstractmethod
    def _recv_internal(self, timeout: float | None) -> bytes | None:
        """Return one frame, or ``None`` if none arrived within ``timeout`` seconds."""

    def _close_internal(self) -> None:  # noqa: B027  (optional hook, deliberately not abstract)
        """Release resources (called once)."""

    @classmethod
    def from_uri(cls, uri: str) -> Transport:
        """Create a transport from its URI."""
        raise ConfigError(f"{cls.__name__} cannot be created from a URI")

    @classmethod
    def check_uri(cls, uri: str) -> UriInfo | None:
        """Parse and check ``uri`` exactly as :meth:`from_uri` will, **opening nothing** (no
        device, socket or file): :class:`ConfigError` naming what is wrong (an unknown option,
        a bad value, a malformed address), else what the URI says (:class:`UriInfo`). ``coex
        config check`` and the daemons' reconnecting links use it, so a URI it passes is one
        :meth:`from_uri` takes. Optional: the default, ``None``, means "cannot be checked without
        opening it" (the config check says so; a link of such a transport must open at start)."""
        return None

    def link_up(self) -> bool:
        """Whether the device or stream behind the transport is there now. A transport that
        reconnects by itself (the MOOS client) says False while it is away, so the outage is
        counted; the default is True (a transport that fails raises :class:`TransportError`
        instead)."""
        return True

    def send_packet(self, frames: Sequence[bytes], rate: int | None = None) -> None:
        """Send the frames of one packet: a modem sends them together at ``rate`` (default its
        own). The default sends each frame with :meth:`send`; a modem transport overrides it."""
        for frame in frames:
            self.send(frame)

    def link_status(self) -> Any:
        """The latest receive statistics as a :class:`~coex_core.messages.LinkStatus` (a modem's
        SNR, Doppler, bad frames), or ``None`` when the transport has none (the default)."""
        return None

    def flush(self) -> None:  # noqa: B027  (optional hook, deliberately not abstract)
        """Wait until every frame given to :meth:`send` has left (a modem's queue, a serial
        port's buffer, a MOOSDB that has not taken them yet); raises
        :class:`~coex_core.errors.TransportError` when they cannot. ``coex send`` calls it
        before it closes the transport. Optional: the default does nothing (a transport whose
        :meth:`send` returns once the frame is out). A transport may add a ``timeout``
        keyword with a default of its own."""

    # ---------------------------------------------------------------- public API
    def send(self, frame: bytes) -> None:
        if self._closed:
            raise TransportError("transport is closed")
        if not isinstance(frame, bytes | bytearray):
            raise TypeError("a frame is bytes")
        if len(frame) > self.mtu:
            raise FrameTooLarge(f"frame of {len(frame)} B exceeds the MTU of {self.mtu} B")
        self._send_internal(bytes(frame))

    def recv(self, timeout: float | None = None) -> bytes | None:
        if self._closed:
            raise TransportError("transport is closed")
        return self._recv_internal(timeout)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._close_internal()

    @property
    def closed(self) -> bool:
        return self._closed

    def stats(self) -> Mapping[str, Any]:
        """Link statistics, transport specific (frames sent/received, SNR ...)."""
        return {}

    def __enter__(self) -> Transport:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def parse_query(query: str, allowed: Mapping[str, type]) -> dict[str, Any]:
    """Parse a URI query string into typed options, rejecting unknown or malformed ones."""
    out: dict[str, Any] = {}
    for key, value in parse_qsl(query, keep_blank_values=True, strict_parsing=False):
        if key not in allowed:
            raise ConfigError(f"unknown option {key!r}; expected one of {sorted(allowed)}")
        typ = allowed[key]
        try:
            if typ is bool:
                if value.lower() not in ("1", "0", "true", "false", "yes", "no"):
                    raise ValueError(value)
                out[key] = value.lower() in ("1", "true", "yes")
            else:
                out[key] = typ(value)
        except ValueError:
            raise ConfigError(f"option {key}={value!r} is not a valid {typ.__name__}") from None
    return out
