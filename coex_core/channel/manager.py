"""The channel manager: streams, the priority contest, packing, pulls, acks, TDMA, links.

Sans-I/O: every method takes ``now`` (float seconds, the shared clock of the deployment or a
simulated one). The only time source besides ``now`` is the optional ``clock`` callable the
caller passes in to measure how long modality senders take while a packet is built.

See ``docs/channel.md`` for the design (ack scheme, schedule switching, watchdog).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from ..acoustic import RateInfo, rate_info
from ..auth import TRAILER_BYTES, CommandSigner, CommandVerifier, is_command
from ..errors import CoexError, ConfigError, EncodeError
from ..messages import (
    AckStatus,
    CommandAck,
    FrameAck,
    FrameAckEntry,
    FrameHeader,
    LinkControl,
    Message,
    QueueConfig,
    QueueStatus,
    ScheduleUpdate,
    StreamStatus,
)
from ..modality import ModalitySender
from ..timefmt import to_stamp
from ..wire import encoded_size, header_size, pack
from .events import (
    Acked,
    CommandApplied,
    CommandResult,
    Dropped,
    Event,
    LinkChanged,
    ScheduleSwitched,
    SenderFailed,
)
from .queue import Entry, StreamConfig, StreamQueue
from .schedule import Schedule, SlotWindow, resolve_cycle

__all__ = [
    "CONTROL_STREAM",
    "QUEUE_STATUS_STREAM",
    "STATUS_STREAM",
    "ChannelManager",
    "LinkConfig",
    "Transmission",
    "default_streams",
]

#: Built-in stream ids (tier 0): vehicle status, queue status, control (commands, command acks,
#: operator requests). Modality streams use ids 3..31.
STATUS_STREAM = 0
QUEUE_STATUS_STREAM = 1
CONTROL_STREAM = 2

SEQ_MODULUS = 256
MAX_ACK_ENTRIES = 16


def default_streams() -> list[StreamConfig]:
    """The three built-in tier-0 streams."""
    return [
        StreamConfig(STATUS_STREAM, "status", tier=0, priority=127, ttl=0, max_depth=1,
                     newest_first=True),
        StreamConfig(QUEUE_STATUS_STREAM, "queue-status", tier=0, priority=80, ttl=0, max_depth=1,
                     newest_first=True),
        StreamConfig(CONTROL_STREAM, "control", tier=0, priority=127, ttl=0, max_depth=64,
                     ack_required=True),
    ]


@dataclass(frozen=True)
class LinkConfig:
    """One modem link: its safe schedule, frame layout and policies.

    ``rate`` picks the Micromodem packet type; ``frames``/``frame_bytes`` override its frame
    count/size (e.g. a 3.5 kHz modem with another layout). ``packet_seconds`` is the time reserved
    per packet (default: the rate's full-packet airtime). ``ack_timeout`` (default one cycle) is
    when an unacked message becomes sendable again; ``watchdog_cycles`` silent cycles on a
    non-safe schedule fall back to ``schedule``. ``dst`` is the frame header destination."""

    link: int
    schedule: Schedule
    rate: int = 5
    frames: int | None = None
    frame_bytes: int | None = None
    crc: bool = False
    enabled: bool = True
    muted: bool = False
    ack_timeout: float | None = None
    watchdog_cycles: int = 3
    packet_seconds: float | None = None
    gap: float = 0.0
    dst: int = 0
    band: str = ""

    def __post_init__(self) -> None:
        if not 0 <= self.link <= 7:
            raise ConfigError(f"link id {self.link} outside 0..7")
        info = rate_info(self.rate)
        if self.frames is not None and not 1 <= self.frames <= 8:
            raise ConfigError("frames per packet must be 1..8 (the ack bitmap has 8 bits)")
        if self.frame_bytes is not None and self.frame_bytes < header_size(FrameHeader(crc=True)) + 2:
            raise ConfigError(f"frame_bytes {self.frame_bytes} too small")
        if self.watchdog_cycles < 1:
            raise ConfigError("watchdog_cycles must be >= 1")
        if (self.frames or info.frames) > 8:
            raise ConfigError("at most 8 frames per packet")

    @property
    def info(self) -> RateInfo:
        return rate_info(self.rate)

    @property
    def n_frames(self) -> int:
        return self.frames or self.info.frames

    @property
    def fbytes(self) -> int:
        return self.frame_bytes or self.info.frame_bytes

    @property
    def packet_time(self) -> float:
        if self.packet_seconds is not None:
            return self.packet_seconds
        return self.info.airtime(self.n_frames * self.fbytes)

    def airtime(self, n_frames: int) -> float:
        return self.info.airtime(n_frames * self.fbytes)


@dataclass(frozen=True)
class Transmission:
    """One packet to send now on ``link_id`` at ``rate``: whole frames, in order.

    ``seq`` is the header seq of the first frame (frame i has ``seq + i`` mod 256);
    ``capacity`` is the byte size of a full packet on this link, ``used`` the message bytes
    packed (headers excluded), ``duration`` the airtime."""

    link_id: int
    rate: int
    frames: tuple[bytes, ...]
    seq: int = 0
    start: float = 0.0
    duration: float = 0.0
    slot: int | None = None
    cycle: int | None = None
    capacity: int = 0
    used: int = 0
    messages: int = 0
    schedule: int = 0


@dataclass
class _PendingSchedule:
    schedule: Schedule  # with epoch/first_cycle set to its activation
    command_id: int


@dataclass
class _Link:
    cfg: LinkConfig
    current: Schedule
    enabled: bool
    muted: bool
    pending: _PendingSchedule | None = None
    #: Topside: proposals awaiting the vehicle's CommandAck (command id -> proposal).
    proposed: dict[int, _PendingSchedule] = field(default_factory=dict)
    seq: int = 0
    busy_until: float = -math.inf
    #: Nothing to send at the last opportunity: do not look again before this (unless pushed).
    idle_until: float = -math.inf
    last_heard: float | None = None
    switched_at: float | None = None
    #: (link, seq) records of this link's transmissions: entry ids per frame seq.
    sent: dict[int, list[tuple[int, int]]] = field(default_factory=dict)
    packets: int = 0
    frames_tx: int = 0
    frames_rx: int = 0

    @property
    def safe(self) -> Schedule:
        return self.cfg.schedule

    @property
    def ack_timeout(self) -> float:
        return self.cfg.ack_timeout if self.cfg.ack_timeout is not None else self.current.cycle


@dataclass
class _Stream:
    queue: StreamQueue
    sender: ModalitySender | None = None


class ChannelManager:
    """Queues, packing, TDMA and links of one node (vehicle or topside).

    ``clock`` (optional, e.g. ``time.perf_counter`` passed in by the runner) measures sender
    fill time: a sender slower than ``sender_budget`` seconds, or any sender once the packet has
    spent ``fill_budget`` seconds, is "no data" for the rest of that packet.
    ``queue_status_interval`` (s) makes the node send a :class:`QueueStatus` that often
    (``None``: never).
    ``command_key`` (at least 16 bytes, shared by topside and vehicle) turns on command
    authentication (spec section 10): frames this node sends that carry commands end with an
    ``AuthTrailer`` (13 bytes reserved while packing), signed by :attr:`signer`; the node checks
    received frames with :attr:`verifier`. Both counters are part of :meth:`export_settings`.
    """

    #: counters a restarted signer skips (frames it may have signed after its last save)
    COUNTER_MARGIN = 1024

    def __init__(
        self,
        node_id: int,
        links: Sequence[LinkConfig],
        streams: Iterable[StreamConfig] = (),
        *,
        clock: Callable[[], float] | None = None,
        fill_budget: float = 1.0,
        sender_budget: float = 0.25,
        queue_status_interval: float | None = None,
        ack_frames: bool = True,
        idle_interval: float = 1.0,
        command_key: bytes | None = None,
    ) -> None:
        if not 1 <= node_id <= 15:
            raise ConfigError(f"node id {node_id} outside 1..15")
        if not links:
            raise ConfigError("a channel manager needs at least one link")
        self.node_id = node_id
        self.clock = clock
        self.fill_budget = float(fill_budget)
        self.sender_budget = float(sender_budget)
        self.queue_status_interval = queue_status_interval
        self.ack_frames = ack_frames
        self.idle_interval = float(idle_interval)
        self.signer = CommandSigner(command_key) if command_key is not None else None
        self.verifier = CommandVerifier(command_key) if command_key is not None else None
        #: which messages are commands (signed when sent, verified when received); the node
        #: extends it with its modalities' request types
        self.is_command: Callable[[Message], bool] = is_command
        self._links: dict[int, _Link] = {}
        for cfg in links:
            if cfg.link in self._links:
                raise ConfigError(f"link {cfg.link} configured twice")
            self._links[cfg.link] = _Link(cfg, cfg.schedule, cfg.enabled, cfg.muted)
        self._streams: dict[int, _Stream] = {}
        self._defaults: dict[int, StreamConfig] = {}
        given = {s.stream: s for s in streams}
        for s in default_streams():
            given.setdefault(s.stream, s)
        for sid in sorted(given):
            self.add_stream(given[sid])
        self._entry_ids = 0
        self._build_no = 0
        self._events: list[Event] = []
        #: (src, link) -> {seq: when received} of the frames to acknowledge
        self._to_ack: dict[tuple[int, int], dict[int, float]] = {}
        self._ack_times: dict[tuple[int, int, int], float] = {}  # of the acks being packed
        self._last_qs: float | None = None
        self._command_id = 0
        self._commands: dict[int, Message] = {}  # topside: sent commands awaiting a CommandAck
        self.stats: dict[str, int] = {"packets": 0, "frames": 0, "used_bytes": 0, "capacity": 0,
                                      "acked": 0, "resent": 0, "sender_failures": 0,
                                      "signed": 0, "stale_acks": 0}

    def __getstate__(self) -> dict[str, Any]:
        """Everything but the ``clock`` callable (the state can be pickled; the restorer
        attaches a clock again)."""
        state = dict(self.__dict__)
        state["clock"] = None
        return state

    # =========================================================================== streams
    def add_stream(self, config: StreamConfig, sender: ModalitySender | None = None) -> StreamQueue:
        """Add (or replace the settings of) a stream; ``sender`` is asked to fill packets."""
        old = self._streams.get(config.stream)
        q = StreamQueue(config)
        if old is not None:
            q.entries = old.queue.entries
            q.last_access = old.queue.last_access
            sender = sender or old.sender
        self._streams[config.stream] = _Stream(q, sender)
        self._defaults[config.stream] = config
        return q

    def expedite(self, stream: int) -> None:
        """Serve ``stream`` first in the next packet (an operator request was just handed to
        its modality): it wins its tier's contest and is asked first for data."""
        self.stream(stream).expedite = True
        for st in self._links.values():
            st.idle_until = -math.inf

    def stream(self, stream: int) -> StreamQueue:
        try:
            return self._streams[stream].queue
        except KeyError:
            raise ConfigError(f"no stream {stream}") from None

    @property
    def streams(self) -> list[StreamQueue]:
        return [self._streams[k].queue for k in sorted(self._streams)]

    def push(self, stream: int, message: Message, now: float) -> int:
        """Queue ``message`` on ``stream``; returns its entry id. An unencodable message raises
        :class:`EncodeError` (nothing is queued)."""
        q = self.stream(stream)
        size = encoded_size(message)  # raises EncodeError for a bad message
        entry = self._new_entry(q, message, size, now)
        for st in self._links.values():
            st.idle_until = -math.inf  # new data: the next opportunity is worth a look
        dropped = q.push(entry)
        if dropped is not None:
            self._forget(dropped)
            self._events.append(Dropped(now, stream, q.overflow_reason))
        return entry.id

    def _new_entry(self, q: StreamQueue, message: Message, size: int, now: float) -> Entry:
        self._entry_ids += 1
        return Entry(self._entry_ids, q.id, message, size, now)

    def flush(self, stream: int, now: float) -> int:
        """Empty ``stream`` (counted as ``flush`` drops); returns how many messages left."""
        return self._remove(stream, lambda m: True, "flush", now)

    def withdraw(self, stream: int, match: Callable[[Message], bool], now: float) -> int:
        """Take off ``stream`` every entry whose message ``match`` accepts, queued or sent and
        awaiting its ack (a later ack for it then clears nothing). Counted as ``superseded``
        drops; returns how many were withdrawn."""
        return self._remove(stream, match, "superseded", now)

    def _remove(self, stream: int, match: Callable[[Message], bool], reason: str, now: float) -> int:
        q = self.stream(stream)
        flags = [bool(match(e.message)) for e in q.entries]  # a match that raises changes nothing
        gone = [e for e, f in zip(q.entries, flags, strict=True) if f]
        q.entries[:] = [e for e, f in zip(q.entries, flags, strict=True) if not f]
        for e in gone:
            self._forget(e)
        if gone:
            q.count_drop(reason, len(gone))
            self._events.append(Dropped(now, stream, reason, len(gone)))
        return len(gone)

    # ============================================================================= links
    def link(self, link: int) -> LinkConfig:
        return self._link(link).cfg

    def _link(self, link: int) -> _Link:
        try:
            return self._links[link]
        except KeyError:
            raise ConfigError(f"no link {link}") from None

    @property
    def links(self) -> list[int]:
        return sorted(self._links)

    def link_state(self, link: int) -> dict[str, Any]:
        st = self._link(link)
        return {"link": link, "enabled": st.enabled, "muted": st.muted,
                "schedule": st.current.version,
                "pending": None if st.pending is None else st.pending.schedule.version,
                "packets": st.packets, "frames_tx": st.frames_tx, "frames_rx": st.frames_rx,
                "last_heard": st.last_heard}

    def schedule(self, link: int) -> Schedule:
        """The schedule link ``link`` runs now."""
        return self._link(link).current

    def pending_schedule(self, link: int) -> Schedule | None:
        p = self._link(link).pending
        return None if p is None else p.schedule

    def set_link_enabled(self, link: int, enabled: bool, now: float) -> int:
        """Enable/disable a link. Disabling returns its unacked messages to their queues at
        once (they become sendable on the other links). Returns how many were returned."""
        st = self._link(link)
        returned = 0
        if not enabled and st.enabled:
            returned = self._release_link(link)
        st.enabled = enabled
        self._events.append(LinkChanged(now, link, st.enabled, st.muted, returned))
        return returned

    def set_mute(self, link: int, muted: bool, now: float) -> None:
        """Software mute: the link keeps receiving but never transmits."""
        st = self._link(link)
        st.muted = muted
        self._events.append(LinkChanged(now, link, st.enabled, st.muted, 0))

    def _release_link(self, link: int) -> int:
        st = self._links[link]
        ids = {eid for refs in st.sent.values() for _, eid in refs}
        st.sent.clear()
        n = 0
        for e in self._all_entries():
            keys = [k for k in e.pending if k[0] == link]
            for k in keys:
                del e.pending[k]
            if keys:
                self._recompute_ready(e)
            if keys and e.id in ids and not e.pending:
                n += 1
        return n

    def _recompute_ready(self, e: Entry) -> None:
        e.ready_at = max((t + self._links[lk].ack_timeout for (lk, _), t in e.pending.items()
                          if lk in self._links), default=-math.inf)

    # ============================================================================== time
    def _window(self, st: _Link, now: float) -> SlotWindow:
        return st.current.window(now)

    def can_transmit(self, link: int, now: float) -> bool:
        """Whether a packet may start on ``link`` at ``now``."""
        st = self._link(link)
        if not st.enabled or st.muted:
            return False
        if now < st.busy_until + st.cfg.gap - 1e-9 or now < st.idle_until - 1e-9:
            return False
        w = self._window(st, now)
        return w.slot.owner == self.node_id and now + st.cfg.packet_time + w.slot.guard <= w.end + 1e-9

    def next_opportunity(self, link: int, now: float) -> float | None:
        """The earliest time >= ``now`` at which ``link`` may start a packet (current schedule)."""
        st = self._link(link)
        if not st.enabled or st.muted:
            return None
        t = max(now, st.busy_until + st.cfg.gap, st.idle_until)
        for _ in range(2 * len(st.current.slots) + 2):
            w = st.current.next_window(t, self.node_id)
            if w is None:
                return None
            start = max(t, w.start)
            if start + st.cfg.packet_time + w.slot.guard <= w.end + 1e-9:
                return start
            t = w.end + 1e-6
        return None

    def next_event(self, now: float) -> float | None:
        """When :meth:`poll` next has something to do (an opportunity, a schedule activation,
        a watchdog deadline); ``None`` if nothing is foreseen."""
        times: list[float] = []
        for link, st in self._links.items():
            t = self.next_opportunity(link, now)
            if t is not None:
                times.append(t)
            if st.pending is not None:
                times.append(max(now, st.pending.schedule.epoch))
            wd = self._watchdog_deadline(st)
            if wd is not None:
                times.append(max(now, wd))
        return min(times) if times else None

    def _watchdog_deadline(self, st: _Link) -> float | None:
        if st.current.version == st.safe.version and st.current.slots == st.safe.slots:
            return None
        ref = max(x for x in (st.last_heard, st.switched_at, -math.inf) if x is not None)
        if ref == -math.inf:
            return None
        # fall back at the first cycle boundary after N silent cycles, so that both ends (each
        # counting from the last frame it heard) switch on a boundary
        late = ref + st.cfg.watchdog_cycles * st.current.cycle
        return st.current.cycle_start(st.current.cycle_at(late) + 1)

    def _tick(self, now: float) -> None:
        """Schedule activations, watchdog, expiry, queue status."""
        for link, st in self._links.items():
            if st.switched_at is None:
                st.switched_at = now
            if st.pending is not None and now >= st.pending.schedule.epoch - 1e-9:
                self._switch(link, st.pending.schedule, now, "activation")
            wd = self._watchdog_deadline(st)
            if wd is not None and now >= wd:
                self._fallback(link, now, "watchdog")
        self._expire(now)
        if self.queue_status_interval is not None and QUEUE_STATUS_STREAM in self._streams and (
            self._last_qs is None or now - self._last_qs >= self.queue_status_interval
        ):
            self._last_qs = now
            self.push(QUEUE_STATUS_STREAM, self.queue_status(now), now)

    def _switch(self, link: int, schedule: Schedule, now: float, reason: str) -> None:
        st = self._links[link]
        st.current = schedule
        st.pending = None
        st.switched_at = now
        self._events.append(ScheduleSwitched(now, link, schedule.version, schedule.cycle_at(now), reason))

    def _fallback(self, link: int, now: float, reason: str) -> None:
        st = self._links[link]
        st.proposed.clear()
        self._switch(link, st.safe, now, reason)

    def _expire(self, now: float) -> None:
        for s in self._streams.values():
            q = s.queue
            ttl = q.config.ttl
            if ttl <= 0:
                continue
            old = [e for e in q.entries if now - e.pushed > ttl]
            for e in old:
                self._forget(e)
                q.drop(e, "ttl")
            if old:
                self._events.append(Dropped(now, q.id, "ttl", len(old)))

    # ============================================================================= build
    def poll(self, now: float) -> list[Transmission]:
        """Housekeeping, then one packet for every link that may transmit now."""
        self._tick(now)
        out = []
        for link in sorted(self._links):
            if self.can_transmit(link, now):
                tx = self.build(link, now)
                if tx is not None:
                    out.append(tx)
                else:
                    self._links[link].idle_until = now + self.idle_interval
        return out

    def build(self, link: int, now: float) -> Transmission | None:
        """Pack one packet for ``link`` now (``None`` when there is nothing to send).

        Order per frame: pending frame acks, then the contest (tier first, then value), then
        pulls from modality senders when no queued message fits."""
        st = self._link(link)
        cfg = st.cfg
        self._build_no += 1
        w = self._window(st, now)
        hdr_bytes = header_size(FrameHeader(crc=cfg.crc))
        # stream -> largest budget for which it had nothing (inf: failed or slow, skip it)
        exhausted: dict[int, float] = {}
        t0 = self.clock() if self.clock is not None else 0.0
        acks = self._take_acks(now)
        signer = self.signer
        reserve = TRAILER_BYTES if signer is not None and any(
            self.is_command(e.message) for e in self._all_entries()) else 0
        frames_msgs: list[tuple[list[Message], list[Entry]]] = []
        used = 0
        for _ in range(cfg.n_frames):
            left = cfg.fbytes - hdr_bytes - reserve
            msgs: list[Message] = []
            taken: list[Entry] = []
            while acks and encoded_size(acks[0]) <= left:
                a = acks.pop(0)
                msgs.append(a)
                left -= encoded_size(a)
            while left > 0:
                pick = self._contest(link, w, left, now)
                if pick is None:
                    if not self._pull(link, w, left, now, exhausted, t0):
                        break
                    continue
                q, e = pick
                msgs.append(e.message)
                taken.append(e)
                left -= e.size
                q.last_access = now
                self._mark_taken(q, e, now)
            if not msgs:
                break
            used += cfg.fbytes - hdr_bytes - reserve - left
            frames_msgs.append((msgs, taken))
        if acks:  # acks that did not fit go back for the next packet
            for a in acks:
                self._requeue_ack(a, now)
        if not frames_msgs:
            return None
        for _, taken in frames_msgs:
            for e in taken:
                self._streams[e.stream].queue.expedite = False
        frames: list[bytes] = []
        seq0 = st.seq
        n_msgs = 0
        for i, (msgs, taken) in enumerate(frames_msgs):
            seq = (seq0 + i) % SEQ_MODULUS
            self._claim_seq(st, link, seq)
            header = FrameHeader(src=self.node_id, dst=cfg.dst, seq=seq, schedule=st.current.version,
                                 crc=cfg.crc)
            if signer is not None and any(self.is_command(m) for m in msgs):
                frames.append(signer.pack(msgs, cfg.fbytes, header))
                self.stats["signed"] += 1
            else:
                frames.append(pack(msgs, cfg.fbytes, header))
            n_msgs += len(msgs)
            refs = []
            for e in taken:
                q = self._streams[e.stream].queue
                if q.config.ack_required:
                    e.pending[(link, seq)] = now
                    e.ready_at = max(e.ready_at, now + st.ack_timeout)
                    refs.append((e.stream, e.id))
            if refs:
                st.sent[seq] = refs
        st.seq = (seq0 + len(frames)) % SEQ_MODULUS
        duration = cfg.airtime(len(frames))
        st.busy_until = now + duration
        st.packets += 1
        st.frames_tx += len(frames)
        capacity = cfg.n_frames * cfg.fbytes
        self.stats["packets"] += 1
        self.stats["frames"] += len(frames)
        self.stats["used_bytes"] += used
        self.stats["capacity"] += capacity
        return Transmission(link, cfg.rate, tuple(frames), seq0, now, duration, w.index, w.cycle,
                            capacity, used, n_msgs, st.current.version)

    def _claim_seq(self, st: _Link, link: int, seq: int) -> None:
        """Reusing a seq forgets the old frame's pending records (its ack can no longer be told
        apart); those messages become sendable again."""
        old = st.sent.pop(seq, None)
        if not old:
            return
        for sid, eid in old:
            e = self._find(sid, eid)
            if e is not None:
                e.pending.pop((link, seq), None)
                self._recompute_ready(e)

    def _mark_taken(self, q: StreamQueue, e: Entry, now: float) -> None:
        if e.first_sent is None:
            e.first_sent = now
        else:
            self.stats["resent"] += 1
        e.sends += 1
        if q.config.ack_required:
            e.hold = self._build_no  # not again in this packet; pending records follow
        else:
            q.entries.remove(e)

    def _eligible(self, q: StreamQueue, link: int, w: SlotWindow, now: float) -> bool:
        c = q.config
        if not c.enabled or (c.links is not None and link not in c.links):
            return False
        if c.tier > 0:
            if c.priority < w.slot.min_priority:
                return False
            if w.slot.tags and not (w.slot.tags & c.tags):
                return False
        return not q.in_blackout(now)

    def _sendable(self, e: Entry, now: float, link: int) -> bool:
        if e.hold == self._build_no or now < e.ready_at:
            return False
        if e.pending:  # every send timed out: avoid the links that failed it if others exist
            e.failed_links.update(lk for lk, _ in e.pending)
        if link in e.failed_links:
            usable = [k for k, st in self._links.items() if st.enabled and not st.muted]
            if all(k in e.failed_links for k in usable):
                e.failed_links.clear()
            else:
                return False
        return True

    def _contest(self, link: int, w: SlotWindow, left: int, now: float) -> tuple[StreamQueue, Entry] | None:
        best: tuple[tuple[float, ...], StreamQueue, Entry] | None = None
        for sid in sorted(self._streams):
            q = self._streams[sid].queue
            if not q.entries or not self._eligible(q, link, w, now):
                continue
            entry = None
            cap = q.config.max_bytes_on(link)
            room = left if cap is None else min(left, cap)
            for e in q.ordered():
                if e.size <= room and self._sendable(e, now, link):
                    entry = e
                    break
            if entry is None:
                continue
            last = q.last_access if q.last_access is not None else -math.inf
            # tier 0 is ordered by priority alone (status before queue status); other tiers
            # compete by value
            value = float(q.config.priority) if q.config.tier == 0 else q.score(now)
            if q.expedite:
                value = math.inf
            key = (-q.config.tier, value, q.config.priority, -last, -sid)
            if best is None or key > best[0]:
                best = (key, q, entry)
        if best is None:
            return None
        # an entry re-sent after its ack timeout keeps its old records: a late ack of the old
        # frame still clears it
        return best[1], best[2]

    def _pull(self, link: int, w: SlotWindow, left: int, now: float, exhausted: dict[int, float],
              t0: float) -> bool:
        """Ask modality senders (best score first) for at most ``left`` bytes. Returns whether a
        usable message was queued."""
        if self.clock is not None and self.clock() - t0 > self.fill_budget:
            return False
        cands = []
        for sid, s in self._streams.items():
            if s.sender is None or left <= exhausted.get(sid, -1) or not self._eligible(s.queue, link, w, now):
                continue
            q = s.queue
            score = math.inf if q.expedite else q.score(now)
            cands.append(((q.config.tier, -score, -q.config.priority, sid), s))
        for _, s in sorted(cands, key=lambda c: c[0]):
            q = s.queue
            sender = s.sender
            assert sender is not None
            cap = q.config.max_bytes_on(link)
            ask = left if cap is None else min(left, cap)
            if ask <= 0:
                continue
            start = self.clock() if self.clock is not None else 0.0
            try:
                got = sender.fill(ask, now)
                if not isinstance(got, list | tuple):
                    raise TypeError(f"fill returned {type(got).__name__}, not a list")
            except Exception as exc:  # a failing sender must never stop the packet
                exhausted[q.id] = math.inf
                self.stats["sender_failures"] += 1
                self._events.append(SenderFailed(now, q.id, f"{type(exc).__name__}: {exc}"))
                continue
            slow = self.clock is not None and self.clock() - start > self.sender_budget
            fits = False
            for m in got:
                try:
                    size = encoded_size(m)
                except (EncodeError, CoexError, TypeError, ValueError) as exc:
                    q.count_drop("encode")
                    self._events.append(Dropped(now, q.id, "encode"))
                    self._events.append(SenderFailed(now, q.id, f"unencodable message: {exc}"))
                    continue
                e = self._new_entry(q, m, size, now)
                if slow:
                    e.hold = self._build_no
                q.push(e, bypass_depth=True)
                if size <= ask and not slow:
                    fits = True
            if slow:
                exhausted[q.id] = math.inf
                self.stats["sender_failures"] += 1
                self._events.append(SenderFailed(now, q.id, "fill overran its deadline", slow=True))
                continue
            if fits:
                return True
            exhausted[q.id] = max(exhausted.get(q.id, -1), left)
            if self.clock is not None and self.clock() - t0 > self.fill_budget:
                return False
        return False

    # ============================================================================== acks
    def _all_entries(self) -> Iterable[Entry]:
        for s in self._streams.values():
            yield from s.queue.entries

    def _find(self, sid: int, eid: int) -> Entry | None:
        s = self._streams.get(sid)
        if s is None:
            return None
        for e in s.queue.entries:
            if e.id == eid:
                return e
        return None

    def _forget(self, e: Entry) -> None:
        for link, seq in list(e.pending):
            st = self._links.get(link)
            if st is not None and seq in st.sent:
                st.sent[seq] = [r for r in st.sent[seq] if r[1] != e.id]
        e.pending.clear()

    def on_ack(self, ack: FrameAck, now: float) -> int:
        """Apply a :class:`FrameAck` (received on any link): every ack-required message packed
        in an acknowledged frame leaves its queue, and every link's pending records. Returns the
        number of messages cleared."""
        return len(self.acknowledge(ack, now))

    def acknowledge(self, ack: FrameAck, now: float) -> list[tuple[int, Message]]:
        """:meth:`on_ack`, returning the ``(stream, message)`` pairs it cleared (each also gives
        an :class:`Acked` event)."""
        if ack.node != self.node_id or ack.link not in self._links:
            return []
        st = self._links[ack.link]
        cleared: list[tuple[int, Message]] = []
        for ent in ack.entries:
            for i in range(8):
                if not ent.frames >> i & 1:
                    continue
                seq = (ent.seq + i) % SEQ_MODULUS
                for sid, eid in st.sent.pop(seq, []):
                    e = self._find(sid, eid)
                    if e is None:
                        continue
                    q = self._streams[sid].queue
                    self._forget(e)
                    q.entries.remove(e)
                    cleared.append((sid, e.message))
                    self.stats["acked"] += 1
                    self._events.append(Acked(now, sid, e.message, now - (e.first_sent or now), ack.link))
        return cleared

    def on_frame(self, link: int, header: FrameHeader, now: float, ackable: bool = True) -> None:
        """Bookkeeping for a good frame received on ``link``: the watchdog, the peer's schedule
        version, and (if ``ackable``) the frame ack to send back."""
        st = self._links.get(link)
        if st is None or header.src == self.node_id:
            return
        st.last_heard = now
        st.frames_rx += 1
        if self.ack_frames and ackable:
            seqs = self._to_ack.setdefault((header.src, link), {})
            seqs[header.seq] = now  # a newer use of a seq: the ack names the newest
            for other in self._links.values():
                other.idle_until = -math.inf
        v = header.schedule
        if v == st.current.version:
            return
        for cid, prop in list(st.proposed.items()):
            if prop.schedule.version == v:  # the vehicle switched: our proposal was accepted
                st.proposed.pop(cid)
                self._switch(link, prop.schedule, now, "peer")
                return
        if st.pending is not None and st.pending.schedule.version == v:
            self._switch(link, st.pending.schedule, now, "peer")
            return
        settled = st.switched_at is None or now - st.switched_at >= st.current.cycle
        if v == st.safe.version and settled:  # the peer's watchdog fired
            self._fallback(link, now, "peer")

    def _take_acks(self, now: float) -> list[Message]:
        """The frame acks to send now. A frame received longer ago than its link's
        ``ack_timeout`` is not acknowledged any more: its sender has made its messages sendable
        again by then, and may have reused the seq (after 256 frames), so a late ack could
        clear messages of a newer frame that never arrived (a restarted node replaying its
        journal, a long outage)."""
        out: list[Message] = []
        self._ack_times = {}
        for (src, link), pending in sorted(self._to_ack.items()):
            st = self._links.get(link)
            horizon = st.ack_timeout if st is not None else math.inf
            seqs = []
            for seq, t in pending.items():
                if now - t > horizon:
                    self.stats["stale_acks"] += 1
                    continue
                seqs.append(seq)
                self._ack_times[(src, link, seq)] = t
            if not seqs:
                continue
            entries: list[FrameAckEntry] = []
            for seq in seqs:
                for k, ent in enumerate(entries):
                    d = (seq - ent.seq) % SEQ_MODULUS
                    if d < 8:
                        entries[k] = FrameAckEntry(ent.seq, ent.frames | 1 << d)
                        break
                else:
                    entries.append(FrameAckEntry(seq, 1))
            for i in range(0, len(entries), MAX_ACK_ENTRIES):
                out.append(FrameAck(src, link, tuple(entries[i:i + MAX_ACK_ENTRIES])))
        self._to_ack.clear()
        return out

    def _requeue_ack(self, ack: Message, now: float) -> None:
        assert isinstance(ack, FrameAck)
        seqs = self._to_ack.setdefault((ack.node, ack.link), {})
        for ent in ack.entries:
            for i in range(8):
                seq = (ent.seq + i) % SEQ_MODULUS
                if ent.frames >> i & 1 and seq not in seqs:
                    seqs[seq] = self._ack_times.get((ack.node, ack.link, seq), now)

    # ============================================================== commands (vehicle side)
    def apply(self, command: Message, now: float) -> CommandAck:
        """Apply a topside command (QueueConfig, ScheduleUpdate, LinkControl) and return the
        CommandAck to send; never raises for a well-formed message."""
        status, reason = AckStatus.REJECTED, "not a channel command"
        if isinstance(command, QueueConfig):
            status, reason = self._apply_queue_config(command, now)
        elif isinstance(command, ScheduleUpdate):
            status, reason = self._apply_schedule(command, now)
        elif isinstance(command, LinkControl):
            status, reason = self._apply_link_control(command, now)
        cid = int(getattr(command, "command_id", 0))
        self._events.append(CommandApplied(now, command, status, reason))
        return CommandAck(cid, status)

    def _apply_queue_config(self, c: QueueConfig, now: float) -> tuple[AckStatus, str]:
        s = self._streams.get(c.stream)
        if s is None:
            return AckStatus.UNKNOWN_TARGET, f"no stream {c.stream}"
        changes: dict[str, Any] = {}
        if c.enabled is not None:
            changes["enabled"] = c.enabled
        if c.priority is not None:
            changes["priority"] = c.priority
        if c.ttl is not None:
            changes["ttl"] = float(c.ttl)
        if c.max_depth is not None:
            changes["max_depth"] = c.max_depth
        if c.newest_first is not None:
            changes["newest_first"] = c.newest_first
        try:
            cfg = s.queue.config.updated(**changes)
        except ConfigError as exc:
            return AckStatus.REJECTED, str(exc)
        s.queue.config = cfg
        for e in s.queue.trim():
            self._forget(e)
            self._events.append(Dropped(now, c.stream, "overflow"))
        if c.flush:
            self.flush(c.stream, now)
        return AckStatus.ACCEPTED, ""

    def _apply_schedule(self, c: ScheduleUpdate, now: float) -> tuple[AckStatus, str]:
        st = self._links.get(c.link)
        if st is None:
            return AckStatus.UNKNOWN_TARGET, f"no link {c.link}"
        if st.pending is not None and st.pending.command_id == c.command_id \
                and st.pending.schedule.version == c.version:
            return AckStatus.ACCEPTED, "duplicate"
        try:
            new = Schedule.from_message(c)
        except ConfigError as exc:
            return AckStatus.REJECTED, str(exc)
        if not new.owns_any(self.node_id, st.cfg.packet_time):
            return AckStatus.REJECTED, "no slot of this node fits a packet"
        cur = st.current.cycle_at(now)
        n = resolve_cycle(c.activate_cycle, cur)
        if n <= cur:
            if new.slots == st.current.slots and new.version == st.current.version:
                return AckStatus.ACCEPTED, "already active"
            return AckStatus.REJECTED, f"activation cycle {n} is not after the current cycle {cur}"
        st.pending = _PendingSchedule(new.starting_at(n, st.current.cycle_start(n)), c.command_id)
        return AckStatus.ACCEPTED, ""

    def _apply_link_control(self, c: LinkControl, now: float) -> tuple[AckStatus, str]:
        st = self._links.get(c.link)
        if st is None:
            return AckStatus.UNKNOWN_TARGET, f"no link {c.link}"
        if not c.enabled or c.mute:
            others = [x for k, x in self._links.items() if k != c.link and x.enabled and not x.muted]
            if not others:
                return AckStatus.REJECTED, "would leave the node without a transmitting link"
        if c.enabled != st.enabled:
            self.set_link_enabled(c.link, c.enabled, now)
        if c.mute != st.muted:
            self.set_mute(c.link, c.mute, now)
        return AckStatus.ACCEPTED, ""

    # ============================================================== commands (topside side)
    def next_command_id(self) -> int:
        self._command_id = (self._command_id + 1) % 256
        return self._command_id

    def send_command(self, command: Message, now: float) -> int:
        """Queue a command (on the control stream, acked) and remember it until its
        CommandAck arrives. Returns its command id."""
        cid = int(getattr(command, "command_id", 0))
        self._commands[cid] = command
        self.push(CONTROL_STREAM, command, now)
        return cid

    def propose_schedule(self, link: int, schedule: Schedule, now: float,
                         activate_cycle: int | None = None, lead_cycles: int = 2) -> ScheduleUpdate:
        """Topside: announce ``schedule`` for ``link`` from cycle ``activate_cycle`` (default: the
        current cycle + ``lead_cycles``). Both ends switch at that cycle boundary once the vehicle
        has acked; if the ack is late, topside switches when it first sees the new version."""
        st = self._link(link)
        cur = st.current.cycle_at(now)
        n = cur + lead_cycles if activate_cycle is None else activate_cycle
        if n <= cur:
            raise ConfigError(f"activation cycle {n} is not after the current cycle {cur}")
        cid = self.next_command_id()
        msg = schedule.to_message(cid, link, n)
        self.send_command(msg, now)
        st.proposed[cid] = _PendingSchedule(schedule.starting_at(n, st.current.cycle_start(n)), cid)
        return msg

    def on_command_ack(self, ack: CommandAck, now: float) -> CommandResult:
        """Topside: the vehicle's answer to one of our commands."""
        command = self._commands.pop(ack.command_id, None)
        for link, st in self._links.items():
            prop = st.proposed.pop(ack.command_id, None)
            if prop is not None and ack.status == AckStatus.ACCEPTED:
                if now >= prop.schedule.epoch:
                    self._switch(link, prop.schedule, now, "activation")
                else:
                    st.pending = prop
        if isinstance(command, LinkControl) and ack.status == AckStatus.ACCEPTED:
            target = self._links.get(command.link)
            if target is not None and target.enabled != command.enabled:
                self.set_link_enabled(command.link, command.enabled, now)
        result = CommandResult(now, ack.command_id, ack.status, command)
        self._events.append(result)
        return result

    # ====================================================================== queue status
    def queue_status(self, now: float) -> QueueStatus:
        """Per-stream state (drop counters restart at each status)."""
        lines = []
        for q in self.streams:
            oldest = max((now - e.pushed for e in q.entries), default=0.0)
            lines.append(StreamStatus(
                q.id, q.config.enabled, q.config.tier, q.config.priority, min(len(q), 63),
                min(q.queued_bytes(), 65472), int(min(oldest, 4080)), min(q.drops, 15)))
            q.drops = 0
        return QueueStatus(to_stamp(now), tuple(lines))

    # ========================================================================== settings
    def export_settings(self) -> dict[str, Any]:
        """Operator settings that must survive a restart (JSON-able): stream settings, link
        enable/mute, active and pending schedules."""
        return {
            "version": 1,
            "streams": {str(sid): s.queue.config.to_dict() for sid, s in sorted(self._streams.items())},
            "links": {
                str(link): {
                    "enabled": st.enabled,
                    "muted": st.muted,
                    "schedule": st.current.to_dict(),
                    "pending": None if st.pending is None else {
                        "schedule": st.pending.schedule.to_dict(), "command_id": st.pending.command_id},
                }
                for link, st in sorted(self._links.items())
            },
            "command_id": self._command_id,
            "auth": {
                # a restart resumes above the last counter it may have used (see import_settings)
                "sent": self.signer.counter if self.signer is not None else None,
                "accepted": self.verifier.counter if self.verifier is not None else None,
            },
        }

    def import_settings(self, settings: dict[str, Any], now: float | None = None) -> None:
        """Restore :meth:`export_settings` output (unknown streams/links are ignored)."""
        try:
            for sid, d in settings.get("streams", {}).items():
                s = self._streams.get(int(sid))
                if s is not None:
                    s.queue.config = StreamConfig.from_dict(d)
            for lid, d in settings.get("links", {}).items():
                st = self._links.get(int(lid))
                if st is None:
                    continue
                st.enabled = bool(d.get("enabled", st.enabled))
                st.muted = bool(d.get("muted", st.muted))
                if d.get("schedule"):
                    st.current = Schedule.from_dict(d["schedule"])
                    st.switched_at = now
                p = d.get("pending")
                st.pending = None if not p else _PendingSchedule(
                    Schedule.from_dict(p["schedule"]), int(p["command_id"]))
            self._command_id = int(settings.get("command_id", self._command_id))
            auth = settings.get("auth") or {}
            if self.signer is not None and auth.get("sent") is not None:
                # frames signed after the last save may have left: skip a margin of counters
                self.signer.counter = max(self.signer.counter,
                                          int(auth["sent"]) + self.COUNTER_MARGIN)
            if self.verifier is not None and auth.get("accepted") is not None:
                self.verifier.counter = max(self.verifier.counter, int(auth["accepted"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"invalid channel settings: {exc}") from exc

    # ============================================================================ events
    def events(self) -> list[Event]:
        out, self._events = self._events, []
        return out

    def fill_ratio(self) -> float:
        """Useful (message) bytes / offered bytes over every packet built so far."""
        cap = self.stats["capacity"]
        return self.stats["used_bytes"] / cap if cap else 0.0
