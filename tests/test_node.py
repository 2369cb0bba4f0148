"""Nodes end to end over the simulated acoustic channel: routing, requests, runtime
reconfiguration (both ends switch on the same cycle), watchdog, links, bad frames, restart."""

from __future__ import annotations

import io
from collections.abc import Mapping
from typing import Any, ClassVar

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from coex import SimNetwork
from coex_core import wire
from coex_core.acoustic import AcousticChannel
from coex_core.channel import (
    CONTROL_STREAM,
    Acked,
    BadFrame,
    ChannelManager,
    CommandApplied,
    CommandResult,
    Dropped,
    LinkConfig,
    ProductUpdated,
    Received,
    Rejected,
    Schedule,
    ScheduleSwitched,
    StreamConfig,
    read_link_log,
)
from coex_core.errors import RequestRejected
from coex_core.messages import (
    AckStatus,
    FrameAck,
    FrameAckEntry,
    FrameHeader,
    MapRoiRequest,
    Message,
    Opaque,
    QueueConfig,
    QueueStatus,
    SubgridMessage,
    VehicleMode,
    VehicleStatus,
)
from coex_core.modality import Modality, ModalityReceiver, ModalitySender, Product
from coex_core.node import Node
from coex_plugins.bathymetry import BathymetryModality, BathymetryReceiver, BathymetrySender

from ._bathy_data import small_survey

VEHICLE, TOPSIDE = 2, 1
DATA, REQUEST = 100, 120  # third-party type ids of the fake modality


class FakeSender(ModalitySender):
    """Endless background data (type DATA, tag 0); a request (type REQUEST, body = tag) makes
    the next fills serve 3 messages tagged with it first."""

    def __init__(self) -> None:
        self.urgent: list[int] = []
        self.counter = 0

    def ingest(self, data: Any, now: float) -> None:
        pass

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        out: list[Message] = []
        room = max_bytes
        while room >= 40:
            tag = self.urgent.pop(0) if self.urgent else 0
            self.counter += 1
            body = bytes([tag]) + self.counter.to_bytes(4, "big") + bytes(min(room, 120) - 7)
            out.append(Opaque(DATA, body))
            room -= len(body) + 2
        return out

    def handle(self, message: Message, now: float) -> list[Message]:
        assert isinstance(message, Opaque)
        if message.body == b"\xff":
            raise RequestRejected("tag 255 is out of bounds")
        self.urgent.extend([message.body[0]] * 3)
        return []


class FakeReceiver(ModalityReceiver):
    def __init__(self) -> None:
        self.got: list[tuple[float, Opaque]] = []

    def receive(self, message: Message, now: float) -> list[Product]:
        assert isinstance(message, Opaque)
        self.got.append((now, message))
        return [Product("fake", str(message.body[0]), len(self.got))]

    def poll(self, now: float) -> list[Message]:
        return []

    def products(self) -> list[Product]:
        return []


class FakeModality(Modality):
    name = "fake"
    message_ids: ClassVar[tuple[int, ...]] = (DATA,)
    request_ids: ClassVar[tuple[int, ...]] = (REQUEST,)

    def sender(self, config: Mapping[str, Any] | None = None) -> ModalitySender:
        return FakeSender()

    def receiver(self, config: Mapping[str, Any] | None = None) -> ModalityReceiver:
        return FakeReceiver()


def nui(version: int = 0) -> Schedule:
    owners = [TOPSIDE, VEHICLE, VEHICLE, TOPSIDE, VEHICLE, VEHICLE]
    return Schedule.simple(owners, 20.0, 2.0, version=version)


def links(n: int = 1, **kw: Any) -> list[LinkConfig]:
    return [LinkConfig(i, nui(), rate=5 if i == 0 else 3, watchdog_cycles=3, **kw) for i in range(n)]


