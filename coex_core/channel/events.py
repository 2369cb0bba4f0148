"""Events the channel manager and the node report (``events()`` drains them)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ..messages import AckStatus, Message

__all__ = [
    "Acked",
    "BadFrame",
    "CommandApplied",
    "CommandResult",
    "Dropped",
    "Event",
    "LinkChanged",
    "LinkStats",
    "ProductUpdated",
    "Received",
    "Rejected",
    "ScheduleSwitched",
    "SenderFailed",
]


@dataclass(frozen=True)
class Event:
    time: float


@dataclass(frozen=True)
class SenderFailed(Event):
    """A modality sender raised (``error``) or overran its deadline (``slow``) while filling a
    packet; it counted as "no data" for the rest of that packet."""

    stream: int
    error: str
    slow: bool = False


@dataclass(frozen=True)
class Dropped(Event):
    """Messages left a queue unsent (or unacknowledged): ``reason`` is ``overflow``,
    ``superseded`` (a newer one replaced it in a newest-only stream, or a receiver's newer
    request made it useless: ``ChannelManager.withdraw``), ``ttl``, ``flush`` or ``encode``."""

    stream: int
    reason: str
    count: int = 1


@dataclass(frozen=True)
class Acked(Event):
    """An ack-required message was acknowledged (on any link) ``latency`` s after its first send."""

    stream: int
    message: Message
    latency: float
    link: int


@dataclass(frozen=True)
class CommandApplied(Event):
    """The vehicle handled a topside command and answers with ``status``."""

    command: Message
    status: AckStatus
    reason: str = ""


@dataclass(frozen=True)
class CommandResult(Event):
    """Topside learned the outcome of one of its commands (``peer``: the node that answered,
    when known)."""

    command_id: int
    status: AckStatus
    command: Message | None = None
    peer: int | None = None


@dataclass(frozen=True)
class CommandUnanswered(Event):
    """Topside: no answer came to one of its commands within
    :data:`~coex_core.channel.commands.ANSWER_CYCLES` TDMA cycles of its last send (it shows as
    "no answer"; an answer that comes later is still a :class:`CommandResult`)."""

    command_id: int
    command: Message | None = None
    #: the node it was sent to (None: unknown)
    peer: int | None = None


@dataclass(frozen=True)
class ScheduleSwitched(Event):
    """A link now runs schedule ``version`` (``reason``: ``activation``, ``watchdog``, ``peer``,
    ``restore``)."""

    link: int
    version: int
    cycle: int
    reason: str


@dataclass(frozen=True)
class LinkChanged(Event):
    """A link was enabled/disabled or (un)muted; ``returned`` messages went back to their queues."""

    link: int
    enabled: bool
    muted: bool
    returned: int = 0


@dataclass(frozen=True)
class BadFrame(Event):
    """A received frame could not be decoded (counted, logged, dropped)."""

    link: int
    reason: str
    size: int = 0


@dataclass(frozen=True)
class Received(Event):
    """A message that no modality consumed (vehicle/queue/link status, command acks ...)."""

    link: int
    src: int
    message: Message


@dataclass(frozen=True)
class ProductUpdated(Event):
    """A topside receiver improved a product (``peer``: the node whose data it is, for a
    per-peer receiver of a network of several nodes; None otherwise)."""

    modality: str
    product: Any
    peer: int | None = None


@dataclass(frozen=True)
class Rejected(Event):
    """A received message was refused (out-of-bounds request, unknown type, failing handler)."""

    message: Message
    reason: str


@dataclass(frozen=True)
class LinkStats(Event):
    """Per-link counters of a node since it started (emitted every ``Node.stats_interval``)."""

    link: int
    frames_rx: int
    bad_frames: int
    packets_tx: int
    frames_tx: int
    schedule: int
    enabled: bool
    muted: bool



def _register() -> None:
    """Events not yet taken by the application are saved with the node (coex_core.state)."""
    import dataclasses

    from ..state import persistent

    for obj in list(globals().values()):
        if isinstance(obj, type) and obj.__module__ == __name__ and dataclasses.is_dataclass(obj):
            persistent("event." + obj.__name__)(obj)


_register()
