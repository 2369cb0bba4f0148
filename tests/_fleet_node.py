"""One node of the three-node network of ``tests/test_fleet.py`` as a process (topside or a
vehicle), on a simulated Micromodem of ``coex modem-sim`` over TCP, in real time::

    python -m tests._fleet_node ID URI

Topside (id 1) prints ``rx 2=<messages from vehicle 2> 3=<from vehicle 3>`` every second; a
vehicle prints ``acked=<its messages topside acknowledged>``. Killed, it saves nothing: the test
``kill -9``s a vehicle and watches the other keep delivering."""

from __future__ import annotations

import sys

from coex import Runner
from coex_core.channel import ChannelManager, LinkConfig, Schedule, StreamConfig
from coex_core.node import Node
from coex_core.registry import open_transport

from .test_fleet import TOPSIDE, Fake, Receiver, Sender

#: a rate-5 packet takes 3 s, and up to 1.4 s to reach the farthest node of the line modem-sim
#: lays out (1000 m apart): one packet per slot (1 s to spare), a cycle of 21 s
SLOT, GUARD = 7.0, 3.0


def main(argv: list[str]) -> int:
    nid, uri = int(argv[0]), argv[1]
    sched = Schedule.simple([TOPSIDE, 2, 3], SLOT, GUARD)
    link = LinkConfig(0, sched, rate=5, watchdog_cycles=3, dst=0 if nid == TOPSIDE else TOPSIDE)
    node = Node(ChannelManager(nid, [link]))
    rxs: dict[int, Receiver] = {}
    if nid == TOPSIDE:
        for v in (2, 3):
            rxs[v] = Receiver()
            node.add_receiver(Fake, rxs[v], peer=v)
    else:
        node.add_sender(Fake, Sender(nid), StreamConfig(5, "fake", ack_required=True))
    runner = Runner(node, {0: open_transport(uri)})
    last = 0.0

    def report(now: float) -> None:
        nonlocal last
        node.events()
        if now - last < 1.0:
            return
        last = now
        if nid == TOPSIDE:
            print("rx " + " ".join(f"{v}={len(r.got)}" for v, r in sorted(rxs.items())), flush=True)
        else:
            print(f"acked={node.manager.stats['acked']}", flush=True)
        st = node.manager.link_state(0)
        print(f"link tx={st['frames_tx']} rx={st['frames_rx']} errors={runner.error_count} "
              f"{list(runner.errors)[-1:]}", flush=True)

    runner.after_step.append(report)
    print(f"node {nid} up", flush=True)
    runner.run(duration=600.0)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
