"""A running node that hears nothing from its peer for ``SILENT_CYCLES`` TDMA cycles says so,
once, and once again when it hears it again: the vehicle daemon in its log and in its status's
fault bits (which the console turns into words), topside in its log and its console."""

from __future__ import annotations

import uuid
from pathlib import Path

import pytest

from coex import SILENT_CYCLES, ChannelManager, LinkConfig, PeerWatch, Schedule
from coex.messages import VehicleMode, VehicleStatus
from coex_apps.console.cli import build_topside
from coex_apps.console.state import ConsoleState
from coex_apps.vehicle.faults import FAULT_PEER_SILENT, FAULT_STORE

from .test_store_disk import Dive, _image


def test_the_watch_says_once_when_a_peer_goes_silent_and_once_when_it_is_heard_again() -> None:
    from coex import Node
    from coex.messages import FrameHeader, LinkHealth
    from coex.wire import pack

    cycle = 10.0
    node = Node(ChannelManager(1, [LinkConfig(0, Schedule.simple([1, 2], cycle / 2, 0.5), dst=2)]))
    watch = PeerWatch(node.manager, [2])
    assert watch.check(0.0) == []
    assert watch.check(SILENT_CYCLES * cycle - 1) == []  # not yet
    (gone,) = watch.check(SILENT_CYCLES * cycle)
    assert gone.silent and gone.link == 0 and gone.peer == 2 and gone.cycles == SILENT_CYCLES
    assert "nothing heard from node 2 for 5 TDMA cycles" in gone.text()
    assert watch.check(SILENT_CYCLES * cycle + 100) == [] and watch.any_silent()  # said once
    node.receive(0, pack([LinkHealth(0, 0, True, 0, 0, 0)], 256, FrameHeader(src=2, dst=1, seq=0)), 200.0)
    (back,) = watch.check(201.0)
    assert not back.silent and back.seconds == pytest.approx(200.0) and "heard again" in back.text("topside")
    assert not watch.any_silent() and watch.check(202.0) == []


def test_a_vehicle_that_hears_nothing_from_topside_logs_it_and_tells_topside(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    _image(tmp_path / "images", "a.png", 1)
    dive = Dive(tmp_path)
    try:
        dive.run(3.0)
        assert not dive.app.faults() & FAULT_PEER_SILENT
        cycle = dive.app.node.manager.schedule(0).cycle
        # topside stops sending (its modem's dest wrong, say): the vehicle still sends its status
        seen = len(dive.statuses)
        with caplog.at_level("INFO", logger="coex.vehicle"):
            dive.run(SILENT_CYCLES * cycle + 6.0, topside_sends=False)
            assert "nothing heard from topside (node 1) for 5 TDMA cycles" in caplog.text
            assert caplog.text.count("nothing heard from topside") == 1
            assert dive.app.faults() & FAULT_PEER_SILENT
            # the status topside still hears says so (the newest one it got)
            assert max(dive.statuses[seen:], key=lambda s: s.stamp).faults & FAULT_PEER_SILENT
            seen = len(dive.statuses)
            dive.run(6.0)  # topside sends again
            assert "topside (node 1) heard again" in caplog.text
        assert not dive.app.faults() & FAULT_PEER_SILENT
        assert max(dive.statuses[seen:], key=lambda s: s.stamp).faults == 0
    finally:
        dive.app.close()


def test_the_console_says_what_the_vehicle_s_fault_bits_mean() -> None:
    state = ConsoleState()

    def status(t: float, faults: int) -> None:
        state.apply_message(VehicleStatus(int(t) % 2**16, 1.0, 2.0, 3.0, None, 0.0, 0.0, 0, VehicleMode.UNKNOWN,
                                          faults), t)

    status(10.0, 0)
    status(20.0, FAULT_STORE)
    status(30.0, FAULT_STORE | FAULT_PEER_SILENT)
    status(40.0, FAULT_PEER_SILENT)
    status(50.0, 0)
    texts = [e["text"] for e in state.log]
    assert texts == [
        "vehicle: its store cannot write (disk full, read-only or damaged): images and survey reports wait, "
        "what else it takes is not kept across a restart",
        "vehicle: it hears nothing from topside (check topside's modem: src, dest, rate, TDMA)",
        "vehicle: its store writes again",
        "vehicle: it hears topside again",
    ]


def test_topside_that_hears_nothing_from_its_vehicle_shows_it_in_the_console() -> None:
    now = [1_800_000_000.0]
    sched = Schedule.simple([1, 2], 4.0, 0.5)
    app = build_topside(f"loopback://silent-{uuid.uuid4().hex[:8]}", "127.0.0.1", 0, schedule=sched,
                        clock=lambda: now[0])
    try:
        for _ in range(int(SILENT_CYCLES * sched.cycle / 0.5) + 4):
            app.step()
            app.transport.inner.link.clock.advance(0.5)
            now[0] += 0.5
        texts = [e["text"] for e in app.hub.state.log]
        assert any("nothing heard from the vehicle (node 2) for 5 TDMA cycles" in t for t in texts), texts
    finally:
        app.close()