class Pair:
    def __init__(self, n_links: int = 1, loss: float = 0.0, seed: int = 1,
                 log: io.StringIO | None = None, link_cfgs: list[LinkConfig] | None = None,
                 sender: FakeSender | None = None, **link_kw: Any) -> None:
        self.sender = sender or FakeSender()
        self.receiver = FakeReceiver()
        cfgs = link_cfgs or links(n_links, **link_kw)
        n_links = len(cfgs)
        self.vmgr = ChannelManager(VEHICLE, cfgs, queue_status_interval=120.0)
        self.vehicle = Node(self.vmgr)
        self.vehicle.add_sender(FakeModality, self.sender, StreamConfig(5, "fake", priority=30,
                                                                       ack_required=True))
        self.tmgr = ChannelManager(TOPSIDE, cfgs)
        self.topside = Node(self.tmgr)
        self.topside.add_receiver(FakeModality, self.receiver)
        self.channels = {i: AcousticChannel(loss=loss, seed=seed + i) for i in range(n_links)}
        self.net = SimNetwork(self.channels, link_log=log)
        self.net.add_node(self.vehicle, (0.0, 0.0, 1000.0))
        self.net.add_node(self.topside, (300.0, 400.0, 0.0))
        self.vevents: list[Any] = []
        self.tevents: list[Any] = []
        self.net.every(10.0, lambda now: self.vehicle.push_status(
            VehicleStatus(int(now), 1.0, 2.0, 1000.0, 10.0, 0.0, 1.0, 90, VehicleMode.SURVEY, 0), now))

    def run(self, until: float) -> None:
        self.net.run(until)
        self.vevents += self.vehicle.events()
        self.tevents += self.topside.events()


def test_data_flows_with_status_first_and_is_acked() -> None:
    log = io.StringIO()
    p = Pair(log=log)
    p.run(600.0)
    assert len(p.receiver.got) > 100
    assert any(isinstance(e, ProductUpdated) for e in p.tevents)
    statuses = [e.message for e in p.tevents if isinstance(e, Received) and isinstance(e.message, VehicleStatus)]
    assert len(statuses) >= 15
    assert any(isinstance(e, Received) and isinstance(e.message, QueueStatus) for e in p.tevents)
    # first message of every vehicle transmission is the status when a fresh one was waiting
    first = [wire.unpack(tx.frames[0])[0] for nid, tx in p.net.transmissions if nid == VEHICLE]
    assert sum(isinstance(m, VehicleStatus) for m in first) >= 15
    acked = [e for e in p.vevents if isinstance(e, Acked)]
    assert len(acked) > 100
    # acks keep the queue short: only what was sent since topside's last slot (540..560) waits
    assert all(e.first_sent is not None and e.first_sent >= 540.0 for e in p.vmgr.stream(5).entries)
    # vehicle transmits only in its slots (1, 2, 4, 5), several packets per slot
    slots = {tx.slot for nid, tx in p.net.transmissions if nid == VEHICLE}
    assert slots == {1, 2, 4, 5}
    recs = read_link_log(log.getvalue().splitlines())
    assert recs and {"time", "link", "slot", "frames", "capacity_bytes", "used_bytes", "delivered"} <= set(recs[0])
    veh = [r for r in recs if r["src"] == VEHICLE]
    assert sum(r["used_bytes"] for r in veh) / sum(r["capacity_bytes"] for r in veh) > 0.9


def test_operator_request_is_served_in_the_next_vehicle_transmission() -> None:
    p = Pair()
    # the operator asks at t = 361, inside topside's slot 3 of cycle 3 (360..380)
    p.net.at(361.0, lambda now: p.topside.request(Opaque(REQUEST, bytes([7])), now))
    p.run(480.0)
    (req_tx,) = [tx for nid, tx in p.net.transmissions if nid == TOPSIDE and 361.0 <= tx.start < 380.0]
    assert req_tx.start == 361.0  # topside sent it at once
    arrived = req_tx.start + req_tx.duration + 500.0 / 1500.0
    after = [tx for nid, tx in p.net.transmissions if nid == VEHICLE and tx.start > arrived]
    first = after[0]
    assert first.start == 380.0  # the next vehicle opportunity (slot 4) ...
    tags = [m.body[0] for f in first.frames for m in wire.unpack(f) if isinstance(m, Opaque)]
    assert tags.count(7) == 3  # ... carries the answer, ahead of the background backlog
    assert min(t for t, m in p.receiver.got if m.body[0] == 7) < 380.0 + first.duration + 1.0


