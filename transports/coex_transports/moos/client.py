"""A native Python client of the MOOS wire protocol (MOOS V10, asynchronous client).

Written from the protocol as core-moos implements it (``CMOOSMsg::Serialize``,
``CMOOSCommPkt::Serialize``, ``CMOOSCommClient::HandShake``, ``MOOSAsyncCommClient``,
``ThreadedCommServer`` and ``CMOOSDB``), without pymoos or libMOOS: a vehicle computer needs
nothing but Python.

Wire format (every integer and double little-endian):

* **message**: ``int32 length`` (of the whole message, this field included), ``int32 id``,
  ``char msg_type``, ``char data_type``, then the strings ``source``, ``source_aux``,
  ``community``, ``key`` (each ``int32 size`` + bytes, no terminator, any byte value), the
  doubles ``time``, ``dval``, ``dval2``, and the string ``sval`` (the value of a ``'S'`` or
  ``'B'`` message).
* **packet**: ``int32 length`` (whole packet), ``int32 count``, ``uint8 compressed`` (always 0),
  then ``count`` messages.
* **handshake**: the client sends the 32-byte, NUL-padded protocol name
  ``ELKS CAN'T DANCE 2/8/10``, then a packet holding one ``'i'`` (data) message whose key is
  ``asynchronous`` and whose string value is the client's name; MOOSDB answers with a ``'W'``
  (welcome: community, ``asynchronous``, the clock skew) or a ``'K'`` (poison: the reason, e.g.
  a client of that name already exists).

An asynchronous client starts every packet it sends with a ``'T'`` (timing) message; MOOSDB
processes the packet, then answers with the timing message echoed (same ``time``) in front of
the mail it holds for the client. This client puts a unique time in each timing message and
so knows which of its packets MOOSDB has processed: a notification is kept until then and sent
again after a reconnect if the answer never came (at least once), and the receiving client
drops the exact duplicates that this (or anything else) may cause. MOOSDB drops a client after
5 s of silence; a timing message goes out every second when there is nothing else to send.

MOOSDB stores the last value of every variable and sends it to a client that registers for the
variable (``CMOOSDB::OnRegister``, with message id -1, in its answer to the packet holding the
registration). On the first registration of a variable this value is older than the client's
interest and is dropped (counted in ``stats()["replays_ignored"]``); on a registration made
again after a reconnect it is delivered unless it was already delivered (it may have been
written while the client was away).

**MOOS time.** Every value carries its writer's MOOS time, and MOOS time is warped: with
``MOOSTimeWarp = W`` in the mission, a MOOS application's clock reads ``W`` times the Unix time
(``MOOSLocalTime``: ``gettimeofday() * W``). ``MoosClient(..., time_warp=W)`` stamps what it
writes the same way (:meth:`MoosClient.moos_time`), so that applications that drop values whose
time is far from theirs (pHelmIvP's ``ok_skew``, 60 MOOS seconds by default) take them;
:meth:`MoosClient.real_time` turns a received value's MOOS time back into Unix seconds. Clock
skew between computers is not estimated (MOOS does it only for a MOOSDB on another host): the
clocks must agree.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import math
import numbers
import select
import socket
import struct
import threading
import time as _time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

__all__ = [
    "PROTOCOL",
    "MAX_TIME_WARP",
    "MoosClient",
    "MoosMessage",
    "MoosProtocolError",
    "RawMessage",
    "decode_packet",
    "encode_packet",
]

log = logging.getLogger(__name__)

#: the largest time warp MOOS accepts (``MAX_TIME_WARP``, ``SetMOOSTimeWarp``)
MAX_TIME_WARP = 400.0
#: the wire protocol name MOOSDB V10 expects first (``MOOS_PROTOCOL_STRING``), sent NUL-padded
PROTOCOL = b"ELKS CAN'T DANCE 2/8/10"
_PROTOCOL_FIELD = 32

# message types (MOOSMsg.h)
NOTIFY = "N"
REGISTER = "R"
UNREGISTER = "U"
NULL_MSG = "."
DATA = "i"
POISON = "K"
WELCOME = "W"
SERVER_REQUEST = "Q"
TIMING = "T"
# data types
DOUBLE = "D"
STRING = "S"
BINARY = "B"
#: id MOOSDB gives its answers to server requests (``MOOS_SERVER_REQUEST_ID``)
SERVER_REQUEST_ID = -2

_HEADER = struct.Struct("<iiB")  # packet: length, message count, compressed flag
_MSG_HEAD = struct.Struct("<iicc")  # message: length, id, message type, data type
_INT = struct.Struct("<i")
_DOUBLES = struct.Struct("<ddd")
_MAX_PACKET = 1 << 28  # refuse a length field above 256 MiB (a corrupt stream)
_PACKET_BUDGET = 1 << 20  # split what is sent into packets of about 1 MiB


class MoosProtocolError(ConnectionError):
    """MOOSDB sent bytes that are not the MOOS wire protocol (the connection is dropped)."""


@dataclass(frozen=True, slots=True)
class RawMessage:
    """One ``CMOOSMsg`` exactly as on the wire (strings as bytes)."""

    msg_type: str
    data_type: str
    key: bytes = b""
    time: float = -1.0
    dval: float = -1.0
    dval2: float = -1.0
    sval: bytes = b""
    source: bytes = b""
    source_aux: bytes = b""
    community: bytes = b""
    id: int = -1

    def encode(self) -> bytes:
        def s(b: bytes) -> bytes:
            return _INT.pack(len(b)) + b

        body = b"".join((
            _INT.pack(self.id),
            self.msg_type.encode("latin-1"),
            self.data_type.encode("latin-1"),
            s(self.source), s(self.source_aux), s(self.community), s(self.key),
            _DOUBLES.pack(self.time, self.dval, self.dval2),
            s(self.sval),
        ))
        return _INT.pack(4 + len(body)) + body

    @classmethod
    def decode(cls, data: bytes | memoryview, pos: int, end: int) -> tuple[RawMessage, int]:
        """Decode the message at ``data[pos:]`` (ending at most at ``end``); return it and the
        position after it."""
        view = memoryview(data)
        if pos + _MSG_HEAD.size > end:
            raise MoosProtocolError("truncated message header")
        length, ident, mtype, dtype = _MSG_HEAD.unpack_from(view, pos)
        stop = pos + length
        if length < _MSG_HEAD.size + 5 * 4 + _DOUBLES.size or stop > end:
            raise MoosProtocolError(f"message length {length} does not fit the packet")
        p = pos + _MSG_HEAD.size

        def string() -> bytes:
            nonlocal p
            if p + 4 > stop:
                raise MoosProtocolError("truncated string size")
            (n,) = _INT.unpack_from(view, p)
            p += 4
            if n < 0 or p + n > stop:
                raise MoosProtocolError(f"string of {n} B overruns its message")
            out = bytes(view[p:p + n])
            p += n
            return out

        source, aux, community, key = string(), string(), string(), string()
        if p + _DOUBLES.size > stop:
            raise MoosProtocolError("truncated doubles")
        t, dval, dval2 = _DOUBLES.unpack_from(view, p)
        p += _DOUBLES.size
        sval = string()
        if p != stop:
            raise MoosProtocolError(f"message has {stop - p} B after its value")
        raw = cls(mtype.decode("latin-1"), dtype.decode("latin-1"), key, t, dval, dval2, sval,
                  source, aux, community, ident)
        return raw, stop


def encode_packet(messages: Iterable[RawMessage]) -> bytes:
    """One ``CMOOSCommPkt``: header and messages."""
    parts = [m.encode() for m in messages]
    body = b"".join(parts)
    return _HEADER.pack(_HEADER.size + len(body), len(parts), 0) + body


def decode_packet(data: bytes | memoryview) -> list[RawMessage]:
    """The messages of one whole packet (``data`` is exactly one packet)."""
    if len(data) < _HEADER.size:
        raise MoosProtocolError("truncated packet header")
    length, count, compressed = _HEADER.unpack_from(data, 0)
    if length != len(data):
        raise MoosProtocolError(f"packet length field {length} != {len(data)} B received")
    if compressed:
        raise MoosProtocolError("compressed MOOS packets are not supported")
    if count < 0:
        raise MoosProtocolError(f"negative message count {count}")
    out = []
    pos = _HEADER.size
    for _ in range(count):
        raw, pos = RawMessage.decode(data, pos, length)
        out.append(raw)
    if pos != length:
        raise MoosProtocolError(f"packet has {length - pos} B after its {count} messages")
    return out


def _text(b: bytes) -> str:
    return b.decode("utf-8", "surrogateescape")


def _bytes(s: str) -> bytes:
    return s.encode("utf-8", "surrogateescape")


@dataclass(frozen=True, slots=True)
class MoosMessage:
    """A notification received from MOOSDB."""

    key: str
    #: ``float`` for ``'D'``, ``str`` for ``'S'``, ``bytes`` for ``'B'``
    value: float | str | bytes
    #: ``'D'`` (double), ``'S'`` (string) or ``'B'`` (binary string)
    kind: str
    #: the time the writer gave the value: its MOOS time (seconds since the epoch times the
    #: community's time warp; :meth:`MoosClient.real_time` undoes the warp)
    time: float
    #: the name of the client that wrote it
    source: str = ""
    #: the MOOS community it was written in
    community: str = ""
    source_aux: str = ""

    @property
    def is_double(self) -> bool:
        return self.kind == DOUBLE

    @property
    def is_string(self) -> bool:
        return self.kind == STRING

    @property
    def is_binary(self) -> bool:
        return self.kind == BINARY

    @classmethod
    def from_raw(cls, raw: RawMessage) -> MoosMessage:
        value: float | str | bytes
        if raw.data_type == DOUBLE:
            value = raw.dval
        elif raw.data_type == BINARY:
            value = raw.sval
        else:
            value = _text(raw.sval)
        return cls(_text(raw.key), value, raw.data_type, raw.time, _text(raw.source),
                   _text(raw.community), _text(raw.source_aux))


def _identity(raw: RawMessage) -> tuple[Any, ...]:
    """What makes two deliveries the same notification: variable, type, writer, time, value."""
    if raw.data_type == DOUBLE:
        value: Any = struct.pack("<d", raw.dval)
    else:
        value = hashlib.blake2b(raw.sval, digest_size=16).digest()
    return (raw.key, raw.data_type, raw.source, struct.pack("<d", raw.time), len(raw.sval), value)


@dataclass
class _Packet:
    """A packet written on the current connection and not yet answered."""

    notifies: list[RawMessage]
    registers: set[bytes] = field(default_factory=set)
    summary: bool = False


class MoosClient:
    """A MOOS client: registers for variables, publishes, receives mail; reconnects by itself.

    ``MoosClient(host, port, name)`` then :meth:`connect` starts a background thread that
    connects to MOOSDB, keeps the connection alive (timing messages every second) and connects
    again after any failure (every ``retry`` seconds, for ever, until :meth:`close`). Nothing
    the caller does blocks longer than the timeout it gives: :meth:`notify`, :meth:`register`
    and :meth:`fetch` only queue or take from queues.

    * :meth:`register` is remembered and sent again after every reconnect.
    * :meth:`notify` queues a value; it is sent when connected, and kept until MOOSDB has
      processed the packet carrying it, so a value given while MOOSDB is down or restarting is
      sent once it is back (at most ``max_pending`` values wait; beyond that the oldest is
      dropped and counted).
    * :meth:`fetch` returns the mail received since the last call, exact duplicates and the
      stored value MOOSDB replays on a first registration removed (see the module
      documentation).
    * ``await_subscribers``: variables whose notifications wait, after each (re)connect, until
      another client has registered for them (MOOSDB is asked with ``PROC_SUMMARY`` server
      requests), or ``await_timeout`` seconds have passed. MOOSDB delivers only to clients
      registered at the time of writing; without this, values queued during a MOOSDB restart
      would be written before the receiving client is back and lost.
    * ``on_connect()`` is called in the client's thread after each successful handshake,
      before anything is sent; it may call :meth:`register` and :meth:`notify` and must not block.
    * ``time_warp``: the community's ``MOOSTimeWarp``; values are stamped with the warped MOOS
      time (see the module documentation).
    """

    def __init__(
        self,
        host: str,
        port: int,
        name: str,
        *,
        on_connect: Callable[[], Any] | None = None,
        await_subscribers: Iterable[str] = (),
        await_timeout: float = 5.0,
        retry: float = 0.5,
        max_pending: int = 10000,
        max_inbox: int = 100000,
        dedupe_window: int = 16384,
        silence_timeout: float = 10.0,
        time_warp: float = 1.0,
    ) -> None:
        if not name:
            raise ValueError("a MOOS client needs a name")
        if isinstance(time_warp, bool) or not 0 < float(time_warp) <= MAX_TIME_WARP:
            raise ValueError(f"time_warp must be a number above 0 and at most {MAX_TIME_WARP:g} "
                             f"(MOOSTimeWarp), got {time_warp!r}")
        self.time_warp = float(time_warp)
        self.host = host
        self.port = int(port)
        self.name = name
        self.on_connect = on_connect
        self.await_subscribers = frozenset(_bytes(v) for v in await_subscribers)
        self.await_timeout = float(await_timeout)
        self.retry = float(retry)
        self.max_pending = int(max_pending)
        self.max_inbox = int(max_inbox)
        self.dedupe_window = int(dedupe_window)
        self.silence_timeout = float(silence_timeout)
        self._name_b = _bytes(name)
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._regs: dict[bytes, float] = {}
        self._registered_once: set[bytes] = set()  # first registration answered (replay dropped)
        self._outbox: deque[RawMessage] = deque()  # notifications not yet written
        self._control: deque[RawMessage] = deque()  # (un)registrations for the current connection
        self._inflight: OrderedDict[float, _Packet] = OrderedDict()
        self._inbox: deque[MoosMessage] = deque()
        self._seen: OrderedDict[tuple[Any, ...], None] = OrderedDict()  # recent, any variable
        self._last_by_key: dict[bytes, tuple[Any, ...]] = {}  # the latest of each variable
        self._subscribed: set[bytes] = set()  # await_subscribers seen subscribed on this connection
        self._summary_at = -math.inf
        self._connected_at = 0.0
        self._sock: socket.socket | None = None
        self._ready = False
        self._community = ""
        self._last_time = 0.0
        self._next_id = 0
        self._thread: threading.Thread | None = None
        self._closing = threading.Event()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._last_error = ""
        self._more = False  # the last packet left sendable notifications behind
        self._counts = {
            "connects": 0, "sent": 0, "received": 0, "duplicates": 0, "replays_ignored": 0,
            "dropped_pending": 0, "dropped_inbox": 0, "resent": 0,
        }

    # ------------------------------------------------------------------ public API
    def connect(self, timeout: float | None = 5.0) -> bool:
        """Start the client (once) and wait up to ``timeout`` seconds until it is connected and
        MOOSDB has processed its registrations. ``False`` on timeout: the client keeps trying."""
        if self._closing.is_set():
            raise ConnectionError("the MOOS client is closed")
        with self._lock:
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name=f"moos-{self.name}", daemon=True)
                self._thread.start()
            return self._cond.wait_for(lambda: self._ready or self._closing.is_set(), timeout) and self._ready

    @property
    def connected(self) -> bool:
        """Connected to MOOSDB, handshake done and the first packet answered."""
        return self._ready

    @property
    def community(self) -> str:
        """The MOOS community of the MOOSDB last connected to ("" before)."""
        return self._community

    def moos_time(self) -> float:
        """Now on the community's MOOS clock: Unix time times ``time_warp`` (``MOOSTime()``)."""
        return _time.time() * self.time_warp

    def real_time(self, moos_time: float) -> float:
        """A MOOS time (a received value's ``time``) as Unix seconds: the warp undone."""
        return moos_time / self.time_warp

    def register(self, var: str, interval: float = 0.0) -> None:
        """Ask for every write of ``var`` (at most one per ``interval`` seconds; 0 = all).
        Remembered: sent again after each reconnect."""
        if not var:
            raise ValueError("cannot register for an empty variable name")
        key = _bytes(var)
        with self._lock:
            self._regs[key] = float(interval)
            if self._sock is not None:
                self._control.append(self._message(REGISTER, DOUBLE, key, dval=float(interval)))
        self._wake()

    def unregister(self, var: str) -> None:
        """Stop receiving ``var``."""
        key = _bytes(var)
        with self._lock:
            if self._regs.pop(key, None) is not None and self._sock is not None:
                self._control.append(self._message(UNREGISTER, DOUBLE, key, dval=0.0))
        self._wake()

    def notify(self, var: str, value: float | str | bytes, time: float | None = None) -> None:
        """Publish ``value`` to ``var``: ``bytes`` as a binary string (``'B'``, any byte values),
        ``str`` as a string (``'S'``), a number as a double (``'D'``). ``time`` (MOOS time)
        defaults to :meth:`moos_time` (strictly increasing within this client). MOOSDB keeps the
        type of a variable's first write and ignores writes of another type: use separate
        variables."""
        if not var:
            raise ValueError("cannot notify an empty variable name")
        key = _bytes(var)
        with self._lock:
            if time is None:
                now = self.moos_time()
                time = now if now > self._last_time else math.nextafter(self._last_time, math.inf)
                self._last_time = time
            if isinstance(value, bytes | bytearray | memoryview):
                msg = self._message(NOTIFY, BINARY, key, time=time, sval=bytes(value))
            elif isinstance(value, str):
                msg = self._message(NOTIFY, STRING, key, time=time, sval=_bytes(value))
            elif isinstance(value, numbers.Real):
                msg = self._message(NOTIFY, DOUBLE, key, time=time, dval=float(value))
            else:
                raise TypeError(f"a MOOS value is bytes, str or a number, not {type(value).__name__}")
            self._outbox.append(msg)
            while len(self._outbox) > self.max_pending:
                self._outbox.popleft()
                self._counts["dropped_pending"] += 1
                if self._counts["dropped_pending"] in (1, 10, 100) or self._counts["dropped_pending"] % 1000 == 0:
                    log.warning("MOOS client %s: %d values waiting for MOOSDB, dropped the oldest (%d so far)",
                                self.name, self.max_pending, self._counts["dropped_pending"])
        self._wake()

    def fetch(self) -> list[MoosMessage]:
        """The mail received since the last call (never blocks)."""
        with self._lock:
            out = list(self._inbox)
            self._inbox.clear()
        return out

    def wait_for_mail(self, timeout: float | None) -> bool:
        """Wait up to ``timeout`` seconds until :meth:`fetch` has something; ``True`` if so."""
        with self._lock:
            return self._cond.wait_for(lambda: bool(self._inbox) or self._closing.is_set(), timeout) \
                and bool(self._inbox)

    def pending(self) -> int:
        """Notifications not yet processed by MOOSDB (queued or written and unanswered)."""
        with self._lock:
            return len(self._outbox) + sum(len(p.notifies) for p in self._inflight.values())

    def flush(self, timeout: float | None = 10.0) -> bool:
        """Wait up to ``timeout`` seconds until MOOSDB has processed every notification given so
        far; ``True`` if it has."""
        with self._lock:
            return self._cond.wait_for(
                lambda: self._closing.is_set() or (
                    not self._outbox and not any(p.notifies for p in self._inflight.values())),
                timeout) and not self._outbox and not any(p.notifies for p in self._inflight.values())

    def close(self) -> None:
        """Stop the thread and drop the connection (idempotent). Call :meth:`flush` first to
        make sure what was notified reached MOOSDB."""
        if self._closing.is_set():
            return
        self._closing.set()
        self._wake()
        with self._lock:
            self._cond.notify_all()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        for s in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                s.close()

    @property
    def closed(self) -> bool:
        return self._closing.is_set()

    def stats(self) -> dict[str, Any]:
        """Counters: ``connects``, ``sent``, ``received``, ``duplicates``, ``replays_ignored``,
        ``dropped_pending``, ``dropped_inbox``, ``resent``; ``pending``, ``connected``,
        ``last_error``."""
        with self._lock:
            pending = len(self._outbox) + sum(len(p.notifies) for p in self._inflight.values())
        return {**self._counts, "pending": pending, "connected": self._ready, "last_error": self._last_error}

    def __enter__(self) -> MoosClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ internals
    def _message(self, mtype: str, dtype: str, key: bytes, *, time: float | None = None,
                 dval: float = -1.0, sval: bytes = b"") -> RawMessage:
        """A message from this client (source and id filled in as ``CMOOSCommClient::Post``)."""
        ident = self._next_id
        self._next_id += 1
        return RawMessage(mtype, dtype, key, self.moos_time() if time is None else time, dval, -1.0,
                          sval, self._name_b, b"", b"", ident)

    def _wake(self) -> None:
        with contextlib.suppress(OSError):
            self._wake_w.send(b"x")

    def _run(self) -> None:
        while not self._closing.is_set():
            sock = self._open()
            if sock is None:
                self._closing.wait(self.retry)
                continue
            try:
                self._serve(sock)
            except (OSError, MoosProtocolError) as exc:
                if not self._closing.is_set():
                    self._last_error = f"{type(exc).__name__}: {exc}"
                    log.warning("MOOS client %s: connection to %s:%d lost (%s); reconnecting",
                                self.name, self.host, self.port, self._last_error)
            finally:
                self._drop(sock)

    def _open(self) -> socket.socket | None:
        """Connect and shake hands; ``None`` (and the reason in ``last_error``) on failure."""
        try:
            sock = socket.create_connection((self.host, self.port), timeout=2.0)
        except OSError as exc:
            self._last_error = f"cannot connect to MOOSDB at {self.host}:{self.port}: {exc}"
            log.debug("MOOS client %s: %s", self.name, self._last_error)
            return None
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.settimeout(5.0)
            hello = RawMessage(DATA, STRING, b"asynchronous", self.moos_time(), -1.0, -1.0, self._name_b)
            sock.sendall(PROTOCOL.ljust(_PROTOCOL_FIELD, b"\0") + encode_packet([hello]))
            reply = decode_packet(self._read_packet(sock))
            if not reply:
                raise MoosProtocolError("empty handshake answer")
            welcome = reply[0]
            if welcome.msg_type == POISON:
                self._last_error = f"MOOSDB refused {self.name!r}: {_text(welcome.sval)}"
                log.warning("MOOS client %s: %s; trying again", self.name, self._last_error)
                sock.close()
                self._closing.wait(max(self.retry, 1.0))  # e.g. our previous connection not yet gone
                return None
            if welcome.msg_type != WELCOME:
                raise MoosProtocolError(f"expected a welcome message, got type {welcome.msg_type!r}")
            if welcome.sval != b"asynchronous":
                log.warning("MOOS client %s: MOOSDB at %s:%d does not say it is asynchronous (%r)",
                            self.name, self.host, self.port, welcome.sval)
            self._community = _text(welcome.community)
        except (OSError, MoosProtocolError) as exc:
            self._last_error = f"handshake with MOOSDB at {self.host}:{self.port} failed: {exc}"
            log.warning("MOOS client %s: %s", self.name, self._last_error)
            sock.close()
            return None
        with self._lock:
            self._sock = sock
            self._connected_at = _time.monotonic()
            self._subscribed = set()
            self._summary_at = -math.inf
            self._control = deque(self._message(REGISTER, DOUBLE, k, dval=v) for k, v in self._regs.items())
            self._counts["connects"] += 1
        log.info("MOOS client %s connected to %s:%d (community %r)", self.name, self.host, self.port,
                 self._community)
        if self.on_connect is not None:
            try:
                self.on_connect()
            except Exception:
                log.exception("MOOS client %s: on_connect failed", self.name)
        return sock

    def _read_packet(self, sock: socket.socket) -> bytes:
        """Read one whole packet with blocking reads (the handshake only)."""
        head = self._read_exact(sock, 4)
        (length,) = _INT.unpack(head)
        if not _HEADER.size <= length <= _MAX_PACKET:
            raise MoosProtocolError(f"bad packet length {length}")
        return head + self._read_exact(sock, length - 4)

    @staticmethod
    def _read_exact(sock: socket.socket, n: int) -> bytes:
        buf = bytearray()
        while len(buf) < n:
            chunk = sock.recv(n - len(buf))
            if not chunk:
                raise ConnectionError("MOOSDB closed the connection")
            buf += chunk
        return bytes(buf)

    def _drop(self, sock: socket.socket) -> None:
        """After a connection ends: what MOOSDB did not confirm goes back to the front of the queue."""
        with contextlib.suppress(OSError):
            sock.close()
        with self._lock:
            self._sock = None
            self._ready = False
            unconfirmed = [m for p in self._inflight.values() for m in p.notifies]
            self._inflight.clear()
            self._control.clear()
            if unconfirmed:
                self._counts["resent"] += len(unconfirmed)
                self._outbox.extendleft(reversed(unconfirmed))
            self._cond.notify_all()

    def _serve(self, sock: socket.socket) -> None:
        buf = bytearray()
        last_sent = -math.inf
        last_heard = _time.monotonic()
        while not self._closing.is_set():
            now = _time.monotonic()
            packet = self._next_packet(now, force=now - last_sent >= 1.0)
            if packet is not None:
                sock.sendall(packet)
                last_sent = now
            # more to write (a backlog split into packets): only look for input, do not wait
            wait = 0.0 if self._more else max(0.0, min(1.0 - (now - last_sent), 0.25))
            readable, _, _ = select.select([sock, self._wake_r], [], [], wait)
            if self._wake_r in readable:
                with contextlib.suppress(OSError):
                    while self._wake_r.recv(4096):
                        pass
            if sock in readable:
                chunk = sock.recv(1 << 16)
                if not chunk:
                    raise ConnectionError("MOOSDB closed the connection")
                buf += chunk
                last_heard = _time.monotonic()
                while len(buf) >= 4:
                    (length,) = _INT.unpack_from(buf, 0)
                    if not _HEADER.size <= length <= _MAX_PACKET:
                        raise MoosProtocolError(f"bad packet length {length}")
                    if len(buf) < length:
                        break
                    self._on_packet(decode_packet(bytes(buf[:length])))
                    del buf[:length]
            elif _time.monotonic() - last_heard > self.silence_timeout:
                raise TimeoutError(f"MOOSDB silent for {self.silence_timeout:.0f} s")

    def _next_packet(self, now: float, force: bool) -> bytes | None:
        """The next packet to write (timing message first), or ``None`` if nothing is due."""
        with self._lock:
            control = list(self._control)
            self._control.clear()
            notifies: list[RawMessage] = []
            size = 0
            held = False
            self._more = False
            hold = now - self._connected_at < self.await_timeout
            if self._outbox:
                keep: deque[RawMessage] = deque()
                for msg in self._outbox:
                    if hold and msg.key in self.await_subscribers and msg.key not in self._subscribed:
                        keep.append(msg)  # no receiver yet: MOOSDB would only store the last one
                        held = True
                        continue
                    if size >= _PACKET_BUDGET:
                        keep.append(msg)
                        self._more = True
                        continue
                    notifies.append(msg)
                    size += len(msg.sval) + 64
                self._outbox = keep
            ask = held and hold and now - self._summary_at >= 0.2
            if not (control or notifies or ask or force):
                return None
            token = _time.time()
            if self._inflight:
                token = max(token, math.nextafter(next(reversed(self._inflight)), math.inf))
            messages = [RawMessage(TIMING, DOUBLE, b"_async_timing", token, 0.0, -1.0, b"", self._name_b)]
            messages += control
            if ask:
                self._summary_at = now
                messages.append(RawMessage(SERVER_REQUEST, STRING, b"PROC_SUMMARY", token, -1.0, -1.0,
                                           b"", self._name_b, b"", b"", SERVER_REQUEST_ID))
            messages += notifies
            self._inflight[token] = _Packet(
                notifies, {m.key for m in control if m.msg_type == REGISTER}, ask)
            self._counts["sent"] += len(notifies)
        return encode_packet(messages)

    def _on_packet(self, messages: list[RawMessage]) -> None:
        with self._lock:
            answered: _Packet | None = None
            if messages and messages[0].msg_type == TIMING:
                token = messages[0].time
                if token in self._inflight:
                    # MOOSDB answers a client's packets in order: everything up to this one is done
                    while self._inflight:
                        t, packet = self._inflight.popitem(last=False)
                        if t == token:
                            answered = packet
                            break
                    if not self._ready:
                        self._ready = True
                messages = messages[1:]
            registered = answered.registers if answered is not None else set()
            for raw in messages:
                if raw.msg_type != NOTIFY:
                    continue  # timing, null messages and anything unexpected
                if raw.id == SERVER_REQUEST_ID and raw.key == b"PROC_SUMMARY":
                    self._on_summary(raw.sval)
                    continue
                ident = _identity(raw)
                if ident in self._seen or self._last_by_key.get(raw.key) == ident:
                    self._counts["duplicates"] += 1
                    continue
                self._seen[ident] = None
                self._last_by_key[raw.key] = ident
                while len(self._seen) > self.dedupe_window:
                    self._seen.popitem(last=False)
                if raw.id == -1 and raw.key in registered and raw.key not in self._registered_once:
                    # the stored value MOOSDB replays to a new subscriber: written before we asked
                    self._counts["replays_ignored"] += 1
                    continue
                self._inbox.append(MoosMessage.from_raw(raw))
                self._counts["received"] += 1
                if len(self._inbox) > self.max_inbox:
                    self._inbox.popleft()
                    self._counts["dropped_inbox"] += 1
            self._registered_once |= registered
            self._cond.notify_all()

    def _on_summary(self, sval: bytes) -> None:
        """``who:SUBSCRIBED=,A,B,PUBLISHED=,C`` (``CMOOSDB::OnProcessSummaryRequested``)."""
        who, _, rest = sval.partition(b":")
        if who == self._name_b:
            return
        subscribed = rest.split(b"PUBLISHED=", 1)[0].removeprefix(b"SUBSCRIBED=")
        for var in subscribed.split(b","):
            if var in self.await_subscribers:
                self._subscribed.add(var)
