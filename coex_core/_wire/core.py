"""Core messages: vehicle status, queues, TDMA schedule, links, command acks and authentication."""

from __future__ import annotations

import construct as cs

from ..messages import (
    AckStatus,
    AuthTrailer,
    CommandAck,
    FrameAck,
    FrameAckEntry,
    LinkControl,
    LinkHealth,
    LinkStatus,
    QueueConfig,
    QueueStatus,
    ScheduleUpdate,
    Slot,
    SpareConfig,
    StreamStatus,
    VehicleMode,
    VehicleStatus,
)
from ._primitives import Bits, Body, Bool, Bounded, Count, Enum, OptBool, RawBytes, Stamp
from ._registry import MessageSpec, register

#: Local-frame coordinates: metres east/north of the survey origin.
XY = dict(lo=-50000, hi=50000, res=0.1, unit="m")
COMMAND_ID = Bounded(0, 255) * "Command id, echoed in the CommandAck (wraps at 256)"
STREAM = Bounded(0, 31) * "Stream (queue) id"
LINK = Bounded(0, 7) * "Link (modem) id"

VEHICLE_STATUS = Body(
    "stamp" / Stamp() * "Time of the status",
    "x" / Bounded(**XY) * "Position east of the origin",  # type: ignore[arg-type]
    "y" / Bounded(**XY) * "Position north of the origin",  # type: ignore[arg-type]
    "depth" / Bounded(0, 6000, 0.1, unit="m") * "Depth below the surface",
    "altitude" / Bounded(0, 500, 0.1, optional=True, unit="m") * "Altitude above the seafloor",
    "heading" / Bounded(0, 359.9, 0.1, unit="deg") * "Heading, clockwise from north",
    "speed" / Bounded(0, 5, 0.01, unit="m/s") * "Speed over ground",
    "battery" / Bounded(0, 100, unit="%") * "Battery state of charge",
    "mode" / Enum(VehicleMode) * "Vehicle mode",
    "faults" / Bits(8) * "Fault flags (vehicle specific)",
)

STREAM_STATUS = cs.Struct(
    "stream" / STREAM,
    "enabled" / Bool() * "Stream enabled",
    "tier" / Bounded(0, 3) * "Tier (0 = strict status tier)",
    "priority" / Bounded(0, 127) * "Value / priority",
    "depth" / Bounded(0, 63, saturating=True, unit="messages") * "Queued messages",
    "queued_bytes" / Bounded(0, 65472, 64, saturating=True, unit="B") * "Queued bytes",
    "oldest_age" / Bounded(0, 4080, 16, saturating=True, unit="s") * "Age of the oldest queued message",
    "drops" / Bounded(0, 15, saturating=True) * "Messages dropped since the last status",
)

QUEUE_STATUS = Body(
    "stamp" / Stamp() * "Time of the status",
    "n_streams" / Count(0, 31, "streams"),
    "streams" / cs.Array(cs.this.n_streams, STREAM_STATUS) * "One entry per stream (see StreamStatus)",
)

QUEUE_CONFIG = Body(
    "command_id" / COMMAND_ID,
    "stream" / STREAM,
    "flush" / Bool() * "Discard everything queued in the stream",
    "enabled" / OptBool() * "Enable or disable the stream",
    "priority" / Bounded(0, 127, optional=True) * "New value / priority",
    "ttl" / Bounded(0, 16383, optional=True, unit="s") * "New time-to-live",
    "max_depth" / Bounded(0, 1023, optional=True, unit="messages") * "New maximum depth",
    "newest_first" / OptBool() * "Newest-first (true) or oldest-first (false)",
)

SLOT = cs.Struct(
    "owner" / Bounded(0, 15) * "Node id that transmits in the slot",
    "duration" / Bounded(0.1, 600, 0.1, unit="s") * "Slot length",
    "guard" / Bounded(0, 25.5, 0.1, unit="s") * "Guard time at the end of the slot",
    "min_priority" / Bounded(0, 127) * "Lowest priority allowed in the slot",
)

SCHEDULE_UPDATE = Body(
    "command_id" / COMMAND_ID,
    "link" / LINK,
    "version" / Bounded(0, 15) * "Schedule version (carried in every frame header)",
    "activate_cycle" / Bounded(0, 65535) * "Cycle number (mod 2^16) at whose start it takes effect",
    "n_slots" / Count(1, 32, "slots"),
    "slots" / cs.Array(cs.this.n_slots, SLOT) * "Slots in cycle order (see Slot)",
)

LINK_CONTROL = Body(
    "command_id" / COMMAND_ID,
    "link" / LINK,
    "enabled" / Bool() * "Link enabled",
    "mute" / Bool() * "Software mute (receive only)",
)

COMMAND_ACK = Body(
    "command_id" / COMMAND_ID,
    "status" / Enum(AckStatus) * "Outcome",
)

FRAME_ACK_ENTRY = cs.Struct(
    "seq" / Bounded(0, 255) * "Sequence number of the acknowledged transmission (frame header seq)",
    "frames" / Bits(8) * "Bitmap of frames received intact (bit 0 = first frame)",
)