def test_rejected_request_is_answered_and_does_not_crash() -> None:
    p = Pair()
    p.vehicle.receive(0, wire.pack([Opaque(REQUEST, b"\xff")], 256,
                                   FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=9)), 1.0)
    ev = p.vehicle.events()
    assert any(isinstance(e, Rejected) and "out of bounds" in e.reason for e in ev)


def test_bad_frames_are_counted_never_raised() -> None:
    p = Pair()
    good = wire.pack([QueueConfig(1, 5, False, None, 99, None, None, None)], 256,
                     FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=1))
    for junk in (b"", b"\x00", b"\xff" * 40, good[:-1] + b"\x7f", good[:4]):
        assert p.vehicle.receive(0, junk, 1.0) == []
    assert p.vehicle.stats["bad_frames"] == 5
    assert sum(isinstance(e, BadFrame) for e in p.vehicle.events()) == 5
    assert p.vehicle.receive(0, good, 2.0) != []
    (stats,) = p.vehicle.link_stats(2.0)
    assert (stats.link, stats.frames_rx, stats.bad_frames) == (0, 1, 5)
    assert p.vmgr.stream(5).config.priority == 99
    # a frame for another node is ignored
    other = wire.pack([QueueConfig(2, 5, False, None, 1, None, None, None)], 256,
                      FrameHeader(src=TOPSIDE, dst=9, seq=2))
    assert p.vehicle.receive(0, other, 3.0) == []
    assert p.vmgr.stream(5).config.priority == 99


def test_queue_config_round_trip_and_restart_keeps_settings() -> None:
    p = Pair()
    p.run(100.0)
    cid = p.topside.queue_config(5, 100.0, priority=90, max_depth=20)
    p.run(400.0)
    results = [e for e in p.tevents if isinstance(e, CommandResult) and e.command_id == cid]
    assert results and results[0].status == AckStatus.ACCEPTED
    assert any(isinstance(e, CommandApplied) for e in p.vevents)
    assert (p.vmgr.stream(5).config.priority, p.vmgr.stream(5).config.max_depth) == (90, 20)
    saved = p.vmgr.export_settings()
    restarted = ChannelManager(VEHICLE, links(1))
    restarted.add_stream(StreamConfig(5, "fake", priority=30, ack_required=True))
    restarted.import_settings(saved)
    assert (restarted.stream(5).config.priority, restarted.stream(5).config.max_depth) == (90, 20)


def _switches(events: list[Any]) -> list[ScheduleSwitched]:
    return [e for e in events if isinstance(e, ScheduleSwitched)]


def test_schedule_update_both_ends_switch_on_the_same_cycle() -> None:
    p = Pair()
    p.run(130.0)
    new = Schedule.simple([TOPSIDE, VEHICLE, VEHICLE, VEHICLE], 30.0, 2.0, version=3)
    cid = p.topside.schedule_update(0, new, 130.0, activate_cycle=4)  # starts at t = 480
    p.run(700.0)
    assert [e.command_id for e in p.tevents if isinstance(e, CommandResult)] == [cid]
    vs, ts = _switches(p.vevents), _switches(p.tevents)
    assert [(e.version, e.cycle, e.time) for e in vs] == [(3, 4, 480.0)]
    assert [(e.version, e.cycle, e.time) for e in ts] == [(3, 4, 480.0)]
    assert p.vmgr.schedule(0) == p.tmgr.schedule(0)
    after = [tx for _, tx in p.net.transmissions if tx.start >= 480.0]
    assert after and all(tx.schedule == 3 for tx in after)
    before = [tx for _, tx in p.net.transmissions if tx.start < 480.0]
    assert all(tx.schedule == 0 for tx in before)
    # new layout: vehicle slots are 30 s long at 30..120 of each 120 s cycle
    assert {tx.slot for nid, tx in p.net.transmissions if nid == VEHICLE and tx.start >= 480} == {1, 2, 3}


