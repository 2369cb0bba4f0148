"""Channel manager: contest, packing, pulls, failing senders, acks, links, schedules, settings."""

from __future__ import annotations

import json
from typing import Any

import pytest

from coex_core import wire
from coex_core.channel import (
    CONTROL_STREAM,
    QUEUE_STATUS_STREAM,
    STATUS_STREAM,
    Acked,
    ChannelManager,
    Dropped,
    LinkConfig,
    Schedule,
    ScheduleSwitched,
    SenderFailed,
    StreamConfig,
    TdmaSlot,
    resolve_cycle,
)
from coex_core.errors import ConfigError, EncodeError
from coex_core.messages import (
    AckStatus,
    FrameAck,
    FrameAckEntry,
    LinkControl,
    Message,
    Opaque,
    QueueConfig,
    QueueStatus,
    ScheduleUpdate,
    VehicleMode,
    VehicleStatus,
)
from coex_core.modality import ModalitySender

VEHICLE, TOPSIDE = 2, 1


def blob(n: int, tag: int = 0) -> Opaque:
    """A third-party message that encodes to exactly ``n`` bytes (1 type + 1 length + body)."""
    assert 3 <= n <= 129
    return Opaque(96 + tag, bytes([tag]) * (n - 2))


def status(t: int = 0) -> VehicleStatus:
    return VehicleStatus(t, 1.0, 2.0, 100.0, 5.0, 90.0, 1.0, 80, VehicleMode.SURVEY, 0)


def vehicle_link(link: int = 0, **kw: Any) -> LinkConfig:
    # the vehicle owns every slot: it may always transmit (unless told otherwise)
    sched = kw.pop("schedule", Schedule.simple([VEHICLE], 20.0, 2.0))
    return LinkConfig(link, sched, **kw)


def manager(*streams: StreamConfig, links: list[LinkConfig] | None = None, **kw: Any) -> ChannelManager:
    return ChannelManager(VEHICLE, links or [vehicle_link()], streams, **kw)


class FakeSender(ModalitySender):
    """Test double: serves messages of a fixed size from an endless (or finite) supply."""

    def __init__(self, size: int = 40, tag: int = 1, supply: int | None = None) -> None:
        self.size, self.tag, self.supply = size, tag, supply
        self.calls: list[int] = []

    def ingest(self, data: Any, now: float) -> None:
        pass

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        self.calls.append(max_bytes)
        out: list[Message] = []
        room = max_bytes
        while room >= 3 and (self.supply is None or self.supply > 0):
            n = min(self.size, room, 129)
            out.append(blob(n, self.tag))
            room -= n
            if self.supply is not None:
                self.supply -= 1
        return out

    def handle(self, message: Message, now: float) -> list[Message]:
        return []


class RaisingSender(FakeSender):
    def fill(self, max_bytes: int, now: float) -> list[Message]:
        self.calls.append(max_bytes)
        raise RuntimeError("sensor driver exploded")


class SlowSender(FakeSender):
    def __init__(self, clock: list[float], delay: float, **kw: Any) -> None:
        super().__init__(**kw)
        self.clock, self.delay = clock, delay

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        self.clock[0] += self.delay  # "takes" delay seconds of the caller's clock
        return super().fill(max_bytes, now)


def messages_of(frames: tuple[bytes, ...]) -> list[Message]:
    return [m for f in frames for m in wire.unpack(f)]


# -------------------------------------------------------------------------------- contest

def test_status_tier_goes_first_then_value_contest() -> None:
    m = manager(StreamConfig(5, "a", priority=10), StreamConfig(6, "b", priority=100),
                links=[vehicle_link(rate=1, frames=1)])  # one 64-byte frame per packet
    m.push(5, blob(30, 5), 0.0)
    m.push(6, blob(30, 6), 0.0)
    m.push(STATUS_STREAM, status(), 0.0)
    tx = m.build(0, 10.0)
    assert tx is not None
    got = messages_of(tx.frames)
    assert isinstance(got[0], VehicleStatus)  # tier 0 before any science
    assert got[1] == blob(30, 6)  # higher value wins the contest
    assert len(got) == 2  # the 30-byte message of stream 5 no longer fits (64 - 3 - 25 - 30)


