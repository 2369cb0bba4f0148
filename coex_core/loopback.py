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

:class:`RoundTrip` is the one sender↔receiver loop: a modality's sender and receiver joined
by two lossy links (seeded :class:`LossModel` per direction), driven round by round without a
node (the conformance kit's ``LinkedPair``, ``coex image roundtrip``/``region``, ``coex bathy
roundtrip``, ``coex timeseries roundtrip`` and the imagery and time-series benchmarks run on it).
"""

from __future__ import annotations

import abc
import heapq
import random
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

from . import wire
from .errors import ConfigError, EncodeError, RequestRejected
from .messages import FrameHeader, Message
from .modality import ModalityReceiver, ModalitySender, Product
from .transport import Transport, UriInfo, parse_query

__all__ = ["Bernoulli", "LoopbackLink", "LoopbackTransport", "LossModel", "RoundTrip", "SimClock", "WireEvent"]


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


class LossModel(abc.ABC):
    """Decides, frame by frame, whether a frame is lost."""

    @abc.abstractmethod
    def lost(self) -> bool:
        """Whether the next frame is lost."""


class Bernoulli(LossModel):
    """Each frame is lost independently with probability ``p``, drawn from
    ``random.Random(seed)`` (the same draws as a :class:`LoopbackLink` of that loss and seed)."""

    def __init__(self, p: float, seed: int = 0) -> None:
        if not 0.0 <= p <= 1.0:
            raise ValueError(f"loss must be in [0, 1], got {p}")
        self.p = p
        self.rng = random.Random(seed)

    def lost(self) -> bool:
        return self.p > 0 and self.rng.random() < self.p


@dataclass
class WireEvent:
    """One message on the wire, in send order."""

    direction: str  # "down" (vehicle to ship) or "up"
    frame: int
    message: Message
    size: int
    lost: bool
    now: float
    wire_total: int  # cumulative wire bytes (both directions, frame headers included)
    down_total: int  # cumulative vehicle-to-ship wire bytes


@dataclass
class _Frame:
    """One frame on the wire: the messages the other side gets (none when it is lost), and
    their events."""

    got: list[Message]
    events: list[WireEvent]


class RoundTrip:
    """The one sender↔receiver loop: a modality's ``sender`` and ``receiver`` joined by a
    down link (vehicle to ship) and an up link, each losing whole frames as its
    :class:`LossModel` says, driven round by round on simulated time (no node, no clock, no I/O).

    Each :meth:`step` (one round, ``round_seconds`` later): the sender fills one frame of at most
    ``mtu`` bytes (its header included) that goes down; the receiver takes what arrives and its
    :meth:`~coex_core.modality.ModalityReceiver.poll` goes up in as many frames as it needs; the
    sender handles what arrives (a request it refuses with one of ``rejects`` is recorded in
    :attr:`rejected`) and its answers go down in as many frames as they need, arriving in the same
    round, or with ``replies_next_round`` one answer a frame arriving before the next round's
    frame. With ``acks`` the sender learns the fate of each filled frame, as a node's channel
    manager tells it from frame acks: ``acked`` for every message of a frame that arrived and
    whose ack (one draw of the up link's loss, riding the receiver's transmission) came back,
    ``lost`` otherwise (a frame's ack that is lost makes its messages look lost, as it does on a
    real link). With ``decode`` each side gets the messages decoded from the frame's bytes
    (``wire.unpack``), otherwise the other side's objects. A sender that fills more than the
    budget raises ``overfill`` (default :class:`~coex_core.errors.EncodeError`).

    Every message sent is in :attr:`events` (:class:`WireEvent`, with the wire bytes so far);
    ``on_message(event, products)`` is called once per message: when it is lost, when it reaches
    the vehicle, or with the receiver's products when it reaches topside."""

    def __init__(
        self,
        sender: ModalitySender,
        receiver: ModalityReceiver,
        *,
        mtu: int = 256,
        down: LossModel | None = None,
        up: LossModel | None = None,
        round_seconds: float = 5.0,
        now: float = 0.0,
        decode: bool = False,
        replies_next_round: bool = False,
        rejects: tuple[type[BaseException], ...] = (RequestRejected,),
        overfill: type[Exception] = EncodeError,
        on_message: Callable[[WireEvent, list[Product]], None] | None = None,
        acks: bool = False,
    ) -> None:
        self.sender = sender
        self.receiver = receiver
        self.mtu = mtu
        self.down: LossModel = down if down is not None else Bernoulli(0.0)
        self.up: LossModel = up if up is not None else Bernoulli(0.0)
        self.round_seconds = round_seconds
        self.now = now
        self.decode = decode
        self.replies_next_round = replies_next_round
        self.rejects = rejects
        self.overfill = overfill
        self.on_message = on_message
        self.acks = acks
        self.events: list[WireEvent] = []
        #: what the sender filled, every message the receiver was handed, every request the
        #: receiver polled (lost or not), and the requests the sender refused
        self.sent: list[Message] = []
        self.received: list[Message] = []
        self.requests: list[Message] = []
        self.rejected: list[Message] = []
        #: the last round's fill and requests
        self.last_fill: list[Message] = []
        self.last_requests: list[Message] = []
        self._frame = 0
        self._wire = 0
        self._down = 0
        self._late: list[_Frame] = []

    # ------------------------------------------------------------------ frames
    def batches(self, messages: list[Message]) -> list[list[Message]]:
        """``messages`` packed greedily, in order, into frames of at most ``mtu`` bytes."""
        batches: list[list[Message]] = []
        batch: list[Message] = []
        used = wire.header_size()
        for m in messages:
            size = wire.encoded_size(m)
            if used + size > self.mtu and batch:
                batches.append(batch)
                batch, used = [], wire.header_size()
            batch.append(m)
            used += size
        if batch:
            batches.append(batch)
        return batches

    def _send(self, direction: str, messages: list[Message]) -> _Frame | None:
        """Put one frame on the wire (EncodeError when it does not fit): its events, the loss
        draw, and ``on_message`` for a lost one. Returns the frame (None without messages)."""
        if not messages:
            return None
        header = FrameHeader(src=2 if direction == "down" else 1, dst=1 if direction == "down" else 2,
                             seq=self._frame % 256)
        data = wire.pack(messages, self.mtu, header)
        lost = (self.down if direction == "down" else self.up).lost()
        self._frame += 1
        events = []
        for i, m in enumerate(messages):
            size = wire.encoded_size(m)
            extra = wire.header_size(header) if i == 0 else 0
            self._wire += size + extra
            if direction == "down":
                self._down += size + extra
            ev = WireEvent(direction, self._frame - 1, m, size, lost, self.now, self._wire, self._down)
            self.events.append(ev)
            events.append(ev)
        if lost:
            if self.on_message is not None:
                for ev in events:
                    self.on_message(ev, [])
            return _Frame([], events)
        return _Frame(wire.unpack(data) if self.decode else list(messages), events)

    def _to_receiver(self, frame: _Frame | None) -> None:
        if frame is None:
            return
        for m, ev in zip(frame.got, frame.events if frame.got else (), strict=True):
            self.received.append(m)
            products = self.receiver.receive(m, self.now)
            if self.on_message is not None:
                self.on_message(ev, products)

    def _to_sender(self, frame: _Frame, replies: list[Message]) -> None:
        for m, ev in zip(frame.got, frame.events if frame.got else (), strict=True):
            if self.on_message is not None:
                self.on_message(ev, [])
            try:
                replies.extend(self.sender.handle(m, self.now))
            except self.rejects:
                self.rejected.append(m)

    # ------------------------------------------------------------------ rounds
    def step(self) -> None:
        """One round (see the class)."""
        self.now += self.round_seconds
        self._exchange(self._fill())

    def poll(self) -> None:
        """The second half of a round at ``now``, without a fill: the receiver's poll goes up
        and the sender's answers come down (a request made between rounds)."""
        self._exchange([])

    def drain(self) -> int:
        """Rounds at ``now``, ``now + round_seconds`` ... while the sender has something to send:
        the first empty fill ends it, at its time, before the receiver polls. Returns the
        rounds that sent something."""
        rounds = 0
        while out := self._fill():
            self._exchange(out)
            self.now += self.round_seconds
            rounds += 1
        return rounds

    def _fill(self) -> list[Message]:
        budget = self.mtu - wire.header_size()
        out = self.sender.fill(budget, self.now)
        total = sum(wire.encoded_size(m) for m in out)
        if total > budget:
            raise self.overfill(f"sender returned {total} B for a budget of {budget} B")
        self.last_fill = out
        self.sent.extend(out)
        return out

    def _exchange(self, out: list[Message]) -> None:
        """The round after the fill: ``out`` goes down, the receiver polls, its requests go up,
        the sender's answers come down."""
        late, self._late = self._late, []
        filled = self._send("down", out)
        for answers in late:  # the last round's answers were on the wire first
            self._to_receiver(answers)
        self._to_receiver(filled)
        if self.acks and filled is not None:
            # the frame ack rides up with the receiver's next transmission (its own loss draw):
            # the sender learns which of its messages arrived, as a node's channel tells it
            acked = bool(filled.got) and not self.up.lost()
            for ev in filled.events:
                if acked:
                    self.sender.acked(ev.message, self.now)
                else:
                    self.sender.lost(ev.message, self.now)
        requests = self.receiver.poll(self.now)
        self.last_requests = requests
        self.requests.extend(requests)
        replies: list[Message] = []
        for batch in self.batches(requests):
            asked = self._send("up", batch)
            if asked is not None:
                self._to_sender(asked, replies)
        for batch in ([[r] for r in replies] if self.replies_next_round else self.batches(replies)):
            try:
                answer = self._send("down", batch)
            except EncodeError:
                continue
            if self.replies_next_round:
                if answer is not None:
                    self._late.append(answer)
            else:
                self._to_receiver(answer)

    def run(self, done: Callable[[], bool], max_rounds: int) -> int:
        """Step until ``done()``; return the rounds used (raises ``TimeoutError`` after
        ``max_rounds``)."""
        for i in range(max_rounds):
            if done():
                return i
            self.step()
        if done():
            return max_rounds
        raise TimeoutError(f"not done after {max_rounds} rounds ({self.now:.0f} simulated s)")
