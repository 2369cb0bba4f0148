"""Spare capacity: the spare tier, delivery notifications, redundancy under loss, standing
requests and the operator's caps (issue: spend every idle byte)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from coex_core import wire
from coex_core.acoustic import AcousticChannel
from coex_core.channel import ChannelManager, LinkConfig, Schedule, StreamConfig
from coex_core.channel.events import CommandResult
from coex_core.errors import ConfigError
from coex_core.messages import (
    AckStatus,
    CommandAck,
    FrameAck,
    FrameAckEntry,
    FrameHeader,
    MapRoiReply,
    MapRoiRequest,
    Message,
    Opaque,
    QueueConfig,
    SpareConfig,
    SubgridMessage,
    TransferProgress,
    VehicleMode,
    VehicleStatus,
)
from coex_core.modality import ModalitySender
from coex_core.node import Node
from coex_plugins.bathymetry import BathymetryModality, BathymetryReceiver, BathymetrySender
from coex_runtime.runner import SimNetwork

from ._bathy_data import small_survey

VEHICLE, TOPSIDE = 2, 1


def nui() -> Schedule:
    return Schedule.simple([TOPSIDE, VEHICLE, VEHICLE, TOPSIDE, VEHICLE, VEHICLE], 20.0, 2.0)


def status(t: float = 0.0) -> VehicleStatus:
    return VehicleStatus(int(t), 1.0, 2.0, 100.0, 10.0, 0.0, 1.0, 90, VehicleMode.SURVEY, 0)


class Sender(ModalitySender):
    """Background pieces from ``fill`` (a finite supply) and spare pieces from ``spare``."""

    def __init__(self, background: int = 0, size: int = 40) -> None:
        self.background, self.size = background, size
        self.spare_calls: list[int] = []
        self.lost_msgs: list[Message] = []
        self.acked_msgs: list[Message] = []

    def ingest(self, data: Any, now: float) -> None:
        pass

    def _piece(self, tag: int) -> Opaque:
        return Opaque(200, bytes([tag]) * (self.size - 3))

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        out: list[Message] = []
        while self.background and max_bytes >= self.size:
            out.append(self._piece(1))
            self.background -= 1
            max_bytes -= self.size
        return out

    def spare(self, max_bytes: int, now: float) -> list[Message]:
        self.spare_calls.append(max_bytes)
        return [self._piece(2) for _ in range(max_bytes // self.size)]

    def spare_bytes(self) -> int:
        return 10**6

    def handle(self, message: Message, now: float) -> list[Message]:
        return []

    def acked(self, message: Message, now: float) -> None:
        self.acked_msgs.append(message)

    def lost(self, message: Message, now: float) -> None:
        self.lost_msgs.append(message)


def vehicle_manager(sender: Sender, *, spare: float = 1.0, stream_spare: float = 1.0,
                    **kw: Any) -> ChannelManager:
    m = ChannelManager(VEHICLE, [LinkConfig(0, Schedule.simple([VEHICLE], 20.0, 2.0), spare=spare, **kw)])
    m.add_stream(StreamConfig(5, "data", spare=stream_spare), sender)
    return m


def kinds(tx: Any) -> list[int]:
    """The tag of every Opaque piece in a transmission (1 background, 2 spare)."""
    return [m.body[0] for f in tx.frames for m in wire.unpack(f) if isinstance(m, Opaque)]


# ---------------------------------------------------------------------------- the spare tier

def test_spare_work_fills_only_what_status_and_background_leave() -> None:
    s = Sender(background=10)
    m = vehicle_manager(s)
    m.push(0, status(), 0.0)
    tx = m.build(0, 0.0)
    assert tx is not None
    msgs = [x for f in tx.frames for x in wire.unpack(f)]
    assert isinstance(msgs[0], VehicleStatus)  # status first, exactly as without spare work
    tags = kinds(tx)
    assert tags[:10] == [1] * 10 and set(tags[10:]) == {2}  # all background before any spare
    assert tx.spare == 40 * tags.count(2) and tx.used > 0.9 * tx.capacity
    assert len(tx.frames) == 8  # the packet is full


def test_no_spare_bytes_when_spare_traffic_is_off_on_the_link_or_the_stream() -> None:
    for kw in ({"spare": 0.0}, {"stream_spare": 0.0}):
        s = Sender(background=3)
        m = vehicle_manager(s, **kw)
        tx = m.build(0, 0.0)
        assert tx is not None and set(kinds(tx)) == {1} and tx.spare == 0
        assert m.build(0, 30.0) is None  # nothing but spare work left: nothing is sent
        assert s.spare_calls == [] and m.stats["spare_bytes"] == 0


def test_spare_share_caps_the_spare_bytes_of_each_packet() -> None:
    s = Sender()
    m = vehicle_manager(s, spare=0.25)
    tx = m.build(0, 0.0)
    assert tx is not None
    room = 8 * (256 - wire.header_size(FrameHeader()))
    assert 0 < tx.spare <= 0.25 * room
    m.set_spare(0.5)
    tx2 = m.build(0, 30.0)
    assert tx2 is not None and 0.25 * room < tx2.spare <= 0.5 * room
    with pytest.raises(ConfigError):
        m.set_spare(1.5)


def test_spare_config_command_from_topside_caps_links_and_streams() -> None:
    s = Sender()
    m = vehicle_manager(s)
    assert m.apply(SpareConfig(1, None, 5, 0), 0.0).status == AckStatus.ACCEPTED
    tx = m.build(0, 0.0)
    assert tx is None and s.spare_calls == []  # the only stream with spare work is off
    assert m.apply(SpareConfig(2, None, 5, 100), 1.0).status == AckStatus.ACCEPTED
    assert m.apply(SpareConfig(3, 0, None, 0), 1.0).status == AckStatus.ACCEPTED
    assert m.build(0, 30.0) is None and m.link_state(0)["spare"] == 0.0
    assert m.apply(SpareConfig(4, 5, None, 10), 1.0).status == AckStatus.UNKNOWN_TARGET
    assert m.apply(SpareConfig(5, None, 9, 10), 1.0).status == AckStatus.UNKNOWN_TARGET
    assert m.apply(SpareConfig(6, 0, 5, 10), 1.0).status == AckStatus.REJECTED  # link or stream
    # the settings survive a restart with the operator's other settings
    fresh = vehicle_manager(Sender())
    fresh.import_settings(m.export_settings())
    assert fresh.link_state(0)["spare"] == 0.0


def test_a_spare_config_travels_signed_and_is_applied_on_the_vehicle() -> None:
    key = b"k" * 16
    vm = ChannelManager(VEHICLE, [LinkConfig(0, nui())], command_key=key)
    tm = ChannelManager(TOPSIDE, [LinkConfig(0, nui())], command_key=key)
    vehicle, topside = Node(vm), Node(tm)
    cid = topside.spare_config(0, 1.0, link=0)
    tx = tm.build(0, 1.0)
    assert tx is not None
    for f in tx.frames:
        vehicle.receive(0, f, 2.0)
    assert vm.link_state(0)["spare"] == 0.0
    back = vm.build(0, 21.0)
    assert back is not None
    for f in back.frames:
        topside.receive(0, f, 22.0)
    results = [e for e in topside.events() if isinstance(e, CommandResult)]
    assert [(r.command_id, r.status) for r in results] == [(cid, AckStatus.ACCEPTED)]


# ------------------------------------------------------------------ delivery and redundancy

def test_senders_hear_which_messages_were_acked_and_which_were_lost() -> None:
    s = Sender(background=16)
    m = vehicle_manager(s, spare=0.0, ack_timeout=30.0)
    tx = m.build(0, 0.0)
    assert tx is not None and len(tx.frames) == 3
    # topside acked frames 0 and 2 only
    got = m.acknowledge(FrameAck(VEHICLE, 0, (FrameAckEntry(tx.seq, 0b101),)), 10.0)
    per_frame = [len([x for x in wire.unpack(f) if isinstance(x, Opaque)]) for f in tx.frames]
    assert len(got) == per_frame[0] + per_frame[2]
    m.poll(31.0)  # past the ack timeout
    assert len(s.lost_msgs) == per_frame[1]
    assert m.frame_loss(0) is None  # three outcomes are not an estimate yet


def test_a_lost_message_waits_for_a_late_ack_only_while_its_frames_seq_is_unused() -> None:
    """A message given to ``lost`` still counts as delivered if its frame's ack comes late; once
    that seq is used again no ack can reach it, and the manager forgets it (its saved state does
    not hold thousands of lost messages)."""
    s = Sender()
    m = vehicle_manager(s, ack_timeout=30.0)
    first = m.build(0, 0.0)
    assert first is not None
    m.poll(31.0)  # no ack in time: lost
    lost = len(s.lost_msgs)
    assert lost == sum(len(wire.unpack(f)) for f in first.frames) > 0
    late = m.acknowledge(FrameAck(VEHICLE, 0, (FrameAckEntry(first.seq, 0b1),)), 32.0)
    assert len(late) == len(wire.unpack(first.frames[0]))  # arrived after all
    frames: list[int] = []  # messages per frame sent, in order
    t = 40.0
    while len(frames) < 600:  # nothing acked: every seq is used again, more than twice
        tx = m.build(0, t)
        assert tx is not None
        frames += [len(wire.unpack(f)) for f in tx.frames]
        t += 20.0
        m.poll(t)
    assert len(s.lost_msgs) > 2000
    # remembered: at most the messages of the frames whose seqs are not used again yet
    assert len(m._lost_recs) <= sum(frames[-256:])


def test_urgent_messages_go_in_several_frames_as_the_measured_loss_grows() -> None:
    m = ChannelManager(VEHICLE, [LinkConfig(0, Schedule.simple([VEHICLE], 20.0, 2.0))])
    assert m.copies(0) == 1  # nothing measured yet
    # the peer's frames arrive with every second seq missing: about 50 % loss
    for seq in range(0, 40, 2):
        m.on_frame(0, FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=seq), 1.0)
    loss = m.frame_loss(0)
    assert loss is not None and 0.4 < loss < 0.6
    assert m.copies(0) == math.ceil(math.log(0.05) / math.log(loss))
    m.push(2, CommandAck(7, AckStatus.ACCEPTED), 1.0)
    tx = m.build(0, 2.0)
    assert tx is not None
    msgs = [[x for x in wire.unpack(f)] for f in tx.frames]
    with_ack = [f for f in msgs if CommandAck(7, AckStatus.ACCEPTED) in f]
    with_frame_ack = [f for f in msgs if any(isinstance(x, FrameAck) for x in f)]
    assert len(with_ack) == len(with_frame_ack) == m.copies(0)
    assert tx.redundant > 0
    # with spare traffic off there is one copy of each
    m.set_spare(0.0)
    m.on_frame(0, FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=42), 3.0)
    m.push(2, CommandAck(8, AckStatus.ACCEPTED), 3.0)
    tx = m.build(0, 30.0)
    assert tx is not None and len(tx.frames) == 1 and tx.redundant == 0


def test_duplicate_copies_of_a_command_are_handled_once_and_answered_once() -> None:
    vm = ChannelManager(VEHICLE, [LinkConfig(0, nui())])
    vehicle = Node(vm)
    frames = []
    cmd = QueueConfig(9, 2, False, None, 90, None, None, None)
    for _ in range(3):
        frames.append(wire.pack([cmd], 256, FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=len(frames))))
    for f in frames:
        vehicle.receive(0, f, 5.0)
    acks = [m for e in vm.stream(2).entries for m in [e.message] if isinstance(m, CommandAck)]
    assert acks == [CommandAck(9, AckStatus.ACCEPTED)]
    assert vehicle.stats["duplicates"] == 2


# ------------------------------------------------------------- bathymetry: lost and standing

def _bathy_pair(loss: float, seed: int, *, spare: float = 1.0) -> tuple[Node, Node, BathymetrySender,
                                                                          BathymetryReceiver, SimNetwork]:
    sender = BathymetrySender({"levels": 3, "send_delay": 5.0})
    receiver = BathymetryReceiver({"levels": 3, "auto_fill": False})
    vm = ChannelManager(VEHICLE, [LinkConfig(0, nui(), spare=spare, dst=TOPSIDE)])
    tm = ChannelManager(TOPSIDE, [LinkConfig(0, nui(), dst=VEHICLE)])
    vehicle, topside = Node(vm), Node(tm)
    vehicle.add_sender(BathymetryModality, sender, StreamConfig(3, "map"))
    topside.add_receiver(BathymetryModality, receiver)
    net = SimNetwork({0: AcousticChannel(loss=loss, seed=seed)})
    net.add_node(vehicle, (0.0, 0.0, 500.0))
    net.add_node(topside, (100.0, 0.0, 0.0))
    return vehicle, topside, sender, receiver, net


def _held(receiver: BathymetryReceiver) -> set[tuple[int, int, int]]:
    return {(lv, ix, iy) for lv in receiver.levels() for ix, iy in receiver.holdings(lv)}


def test_subgrids_lost_in_the_water_are_sent_again_by_spare_capacity() -> None:
    _, survey = small_survey(48.0, 128)
    results = {}
    for spare in (0.0, 1.0):
        vehicle, _, sender, receiver, net = _bathy_pair(loss=0.4, seed=3, spare=spare)
        for t, xyz in survey.pings(batch=10):
            sender.ingest(xyz, t)
        net.run(1200.0)
        results[spare] = (_held(receiver), set(sender.inventory()), vehicle.manager.stats)
    held_off, inv, stats_off = results[0.0]
    held_on, inv_on, stats_on = results[1.0]
    assert inv == inv_on
    assert held_off < inv, "with this seed some subgrids are lost and, without spare work, never sent again"
    assert held_on == inv, "spare capacity re-sent every lost subgrid"
    assert stats_off["spare_bytes"] == 0 and stats_on["spare_bytes"] > 0 and stats_on["lost"] > 0


def test_a_region_request_over_ground_not_yet_surveyed_stands_until_the_data_exists() -> None:
    sender = BathymetrySender({"levels": 3, "send_delay": 5.0})
    receiver = BathymetryReceiver({"levels": 3, "auto_fill": False})
    receiver.request_region(0, 0, 0, 2, 2)
    (req,) = receiver.poll(0.0)
    assert isinstance(req, MapRoiRequest)
    (reply,) = sender.handle(req, 0.0)
    assert reply == MapRoiReply(req.request_id, 0, 0, 4)  # nothing yet; 4 subgrids awaited
    receiver.receive(reply, 1.0)
    (region,) = receiver.active_regions()
    assert region.waiting == 4 and not region.done
    assert sender.standing() and sender.fill(240, 2.0) == []
    # the vehicle surveys there later: the awaited subgrids go out as requested ones, at once
    xs, ys = np.meshgrid(np.arange(0.5, 16.0, 0.5), np.arange(0.5, 16.0, 0.5))
    pts = np.column_stack([xs.ravel(), ys.ravel(), -50.0 + 0.01 * xs.ravel()])
    sender.ingest(pts, 100.0)
    sent = [m for m in sender.fill(240, 106.0) if isinstance(m, SubgridMessage)]
    assert {(s.level, s.ix, s.iy) for s in sent} >= {(0, 0, 0), (0, 1, 0), (0, 0, 1), (0, 1, 1)}
    assert sender.standing() == []
    # an expired standing request is forgotten
    sender.handle(MapRoiRequest(99, 0, 40, 40, 1, 1, False, (None,)), 200.0)
    assert len(sender.standing()) == 1
    sender.fill(240, 200.0 + sender.standing_expiry + 1.0)
    assert sender.standing() == []


# ------------------------------------------------------------------ imagery: standing requests

def test_an_image_request_for_a_time_not_captured_yet_stands_until_the_image_exists() -> None:
    from coex_core.messages import ImageByTimeRequest, TimeDirection
    from coex_core.timefmt import to_stamp
    from coex_plugins.imagery import ImageryModality
    from coex_plugins.imagery.sender import ImageInput

    vm = ChannelManager(VEHICLE, [LinkConfig(0, nui(), dst=TOPSIDE)])
    tm = ChannelManager(TOPSIDE, [LinkConfig(0, nui(), dst=VEHICLE)])
    vehicle, topside = Node(vm), Node(tm)
    sender = ImageryModality().sender({"standing_expiry": 900.0})
    receiver = ImageryModality().receiver(None)
    vehicle.add_sender(ImageryModality, sender, StreamConfig(4, "images"))
    topside.add_receiver(ImageryModality, receiver)
    net = SimNetwork({0: AcousticChannel(loss=0.0, seed=1)})
    net.add_node(vehicle, (0.0, 0.0, 100.0))
    net.add_node(topside, (10.0, 0.0, 0.0))
    rng = np.random.default_rng(1)
    sender.ingest(ImageInput(rng.integers(0, 255, (64, 64), np.uint8), time=10.0), 10.0)
    receiver.request_by_time(500.0, TimeDirection.NEAREST, 20.0)  # not captured yet
    net.run(200.0)
    assert [r.stamp for r, _ in sender.standing()] == [to_stamp(500.0)]
    (waiting,) = receiver.waiting_requests()
    assert isinstance(waiting[0], ImageByTimeRequest)
    assert receiver.pending_requests() == []  # answered PENDING: not retried, shown as waiting
    results = [e for e in topside.events() if isinstance(e, CommandResult)]
    assert [r.status for r in results] == [AckStatus.PENDING]
    # the image of that time is captured: the request is served and answered
    sender.ingest(ImageInput(rng.integers(0, 255, (64, 64), np.uint8), time=505.0), 505.0)
    net.run(900.0)
    assert sender.standing() == [] and receiver.waiting_requests() == []
    results = [e for e in topside.events() if isinstance(e, CommandResult)]
    assert [r.status for r in results] == [AckStatus.ACCEPTED]
    served = max(sender.images.values(), key=lambda tx: tx.time)
    assert served.explicit is not None and served.time == 505.0
    products = {int(p.meta["image_id"]) for _, p in topside.products() if p.kind == "image"}
    assert served.image_id in products
    # one that never comes expires: rejected, and topside stops waiting
    receiver.request_by_time(5000.0, TimeDirection.AFTER, 900.0)
    net.run(2000.0)
    results = [e for e in topside.events() if isinstance(e, CommandResult)]
    assert [r.status for r in results] == [AckStatus.PENDING, AckStatus.REJECTED]
    assert receiver.waiting_requests() == [] and sender.standing() == []


def test_imagery_spare_work_sends_further_layers_newest_image_first() -> None:
    """Once every image is at its goal, spare work brings the newest image beyond it (up to its
    whole codestream) before the older ones; the background sends nothing more."""
    from coex_plugins.imagery import ImageryModality
    from coex_plugins.imagery.sender import ImageInput

    sender = ImageryModality().sender({"default_goal": "layer:2"})
    rng = np.random.default_rng(2)
    for t in (10.0, 20.0):
        sender.ingest(ImageInput(rng.integers(0, 255, (96, 96), np.uint8), time=t), t)
    def drain(pull: Any, now: float, rounds: int) -> float:
        """Pull until nothing comes, every byte acknowledged as it goes; returns the time."""
        for _ in range(rounds):
            out = pull(240, now)
            for m in out:
                sender.acked(m, now)
            if not out:
                break
            now += 1.0
        return now

    now = drain(sender.fill, 30.0, 200)  # the background
    old, new = sorted(sender.images.values(), key=lambda tx: tx.time)
    assert not old.needs() and not new.needs() and new.goal < new.total
    assert sender.spare_bytes() == (old.total - old.goal) + (new.total - new.goal)
    got = sender.spare(240, now)
    assert got and {m.image_id for m in got} == {new.image_id}
    assert min(m.offset for m in got) >= new.goal
    for m in got:
        sender.acked(m, now)
    now = drain(sender.spare, now, 500)
    assert new.acked.all() and old.acked.all() and sender.spare_bytes() == 0
    assert not [m for m in sender.fill(240, now) if not isinstance(m, TransferProgress)]


def test_a_requested_images_lost_bytes_get_all_their_repeats_again_after_each_loss() -> None:
    """Under loss a requested image's bytes go out ``copies()`` times before topside can answer;
    when every copy of some bytes is reported lost they get ``copies()`` repeats again (not one
    per ack round), and bytes sent before the request count for nothing once it comes."""
    from coex_core.messages import ImageByTimeRequest, ImageFragment, TimeDirection
    from coex_core.timefmt import to_stamp
    from coex_plugins.imagery import ImageryModality
    from coex_plugins.imagery.sender import ImageInput

    sender = ImageryModality().sender({"default_goal": "layer:16", "request_goal": "layer:24"})
    rng = np.random.default_rng(3)
    sender.ingest(ImageInput(rng.integers(0, 255, (256, 256), np.uint8), time=10.0), 10.0)
    (tx,) = sender.images.values()
    now = 20.0
    first = [m for m in sender.fill(4000, now) if isinstance(m, ImageFragment)]
    assert len(first) >= 8 and tx.explicit is None
    for i, m in enumerate(first):  # three frames in four lost: the loss the sender measures
        (sender.lost if i % 4 else sender.acked)(m, now)
    k = sender.copies()
    assert k == min(8, math.ceil(math.log(0.05) / math.log(sender.frame_loss() or 0.0))) and k > 1
    sender.handle(ImageByTimeRequest(1, to_stamp(10.0), TimeDirection.NEAREST), now)
    assert tx.explicit is not None
    goal = tx.goal
    missing = ~tx.acked[:goal]
    assert missing.any()

    def round_of_sends() -> list[ImageFragment]:
        nonlocal now
        sent: list[ImageFragment] = []
        for _ in range(3 * k):  # one packet a second, no answer from topside yet
            now += 1.0
            sent += [m for m in sender.fill(50000, now) if isinstance(m, ImageFragment) and m.image_id == tx.image_id]
        return sent

    def times_sent(frags: list[ImageFragment]) -> np.ndarray:
        n = np.zeros(tx.total, int)
        for m in frags:
            n[m.offset:m.offset + len(m.data)] += 1
        return n

    sent = round_of_sends()
    assert (times_sent(sent)[:goal][missing] == k).all()  # the earlier default sends do not count
    for m in sent:  # every copy lost
        sender.lost(m, now)
    again = round_of_sends()
    assert (times_sent(again)[:goal][missing] == k).all()
    for m in again:
        sender.acked(m, now)
    assert not tx.needs() and not round_of_sends()


def test_a_requested_images_announcement_goes_as_many_times_as_its_bytes_until_heard() -> None:
    """Topside can decode none of a requested image's bytes without its announcement: under loss
    the announcement goes in ``copies()`` packets, as the bytes do (issue 41: one copy per ack
    round lost four rounds running at 60 % loss and held a confirmation back by three TDMA
    cycles); once every copy is reported lost it gets its copies again; once heard, it stops.
    An image nobody asked for is announced once per round."""
    from coex_core.messages import ImageAnnounce, ImageByTimeRequest, ImageFragment, TimeDirection
    from coex_core.timefmt import to_stamp
    from coex_plugins.imagery import ImageryModality
    from coex_plugins.imagery.sender import ImageInput

    sender = ImageryModality().sender({"default_goal": "layer:16", "request_goal": "layer:24"})
    rng = np.random.default_rng(3)
    for t in (10.0, 11.0):
        sender.ingest(ImageInput(rng.integers(0, 255, (256, 256), np.uint8), time=t), t)
    asked, other = sorted(sender.images.values(), key=lambda tx: tx.time)
    now = 20.0
    first = sender.fill(4000, now)
    for i, m in enumerate(first):  # three frames in four lost, the announcements among them
        (sender.acked if isinstance(m, ImageFragment) and i % 4 == 0 else sender.lost)(m, now)
    k = sender.copies()
    assert k > 1 and not asked.heard and not other.heard
    sender.handle(ImageByTimeRequest(1, to_stamp(10.0), TimeDirection.NEAREST), now)

    def round_of_announces() -> list[ImageAnnounce]:
        nonlocal now
        sent: list[ImageAnnounce] = []
        for _ in range(3 * k):  # one packet a second, no answer from topside yet
            now += 1.0
            sent += [m for m in sender.fill(50000, now) if isinstance(m, ImageAnnounce)]
        return sent

    sent = round_of_announces()
    assert sum(m.image_id == asked.image_id for m in sent) == k
    assert sum(m.image_id == other.image_id for m in sent) == 1  # not asked for: once a round
    for m in sent:  # every copy lost
        sender.lost(m, now)
    again = round_of_announces()
    assert sum(m.image_id == asked.image_id for m in again) == k
    sender.acked(next(m for m in again if m.image_id == asked.image_id), now)
    assert asked.heard and not [m for m in round_of_announces() if m.image_id == asked.image_id]


def test_a_newer_image_ack_replaces_an_older_one_of_the_same_image_in_the_uplink() -> None:
    """Topside's acks of one image are not stacked up in the uplink under loss: the newest
    replaces the older ones still queued or in flight; acks of other images stay."""
    from coex_core.messages import ByteRange, ImageAck
    from coex_plugins.imagery import ImageryModality

    receiver = ImageryModality().receiver(None)
    old, new = ImageAck(3, 10, ()), ImageAck(3, 40, (ByteRange(60, 80),))
    assert receiver.supersedes(old, new)
    assert not receiver.supersedes(ImageAck(4, 10, ()), new)
    assert not receiver.supersedes(old, ImageAck(4, 40, ()))
    tm = ChannelManager(TOPSIDE, [LinkConfig(0, nui(), dst=VEHICLE)])
    topside = Node(tm)
    topside.add_receiver(ImageryModality, receiver)
    acks = iter([[old, ImageAck(4, 5, ())], [new]])
    receiver.poll = lambda now: next(acks, [])  # type: ignore[method-assign]
    assert not topside.poll(21.0)  # a vehicle slot: queued
    assert not topside.poll(22.0)
    (tx,) = topside.poll(60.0)  # topside's next slot
    sent = [m for f in tx.frames for m in wire.unpack(f) if isinstance(m, ImageAck)]
    assert {(m.image_id, m.contiguous) for m in sent} == {(3, 40), (4, 5)}


def test_an_announcement_with_unusable_coding_parameters_is_refused_and_said(caplog: Any) -> None:
    """Invalid params (precincts with the RPCL progression), or a grey flag that disagrees with params: the image is not
    decoded (spec/payloads.md 3.1), and the receiver says so instead of dropping it silently."""
    from coex_core.messages import ImageAnnounce
    from coex_plugins.imagery import ImageryModality
    from coex_plugins.imagery.codec import params_code

    receiver = ImageryModality().receiver(None)
    good = params_code("LRCP", 3, 4, False, False)
    assert receiver.receive(ImageAnnounce(1, 10, None, None, 64, 64, True, 100, good), 10.0)
    with caplog.at_level("WARNING", logger="coex.imagery"):
        assert receiver.receive(ImageAnnounce(2, 10, None, None, 64, 64, True, 100, good | 1 << 14 | 2 << 10), 10.0) == []
        assert receiver.receive(ImageAnnounce(3, 10, None, None, 64, 64, False, 100, good), 10.0) == []
    assert receiver.rejected_announces == 2 and set(receiver.images) == {1}
    assert "unusable coding parameters" in caplog.text


_RESTARTED_SENDER = """
import sys
import coex_plugins.bathymetry  # registers its state classes
from coex_core import state
from coex_core.messages import SubgridMessage
sender = state.loads(sys.stdin.buffer.read())
sg = sender._built((0, 0, 0))[0]
sender.lost(sg, 200.0)  # a copy sent before the restart was lost; another copy had arrived
keys = [(m.level, m.ix, m.iy) for m in sender.spare(4096, 201.0) if isinstance(m, SubgridMessage)]
print((0, 0, 0) in keys)
"""


def test_a_confirmed_subgrid_stays_confirmed_in_a_restarted_process() -> None:
    """What an ack confirmed is saved with the sender in a form every process reads alike: after
    a restart (another process, another hash seed), the loss of another copy of a confirmed
    version does not make it spare work again (Python's hash() of a subgrid differs between
    processes)."""
    import os
    import subprocess
    import sys

    from coex_core import state

    sender = BathymetrySender({"levels": 3, "send_delay": 5.0})
    xs, ys = np.meshgrid(np.arange(0.5, 16.0, 0.5), np.arange(0.5, 16.0, 0.5))
    sender.ingest(np.column_stack([xs.ravel(), ys.ravel(), -50.0 + 0.01 * xs.ravel()]), 100.0)
    sent = [m for m in sender.fill(4096, 110.0) if isinstance(m, SubgridMessage)]
    sg = next(m for m in sent if (m.level, m.ix, m.iy) == (0, 0, 0))
    sender.acked(sg, 150.0)
    sender.lost(sg, 151.0)  # in the same process: confirmed, not spare work
    assert (0, 0, 0) not in {(m.level, m.ix, m.iy) for m in sender.spare(4096, 152.0) if isinstance(m, SubgridMessage)}
    blob = state.dumps(sender)
    for seed in ("1", "2"):
        out = subprocess.run([sys.executable, "-c", _RESTARTED_SENDER], input=blob, capture_output=True,
                             env={**os.environ, "PYTHONHASHSEED": seed}, timeout=120)
        assert out.returncode == 0 and out.stdout.decode().strip() == "False", out.stderr.decode()[-2000:]
