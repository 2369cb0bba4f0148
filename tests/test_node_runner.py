"""The runner drives nodes over real Transport objects (loopback here) on a simulated clock."""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

from coex import Runner, SimulatedClock
from coex_core import wire
from coex_core.channel import Acked, ChannelManager, LinkConfig, Schedule, StreamConfig
from coex_core.loopback import LoopbackLink
from coex_core.messages import Message, Opaque
from coex_core.modality import Modality, ModalitySender
from coex_core.node import Node

VEHICLE, TOPSIDE = 2, 1


class Counter(ModalitySender):
    def __init__(self) -> None:
        self.n = 0

    def ingest(self, data: Any, now: float) -> None:
        pass

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        if max_bytes < 60:
            return []
        self.n += 1
        return [Opaque(100, self.n.to_bytes(4, "big") + bytes(54))]

    def handle(self, message: Message, now: float) -> list[Message]:
        return []


def _nodes() -> tuple[Node, Node, Counter]:
    sched = Schedule.simple([TOPSIDE, VEHICLE, VEHICLE], 10.0, 1.0)
    link = LinkConfig(0, sched, rate=1, frames=3)  # 3 x 64 B frames, ~3 s per packet
    vehicle = Node(ChannelManager(VEHICLE, [link]))
    sender = Counter()
    vehicle.add_sender(type("M", (Modality,), {"name": "m"}),
                       sender, StreamConfig(5, "m", ack_required=True))
    topside = Node(ChannelManager(TOPSIDE, [link]))
    return vehicle, topside, sender


def test_two_runners_over_a_loopback_link() -> None:
    lb = LoopbackLink(mtu=64, bytes_per_s=200.0, delay=0.7, seed=2)
    clock = SimulatedClock(sim=lb.clock)
    vehicle, topside, _sender = _nodes()
    log = io.StringIO()
    rv = Runner(vehicle, {0: lb.a}, clock, link_log=log)
    rt = Runner(topside, {0: lb.b}, clock)
    while clock.time() < 300.0:
        nxt = min(rv.step(), rt.step(), clock.time() + 0.25)
        clock.wait_until(max(nxt, clock.time() + 1e-3))
    assert rv.error_count == 0 and rt.error_count == 0
    got = [e for e in topside.events() if type(e).__name__ == "ProductUpdated" or type(e).__name__ == "Received"]
    assert len(got) > 20  # data reached topside, one frame at a time through the transport
    acked = [e for e in vehicle.events() if isinstance(e, Acked)]
    assert len(acked) > 20  # and topside's frame acks came back
    # only messages sent since topside's last slot (270..280) still wait for their ack
    assert all(e.first_sent is not None and e.first_sent >= 279.0 for e in vehicle.manager.stream(5).entries)
    lines = [line for line in log.getvalue().splitlines() if line]
    assert lines and all('"capacity_bytes":192' in line for line in lines)


def test_runner_run_until_on_simulated_clock() -> None:
    lb = LoopbackLink(mtu=64, bytes_per_s=200.0)
    clock = SimulatedClock(sim=lb.clock)
    vehicle, _, sender = _nodes()
    Runner(vehicle, {0: lb.a}, clock).run(until=60.0)
    assert clock.time() >= 60.0
    frames = []
    while (f := lb.b.recv(timeout=0)) is not None:
        frames.append(f)
    assert frames and all(wire.unpack_frame(f).header.src == VEHICLE for f in frames)
    assert sender.n > 10


def test_runner_persists_settings_across_a_restart(tmp_path: Path) -> None:
    from coex_core.messages import LinkControl, QueueConfig

    path = tmp_path / "vehicle-settings.json"
    lb = LoopbackLink(mtu=64)
    clock = SimulatedClock(sim=lb.clock)
    vehicle, _, _ = _nodes()
    runner = Runner(vehicle, {0: lb.a}, clock, settings_path=path)
    runner.step()
    assert path.exists()
    vehicle.manager.apply(QueueConfig(1, 5, False, True, 77, 600, 9, True), 1.0)
    vehicle.manager.apply(LinkControl(2, 0, True, True), 1.0)  # muted (the only link: refused)
    runner.step()
    saved = json.loads(path.read_text())
    assert saved["streams"]["5"]["priority"] == 77
    # restart: a fresh node built from the same configuration picks the settings up
    again, _, _ = _nodes()
    assert again.manager.stream(5).config.priority != 77
    Runner(again, {0: lb.a}, clock, settings_path=path)
    c = again.manager.stream(5).config
    assert (c.priority, c.ttl, c.max_depth, c.newest_first) == (77, 600.0, 9, True)
    assert not again.manager.link_state(0)["muted"]



def test_runner_survives_a_failing_transport() -> None:
    from coex_core.errors import TransportError
    from coex_core.transport import Transport

    class Broken(Transport):
        def __init__(self) -> None:
            super().__init__(mtu=32)  # smaller than the link's 64 B frames: FrameTooLarge

        def _send_internal(self, frame: bytes) -> None:
            raise AssertionError("never reached: every frame is above the MTU")

        def _recv_internal(self, timeout: float | None) -> bytes | None:
            raise TransportError("serial port gone")

    clock = SimulatedClock(start=0.0)
    vehicle, _, sender = _nodes()
    runner = Runner(vehicle, {0: Broken()}, clock)
    runner.run(until=40.0)
    assert any("receive" in e for e in runner.errors)
    assert any("send" in e and "MTU" in e for e in runner.errors)
    assert sender.n > 0  # the node kept building packets
