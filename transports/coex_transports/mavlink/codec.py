"""Sans-I/O codec of the CoEx MAVLink binding: CoEx frames <-> MAVLink 2 ``TUNNEL`` packets.

:class:`TunnelCodec` turns a CoEx frame into MAVLink packet bytes and turns received bytes (UDP
datagrams or a TCP/serial byte stream) back into whole CoEx frames. It never sleeps, never reads a
clock and never touches a socket: every method that depends on time takes ``now`` (float seconds,
monotonic). It uses the generated ``MAVLink`` class of ``pymavlink.dialects.v20.common``
(``pack`` / ``parse_buffer``) and never imports ``mavutil``.

The receive path never raises on bad input: every rejected packet or fragment is counted and its
:class:`~coex_core.errors.DecodeError` kept in :attr:`TunnelCodec.errors` (the most recent
``max_errors``), and parsing resumes at the next byte, so a good packet that follows garbage is
never lost.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from coex_core.errors import ConfigError, DecodeError, EncodeError

from ._fragment import (
    MAX_FRAME_BYTES,
    TUNNEL_PAYLOAD_BYTES,
    Fragment,
    Reassembler,
    fragments_needed,
    parse_fragment,
    split_frame,
)

__all__ = [
    "DEFAULT_COMPONENT_ID",
    "DEFAULT_MTU",
    "DEFAULT_SYSTEM_ID",
    "PAYLOAD_TYPE",
    "TunnelCodec",
    "parse_tunnel",
]

#: ``TUNNEL.payload_type`` of CoEx frames: 0xC0E5, in the range common.xml reserves for local
#: use (32768..65535).
PAYLOAD_TYPE = 0xC0E5
#: Default MAVLink system id of a CoEx node.
DEFAULT_SYSTEM_ID = 1
#: Default MAVLink component id: ``MAV_COMP_ID_ONBOARD_COMPUTER`` (191).
DEFAULT_COMPONENT_ID = mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER
#: Default largest CoEx frame (17 fragments).
DEFAULT_MTU = 2048

_TUNNEL_ID = mavlink2.MAVLINK_MSG_ID_TUNNEL
_HEARTBEAT_ID = mavlink2.MAVLINK_MSG_ID_HEARTBEAT
_BAD_DATA_ID = mavlink2.MAVLINK_MSG_ID_BAD_DATA
_UNKNOWN_ID = mavlink2.MAVLINK_MSG_ID_UNKNOWN


class _Collector:
    """The ``file`` of the generated ``MAVLink`` object: collects packed packets in memory."""

    def __init__(self) -> None:
        self.packets: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.packets.append(bytes(data))

    def take(self) -> list[bytes]:
        out, self.packets = self.packets, []
        return out


def _check_id(name: str, value: int, low: int, high: int) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
        raise ConfigError(f"{name} must be an integer in {low}..{high}, got {value!r}")
    return value


def parse_tunnel(msg: Any) -> bytes:
    """The significant payload bytes of a decoded ``TUNNEL`` message.

    Raises :class:`~coex_core.errors.DecodeError` if ``payload_length`` exceeds 128 or if a byte
    after ``payload_length`` is not zero (a sender must zero-fill the unused payload)."""
    length = int(msg.payload_length)
    if length > TUNNEL_PAYLOAD_BYTES:
        raise DecodeError(f"TUNNEL payload_length {length} exceeds {TUNNEL_PAYLOAD_BYTES}")
    payload = bytes(msg.payload)
    if any(payload[length:]):
        raise DecodeError(f"TUNNEL payload has non-zero bytes after payload_length {length}")
    return payload[:length]


class TunnelCodec:
    """Frames to ``TUNNEL`` packets and back, for one MAVLink component.

    Parameters
    ----------
    system_id, component_id:
        Our MAVLink identity (1..255). Packets that carry it as their source are our own echo and
        are ignored.
    target_system, target_component:
        Where our ``TUNNEL`` messages are addressed (0 = broadcast). Received ``TUNNEL`` messages
        are accepted only if their target system is 0 or ``system_id`` and their target component
        is 0 or ``component_id``.
    payload_type:
        ``TUNNEL.payload_type`` of CoEx frames (32768..65535, default :data:`PAYLOAD_TYPE`);
        ``TUNNEL`` messages of any other type are ignored (they are someone else's).
    mtu:
        Largest CoEx frame sent or accepted (at most 31,620 bytes).
    reassembly_timeout, max_partial:
        A partial frame is dropped this many seconds after its first fragment; at most
        ``max_partial`` partial frames are held at once.
    heartbeat_interval:
        Seconds between ``HEARTBEAT`` messages returned by :meth:`poll` (0 disables them).
    """

    def __init__(
        self,
        *,
        system_id: int = DEFAULT_SYSTEM_ID,
        component_id: int = DEFAULT_COMPONENT_ID,
        target_system: int = 0,
        target_component: int = 0,
        payload_type: int = PAYLOAD_TYPE,
        mtu: int = DEFAULT_MTU,
        reassembly_timeout: float = 5.0,
        max_partial: int = 8,
        heartbeat_interval: float = 1.0,
        max_errors: int = 32,
    ) -> None:
        self.system_id = _check_id("sysid", system_id, 1, 255)
        self.component_id = _check_id("compid", component_id, 1, 255)
        self.target_system = _check_id("target_system", target_system, 0, 255)
        self.target_component = _check_id("target_component", target_component, 0, 255)
        self.payload_type = _check_id("payload_type", payload_type, 32768, 65535)
        self.mtu = _check_id("mtu", mtu, 1, MAX_FRAME_BYTES)
        if heartbeat_interval < 0:
            raise ConfigError(f"heartbeat interval must not be negative, got {heartbeat_interval}")
        self.heartbeat_interval = float(heartbeat_interval)
        self.reassembler = Reassembler(timeout=reassembly_timeout, max_partial=max_partial, max_frame=mtu)
        self._out = _Collector()
        self._mav = mavlink2.MAVLink(self._out, srcSystem=self.system_id, srcComponent=self.component_id)
        self._parser = mavlink2.MAVLink(None, srcSystem=self.system_id, srcComponent=self.component_id)
        self._parser.robust_parsing = True
        self._quiet_end = 0
        self._frame_id = 0
        self._next_heartbeat: float | None = None
        self.errors: deque[DecodeError] = deque(maxlen=max_errors)
        #: ``(system, component) -> now`` of the last ``HEARTBEAT`` seen from each other component.
        self.peers: dict[tuple[int, int], float] = {}
        self.counters: dict[str, int] = dict.fromkeys(
            ("frames_sent", "packets_sent", "heartbeats_sent", "bytes_received", "packets_received",
             "frames_received", "fragments_received", "rejected", "own", "not_for_us",
             "other_payload_type", "other_messages"),
            0,
        )

    # ------------------------------------------------------------------------------- sending
    def encode(self, frame: bytes) -> list[bytes]:
        """MAVLink packets (one ``TUNNEL`` each) that carry ``frame``; send them in order."""
        if not isinstance(frame, bytes | bytearray | memoryview):
            raise TypeError("a frame is bytes")
        if len(frame) > self.mtu:
            raise EncodeError(f"frame of {len(frame)} B exceeds the MTU of {self.mtu} B")
        for payload in split_frame(bytes(frame), self._frame_id):
            padded = list(payload) + [0] * (TUNNEL_PAYLOAD_BYTES - len(payload))
            self._mav.send(self._mav.tunnel_encode(
                self.target_system, self.target_component, self.payload_type, len(payload), padded
            ))
        self._frame_id = (self._frame_id + 1) % 256
        packets = self._out.take()
        self.counters["frames_sent"] += 1
        self.counters["packets_sent"] += len(packets)
        return packets

    def packets_for(self, size: int) -> int:
        """How many ``TUNNEL`` packets a frame of ``size`` bytes needs."""
        return fragments_needed(size)

    def heartbeat(self) -> bytes:
        """One ``HEARTBEAT`` packet announcing this component (an onboard controller, active)."""
        self._mav.send(self._mav.heartbeat_encode(
            mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0,
            mavlink2.MAV_STATE_ACTIVE,
        ))
        self.counters["heartbeats_sent"] += 1
        return self._out.take()[0]

    def poll(self, now: float, *, can_send: bool = True) -> list[bytes]:
        """Housekeeping at time ``now``: expire stale partial frames and return the packets due
        (a ``HEARTBEAT`` when one is due; the first call always returns one if enabled).

        ``can_send=False`` (a listening end that has no peer yet) keeps a due heartbeat due, so it
        goes out at the first call that can send it."""
        self.reassembler.expire(now)
        if self.heartbeat_interval <= 0 or not can_send:
            return []
        if self._next_heartbeat is None or now >= self._next_heartbeat or now < self._next_heartbeat - self.heartbeat_interval:
            self._next_heartbeat = now + self.heartbeat_interval
            return [self.heartbeat()]
        return []

    def next_deadline(self) -> float | None:
        """When :meth:`poll` next has something to do (a heartbeat), or ``None``."""
        return self._next_heartbeat if self.heartbeat_interval > 0 else None

    # ----------------------------------------------------------------------------- receiving
    def receive(self, data: bytes, now: float, *, datagram: bool = False) -> list[bytes]:
        """Feed received bytes; return the CoEx frames they complete, in order.

        With ``datagram=True`` (UDP) the bytes are one whole datagram: an incomplete packet at
        its end is rejected rather than kept for the next call. Without it (TCP, serial) the
        bytes are a piece of a stream and an incomplete packet waits for more.

        Never raises on bad input (see :attr:`errors` and :attr:`counters`)."""
        self.counters["bytes_received"] += len(data)
        frames: list[bytes] = []
        for msg in self._parse(bytes(data)):
            frame = self._handle(msg, now)
            if frame is not None:
                frames.append(frame)
        parser = self._parser
        while datagram and parser.buf_len() > 0:
            # an incomplete packet at the end of a datagram never completes; it may be a false
            # start hiding good packets, so re-scan from its second byte (at most ~280 bytes)
            start = parser.buf_index
            rest = bytes(parser.buf[start:])
            if start >= self._quiet_end:
                self._reject(f"truncated MAVLink packet: {len(rest)} B left at the end of a datagram")
            for msg in self._parse(self._restart(rest, start)):
                frame = self._handle(msg, now)
                if frame is not None:
                    frames.append(frame)
        if datagram:
            self._reset_parser()
        return frames

    def _reset_parser(self) -> None:
        self._parser.buf = bytearray()
        self._parser.buf_index = 0
        self._parser.expected_length = mavlink2.HEADER_LEN_V1 + 2
        self._parser.have_prefix_error = False
        self._quiet_end = 0

    def _restart(self, region: bytes, start: int) -> bytes:
        """Give up the candidate packet ``region`` found at buffer offset ``start``: reset the
        parser and return what to feed it again, the candidate minus its first byte followed by
        everything after it. Errors inside the re-fed candidate are not counted again."""
        parser = self._parser
        after = bytes(parser.buf[parser.buf_index:]) if parser.buf_index >= start + len(region) else b""
        old_quiet = self._quiet_end
        self._reset_parser()
        interior = region[1:]
        self._quiet_end = max(len(interior), old_quiet - (start + 1))
        return interior + after

    def _parse(self, data: bytes) -> Iterator[Any]:
        """Packets in ``data`` (plus what the parser holds), resynchronising byte by byte.

        When a candidate packet fails its length, flags or CRC check, or is a MAVLink 1 message
        of an id the common dialect lacks (so its CRC cannot be checked), or claims a MAVLink 2
        id above 65535 (no dialect uses one), parsing restarts one byte after its start: a good
        packet hidden behind a corrupt or false header is still found. Each rejected candidate
        is counted once; the junk re-scanned inside it is not counted again."""
        parser = self._parser
        feed = data
        while True:
            start = parser.buf_index
            quiet = start < self._quiet_end
            try:
                msg = parser.parse_char(feed)
            except Exception as exc:  # pymavlink is robust_parsing; anything else is its bug
                if not quiet:
                    self._reject(f"MAVLink parser error: {type(exc).__name__}: {exc}")
                held = bytes(parser.buf[start:])
                old_quiet = self._quiet_end
                self._reset_parser()
                self._quiet_end = max(0, old_quiet - (start + 1))
                feed = held[1:]
                continue
            feed = b""
            if parser.buf_index == 0 and not parser.buf:
                self._quiet_end = 0  # the parser emptied (and reset) its buffer
            if msg is None:
                return
            msg_id = msg.get_msgId()
            if msg_id == _BAD_DATA_ID:
                reason = str(getattr(msg, "reason", "bad data"))
                bad = bytes(getattr(msg, "data", b""))
                if not quiet:
                    self._reject(f"bad MAVLink data ({len(bad)} B): {reason}")
                if reason != "Bad prefix" and len(bad) > 1:
                    feed = self._restart(bad, start)
                continue
            if msg_id == _UNKNOWN_ID:
                raw = bytes(getattr(msg, "data", b""))
                if raw[:1] == b"\xfe":
                    if not quiet:
                        self.counters["other_messages"] += 1
                    feed = self._restart(raw, start)
                    continue
                if len(raw) >= 10 and raw[9]:
                    if not quiet:
                        ident = raw[7] | raw[8] << 8 | raw[9] << 16
                        self._reject(f"bad MAVLink data ({len(raw)} B): implausible message id {ident}")
                    feed = self._restart(raw, start)
                    continue
            yield msg

    def _reject(self, reason: str) -> None:
        self.counters["rejected"] += 1
        self.errors.append(DecodeError(reason))

    def _handle(self, msg: Any, now: float) -> bytes | None:
        self.counters["packets_received"] += 1
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if src == (self.system_id, self.component_id):
            self.counters["own"] += 1
            return None
        msg_id = msg.get_msgId()
        if msg_id == _HEARTBEAT_ID:
            self.peers[src] = now
            if len(self.peers) > 64:
                self.peers.pop(min(self.peers, key=self.peers.__getitem__))
            return None
        if msg_id != _TUNNEL_ID:
            self.counters["other_messages"] += 1
            return None
        if msg.payload_type != self.payload_type:
            self.counters["other_payload_type"] += 1
            return None
        if msg.target_system not in (0, self.system_id) or msg.target_component not in (0, self.component_id):
            self.counters["not_for_us"] += 1
            return None
        try:
            fragment: Fragment = parse_fragment(parse_tunnel(msg))
            self.counters["fragments_received"] += 1
            frame = self.reassembler.add(src, fragment, now)
        except DecodeError as exc:
            self.counters["rejected"] += 1
            self.errors.append(DecodeError(f"from {src[0]}/{src[1]}: {exc}"))
            return None
        if frame is not None:
            self.counters["frames_received"] += 1
        return frame

    def stats(self) -> dict[str, Any]:
        """Counters of both directions, reassembly state, peers seen and the last error."""
        out: dict[str, Any] = dict(self.counters)
        out.update({f"reassembly_{k}": v for k, v in self.reassembler.stats().items()})
        out["peers"] = sorted(self.peers)
        out["last_error"] = str(self.errors[-1]) if self.errors else ""
        return out