def test_lost_command_ack_topside_follows_the_vehicle_version() -> None:
    p = Pair()
    p.run(130.0)
    p.tmgr.on_command_ack = lambda ack, now: None  # type: ignore[method-assign,assignment,return-value]
    new = Schedule.simple([TOPSIDE, VEHICLE, VEHICLE, VEHICLE], 30.0, 2.0, version=5)
    p.topside.schedule_update(0, new, 130.0, activate_cycle=3)  # every CommandAck is lost
    p.run(700.0)
    assert p.vmgr.schedule(0).version == 5
    assert p.tmgr.schedule(0).version == 5  # seen in the vehicle's frame headers
    (sw,) = _switches(p.tevents)
    assert sw.reason == "peer" and 360.0 < sw.time < 400.0
    assert p.tmgr.schedule(0) == p.vmgr.schedule(0)


def test_watchdog_falls_back_to_the_safe_schedule() -> None:
    p = Pair()
    new = Schedule.simple([TOPSIDE, VEHICLE, VEHICLE, VEHICLE], 30.0, 2.0, version=2)
    p.topside.schedule_update(0, new, 0.0, activate_cycle=2)
    p.run(400.0)
    assert p.vmgr.schedule(0).version == 2 and p.tmgr.schedule(0).version == 2
    p.channels[0].loss = 1.0  # the link goes silent
    p.run(400.0 + 5 * 120.0)
    assert p.vmgr.schedule(0).version == 0 and p.tmgr.schedule(0).version == 0
    assert any(e.reason == "watchdog" for e in _switches(p.vevents))
    p.channels[0].loss = 0.0
    n = len(p.receiver.got)
    p.run(1400.0)
    assert len(p.receiver.got) > n  # traffic resumes on the safe schedule


def test_link_disable_via_command_moves_traffic_to_the_other_link() -> None:
    p = Pair(n_links=2)
    p.run(200.0)
    assert {tx.link_id for nid, tx in p.net.transmissions if nid == VEHICLE} == {0, 1}
    cid = p.topside.link_control(1, 200.0, enabled=False)
    p.run(500.0)
    assert any(isinstance(e, CommandResult) and e.command_id == cid and e.status == AckStatus.ACCEPTED
               for e in p.tevents)
    t_off = max(e.time for e in p.vevents if isinstance(e, CommandApplied))
    later = [tx.link_id for nid, tx in p.net.transmissions if nid == VEHICLE and tx.start > t_off]
    assert later and set(later) == {0}
    n = len(p.receiver.got)
    p.run(800.0)
    assert len(p.receiver.got) > n


def test_ack_received_on_other_link_clears_message() -> None:
    p = Pair(n_links=2)
    p.channels[1].loss = 1.0  # nothing crosses link 1
    p.run(600.0)
    acked = [e for e in p.vevents if isinstance(e, Acked)]
    assert acked and {e.link for e in acked} == {0}
    # messages first sent on the dead link were re-sent on link 0 after their ack timeout and
    # cleared by link 0's acks: nothing older than two cycles is still waiting
    assert all(e.first_sent is not None and e.first_sent > 600.0 - 240.0 for e in p.vmgr.stream(5).entries)
    ids = {int.from_bytes(m.body[1:5], "big") for _, m in p.receiver.got}
    sent_on_1 = {int.from_bytes(m.body[1:5], "big")
                 for nid, tx in p.net.transmissions if nid == VEHICLE and tx.link_id == 1 and tx.start < 300
                 for f in tx.frames for m in wire.unpack(f) if isinstance(m, Opaque)}
    assert sent_on_1 and sent_on_1 <= ids  # every one of them reached topside over link 0


