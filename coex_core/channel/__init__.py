"""The channel manager: stream queues, the priority contest, packing, TDMA schedules and links.

Sans-I/O like the rest of ``coex_core``: bytes and ``now`` in, transmissions and events out.
"""

from __future__ import annotations

from .events import (
    Acked,
    BadFrame,
    CommandApplied,
    CommandResult,
    CommandUnanswered,
    Dropped,
    Event,
    LinkChanged,
    LinkStats,
    ProductUpdated,
    Received,
    Rejected,
    ScheduleSwitched,
    SenderFailed,
)
from .linklog import link_record, read_link_log, to_json_line
from .manager import (
    CONTROL_STREAM,
    QUEUE_STATUS_STREAM,
    STATUS_STREAM,
    ChannelManager,
    LinkConfig,
    Transmission,
    default_streams,
)
from .queue import DEFAULT_TTL, Entry, StreamConfig, StreamQueue
from .schedule import CYCLE_MODULUS, Schedule, SlotWindow, TdmaSlot, resolve_cycle

__all__ = [
    "CONTROL_STREAM",
    "CYCLE_MODULUS",
    "DEFAULT_TTL",
    "QUEUE_STATUS_STREAM",
    "STATUS_STREAM",
    "Acked",
    "BadFrame",
    "ChannelManager",
    "CommandApplied",
    "CommandResult",
    "CommandUnanswered",
    "Dropped",
    "Entry",
    "Event",
    "LinkChanged",
    "LinkConfig",
    "LinkStats",
    "ProductUpdated",
    "Received",
    "Rejected",
    "Schedule",
    "ScheduleSwitched",
    "SenderFailed",
    "SlotWindow",
    "StreamConfig",
    "StreamQueue",
    "TdmaSlot",
    "Transmission",
    "default_streams",
    "link_record",
    "read_link_log",
    "resolve_cycle",
    "to_json_line",
]
