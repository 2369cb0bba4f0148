"""Per-stream queues: settings, entries, overflow, expiry, pending acks."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field, fields, replace
from typing import Any

from ..errors import ConfigError
from ..messages import Message
from ..state import persistent

__all__ = ["DEFAULT_TTL", "Entry", "StreamConfig", "StreamQueue"]

#: Time-to-live used as the contest divisor when a stream's ttl is 0 (= never expires).
DEFAULT_TTL = 1800.0


@persistent("channel.StreamConfig")
@dataclass(frozen=True)
class StreamConfig:
    """Settings of one stream (queue).

    ``tier`` 0 is the strict status/control tier: any sendable tier-0 message goes before any
    tier-1 message, and so on. Within a tier, streams compete by Goby's value
    ``priority * (now - last_send) / ttl``. ``ttl`` 0 means messages never expire. ``blackout``
    is the minimum gap between two sends from the stream. ``max_depth`` bounds pushed messages
    (a full newest-first queue drops its oldest, a full oldest-first queue refuses the new one).
    ``ack_required`` keeps a message until a :class:`~coex_core.messages.FrameAck` covers a frame
    that carried it. ``links`` restricts the stream to some links (``None`` = all);
    ``link_max_bytes`` caps message sizes per link. ``tags`` let a slot reserve itself for some
    streams. ``spare`` caps the share of a packet the stream's spare work may fill (0: none)."""

    stream: int
    name: str = ""
    tier: int = 1
    priority: int = 30
    ttl: float = 1800.0
    blackout: float = 0.0
    max_depth: int = 100
    newest_first: bool = False
    ack_required: bool = False
    enabled: bool = True
    links: frozenset[int] | None = None
    tags: frozenset[str] = field(default_factory=frozenset)
    #: ``((link, max_bytes), ...)``: largest message this stream may put on a link (smaller,
    #: coarser pieces on a slow modem); senders are asked for at most that much there.
    link_max_bytes: tuple[tuple[int, int], ...] = ()
    #: the largest share of a packet this stream's spare work (``ModalitySender.spare``) may
    #: fill: 0 switches its spare traffic off, 1 lets it use every idle byte
    spare: float = 1.0
    #: the priority while the channel finds the link low (None: ``priority`` always): what
    #: decides goes first on a slow link (docs/channel.md, priorities that follow the link)
    low_priority: int | None = None

    def __post_init__(self) -> None:
        if not 0 <= self.stream <= 31:
            raise ConfigError(f"stream id {self.stream} outside 0..31")
        if not 0 <= self.tier <= 3:
            raise ConfigError(f"tier {self.tier} outside 0..3")
        if not 0 <= self.priority <= 127:
            raise ConfigError(f"priority {self.priority} outside 0..127")
        if self.ttl < 0 or self.blackout < 0 or self.max_depth < 0:
            raise ConfigError("ttl, blackout and max_depth must not be negative")
        if not 0.0 <= self.spare <= 1.0:
            raise ConfigError(f"spare {self.spare} outside 0..1 (a share of each packet)")
        if self.low_priority is not None and not 0 <= self.low_priority <= 127:
            raise ConfigError(f"low_priority {self.low_priority} outside 0..127")

    #: Settings an operator may change at runtime (and that :meth:`to_dict` saves).
    RUNTIME = ("enabled", "priority", "ttl", "max_depth", "newest_first", "blackout", "tier",
               "ack_required", "spare")

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, frozenset):
                v = sorted(v)
            out[f.name] = v
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> StreamConfig:
        kw = dict(d)
        if kw.get("links") is not None:
            kw["links"] = frozenset(int(x) for x in kw["links"])
        kw["tags"] = frozenset(kw.get("tags", ()))
        kw["link_max_bytes"] = tuple((int(a), int(b)) for a, b in kw.get("link_max_bytes", ()))
        return cls(**kw)

    def priority_now(self, low: bool) -> int:
        """The stream's priority, on a low link (``low_priority``, when set) or a normal one."""
        return self.low_priority if low and self.low_priority is not None else self.priority

    def max_bytes_on(self, link: int) -> int | None:
        """The message size cap on ``link`` (``None``: only the frame limits it)."""
        for lk, n in self.link_max_bytes:
            if lk == link:
                return n
        return None

    def updated(self, **changes: Any) -> StreamConfig:
        return replace(self, **changes)