@pytest.mark.parametrize("seed", [3, 4])
def test_lossy_channel_delivers_every_message_and_loses_none(seed: int) -> None:
    """At 30 % frame loss, every message the sender made is accounted for: received topside,
    or still waiting (unacked) in the vehicle's queue; every message the vehicle let go of (its
    ack arrived) was received. A message arrives more than once only when its ack was lost and
    the vehicle sent it again: never more often than it was transmitted."""
    from collections import Counter

    def tag(m: Opaque) -> int:
        return int.from_bytes(m.body[1:5], "big")

    p = Pair(loss=0.3, seed=seed)
    p.run(1200.0)
    received = Counter(tag(m) for _, m in p.receiver.got)
    transmitted = Counter(tag(m) for nid, tx in p.net.transmissions if nid == VEHICLE
                          for f in tx.frames for m in wire.unpack(f) if isinstance(m, Opaque))
    waiting = {tag(e.message) for e in p.vmgr.stream(5).entries}
    made = set(range(1, p.sender.counter + 1))
    assert len(received) > 1000 and waiting
    assert made - set(received) <= waiting, "a message was let go of without reaching topside"
    assert set(received) <= made
    assert all(n <= transmitted[k] for k, n in received.items())
    acked = {tag(e.message) for e in p.vevents if isinstance(e, Acked) and e.stream == 5}
    assert acked == made - waiting  # let go of exactly when acked


def test_a_repeated_command_is_answered_but_not_applied_twice() -> None:
    p = Pair()
    p.vmgr.push(5, Opaque(DATA, b"\x00keep"), 0.0)
    flush = wire.pack([QueueConfig(4, 5, True, None, None, None, None, None)], 256,
                      FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=1))
    p.vehicle.receive(0, flush, 1.0)
    p.vmgr.push(5, Opaque(DATA, b"\x00new!"), 2.0)
    again = wire.pack([QueueConfig(4, 5, True, None, None, None, None, None)], 256,
                      FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=2))
    p.vehicle.receive(0, again, 3.0)  # topside re-sent it: its frame ack was lost
    assert [e.message for e in p.vmgr.stream(5).entries] == [Opaque(DATA, b"\x00new!")]
    assert p.vehicle.stats["duplicates"] == 1
    acks = [e.message for e in p.vmgr.stream(2).entries]
    assert len(acks) == 2 and all(a.status == AckStatus.ACCEPTED for a in acks)



def _fuzz_node() -> Node:
    node = Node(ChannelManager(VEHICLE, links(2)))
    node.add_sender(FakeModality, FakeSender(), StreamConfig(5, "fake", ack_required=True))
    return node


_FUZZ_NODE = _fuzz_node()
_SEED_FRAME = wire.pack(
    [QueueConfig(1, 5, False, None, 40, None, None, None), Opaque(REQUEST, b"\x03"),
     Opaque(DATA, b"\x00abc")], 256, FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=4))


@settings(max_examples=150, deadline=None)
@given(st.binary(max_size=300) | st.builds(
    lambda pos, val: _SEED_FRAME[:pos] + bytes([val]) + _SEED_FRAME[pos + 1:],
    st.integers(0, len(_SEED_FRAME) - 1), st.integers(0, 255)))
def test_receive_never_raises_on_arbitrary_bytes(data: bytes) -> None:
    node = _FUZZ_NODE
    node.receive(0, data, 5.0)
    node.receive(7, data, 5.0)  # unknown link id too
    node.events()
    node.poll(30.0)  # and the node still builds packets


def test_each_link_has_its_own_schedule_and_layout() -> None:
    other = Schedule.simple([TOPSIDE, VEHICLE], 30.0, 3.0)  # the 3.5 kHz modem: 60 s cycle
    p = Pair(link_cfgs=[LinkConfig(0, nui(), rate=5), LinkConfig(1, other, rate=3)])
    p.run(240.0)
    new1 = Schedule.simple([TOPSIDE, VEHICLE, VEHICLE], 30.0, 3.0, version=4)
    p.topside.schedule_update(1, new1, 240.0, activate_cycle=7)  # link 1 cycle 7 = t 420
    p.run(600.0)
    v = [tx for nid, tx in p.net.transmissions if nid == VEHICLE]
    l0 = [tx for tx in v if tx.link_id == 0]
    l1 = [tx for tx in v if tx.link_id == 1]
    assert l0 and all(len(tx.frames) <= 8 and tx.slot in (1, 2, 4, 5) and tx.schedule == 0 for tx in l0)
    assert all(len(tx.frames) <= 2 for tx in l1)  # rate 3: 2 x 256 B
    before = [tx for tx in l1 if tx.start < 420.0]
    after = [tx for tx in l1 if tx.start >= 420.0]
    assert before and all(tx.slot == 1 and (tx.start % 60.0) >= 30.0 for tx in before)
    assert after and all(tx.schedule == 4 and tx.slot in (1, 2) for tx in after)
    assert p.vmgr.schedule(0).version == 0 and p.tmgr.schedule(0).version == 0
    assert p.vmgr.schedule(1) == p.tmgr.schedule(1)


