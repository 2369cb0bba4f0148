"""A CommandAck for a modality's request goes back to the receiver that sent the request."""

from __future__ import annotations

from coex_core import wire
from coex_core.channel import ChannelManager, LinkConfig, Schedule
from coex_core.messages import AckStatus, CommandAck, FrameHeader, ImageByTimeRequest
from coex_core.node import Node
from coex_plugins.imagery import ImageryModality


def test_command_ack_reaches_the_requesting_receiver() -> None:
    sched = Schedule.simple([1, 2], 20.0, 2.0)
    topside = Node(ChannelManager(1, [LinkConfig(0, sched, rate=5, dst=2)]))
    receiver = ImageryModality().receiver(None)
    topside.add_receiver(ImageryModality, receiver)
    receiver.request_by_time(1000.0, "before", 0.0)
    topside.poll(1.0)  # collects the request (and would send it in topside's slot)
    [cid] = [m.command_id for m in receiver.pending_requests()
             if isinstance(m, ImageByTimeRequest)]
    assert receiver.pending_requests()
    frame = wire.pack([CommandAck(cid, AckStatus.ACCEPTED)], 64, FrameHeader(src=2, dst=1, seq=1))
    topside.receive(0, frame, 30.0)
    assert not receiver.pending_requests(), "the receiver stops retrying an acknowledged request"