def _upgrade_entry(fields: dict[str, Any], saved: int) -> dict[str, Any]:
    """Version 1 (before networks of several nodes) had no ``dst``: the link's destination."""
    fields.setdefault("dst", None)
    return fields


@persistent("channel.Entry", version=2, upgrade=_upgrade_entry)
@dataclass
class Entry:
    """A queued message and its bookkeeping."""

    id: int
    stream: int
    message: Message
    size: int
    pushed: float
    #: (link, seq) -> send time of every live transmission awaiting an ack.
    pending: dict[tuple[int, int], float] = field(default_factory=dict)
    first_sent: float | None = None
    sends: int = 0
    #: Build number during which this entry must not be used (late data from a slow sender).
    hold: int = -1
    #: While acks are awaited: when the last of them times out.
    ready_at: float = float("-inf")
    #: Links on which a send of this entry timed out (re-sends prefer other links).
    failed_links: set[int] = field(default_factory=set)
    #: The node it is for (frame header ``dst``; 0: every node); ``None``: the ``dst`` of the
    #: link it goes out on (``LinkConfig.dst``)
    dst: int | None = None


@persistent("channel.StreamQueue")
class StreamQueue:
    """One stream's queue and its counters."""

    def __init__(self, config: StreamConfig) -> None:
        self.config = config
        self.entries: list[Entry] = []  # push order, oldest first
        self.last_access: float | None = None
        #: Set when the stream's modality took an operator request: it wins its tier's contest
        #: (and is asked first for data) until a packet carried something from it.
        self.expedite = False
        self.drops = 0  # since the last queue status
        self.drops_total = 0
        self.drop_reasons: dict[str, int] = {}

    @property
    def id(self) -> int:
        return self.config.stream

    def __len__(self) -> int:
        return len(self.entries)

    def queued_bytes(self) -> int:
        return sum(e.size for e in self.entries)

    def ordered(self) -> Iterator[Entry]:
        return reversed(self.entries) if self.config.newest_first else iter(self.entries)

    def drop(self, entry: Entry, reason: str) -> None:
        self.entries.remove(entry)
        self.count_drop(reason)

    def count_drop(self, reason: str, n: int = 1) -> None:
        self.drops += n
        self.drops_total += n
        self.drop_reasons[reason] = self.drop_reasons.get(reason, 0) + n

    def push(self, entry: Entry, *, bypass_depth: bool = False) -> Entry | None:
        """Append ``entry``; returns the entry dropped by overflow (maybe ``entry`` itself)."""
        depth = self.config.max_depth
        if not bypass_depth and len(self.entries) >= depth:
            if not self.config.newest_first or depth == 0:
                self.count_drop("overflow")
                return entry
            victim = self.entries[0]
            self.drop(victim, self.overflow_reason)
            self.entries.append(entry)
            return victim
        self.entries.append(entry)
        return None

    @property
    def overflow_reason(self) -> str:
        """``superseded`` for a newest-only stream (depth 1, newest first), else ``overflow``."""
        return "superseded" if self.config.newest_first and self.config.max_depth == 1 else "overflow"

    def trim(self) -> list[Entry]:
        """Enforce ``max_depth`` after a change (drops oldest when newest-first, else newest)."""
        out = []
        while len(self.entries) > self.config.max_depth:
            victim = self.entries[0] if self.config.newest_first else self.entries[-1]
            self.drop(victim, "overflow")
            out.append(victim)
        return out

    def in_blackout(self, now: float) -> bool:
        return (self.config.blackout > 0 and self.last_access is not None
                and now < self.last_access + self.config.blackout)

    def score(self, now: float, low: bool = False) -> float:
        """Goby's value: priority x time since the last send / ttl (never-sent streams count from
        their oldest message); ``low``: on a low link (the stream's ``low_priority``)."""
        ttl = self.config.ttl if self.config.ttl > 0 else DEFAULT_TTL
        if self.last_access is not None:
            since = self.last_access
        elif self.entries:
            since = min(e.pushed for e in self.entries)
        else:
            since = now
        return self.config.priority_now(low) * max(0.0, now - since) / ttl