class _AckListener(FakeSender):
    def __init__(self, fail: bool = False) -> None:
        super().__init__()
        self.heard: list[Message] = []
        self.fail = fail

    def acked(self, message: Message, now: float) -> None:
        self.heard.append(message)
        if self.fail:
            raise RuntimeError("hook broken")


@pytest.mark.parametrize("fail", [False, True])
def test_senders_hear_which_of_their_messages_were_acked(fail: bool) -> None:
    """The node tells a sender (``ModalitySender.acked``) each of its messages the other side
    acknowledged, exactly the manager's ``Acked`` events; a hook that raises is logged and
    counted, and the acks still clear the queue."""
    listener = _AckListener(fail)
    p = Pair(sender=listener)
    p.run(300.0)
    acked = [e.message for e in p.vevents if isinstance(e, Acked) and e.stream == 5]
    assert len(acked) > 20
    assert listener.heard == acked
    assert p.vmgr.stats["acked"] >= len(acked)
    assert p.vehicle.stats["rejected"] == (len(acked) if fail else 0)


def test_a_gap_request_packed_before_the_ack_of_what_it_asks_for_resends_nothing() -> None:
    """Topside's packet carries a FrameAck (built at packing time) and a gap request built
    earlier, when topside still lacked a subgrid the acked frame carried. The node applies the
    frame's acks after its other messages, so the bathymetry sender drops that subgrid from its
    request queue instead of sending it again."""
    _, survey = small_survey(48.0, 128)
    sender = BathymetrySender({"levels": 3})
    for t, xyz in survey.pings(batch=10):
        sender.ingest(xyz, t)
    vmgr = ChannelManager(VEHICLE, links(), queue_status_interval=1e9)
    vehicle = Node(vmgr)
    vehicle.add_sender(BathymetryModality, sender, StreamConfig(3, "map", priority=30, ack_required=True))
    now = float(survey.times[-1]) + 1000.0
    while not vmgr.can_transmit(0, now):
        now += 1.0
    (tx,) = vehicle.poll(now)
    seq, first = next((tx.seq + i, sg) for i, f in enumerate(tx.frames)
                      for sg in wire.unpack(f) if isinstance(sg, SubgridMessage))
    key = (first.level, first.ix, first.iy)
    request = MapRoiRequest(7, first.level, first.ix, first.iy, 1, 1, True, (), 0)  # "I lack it"
    ack = FrameAck(VEHICLE, 0, (FrameAckEntry(seq, 1),))
    frame = wire.pack([ack, request], 256, FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=3))
    vehicle.receive(0, frame, now + 10.0)
    assert [e for e in vehicle.events() if isinstance(e, Acked)]
    again = [(m.level, m.ix, m.iy) for m in sender.fill(10_000, now + 11.0) if isinstance(m, SubgridMessage)]
    assert key not in again
    # the same request after the ack (a real new loss) is served
    vehicle.receive(0, wire.pack([MapRoiRequest(8, *key, 1, 1, True, (), 0)], 256,
                                 FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=4)), now + 12.0)
    assert key in [(m.level, m.ix, m.iy) for m in sender.fill(10_000, now + 13.0) if isinstance(m, SubgridMessage)]


