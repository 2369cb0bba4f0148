"""The data of a channel manager: built-in streams, link configuration, transmissions, and
the per-link and per-stream state (see :mod:`coex_core.channel.manager`)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ..acoustic import RateInfo, rate_info
from ..auth import CommandSigner, CommandVerifier
from ..errors import ConfigError
from ..messages import (
    FrameHeader,
    Message,
)
from ..modality import ModalitySender
from ..state import persistent
from ..tracker import Tracked
from ..wire import header_size
from .events import Event
from .queue import StreamConfig, StreamQueue
from .schedule import Schedule

__all__ = [
    "CONTROL_STREAM",
    "QUEUE_STATUS_STREAM",
    "STATUS_STREAM",
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


@persistent("channel.LinkConfig")
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
    #: the share of each packet that spare traffic (the spare tier and redundant copies) may
    #: fill: 0 switches it off on this link (acoustic transmissions cost the vehicle energy)
    spare: float = 1.0

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
        if not 0.0 <= self.spare <= 1.0:
            raise ConfigError(f"spare {self.spare} outside 0..1 (a share of each packet)")

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
    packed (headers excluded), ``duration`` the airtime. Of ``used``, ``spare`` bytes came from
    the spare tier and ``redundant`` bytes are extra copies of urgent messages; ``backlog`` is
    the work left after this packet (queued bytes plus what senders say they still have,
    background and spare)."""

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
    spare: int = 0
    redundant: int = 0
    backlog: int = 0


def _upgrade_pending(fields: dict[str, Any], saved: int) -> dict[str, Any]:
    """Version 1 (before networks of several nodes): a proposal between two nodes."""
    fields.setdefault("awaiting", set())
    fields.setdefault("fleet", False)
    fields.setdefault("committed", False)
    return fields


@persistent("channel.PendingSchedule", version=2, upgrade=_upgrade_pending)
@dataclass
class _PendingSchedule:
    schedule: Schedule  # with epoch/first_cycle set to its activation
    command_id: int
    #: a network of several nodes (docs/channel.md): the peers whose ACCEPTED the proposer
    #: still awaits (a peer silent for ``watchdog_cycles`` cycles is not awaited)
    awaiting: set[int] = field(default_factory=set)
    #: proposed to a network of several nodes: it takes effect only once committed
    fleet: bool = False
    #: every node agreed: the proposer announced it (a second ``ScheduleUpdate``, same content)
    committed: bool = False


@persistent("channel.Link")
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
    #: runtime share of each packet spare traffic may fill (starts at ``cfg.spare``)
    spare: float = 1.0

    @property
    def safe(self) -> Schedule:
        return self.cfg.schedule

    @property
    def ack_timeout(self) -> float:
        return self.cfg.ack_timeout if self.cfg.ack_timeout is not None else self.current.cycle


@persistent("channel.Stream", transient=("sender",))  # the node links its sender again
@dataclass
class _Stream:
    queue: StreamQueue
    sender: ModalitySender | None = None


class _ManagerState:
    """The attributes every part of :class:`~coex_core.channel.manager.ChannelManager` shares
    (set by its ``__init__``)."""

    COUNTER_MARGIN: int
    node_id: int
    clock: Callable[[], float] | None
    fill_budget: float
    sender_budget: float
    queue_status_interval: float | None
    ack_frames: bool
    idle_interval: float
    signer: CommandSigner | None
    verifier: CommandVerifier | None
    peer_signers: dict[int, CommandSigner]
    peer_verifiers: dict[int, CommandVerifier]
    is_command: Callable[[Message], bool]
    _links: dict[int, _Link]
    _streams: dict[int, _Stream]
    _defaults: dict[int, StreamConfig]
    _entry_ids: int
    _build_no: int
    _events: list[Event]
    _to_ack: dict[tuple[int, int], dict[int, float]]
    _ack_times: dict[tuple[int, int, int], float]
    _last_qs: float | None
    _command_id: int
    _commands: dict[int, Tracked[Message]]
    _command_dst: dict[int, int | None]
    stats: dict[str, int]
    #: stream name -> failures of its sender (each also in ``stats["sender_failures"]``)
    sender_failures_by_stream: dict[str, int]

    def _sender_failed(self, now: float, sid: int, error: str, *, slow: bool = False) -> None:
        """A sender failed (raised, or overran its deadline): counted, per stream by name, and
        told as a :class:`SenderFailed` event naming the stream. Never raised: a failing sender
        never stops a packet or the channel."""
        from .events import SenderFailed

        s = self._streams.get(sid)
        name = s.queue.config.name if s is not None else str(sid)
        self.stats["sender_failures"] += 1
        self.sender_failures_by_stream[name] = self.sender_failures_by_stream.get(name, 0) + 1
        self._events.append(SenderFailed(now, sid, f"{name}: {error}", slow=slow))

    def signer_for(self, dst: int) -> CommandSigner | None:
        """The signer of frames addressed to ``dst``: that peer's key, else the command key."""
        return self.peer_signers.get(dst, self.signer)

    def verifier_for(self, src: int, dst: int) -> CommandVerifier | None:
        """The verifier of a frame from ``src`` addressed to ``dst``: the key shared with
        ``src`` for a frame addressed to this node, the command key for a broadcast."""
        if dst != 0 and src in self.peer_verifiers:
            return self.peer_verifiers[src]
        return self.verifier