def test_contest_shares_in_proportion_to_value_over_ttl() -> None:
    m = manager(StreamConfig(5, "lo", priority=10, max_depth=1000),
                StreamConfig(6, "hi", priority=30, max_depth=1000),
                links=[vehicle_link(rate=1, frames=1)])
    for _ in range(400):
        m.push(5, blob(58, 5), 0.0)
        m.push(6, blob(58, 6), 0.0)
    sent = {5: 0, 6: 0}
    for k in range(200):  # one 58-byte message per packet
        tx = m.build(0, 100.0 + 10 * k)
        assert tx is not None
        (msg,) = messages_of(tx.frames)
        assert isinstance(msg, Opaque)
        sent[msg.type_id - 96] += 1
    # Goby's contest: message share ~ value/ttl, i.e. 3:1 here, nobody starves
    assert 2.5 < sent[6] / sent[5] < 3.5


def test_blackout_newest_first_and_depth() -> None:
    m = manager(StreamConfig(5, "a", blackout=30.0, newest_first=True, max_depth=2))
    for i in range(3):
        m.push(5, blob(10, i), float(i))
    assert [e.message for e in m.stream(5).entries] == [blob(10, 1), blob(10, 2)]  # oldest dropped
    tx = m.build(0, 10.0)
    assert tx is not None and messages_of(tx.frames) == [blob(10, 2)]  # newest first, one only
    assert m.build(0, 20.0) is None  # in blackout
    tx = m.build(0, 41.0)
    assert tx is not None and messages_of(tx.frames) == [blob(10, 1)]
    fifo = manager(StreamConfig(5, "f", max_depth=1))
    fifo.push(5, blob(10, 1), 0.0)
    fifo.push(5, blob(10, 2), 0.0)
    assert [e.message for e in fifo.stream(5).entries] == [blob(10, 1)]  # a full FIFO refuses
    assert any(isinstance(e, Dropped) and e.reason == "overflow" for e in fifo.events())


def test_ttl_expiry_and_bad_push() -> None:
    m = manager(StreamConfig(5, "a", ttl=60.0))
    m.push(5, blob(10), 0.0)
    assert m.poll(61.0) == []
    assert len(m.stream(5)) == 0
    assert any(isinstance(e, Dropped) and e.reason == "ttl" for e in m.events())
    with pytest.raises(EncodeError):
        m.push(5, Opaque(5, b"x"), 0.0)  # not a third-party id
    with pytest.raises(ConfigError):
        m.push(17, blob(10), 0.0)


def test_slot_min_priority_and_tags() -> None:
    sched = Schedule((TdmaSlot(VEHICLE, 20.0, 2.0, min_priority=50),
                      TdmaSlot(VEHICLE, 20.0, 2.0, tags=frozenset({"img"}))))
    m = manager(StreamConfig(5, "low", priority=10), StreamConfig(6, "img", priority=20,
                                                                  tags=frozenset({"img"})),
                links=[vehicle_link(schedule=sched)])
    m.push(5, blob(10, 5), 0.0)
    m.push(6, blob(10, 6), 0.0)
    m.push(STATUS_STREAM, status(), 0.0)
    tx = m.build(0, 1.0)  # slot 0: only priority >= 50 (and tier 0)
    assert tx is not None and [type(x) for x in messages_of(tx.frames)] == [VehicleStatus]
    tx = m.build(0, 21.0)  # slot 1: only tagged streams
    assert tx is not None and messages_of(tx.frames) == [blob(10, 6)]


# ------------------------------------------------------------------------------- packing

def test_packing_fills_frames_and_pulls_from_senders() -> None:
    m = manager()
    s = FakeSender(size=100)
    m.add_stream(StreamConfig(5, "data"), s)
    m.push(STATUS_STREAM, status(), 0.0)
    tx = m.build(0, 1.0)
    assert tx is not None
    assert len(tx.frames) == 8 and all(len(f) == 256 for f in tx.frames)  # every frame full
    assert tx.used == 8 * 253
    assert tx.capacity == 2048
    assert all(c <= 253 for c in s.calls)  # the sender was asked for at most what was left
    got = messages_of(tx.frames)
    assert isinstance(got[0], VehicleStatus)
    assert sum(wire.encoded_size(x) for x in got) == tx.used