FRAME_ACK = Body(
    "node" / Bounded(0, 15) * "Node id whose transmissions are acknowledged",
    "link" / LINK,
    "n_entries" / Count(1, 16, "entries"),
    "entries" / cs.Array(cs.this.n_entries, FRAME_ACK_ENTRY) * "Acknowledged transmissions (see FrameAckEntry)",
)

AUTH_TRAILER = Body(
    "counter" / Bounded(0, 2**32 - 1) * "Monotonic command counter (never reused under one key)",
    "tag" / RawBytes(fixed=8) * "HMAC-SHA256 tag truncated to its first 8 bytes",
)

LINK_STATUS = Body(
    "stamp" / Stamp() * "Time of the reception",
    "link" / LINK,
    "frames" / Bounded(0, 63, saturating=True) * "Frames in the packet",
    "bad_frames" / Bounded(0, 63, saturating=True) * "Frames that failed their CRC",
    "snr" / Bounded(-20, 50, 0.5, optional=True, unit="dB") * "Output SNR",
    "doppler" / Bounded(-12.7, 12.7, 0.1, optional=True, unit="m/s") * "Doppler",
)


LINK_HEALTH = Body(
    "stamp" / Stamp() * "Time of the report",
    "link" / LINK,
    "up" / Bool() * "The modem is there now",
    "outages" / Bounded(0, 255, saturating=True) * "Outages since the node started",
    "down_total" / Bounded(0, 2**20 - 1, saturating=True, unit="s") * "Time down in all, outages so far",
    "last_down" / Bounded(0, 2**20 - 1, saturating=True, unit="s")
    * "Length of the last outage (up = 0: of the present one so far)",
)


def _status(**kw: object) -> VehicleStatus:
    base: dict[str, object] = dict(
        stamp=0, x=0.0, y=0.0, depth=0.0, altitude=None, heading=0.0, speed=0.0, battery=0,
        mode=VehicleMode.UNKNOWN, faults=0,
    )
    base.update(kw)
    return VehicleStatus(**base)  # type: ignore[arg-type]


def _stream(i: int, **kw: object) -> StreamStatus:
    base: dict[str, object] = dict(
        stream=i, enabled=True, tier=1, priority=30, depth=0, queued_bytes=0, oldest_age=0, drops=0
    )
    base.update(kw)
    return StreamStatus(**base)  # type: ignore[arg-type]


_MAX_STREAM = _stream(31, tier=3, priority=127, depth=63, queued_bytes=65472, oldest_age=4080, drops=15)
_MAX_SLOT = Slot(owner=15, duration=600.0, guard=25.5, min_priority=127)

