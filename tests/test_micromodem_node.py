"""Two CoEx nodes (channel manager + runner) talking through simulated Micromodem-2s and the real
driver, on the simulated clock: the path the demo takes."""

from __future__ import annotations

from typing import Any

from coex import Runner
from coex_core import wire
from coex_core.acoustic import AcousticChannel
from coex_core.channel import Acked, ChannelManager, LinkConfig, Schedule, StreamConfig
from coex_core.messages import Message, Opaque
from coex_core.modality import Modality, ModalitySender
from coex_core.node import Node
from coex_transports.micromodem import ModemNetwork

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


def test_two_nodes_over_simulated_modems() -> None:
    sched = Schedule.simple([TOPSIDE, VEHICLE, VEHICLE], 10.0, 1.0)
    link = LinkConfig(0, sched, rate=1, frames=3)  # 3 x 64 B frames, ~3 s per packet
    vehicle = Node(ChannelManager(VEHICLE, [link]))
    vehicle.add_sender(type("M", (Modality,), {"name": "m"}),
                       Counter(), StreamConfig(5, "m", ack_required=True))
    topside = Node(ChannelManager(TOPSIDE, [link]))
    net = ModemNetwork({VEHICLE: (0.0, 0.0, 0.0), TOPSIDE: (1500.0, 0.0, 0.0)},
                       channel=AcousticChannel(loss=0.05, seed=4))
    clock = net.as_clock()
    tv = net.transport(VEHICLE, dest=TOPSIDE, rate=1)
    tt = net.transport(TOPSIDE, dest=VEHICLE, rate=1)
    rv, rt = Runner(vehicle, {0: tv}, clock), Runner(topside, {0: tt}, clock)
    start = clock.time()
    while clock.time() < start + 600.0:
        nxt = min(rv.step(), rt.step(), clock.time() + 0.25)
        clock.wait_until(max(nxt, clock.time() + 1e-3))
    assert rv.error_count == 0 and rt.error_count == 0, (rv.errors, rt.errors)
    got = [e for e in topside.events() if type(e).__name__ in ("ProductUpdated", "Received")]
    assert len(got) > 40  # data reached topside through NMEA, the modems and the channel
    assert len([e for e in vehicle.events() if isinstance(e, Acked)]) > 40  # and the acks came back
    st = tv.stats()
    assert st["packets_sent"] > 30 and st["tx_failed"] == 0 and st["handler_errors"] == 0
    assert tt.link_status() is not None
    # every frame the vehicle's modem was given is a CoEx frame of the vehicle
    lines = [x for x in net.modems[VEHICLE].host_lines if x.startswith(b"$CCTXD")]
    from coex_transports.micromodem import nmea

    frames = [bytes.fromhex(nmea.parse(x).fields[3]) for x in lines]
    assert frames and all(wire.unpack_frame(f).header.src == VEHICLE for f in frames if f)
