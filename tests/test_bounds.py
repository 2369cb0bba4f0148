"""Requests are bounded: absurd ones get a clear rejection (a ``Rejected`` event and
``CommandAck(REJECTED)``), never a crash, and a flood of them leaves memory bounded."""

from __future__ import annotations

import pytest

from coex_core import wire
from coex_core.channel import ChannelManager, LinkConfig, Rejected, Schedule, StreamConfig
from coex_core.channel.manager import CONTROL_STREAM
from coex_core.errors import EncodeError
from coex_core.messages import (
    AckStatus,
    CommandAck,
    FrameHeader,
    GoalKind,
    ImageGoal,
    MapRoiRequest,
    Message,
    QueueConfig,
    TimeSeriesRequest,
)
from coex_core.node import Node
from coex_plugins.bathymetry import BathymetryModality
from coex_plugins.imagery import ImageryModality
from coex_plugins.timeseries import TimeSeriesModality, synth

TOPSIDE, VEHICLE = 1, 2


def vehicle() -> tuple[Node, dict[str, object]]:
    sched = Schedule.simple([TOPSIDE, VEHICLE], 20.0, 2.0)
    node = Node(ChannelManager(VEHICLE, [LinkConfig(0, sched, rate=5, dst=TOPSIDE)]))
    channels = [s.channel() for s in synth.dataset(duration=600.0, seed=1)]
    senders = {
        "bathymetry": BathymetryModality().sender(None),
        "imagery": ImageryModality().sender(None),
        "timeseries": TimeSeriesModality().sender({"channels": channels}),
    }
    for i, (name, cls) in enumerate((("bathymetry", BathymetryModality), ("imagery", ImageryModality),
                                     ("timeseries", TimeSeriesModality))):
        node.add_sender(cls, senders[name], StreamConfig(3 + i, name, priority=30))
    return node, senders


def deliver(node: Node, messages: list[Message], seq: int, now: float) -> list[object]:
    node.receive(0, wire.pack(messages, 256, FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=seq % 256)), now)
    return node.events()


ABSURD = [
    # a map level the vehicle does not have
    MapRoiRequest(1, 15, 0, 0, 1, 1, False, (None,)),
    # a region at the edge of the addressable map (subgrid indices past +-8192)
    MapRoiRequest(2, 0, 8190, 8190, 16, 16, True, (), 0),
    # an image the vehicle never took, a 0 % goal
    ImageGoal(10, 1000, GoalKind.FRACTION, 50),
    ImageGoal(11, 0, GoalKind.FRACTION, 0),
    # a channel that does not exist, an error bound finer than the sensor's resolution
    TimeSeriesRequest(12, 30, 0, 100, 1.0),
    TimeSeriesRequest(13, 0, 0, 100, 1e-9),
    # a queue change for a stream that does not exist
    QueueConfig(14, 29, False, None, 50, None, None, None),
]


@pytest.mark.parametrize("request_", ABSURD, ids=lambda m: type(m).__name__)
def test_absurd_requests_are_rejected_with_a_clear_reason(request_: Message) -> None:
    node, _ = vehicle()
    events = deliver(node, [request_], 1, 10.0)
    rejected = [e for e in events if isinstance(e, Rejected)]
    acks = [e.message for e in node.manager.stream(CONTROL_STREAM).entries
            if isinstance(e.message, CommandAck)]
    cid = getattr(request_, "command_id", getattr(request_, "request_id", None))
    if isinstance(request_, QueueConfig):
        assert acks == [CommandAck(14, AckStatus.UNKNOWN_TARGET)]
    else:
        assert len(rejected) == 1 and len(rejected[0].reason) > 10, "a reason a person can read"
        if isinstance(request_, ImageGoal | TimeSeriesRequest):
            assert CommandAck(int(cid), AckStatus.REJECTED) in acks  # type: ignore[arg-type]
    # and the node still works: a sane request after the absurd one is accepted
    deliver(node, [ImageGoal(99, 0, GoalKind.FULL, 0)], 2, 11.0)
    assert node.stats["frames"] == 2


def test_values_beyond_the_wire_format_cannot_even_be_sent() -> None:
    with pytest.raises(EncodeError):
        wire.encode(MapRoiRequest(1, 0, 0, 0, 100, 100, True, (), 0))
    with pytest.raises(EncodeError):
        wire.encode(TimeSeriesRequest(1, 0, 0, 2**20, 1.0))
    with pytest.raises(EncodeError):  # a stamp list that does not match the region
        wire.encode(MapRoiRequest(3, 0, 0, 0, 4, 4, False, (None,)))


def test_a_flood_of_requests_keeps_memory_bounded() -> None:
    node, senders = vehicle()
    bathy = senders["bathymetry"]
    # 5 000 frames of distinct requests: region requests, goals, refinements
    for i in range(5_000):
        msgs: list[Message] = [
            MapRoiRequest(i % 256, i % 4, (i * 7) % 4000 - 2000, (i * 13) % 4000 - 2000, 16, 16, True, (), 0),
            ImageGoal(i % 256, i % 1024, GoalKind.FULL, 0),
            TimeSeriesRequest((i + 1) % 256, i % 2, i % 1000, i % 1000 + 50, 1.0),
        ]
        deliver(node, msgs, i, 10.0 + i)
    assert node.stats["frames"] == 5_000
    # the tables that remember requests are bounded by the 8-bit command ids, queues by depth
    assert len(node._recent) <= 256
    assert len(node._command_owner) <= 256
    assert len(node.manager.stream(CONTROL_STREAM).entries) <= node.manager.stream(CONTROL_STREAM).config.max_depth
    assert len(bathy._queue) <= bathy.max_queue  # type: ignore[attr-defined]
    for q in node.manager.streams:
        assert len(q.entries) <= max(q.config.max_depth, 1) + 64
