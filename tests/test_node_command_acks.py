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


def test_a_command_unanswered_for_three_cycles_shows_no_answer_and_a_late_answer_still_lands() -> None:
    """The ship knows a command's true state: unanswered for ANSWER_CYCLES TDMA cycles it is "no
    answer" (an event, the console's word); the vehicle's answer that comes after all is taken."""
    from coex_apps.console.state import ConsoleState
    from coex_core.channel import CommandResult, CommandUnanswered
    from coex_core.channel.commands import ANSWER_CYCLES
    from coex_core.tracker import State

    sched = Schedule.simple([1, 2], 20.0, 2.0)
    topside = Node(ChannelManager(1, [LinkConfig(0, sched, rate=5, dst=2)]))
    console = ConsoleState(node_id=1, vehicle_id=2)
    cid = topside.queue_config(1, 0.0, enabled=False)
    msg = topside.manager._commands[cid].message
    console.record_command(msg, 0.0, "disable stream 1")

    def step(now: float) -> list[object]:
        topside.poll(now)
        events = topside.events()
        for e in events:
            console.apply_event(e)
        return events

    cycle = sched.cycle
    heard = [e for t in range(1, int(ANSWER_CYCLES * cycle) - 1, 10) for e in step(float(t))]
    assert not any(isinstance(e, CommandUnanswered) for e in heard)
    assert console.snapshot()["commands"][0]["status"] == "sent"
    late = step(ANSWER_CYCLES * cycle + 5.0)
    assert [e.command_id for e in late if isinstance(e, CommandUnanswered)] == [cid]
    assert topside.manager._commands[cid].state is State.NO_ANSWER
    assert console.snapshot()["commands"][0]["status"] == "no answer"
    assert not any(isinstance(e, CommandUnanswered) for e in step(10 * cycle)), "said once"

    frame = wire.pack([CommandAck(cid, AckStatus.ACCEPTED)], 64, FrameHeader(src=2, dst=1, seq=1))
    topside.receive(0, frame, 11 * cycle)
    events = topside.events()
    for e in events:
        console.apply_event(e)
    [result] = [e for e in events if isinstance(e, CommandResult)]
    assert result.command == msg and cid not in topside.manager._commands
    assert console.snapshot()["commands"][0]["status"] == "accepted"