def test_queued_message_that_does_not_fit_lets_smaller_ones_through() -> None:
    m = manager(StreamConfig(5, "a"), links=[vehicle_link(rate=1, frames=1)])
    m.push(5, blob(60, 1), 0.0)  # 60 > 61 - 3? no: frame budget is 64 - 3 = 61, fits
    m.push(5, blob(61, 2), 0.0)
    m.push(5, blob(5, 3), 0.0)
    tx = m.build(0, 1.0)
    assert tx is not None and messages_of(tx.frames) == [blob(60, 1)]
    tx = m.build(0, 2.0)
    assert tx is not None and messages_of(tx.frames) == [blob(61, 2)]


def test_failing_sender_never_stops_the_packet() -> None:
    m = manager()
    bad = RaisingSender()
    good = FakeSender(size=50, tag=2)
    m.add_stream(StreamConfig(5, "bad", priority=100), bad)
    m.add_stream(StreamConfig(6, "good", priority=10), good)
    tx = m.build(0, 1.0)
    assert tx is not None and len(tx.frames) == 8
    assert len(bad.calls) == 1  # asked once, then "no data" for the rest of the packet
    assert {type(x) for x in messages_of(tx.frames)} == {Opaque}
    fails = [e for e in m.events() if isinstance(e, SenderFailed)]
    assert len(fails) == 1 and "exploded" in fails[0].error
    m.build(0, 10.0)
    assert len(bad.calls) == 2  # asked again in the next packet


class EstimateRaisingSender(FakeSender):
    def ready_bytes(self, now: float) -> int:
        raise RuntimeError("estimate exploded")


def test_a_sender_whose_estimate_fails_is_counted_and_named() -> None:
    """``ready_bytes`` (the packet's backlog estimate) raising never stops a packet, and is no
    longer skipped quietly: counted in ``sender_failures``, per stream by name, and told as a
    SenderFailed event naming the stream."""
    m = manager()
    m.add_stream(StreamConfig(5, "sonar", priority=10), EstimateRaisingSender(size=50, tag=2))
    tx = m.build(0, 1.0)
    assert tx is not None and tx.frames  # the packet still goes
    assert m.stats["sender_failures"] >= 1
    assert m.sender_failures_by_stream["sonar"] == m.stats["sender_failures"]
    fails = [e for e in m.events() if isinstance(e, SenderFailed)]
    assert fails and fails[0].stream == 5 and fails[0].error.startswith("sonar: ready_bytes() failed")


def test_slow_sender_is_cut_off_and_loses_nothing() -> None:
    clock = [0.0]
    m = manager(clock=lambda: clock[0], sender_budget=0.1)
    slow = SlowSender(clock, delay=0.5, size=50, tag=3, supply=4)
    fast = FakeSender(size=50, tag=4)
    m.add_stream(StreamConfig(5, "slow", priority=100), slow)
    m.add_stream(StreamConfig(6, "fast", priority=10), fast)
    tx = m.build(0, 1.0)
    assert tx is not None and len(tx.frames) == 8
    got = messages_of(tx.frames)
    assert blob(50, 3) not in got  # late data is not used in this packet ...
    assert len(slow.calls) == 1
    assert any(isinstance(e, SenderFailed) and e.slow for e in m.events())
    assert len(m.stream(5)) == 4  # ... but it is kept for the next one
    tx2 = m.build(0, 10.0)
    assert tx2 is not None and messages_of(tx2.frames).count(blob(50, 3)) == 4


def test_packet_deadline_stops_pulling() -> None:
    clock = [0.0]
    m = manager(clock=lambda: clock[0], fill_budget=1.0, sender_budget=10.0)
    s = SlowSender(clock, delay=0.4, size=50)
    m.add_stream(StreamConfig(5, "s"), s)
    tx = m.build(0, 1.0)
    assert tx is not None
    assert len(s.calls) <= 4  # after 1 s of filling, no more calls


def test_unencodable_pulled_message_is_reported() -> None:
    class Bad(FakeSender):
        def fill(self, max_bytes: int, now: float) -> list[Message]:
            return [Opaque(3, b"bad"), blob(10)]

    m = manager()
    m.add_stream(StreamConfig(5, "bad"), Bad())
    tx = m.build(0, 1.0)
    assert tx is not None and blob(10) in messages_of(tx.frames)
    assert any(isinstance(e, Dropped) and e.reason == "encode" for e in m.events())


# ------------------------------------------------------------------------ acks and links

def two_links() -> list[LinkConfig]:
    return [vehicle_link(0, ack_timeout=100.0), vehicle_link(1, rate=3, ack_timeout=100.0)]


