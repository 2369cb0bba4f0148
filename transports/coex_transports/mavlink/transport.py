"""``MavlinkTransport``: CoEx frames in MAVLink 2 ``TUNNEL`` messages over UDP, TCP or serial.

URIs::

    mavlink:udpout:127.0.0.1:14550?sysid=1&compid=191   send to a router / GCS listening there
    mavlink:udpin:0.0.0.0:14550                          listen; answer whoever spoke last (8 peers)
    mavlink:tcp:127.0.0.1:5760                           TCP client (SITL, MAVProxy, mavlink-router)
    mavlink:tcpin:0.0.0.0:5760                           TCP server
    mavlink:serial:/dev/ttyUSB0:57600                    serial port (pyserial), baud optional

Options (query string): ``sysid`` (1..255, default 1), ``compid`` (1..255, default 191),
``target_system`` / ``target_component`` (0..255, default 0 = broadcast), ``payload_type``
(32768..65535, default 0xC0E5 = 49381), ``mtu`` (largest frame, default 2048, at most 31620),
``heartbeat`` (seconds between HEARTBEATs, default 1, 0 = off), ``reassembly_timeout`` (seconds,
default 5), ``max_partial`` (partial frames held, default 8).

The protocol logic is the sans-I/O :class:`~coex_transports.mavlink.codec.TunnelCodec`; this class
only moves its bytes and supplies ``now`` from ``time.monotonic``. Heartbeats go out when the
transport is opened and then whenever one is due during :meth:`send` or :meth:`recv` (``recv``
wakes up for them while it waits); an application that neither sends nor receives for a while
should call :meth:`service`.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

from coex_core.errors import ConfigError
from coex_core.transport import Transport, UriInfo, parse_query

from ._links import Link, SerialLink, TcpClientLink, TcpServerLink, UdpInLink, UdpOutLink
from .codec import DEFAULT_COMPONENT_ID, DEFAULT_MTU, DEFAULT_SYSTEM_ID, PAYLOAD_TYPE, TunnelCodec

__all__ = ["MavlinkEndpoint", "MavlinkTransport", "parse_mavlink_uri"]

_OPTIONS: dict[str, type] = {
    "sysid": int,
    "compid": int,
    "target_system": int,
    "target_component": int,
    "payload_type": int,
    "mtu": int,
    "heartbeat": float,
    "reassembly_timeout": float,
    "max_partial": int,
}
_KINDS = ("udpout", "udpin", "tcp", "tcpin", "serial")
DEFAULT_BAUD = 57600


@dataclass(frozen=True)
class MavlinkEndpoint:
    """A parsed ``mavlink:`` URI: the link (kind, host or device, port or baud) and options."""

    kind: str
    address: str
    port: int
    options: dict[str, Any]


def _port(text: str, uri: str) -> int:
    try:
        port = int(text)
    except ValueError:
        raise ConfigError(f"{uri!r}: port {text!r} is not a number") from None
    if not 0 <= port <= 65535:
        raise ConfigError(f"{uri!r}: port {port} out of range")
    return port


def parse_mavlink_uri(uri: str) -> MavlinkEndpoint:
    """Split ``mavlink:KIND:ADDRESS:PORT?options`` (``serial:DEVICE[:BAUD]``); raise ConfigError."""
    parts = urlsplit(uri)
    if parts.scheme != "mavlink":
        raise ConfigError(f"not a mavlink URI: {uri!r}")
    path = parts.path
    if parts.netloc:  # "mavlink://udpout:..." is tolerated
        path = parts.netloc + path
    kind, _, rest = path.partition(":")
    if kind not in _KINDS:
        raise ConfigError(f"{uri!r}: connection kind must be one of {', '.join(_KINDS)}, got {kind!r}")
    options = parse_query(parts.query, _OPTIONS)
    if kind == "serial":
        device, sep, baud_text = rest.rpartition(":")
        if not sep or not baud_text.isdigit():
            device, baud_text = rest, str(DEFAULT_BAUD)
        if not device:
            raise ConfigError(f"{uri!r}: serial needs a device, e.g. mavlink:serial:/dev/ttyUSB0:57600")
        baud = int(baud_text)
        if baud <= 0:
            raise ConfigError(f"{uri!r}: baud rate must be positive")
        return MavlinkEndpoint(kind, device, baud, options)
    host, sep, port_text = rest.rpartition(":")
    if not sep or not host:
        raise ConfigError(f"{uri!r}: expected {kind}:HOST:PORT")
    return MavlinkEndpoint(kind, host.strip("[]"), _port(port_text, uri), options)


def _codec(ep: MavlinkEndpoint) -> TunnelCodec:
    o = ep.options
    return TunnelCodec(
        system_id=o.get("sysid", DEFAULT_SYSTEM_ID),
        component_id=o.get("compid", DEFAULT_COMPONENT_ID),
        target_system=o.get("target_system", 0),
        target_component=o.get("target_component", 0),
        payload_type=o.get("payload_type", PAYLOAD_TYPE),
        mtu=o.get("mtu", DEFAULT_MTU),
        heartbeat_interval=o.get("heartbeat", 1.0),
        reassembly_timeout=o.get("reassembly_timeout", 5.0),
        max_partial=o.get("max_partial", 8),
    )


def _open_link(ep: MavlinkEndpoint) -> Link:
    if ep.kind == "udpout":
        return UdpOutLink(ep.address, ep.port)
    if ep.kind == "udpin":
        return UdpInLink(ep.address, ep.port)
    if ep.kind == "tcp":
        return TcpClientLink(ep.address, ep.port)
    if ep.kind == "tcpin":
        return TcpServerLink(ep.address, ep.port)
    return SerialLink(ep.address, ep.port)


class MavlinkTransport(Transport):
    """CoEx frames over MAVLink 2 ``TUNNEL`` (#385), fragmented above 124 bytes.

    ``send`` raises :class:`~coex_core.errors.TransportError` if the link fails or has nowhere to
    send (``udpin`` before any peer spoke, ``tcpin`` with no client). ``recv`` returns whole frames
    only; bad packets and fragments are counted in :meth:`stats` and never end a ``recv``."""

    scheme = "mavlink"
    options = _OPTIONS  # its URI query options (parse_query)

    def __init__(self, link: Link, codec: TunnelCodec) -> None:
        super().__init__(codec.mtu)
        self.link = link
        self.codec = codec
        self._ready: deque[bytes] = deque()
        try:
            self.service()  # the first heartbeat, so routers learn about us at once
        except BaseException:
            link.close()
            raise

    @classmethod
    def from_uri(cls, uri: str) -> MavlinkTransport:
        ep = parse_mavlink_uri(uri)
        return cls(_open_link(ep), _codec(ep))

    @classmethod
    def check_uri(cls, uri: str) -> UriInfo:
        """The URI through :func:`parse_mavlink_uri` and the options through the codec's own
        checks (building a codec opens nothing); a serial device is listed in ``paths``."""
        ep = parse_mavlink_uri(uri)
        codec = _codec(ep)
        return UriInfo(uri, codec.mtu, (ep.address,) if ep.kind == "serial" else ())

    # ---------------------------------------------------------------------------- internals
    def _write(self, packets: list[bytes]) -> None:
        for packet in packets:
            self.link.write(packet)

    def _feed(self, data: bytes) -> None:
        self._ready.extend(self.codec.receive(data, time.monotonic(), datagram=self.link.datagram))

    def service(self) -> None:
        """Send a heartbeat if one is due and expire stale partial frames (no blocking)."""
        due = self.codec.poll(time.monotonic(), can_send=self.link.can_write())
        self._write(due)

    def _send_internal(self, frame: bytes) -> None:
        self.service()
        if not self.link.can_write():
            # a udpin/tcpin end learns where to send from what it receives: look once
            data = self.link.read(0.0)
            if data is not None:
                self._feed(data)
        self._write(self.codec.encode(frame))

    def _recv_internal(self, timeout: float | None) -> bytes | None:
        deadline = None if timeout is None else time.monotonic() + max(0.0, timeout)
        late_reads = 0
        while True:
            self.service()
            if self._ready:
                return self._ready.popleft()
            now = time.monotonic()
            if deadline is not None and now >= deadline:
                # a last non-blocking look, so that timeout=0 still reads what is waiting
                # (bounded, so a busy link of other traffic cannot hold recv past its timeout)
                late_reads += 1
                data = self.link.read(0.0) if late_reads <= 64 else None
                if data is None:
                    return None
                self._feed(data)
                if self._ready:
                    return self._ready.popleft()
                continue
            wait = None if deadline is None else deadline - now
            beat = self.codec.next_deadline() if self.link.can_write() else None
            if beat is not None:
                wait = max(0.0, beat - now) if wait is None else min(wait, max(0.0, beat - now))
            data = self.link.read(wait)
            if data is not None:
                self._feed(data)

    def _close_internal(self) -> None:
        self.link.close()

    # ------------------------------------------------------------------------------- public
    def flush(self) -> None:
        """Push buffered output to the wire (serial); UDP and TCP send at once."""
        self.link.flush()

    def stats(self) -> dict[str, Any]:
        out = self.codec.stats()
        out["link"] = self.link.describe()
        out["queued_frames"] = len(self._ready)
        return out

    def __repr__(self) -> str:
        return (f"<MavlinkTransport {self.link.describe()} sysid={self.codec.system_id} "
                f"compid={self.codec.component_id} mtu={self.mtu}>")

