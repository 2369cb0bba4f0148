"""Command authentication in the node (spec section 10): with a shared key, topside signs every
frame that carries a command, the vehicle rejects forged, replayed and unauthenticated commands,
logs and counts them, and both counters survive a restart through the exported settings."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from coex import SimNetwork
from coex_core import wire
from coex_core.acoustic import AcousticChannel
from coex_core.auth import TRAILER_BYTES, CommandSigner
from coex_core.channel import ChannelManager, CommandResult, Rejected, StreamConfig
from coex_core.messages import (
    AckStatus,
    AuthTrailer,
    CommandAck,
    FrameAck,
    FrameHeader,
    ImageGoal,
    LinkStatus,
    Opaque,
    QueueConfig,
)
from coex_core.node import Node
from tests.test_node import REQUEST, TOPSIDE, VEHICLE, FakeModality, FakeReceiver, FakeSender, links

KEY = b"ship-and-vehicle-share-this-key!"
OTHER = b"an-attacker-guesses-this-key...."


class KeyedPair:
    """A vehicle and a topside node over a lossless simulated channel, each with its own key."""

    def __init__(self, vehicle_key: bytes | None, topside_key: bytes | None) -> None:
        cfgs = links()
        self.sender = FakeSender()
        self.receiver = FakeReceiver()
        self.vlog: list[str] = []
        self.vmgr = ChannelManager(VEHICLE, cfgs, command_key=vehicle_key)
        self.vehicle = Node(self.vmgr, log=self.vlog.append)
        self.vehicle.add_sender(FakeModality, self.sender, StreamConfig(5, "fake", priority=30))
        self.tmgr = ChannelManager(TOPSIDE, cfgs, command_key=topside_key)
        self.topside = Node(self.tmgr)
        self.topside.add_receiver(FakeModality, self.receiver)
        self.net = SimNetwork({0: AcousticChannel(seed=1)})
        self.net.add_node(self.vehicle, (0.0, 0.0, 500.0))
        self.net.add_node(self.topside, (0.0, 0.0, 0.0))
        self.tevents: list[Any] = []
        self.vevents: list[Any] = []

    def run(self, until: float) -> None:
        self.net.run(until)
        self.tevents += self.topside.events()
        self.vevents += self.vehicle.events()

    def results(self) -> dict[int, AckStatus]:
        return {e.command_id: e.status for e in self.tevents if isinstance(e, CommandResult)}

    def topside_frames(self) -> list[bytes]:
        return [f for nid, tx in self.net.transmissions if nid == TOPSIDE for f in tx.frames]


def signed_frame(messages: list[Any], key: bytes = KEY, counter: int = 0, seq: int = 1) -> bytes:
    return CommandSigner(key, counter).pack(messages, 256, FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=seq))


def test_authenticated_commands_work_end_to_end() -> None:
    p = KeyedPair(KEY, KEY)
    p.net.at(1.0, lambda now: p.topside.queue_config(5, now, priority=77))
    p.net.at(1.0, lambda now: p.topside.request(Opaque(REQUEST, bytes([7])), now))
    p.run(200.0)
    assert set(p.results().values()) == {AckStatus.ACCEPTED}
    assert p.vmgr.stream(5).config.priority == 77
    assert any(m.body[0] == 7 for _, m in p.receiver.got), "the authenticated request was served"
    assert p.vehicle.stats["unauthenticated"] == 0
    # topside's command frames end with the 13-byte trailer; the vehicle's frames carry none
    command_frames = [f for f in p.topside_frames()
                      if any(isinstance(m, QueueConfig | Opaque) for m in wire.unpack(f))]
    assert command_frames and all(isinstance(wire.unpack(f)[-1], AuthTrailer) for f in command_frames)
    assert p.tmgr.stats["signed"] >= len(command_frames)
    vehicle_msgs = [m for nid, tx in p.net.transmissions if nid == VEHICLE
                    for f in tx.frames for m in wire.unpack(f)]
    assert vehicle_msgs and not any(isinstance(m, AuthTrailer) for m in vehicle_msgs)


def test_unauthenticated_commands_are_rejected_logged_and_answered() -> None:
    p = KeyedPair(KEY, None)  # an operator console without the key
    p.net.at(1.0, lambda now: p.topside.queue_config(5, now, priority=77))
    p.net.at(1.0, lambda now: p.topside.request(Opaque(REQUEST, bytes([7])), now))
    p.run(200.0)
    assert set(p.results().values()) == {AckStatus.UNAUTHENTICATED}
    assert p.vmgr.stream(5).config.priority == 30, "the unauthenticated queue change changed nothing"
    assert not any(m.body[0] == 7 for _, m in p.receiver.got), "the unauthenticated request was not served"
    assert p.vehicle.stats["unauthenticated"] >= 1
    assert any(isinstance(e, Rejected) and "unauthenticated" in e.reason for e in p.vevents)
    assert any("commands rejected" in line for line in p.vlog)
    # data still flows: only commands need the key
    assert len(p.receiver.got) > 10


def test_commands_signed_with_another_key_are_rejected() -> None:
    p = KeyedPair(KEY, OTHER)
    p.net.at(1.0, lambda now: p.topside.queue_config(5, now, priority=77))
    p.run(200.0)
    assert set(p.results().values()) == {AckStatus.UNAUTHENTICATED}
    assert p.vmgr.stream(5).config.priority == 30
    assert any(isinstance(e, Rejected) and "bad authentication tag" in e.reason for e in p.vevents)


def test_a_flipped_tag_bit_or_altered_command_is_rejected() -> None:
    p = KeyedPair(KEY, KEY)
    frame = signed_frame([QueueConfig(4, 5, False, None, 77, None, None, None)])
    flipped = frame[:-3] + bytes([frame[-3] ^ 0x01]) + frame[-2:]
    p.vehicle.receive(0, flipped, 1.0)
    assert p.vmgr.stream(5).config.priority == 30
    assert p.vehicle.stats["unauthenticated"] == 1
    # the command itself altered (priority 77 -> 78, same tag): rejected too
    altered = wire.pack([QueueConfig(4, 5, False, None, 78, None, None, None), wire.unpack(frame)[-1]],
                        256, FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=1))
    p.vehicle.receive(0, altered, 2.0)
    assert p.vmgr.stream(5).config.priority == 30
    assert p.vehicle.stats["unauthenticated"] == 2
    acks = [m for m in p.vmgr.stream(2).entries if isinstance(m.message, CommandAck)]
    assert [a.message.status for a in acks] == [AckStatus.UNAUTHENTICATED] * 2
    p.vehicle.receive(0, frame, 3.0)  # the genuine frame still works
    assert p.vmgr.stream(5).config.priority == 77


def test_a_trailer_not_last_or_twice_makes_the_frames_commands_unauthenticated() -> None:
    """Spec section 10: such a frame is valid (the decoder takes it), but a keyed vehicle
    rejects every command in it, answers UNAUTHENTICATED and takes the other messages; a node
    without a key ignores trailers wherever they are."""
    command = QueueConfig(4, 5, False, None, 77, None, None, None)
    status = LinkStatus(10, 0, 8, 0, None, None)
    genuine = wire.unpack(signed_frame([command]))
    trailer = genuine[-1]
    assert isinstance(trailer, AuthTrailer)
    header = FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=1)
    for n, messages in enumerate(([trailer, command, status], [command, trailer, trailer, status])):
        frame = wire.pack(messages, 256, header)
        assert wire.unpack(frame) == messages, "a valid frame"
        p = KeyedPair(KEY, KEY)
        taken = p.vehicle.receive(0, frame, 1.0)
        assert p.vmgr.stream(5).config.priority == 30, f"case {n}: the command was applied"
        assert p.vehicle.stats["unauthenticated"] == 1
        assert status in taken and command not in taken
        acks = [e.message for e in p.vmgr.stream(2).entries if isinstance(e.message, CommandAck)]
        assert acks == [CommandAck(4, AckStatus.UNAUTHENTICATED)]
        assert any(isinstance(e, Rejected) and "last message and appear once" in e.reason
                   for e in p.vehicle.events())
    keyless = KeyedPair(None, None)
    keyless.vehicle.receive(0, wire.pack([trailer, command], 256, header), 1.0)
    assert keyless.vmgr.stream(5).config.priority == 77, "without a key the trailer is ignored"


def test_a_replayed_frame_is_rejected_and_not_applied_twice() -> None:
    p = KeyedPair(KEY, KEY)
    frame = signed_frame([Opaque(REQUEST, bytes([9]))])
    p.vehicle.receive(0, frame, 1.0)
    assert p.sender.urgent == [9, 9, 9]
    p.sender.urgent.clear()
    p.vehicle.receive(0, frame, 50.0)  # an eavesdropper plays it back
    assert p.sender.urgent == [], "the replayed request did nothing"
    assert p.vehicle.stats["unauthenticated"] == 1
    assert any(isinstance(e, Rejected) and "replayed" in e.reason for e in p.vehicle.events())
    # an older counter (frames reordered, or recorded earlier) is a replay too, and is not acked,
    # so a genuine sender re-sends it under a new counter
    old = signed_frame([Opaque(REQUEST, bytes([8]))], counter=0, seq=2)
    newer = signed_frame([Opaque(REQUEST, bytes([6]))], counter=5, seq=3)
    p.vehicle.receive(0, newer, 60.0)
    p.vehicle.receive(0, old, 61.0)
    assert p.sender.urgent == [6, 6, 6]
    acked = {(e.seq + d) % 256 for f in p.vehicle.manager._take_acks(62.0) if isinstance(f, FrameAck)
             for e in f.entries for d in range(8) if e.frames >> d & 1}
    assert 3 in acked and 2 not in acked


def test_counters_survive_a_restart() -> None:
    p = KeyedPair(KEY, KEY)
    p.net.at(1.0, lambda now: p.topside.queue_config(5, now, priority=77))
    p.run(200.0)
    assert p.vmgr.stream(5).config.priority == 77
    pre_restart = [f for f in p.topside_frames() if isinstance(wire.unpack(f)[-1], AuthTrailer)]
    assert pre_restart
    saved_vehicle = p.vmgr.export_settings()
    saved_topside = p.tmgr.export_settings()
    assert saved_vehicle["auth"]["accepted"] >= 1 and saved_topside["auth"]["sent"] >= 1
    # the vehicle restarts from its saved settings: a recording of an old frame is a replay
    v2 = ChannelManager(VEHICLE, links(), command_key=KEY)
    vehicle2 = Node(v2)
    vehicle2.add_sender(FakeModality, FakeSender(), StreamConfig(5, "fake", priority=30))
    v2.import_settings(saved_vehicle)  # as the Runner does, once the node is built
    for f in pre_restart:
        vehicle2.receive(0, f, 300.0)
    assert vehicle2.stats["unauthenticated"] == len(pre_restart)
    assert v2.stream(5).config.priority == 77  # restored from the settings, not from the replay
    # topside restarts too: its counter resumes above anything it may have sent before
    t2 = ChannelManager(TOPSIDE, links(), command_key=KEY)
    t2.import_settings(saved_topside)
    assert t2.signer is not None and t2.signer.counter > saved_topside["auth"]["sent"]
    frame = t2.signer.pack([QueueConfig(9, 5, False, None, 55, None, None, None)], 256,
                           FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=7))
    vehicle2.receive(0, frame, 310.0)
    assert v2.stream(5).config.priority == 55


def test_goal_for_the_imagery_modality_is_a_command() -> None:
    p = KeyedPair(KEY, KEY)
    assert p.vehicle.is_command(ImageGoal(1, 3, 0, 1))
    assert p.vehicle.is_command(Opaque(REQUEST, b"\x01"))  # a third-party modality's request
    assert not p.vehicle.is_command(Opaque(100, b"\x01"))  # its data is not


def test_the_trailer_costs_thirteen_bytes_as_the_spec_says() -> None:
    assert wire.encoded_size(AuthTrailer(1, bytes(8))) == TRAILER_BYTES == 13
    spec = (Path(__file__).resolve().parents[1] / "spec" / "wire-format.md").read_text()
    assert "Cost: 13 bytes per authenticated frame" in spec