def test_ack_required_messages_stay_until_acked_and_resend_after_timeout() -> None:
    m = manager(StreamConfig(5, "img", ack_required=True), links=[vehicle_link(ack_timeout=50.0)])
    m.push(5, blob(40, 1), 0.0)
    tx = m.build(0, 1.0)
    assert tx is not None and messages_of(tx.frames) == [blob(40, 1)]
    assert m.build(0, 10.0) is None  # waiting for its ack
    tx = m.build(0, 52.0)  # ack timeout: sent again
    assert tx is not None and messages_of(tx.frames) == [blob(40, 1)]
    ack = FrameAck(VEHICLE, 0, (FrameAckEntry(tx.seq, 1),))
    assert m.on_ack(ack, 60.0) == 1
    assert len(m.stream(5)) == 0
    (acked,) = [e for e in m.events() if isinstance(e, Acked)]
    assert acked.latency == pytest.approx(59.0)


def test_ack_on_one_link_clears_the_message_everywhere() -> None:
    m = manager(StreamConfig(5, "img", ack_required=True), links=two_links())
    m.push(5, blob(40, 1), 0.0)
    m.push(5, blob(40, 2), 0.0)
    tx0 = m.build(0, 1.0)
    assert tx0 is not None
    assert m.build(1, 2.0) is None  # both pending (sent on link 0)
    # link 0's ack is lost; after the timeout link 1 re-sends them
    tx1 = m.build(1, 102.0)
    assert tx1 is not None and messages_of(tx1.frames) == [blob(40, 1), blob(40, 2)]
    # the ack for link 1's frame arrives (it could arrive over link 0: on_ack does not care)
    m.on_ack(FrameAck(VEHICLE, 1, (FrameAckEntry(tx1.seq, 1),)), 110.0)
    assert len(m.stream(5)) == 0
    assert m.build(0, 300.0) is None  # nothing left to re-send on link 0
    # a late ack of the old link-0 frame is harmless
    assert m.on_ack(FrameAck(VEHICLE, 0, (FrameAckEntry(tx0.seq, 1),)), 120.0) == 0


def test_withdrawn_messages_leave_queued_or_in_flight_and_their_late_ack_clears_nothing() -> None:
    m = manager(StreamConfig(5, "img", ack_required=True), links=[vehicle_link(ack_timeout=50.0)])
    m.push(5, blob(40, 1), 0.0)
    m.push(5, blob(40, 2), 0.0)
    tx = m.build(0, 1.0)
    assert tx is not None and messages_of(tx.frames) == [blob(40, 1), blob(40, 2)]
    m.push(5, blob(40, 3), 5.0)
    m.events()
    assert m.withdraw(5, lambda msg: msg in (blob(40, 1), blob(40, 3)), 6.0) == 2
    assert [e.message for e in m.stream(5).entries] == [blob(40, 2)]
    (dropped,) = [e for e in m.events() if isinstance(e, Dropped)]
    assert (dropped.stream, dropped.reason, dropped.count) == (5, "superseded", 2)
    assert m.stream(5).drop_reasons == {"superseded": 2}
    # the frame's ack clears only what is still there; nothing withdrawn is ever sent again
    assert m.on_ack(FrameAck(VEHICLE, 0, (FrameAckEntry(tx.seq, 1),)), 10.0) == 1
    assert m.build(0, 200.0) is None
    assert m.withdraw(5, lambda msg: True, 201.0) == 0


def test_disabling_a_link_returns_unacked_messages() -> None:
    m = manager(StreamConfig(5, "img", ack_required=True), links=two_links())
    m.push(5, blob(40, 1), 0.0)
    assert m.build(0, 1.0) is not None
    assert m.build(1, 2.0) is None
    assert m.set_link_enabled(0, False, 3.0) == 1
    tx = m.build(1, 4.0)  # at once, not after the ack timeout
    assert tx is not None and messages_of(tx.frames) == [blob(40, 1)]
    assert not m.can_transmit(0, 20.0)
    m.push(5, blob(20, 2), 20.0)
    assert [t.link_id for t in m.poll(20.0)] == [1]  # only the enabled link transmits