def test_a_retried_region_request_replaces_the_unacked_one_in_the_channel() -> None:
    """The vehicle never hears topside: a region request goes out, is not acked, and the receiver
    retries it with what it holds now. The retry withdraws the earlier copy from the channel
    (``ModalityReceiver.supersedes``), so the channel never re-sends an outdated request after
    the fresh one; a request for another region stays."""
    receiver = BathymetryReceiver({"levels": 3, "request_timeout": 100.0, "max_requests_per_poll": 4})
    tmgr = ChannelManager(TOPSIDE, links())
    topside = Node(tmgr)
    topside.add_receiver(BathymetryModality, receiver)
    receiver.request_gaps(0, 0, 0, 2, 2)
    receiver.request_region(1, 0, 0, 1, 1)
    sent: list[tuple[float, int]] = []
    now = 0.0
    while now < 450.0:
        for tx in topside.poll(now):
            sent += [(now, m.request_id) for f in tx.frames for m in wire.unpack(f)
                     if isinstance(m, MapRoiRequest) and m.level == 0]
        now += 1.0
    ids = [rid for _, rid in sent]
    assert len(set(ids)) >= 4  # the receiver retried every 100 s
    # once a newer request for the region exists, no older one is ever sent again
    for i, rid in enumerate(ids):
        assert all(rid >= earlier for earlier in ids[:i]), sent
    # the channel holds one request per region: the newest of each
    newest = {r.level: r.request_id for r in receiver.active_regions()}
    queued = [e.message.request_id for e in tmgr.stream(CONTROL_STREAM).entries
              if isinstance(e.message, MapRoiRequest)]
    assert sorted(queued) == sorted(newest.values())
    dropped = [e for e in topside.events() if isinstance(e, Dropped) and e.reason == "superseded"]
    assert sum(e.count for e in dropped) >= 2 * (len(set(ids)) - 1)


class _BadSupersedes(FakeReceiver):
    def poll(self, now: float) -> list[Message]:
        return [Opaque(REQUEST, bytes([int(now) % 200]))]

    def supersedes(self, old: Message, new: Message) -> bool:
        raise RuntimeError("broken hook")


def test_a_supersedes_hook_that_raises_withdraws_nothing_and_queues_the_request() -> None:
    tmgr = ChannelManager(TOPSIDE, links())
    topside = Node(tmgr)
    topside.add_receiver(FakeModality, _BadSupersedes())
    topside.poll(1.0)
    topside.poll(2.0)
    assert [e.message.body for e in tmgr.stream(CONTROL_STREAM).entries] == [b"\x01", b"\x02"]


def test_subscribers_see_every_drained_event_and_never_cost_the_node() -> None:
    """An application watches a node that another loop drives (the console does): whoever
    calls ``events()`` gets the events, and every subscriber sees them too; a subscriber that
    raises is logged, and the others and the caller still get everything."""
    notes: list[str] = []
    p = Pair()
    p.topside.set_log(notes.append)
    seen: list[Any] = []

    def broken(events: list[Any]) -> None:
        raise RuntimeError("console bug")

    p.topside.subscribe(broken)
    stop = p.topside.subscribe(seen.extend)
    p.run(300.0)
    assert p.tevents and seen == p.tevents
    assert any("event listener failed: console bug" in n for n in notes)
    stop()
    p.run(400.0)
    assert len(p.tevents) > len(seen)  # unsubscribed: no longer told


def test_command_id_is_read_from_the_types_that_declare_it() -> None:
    """coex.messages.command_id: the id of a command, a request answered with a CommandAck and
    the answer; None for any other message (no getattr on whatever comes)."""
    from coex_core import messages as m

    assert m.command_id(m.CommandAck(7, m.AckStatus.ACCEPTED)) == 7
    assert m.command_id(m.ImageByTimeRequest(9, 100, m.TimeDirection.NEAREST)) == 9
    assert m.command_id(m.MapRoiRequest(3, 0, 0, 0, 1, 1, False, (None,))) is None  # a request_id, not a command
    assert m.command_id(object()) is None
    assert {m.CommandAck, m.SurveyCommand, m.ImageRegionRequest} <= m.WITH_COMMAND_ID
    assert m.VehicleStatus not in m.WITH_COMMAND_ID