register(MessageSpec(
    1, VehicleStatus, VEHICLE_STATUS, False, "core",
    "Vehicle safety status; strict tier above all science data.",
    largest=lambda: _status(),
    cases=lambda: [
        ("minimum", _status()),
        ("maximum", _status(stamp=2**18 - 1, x=50000.0, y=50000.0, depth=6000.0, altitude=500.0,
                            heading=359.9, speed=5.0, battery=100, mode=VehicleMode.MANUAL, faults=255)),
        ("negative_xy", _status(stamp=3600, x=-50000.0, y=-123.4, depth=2503.7, altitude=29.8,
                                heading=87.5, speed=0.75, battery=64, mode=VehicleMode.SURVEY, faults=0b1001)),
    ],
))
register(MessageSpec(
    2, QueueStatus, QUEUE_STATUS, False, "core",
    "Per-stream queue state, sent topside regularly (saturating counters).",
    largest=lambda: QueueStatus(stamp=2**18 - 1, streams=(_MAX_STREAM,) * 31),
    cases=lambda: [
        ("empty", QueueStatus(stamp=0, streams=())),
        ("three_streams", QueueStatus(stamp=1234, streams=(
            _stream(0, tier=0, priority=127, depth=1, queued_bytes=64, oldest_age=16),
            _stream(3, priority=30, depth=12, queued_bytes=2880, oldest_age=96, drops=2),
            _stream(4, enabled=False, priority=45),
        ))),
        ("largest", QueueStatus(stamp=2**18 - 1, streams=(_MAX_STREAM,) * 31)),
    ],
))
register(MessageSpec(
    3, QueueConfig, QUEUE_CONFIG, False, "core",
    "Topside command: change a stream's settings at runtime, or flush it.",
    largest=lambda: QueueConfig(255, 31, True, True, 127, 16383, 1023, True),
    cases=lambda: [
        ("no_change", QueueConfig(0, 0, False, None, None, None, None, None)),
        ("flush", QueueConfig(7, 5, True, None, None, None, None, None)),
        ("all_fields_max", QueueConfig(255, 31, True, True, 127, 16383, 1023, True)),
        ("disable_fifo", QueueConfig(12, 3, False, False, 0, 0, 0, False)),
    ],
))
register(MessageSpec(
    4, ScheduleUpdate, SCHEDULE_UPDATE, False, "core",
    "Topside command: a versioned TDMA schedule that both ends switch to at one cycle boundary.",
    largest=lambda: ScheduleUpdate(255, 7, 15, 65535, (_MAX_SLOT,) * 32),
    cases=lambda: [
        ("one_slot_min", ScheduleUpdate(0, 0, 0, 0, (Slot(0, 0.1, 0.0, 0),))),
        ("nui_2022", ScheduleUpdate(9, 1, 2, 4321, tuple(
            Slot(owner=1 if i in (0, 3) else 2, duration=20.0, guard=2.0, min_priority=0) for i in range(6)))),
        ("largest", ScheduleUpdate(255, 7, 15, 65535, (_MAX_SLOT,) * 32)),
    ],
))
register(MessageSpec(
    5, LinkControl, LINK_CONTROL, False, "core",
    "Topside command: enable/disable or mute one modem link.",
    largest=lambda: LinkControl(255, 7, True, True),
    cases=lambda: [
        ("disable_link0", LinkControl(0, 0, False, False)),
        ("enable_link1", LinkControl(17, 1, True, False)),
        ("max_muted", LinkControl(255, 7, True, True)),
    ],
))
SPARE_CONFIG = Body(
    "command_id" / COMMAND_ID,
    "link" / Bounded(0, 7, optional=True) * "Link whose share is set (absent: every link, or none when stream is given)",
    "stream" / Bounded(0, 31, optional=True) * "Stream whose share is set (absent: the link's share)",
    "percent" / Bounded(0, 100, unit="%") * "Share of each packet spare traffic may fill (0: off)",
)
register(MessageSpec(
    10, SpareConfig, SPARE_CONFIG, False, "core",
    "Topside command: cap or switch off spare traffic, per link or per stream.",
    largest=lambda: SpareConfig(255, 7, None, 100),
    cases=lambda: [
        ("all_links_off", SpareConfig(0, None, None, 0)),
        ("link1_quarter", SpareConfig(21, 1, None, 25)),
        ("stream3_half", SpareConfig(22, None, 3, 50)),
        ("maximum", SpareConfig(255, 7, None, 100)),
    ],
))
register(MessageSpec(
    6, CommandAck, COMMAND_ACK, False, "core",
    "Vehicle acknowledgement of a topside command.",
    largest=lambda: CommandAck(255, AckStatus.PENDING),
    cases=lambda: [
        ("accepted_0", CommandAck(0, AckStatus.ACCEPTED)),
        ("rejected", CommandAck(42, AckStatus.REJECTED)),
        ("unknown_target", CommandAck(255, AckStatus.UNKNOWN_TARGET)),
        ("pending", CommandAck(13, AckStatus.PENDING)),
    ],
))
register(MessageSpec(
    7, AuthTrailer, AUTH_TRAILER, False, "core",
    "Command authentication trailer: last message of a frame of topside commands.",
    largest=lambda: AuthTrailer(2**32 - 1, b"\xff" * 8),
    cases=lambda: [
        ("zero", AuthTrailer(0, bytes(8))),
        ("typical", AuthTrailer(1001, bytes.fromhex("0123456789abcdef"))),
        ("max", AuthTrailer(2**32 - 1, b"\xff" * 8)),
    ],
))
register(MessageSpec(
    8, LinkStatus, LINK_STATUS, False, "core",
    "Modem link statistics for the topside console.",
    largest=lambda: LinkStatus(0, 0, 0, 0, None, None),
    cases=lambda: [
        ("unknown_stats", LinkStatus(0, 0, 0, 0, None, None)),
        ("typical", LinkStatus(7200, 1, 9, 2, 12.5, -0.3)),
        ("extremes", LinkStatus(2**18 - 1, 7, 63, 63, -20.0, 12.7)),
    ],
))
register(MessageSpec(
    9, FrameAck, FRAME_ACK, False, "core",
    "Acknowledgement of received frames (per transmission seq, a frame bitmap); clears acked messages on every link.",
    largest=lambda: FrameAck(15, 7, tuple(FrameAckEntry(255, 255) for _ in range(16))),
    cases=lambda: [
        ("one_frame", FrameAck(2, 0, (FrameAckEntry(0, 0b1),))),
        ("two_packets", FrameAck(1, 1, (FrameAckEntry(17, 0b11111111), FrameAckEntry(18, 0b00100101)))),
        ("largest", FrameAck(15, 7, tuple(FrameAckEntry(255, 255) for _ in range(16)))),
    ],
))
register(MessageSpec(
    13, LinkHealth, LINK_HEALTH, False, "core",
    "Vehicle report: a modem's outages (gone and back), so the ship knows how long it was deaf.",
    largest=lambda: LinkHealth(2**18 - 1, 7, True, 255, 2**20 - 1, 2**20 - 1),
    cases=lambda: [
        ("never_down", LinkHealth(0, 0, True, 0, 0, 0)),
        ("back_after_3_min", LinkHealth(7200, 0, True, 2, 412, 185)),
        ("down_now", LinkHealth(9000, 1, False, 1, 60, 60)),
        ("saturated", LinkHealth(2**18 - 1, 7, True, 255, 2**20 - 1, 2**20 - 1)),
    ],
))