def test_link_control_command_and_last_link_protection() -> None:
    m = manager(links=two_links())
    ack = m.apply(LinkControl(7, 1, False, False), 1.0)
    assert ack.command_id == 7 and ack.status == AckStatus.ACCEPTED
    assert not m.can_transmit(1, 2.0)
    ack = m.apply(LinkControl(8, 0, False, False), 2.0)  # would leave no transmitting link
    assert ack.status == AckStatus.REJECTED and m.can_transmit(0, 2.0)
    assert m.apply(LinkControl(9, 5, True, False), 2.0).status == AckStatus.UNKNOWN_TARGET
    assert m.apply(LinkControl(10, 1, True, True), 3.0).status == AckStatus.ACCEPTED
    assert not m.can_transmit(1, 4.0)  # enabled but muted
    assert m.apply(LinkControl(11, 1, True, False), 5.0).status == AckStatus.ACCEPTED
    assert m.can_transmit(1, 6.0)


def test_frame_acks_are_generated_for_received_frames() -> None:
    m = manager()
    from coex_core.messages import FrameHeader

    for seq in (3, 4, 6, 40):
        m.on_frame(0, FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=seq), 1.0)
    m.on_frame(0, FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=41), 1.0, ackable=False)
    tx = m.build(0, 2.0)
    assert tx is not None
    # the gaps in the peer's seqs (5, 7..39) measure heavy loss: the ack goes in several frames
    acks = messages_of(tx.frames)
    assert len(acks) == len(tx.frames) == m.copies(0) > 1
    assert set(acks) == {FrameAck(TOPSIDE, 0, (FrameAckEntry(3, 0b1011), FrameAckEntry(40, 1)))}


def test_frames_received_longer_ago_than_the_ack_timeout_are_not_acked() -> None:
    from coex_core.messages import FrameHeader

    m = manager(links=[vehicle_link(ack_timeout=50.0)])
    m.on_frame(0, FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=3), 0.0)
    m.on_frame(0, FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=9), 30.0)
    tx = m.build(0, 60.0)  # seq 3 is 60 s old: its sender has re-sent (and may reuse seq 3)
    assert tx is not None
    assert messages_of(tx.frames) == [FrameAck(TOPSIDE, 0, (FrameAckEntry(9, 1),))]
    assert m.stats["stale_acks"] == 1
    m.on_frame(0, FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=10), 100.0)
    assert m.build(0, 200.0) is None  # nothing but a stale ack: nothing to send
    assert m.stats["stale_acks"] == 2


def test_a_late_ack_cannot_clear_a_newer_frame_with_the_same_seq() -> None:
    """The sender reuses a seq after 256 frames. An ack of the old use sent late (a receiver
    restarted from its journal, a long outage) would clear the messages of the newer frame,
    lost on the way, as if they had arrived. The receiver sends no ack older than the ack
    timeout (shorter than a wrap), so they stay queued and go again."""
    v = ChannelManager(VEHICLE, [LinkConfig(0, Schedule.simple([VEHICLE], 4.0, 0.0), rate=5,
                                            dst=TOPSIDE, ack_timeout=20.0)])
    v.add_stream(StreamConfig(5, "data", ack_required=True, max_depth=1000))
    t = ChannelManager(TOPSIDE, [LinkConfig(0, Schedule.simple([TOPSIDE], 4.0, 0.0), rate=5,
                                            dst=VEHICLE, ack_timeout=20.0)])
    now, j = 0.0, 0
    reused: list[Message] = []
    for k in range(33):  # 33 packets of 8 frames: seqs 0..7 are used again by packet 32
        for _ in range(16):
            v.push(5, Opaque(96 + j, j.to_bytes(2, "big") * 50), now)
            j += 1
        tx = v.build(0, now)
        assert tx is not None
        if k == 0:  # topside gets the first packet; its ack is held back (topside is down)
            for f in tx.frames:
                t.on_frame(0, wire.unpack_frame(f).header, now)
        elif k == 32:  # the packet that reuses seqs 0..7 is lost
            assert tx.seq == 0
            reused = messages_of(tx.frames)
        else:  # the others are acked at once
            v.on_ack(FrameAck(VEHICLE, 0, (FrameAckEntry(tx.seq, 0xFF),)), now + 1.0)
        now += 4.0
    assert reused
    late = t.build(0, now)  # topside is back, 132 s after packet 0
    for msg in messages_of(late.frames) if late is not None else []:
        if isinstance(msg, FrameAck):
            v.on_ack(msg, now)
    assert t.stats["stale_acks"] == 8
    queued = {e.message for e in v.stream(5).entries}
    assert set(reused) <= queued  # not cleared by an ack of other frames


# ---------------------------------------------------------------- queue config / status

def test_queue_config_changes_settings_and_flushes() -> None:
    m = manager(StreamConfig(5, "a", priority=10, max_depth=10))
    for i in range(5):
        m.push(5, blob(10, i), 0.0)
    ack = m.apply(QueueConfig(3, 5, False, None, 99, 600, 2, True), 1.0)
    assert ack.status == AckStatus.ACCEPTED
    c = m.stream(5).config
    assert (c.priority, c.ttl, c.max_depth, c.newest_first) == (99, 600.0, 2, True)
    assert [e.message for e in m.stream(5).entries] == [blob(10, 3), blob(10, 4)]
    assert m.apply(QueueConfig(4, 5, True, False, None, None, None, None), 2.0).status == AckStatus.ACCEPTED
    assert len(m.stream(5)) == 0 and not m.stream(5).config.enabled
    assert m.apply(QueueConfig(5, 20, False, None, None, None, None, None), 2.0).status == \
        AckStatus.UNKNOWN_TARGET


def test_queue_status_is_sent_regularly() -> None:
    m = manager(StreamConfig(5, "a"), queue_status_interval=120.0)
    m.push(5, blob(100), 0.0)
    m.push(5, blob(100), 0.0)
    txs = m.poll(10.0)
    got = messages_of(txs[0].frames)
    qs = [x for x in got if isinstance(x, QueueStatus)]
    assert len(qs) == 1
    lines = {s.stream: s for s in qs[0].streams}
    # quantised on the wire: bytes in 64 B steps, age in 16 s steps
    assert lines[5].depth == 2 and lines[5].queued_bytes == 192 and lines[5].oldest_age == 16
    assert {STATUS_STREAM, QUEUE_STATUS_STREAM, CONTROL_STREAM, 5} == set(lines)
    txs = m.poll(60.0)
    assert not any(isinstance(x, QueueStatus) for t in txs for x in messages_of(t.frames))
    txs = m.poll(131.0)
    assert any(isinstance(x, QueueStatus) for t in txs for x in messages_of(t.frames))


def test_settings_survive_a_restart() -> None:
    def build() -> ChannelManager:
        return manager(StreamConfig(5, "a", priority=10), links=two_links())

    m = build()
    m.apply(QueueConfig(1, 5, False, False, 77, 300, 5, True), 1.0)
    m.apply(LinkControl(2, 1, False, False), 1.0)
    new = Schedule.simple([VEHICLE, TOPSIDE], 30.0, 2.0, version=3)
    cur = m.schedule(0).cycle_at(1.0)
    m.apply(new.to_message(3, 0, cur + 2), 1.0)
    saved = json.loads(json.dumps(m.export_settings()))  # JSON-able
    again = build()
    again.import_settings(saved, now=2.0)
    c = again.stream(5).config
    assert (c.enabled, c.priority, c.ttl, c.max_depth, c.newest_first) == (False, 77, 300.0, 5, True)
    assert not again.can_transmit(1, 3.0)
    pend = again.pending_schedule(0)
    assert pend is not None and pend.version == 3
    with pytest.raises(ConfigError):
        again.import_settings({"streams": {"5": {"stream": 5, "priority": 1000}}})


# ---------------------------------------------------------------------------- schedules

def nui(version: int = 0) -> Schedule:
    # 6 x 20 s, topside slots 0 and 3, vehicle 1, 2, 4, 5
    owners = [TOPSIDE, VEHICLE, VEHICLE, TOPSIDE, VEHICLE, VEHICLE]
    return Schedule.simple(owners, 20.0, 2.0, version=version)


def test_tdma_opportunities_several_packets_per_slot() -> None:
    m = manager(links=[LinkConfig(0, nui())])
    assert not m.can_transmit(0, 5.0)  # topside slot
    assert m.next_opportunity(0, 5.0) == pytest.approx(20.0)
    assert m.can_transmit(0, 20.0)
    m.add_stream(StreamConfig(5, "d"), FakeSender(size=120))
    starts = []
    t = 20.0
    while t < 40.0:
        nxt = m.next_opportunity(0, t)
        assert nxt is not None
        if nxt >= 40.0:
            break
        txs = m.poll(nxt)
        assert len(txs) == 1
        starts.append(nxt)
        t = nxt + 1e-6
    # 3.0 s packets, 2 s guard: starts at 20, 23, ..., 35 (35 + 3 + 2 = 40)
    assert len(starts) == 6
    assert starts[-1] + RATE5_PACKET + 2.0 <= 40.0 + 1e-6


RATE5_PACKET = LinkConfig(0, nui()).packet_time


def test_resolve_cycle_wraps() -> None:
    assert resolve_cycle(5, 3) == 5
    assert resolve_cycle(2, 65535) == 65538
    assert resolve_cycle(65535, 65536 * 3 + 1) == 65536 * 3 - 1  # in the past


def test_schedule_update_rejections() -> None:
    m = manager(links=[LinkConfig(0, nui())])
    no_slot = Schedule.simple([TOPSIDE], 60.0, 2.0, version=1)
    assert m.apply(no_slot.to_message(1, 0, 10), 0.0).status == AckStatus.REJECTED
    late = nui(2).to_message(2, 0, 0)
    assert m.apply(late, 130.0).status == AckStatus.REJECTED  # cycle 0 has passed
    assert m.apply(nui(2).to_message(3, 4, 9), 0.0).status == AckStatus.UNKNOWN_TARGET
    ok = m.apply(ScheduleUpdate(4, 0, 2, 3, nui().to_message(0, 0, 0).slots), 130.0)
    assert ok.status == AckStatus.ACCEPTED
    assert m.schedule(0).version == 0
    m.poll(359.0)
    assert m.schedule(0).version == 0
    m.poll(360.0)  # start of cycle 3
    assert m.schedule(0).version == 2
    assert any(isinstance(e, ScheduleSwitched) and e.version == 2 for e in m.events())


def test_expedited_stream_is_asked_first() -> None:
    m = manager(links=[vehicle_link(rate=1, frames=1)])
    busy = FakeSender(size=61, tag=1)
    asked = FakeSender(size=61, tag=2)
    m.add_stream(StreamConfig(5, "busy", priority=100), busy)
    m.add_stream(StreamConfig(6, "asked", priority=1), asked)
    tx = m.build(0, 1.0)
    assert tx is not None and messages_of(tx.frames) == [blob(61, 1)]
    m.expedite(6)  # an operator request reached stream 6's modality
    tx = m.build(0, 2.0)
    assert tx is not None and messages_of(tx.frames) == [blob(61, 2)]
    tx = m.build(0, 3.0)  # served once: back to the normal contest
    assert tx is not None and messages_of(tx.frames) == [blob(61, 1)]


def test_posix_times_from_a_zero_epoch() -> None:
    # deployments run on time.time(): slot arithmetic must hold at 1.7e9 s
    m = manager(links=[LinkConfig(0, nui())])
    m.add_stream(StreamConfig(5, "d"), FakeSender(size=120))
    base = 14_166_667 * 120.0 + 40.0  # 1.7e9 s + 80 s: slot 2 (vehicle) of its cycle
    assert m.schedule(0).window(base).index == 2
    assert m.schedule(0).window(base - 1e-3).index == 1
    starts = []
    cycle0 = base - 40.0
    t = cycle0 + 1.0  # in topside's slot 0
    while True:
        nxt = m.next_opportunity(0, t)
        assert nxt is not None
        if nxt >= cycle0 + 120.0:
            break
        assert m.can_transmit(0, nxt)
        (tx,) = m.poll(nxt)
        starts.append((tx.slot, nxt))
        t = nxt + 1e-6
    assert {s for s, _ in starts} == {1, 2, 4, 5}
    assert len(starts) == 6 * 4  # 6 packets in each of the 4 vehicle slots


def test_per_link_message_size_cap() -> None:
    m = manager(links=two_links())
    s = FakeSender(size=200, tag=1)
    m.add_stream(StreamConfig(5, "img", link_max_bytes=((1, 60),)), s)
    tx = m.build(1, 1.0)  # the slow modem: small pieces only
    assert tx is not None and all(wire.encoded_size(x) <= 60 for x in messages_of(tx.frames))
    assert max(s.calls) == 60
    m.push(5, blob(100, 2), 2.0)
    tx = m.build(1, 3.0)
    assert tx is not None and blob(100, 2) not in messages_of(tx.frames)  # too big for link 1
    tx = m.build(0, 4.0)
    assert tx is not None and blob(100, 2) in messages_of(tx.frames)
    cfg = StreamConfig.from_dict(json.loads(json.dumps(m.stream(5).config.to_dict())))
    assert cfg.max_bytes_on(1) == 60 and cfg.max_bytes_on(0) is None
