"""One side of the kill/restart test, as a real process: the vehicle or the topside node of the
fault suite's short dive (``tests/_faults.py``), with a :class:`NodeStore`, over a real transport,
on a dive clock running ``--speed`` times faster than the wall clock from ``--epoch``.

    python -m tests._persist_node --role vehicle --db v.sqlite --uri lcm:udpm://... --epoch E

The vehicle takes its sensor data (``sensor_feed``) when the dive clock passes each item's time;
after a restart it first takes what it missed (a vehicle's sensors log on their own; CoEx
catches up from its journal). The topside asks for image 1 in full at 200 s, once. SIGTERM ends
the process cleanly; SIGKILL is what the test uses to crash it."""

from __future__ import annotations

import argparse
import signal
import sys
from typing import Any

from coex import RealClock, Runner
from coex_core.registry import open_transport
from coex_runtime.store import NodeStore

from ._faults import T0, build_dive

#: LCM has no airtime: a packet takes 1 s of the 4-s slot, so a node that polls late in its
#: slot (a busy machine) still sends in it
PACKET_SECONDS = 1.0
#: two TDMA cycles: processes on a busy machine answer late; wait for their acks before re-sending
ACK_TIMEOUT = 32.0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--role", choices=("vehicle", "topside"), required=True)
    p.add_argument("--db", required=True)
    p.add_argument("--uri", required=True)
    p.add_argument("--epoch", type=float, required=True)
    p.add_argument("--speed", type=float, default=20.0)
    p.add_argument("--minutes", type=int, default=5)
    args = p.parse_args(argv)

    def stop(*_: Any) -> None:
        raise SystemExit(0)

    signal.signal(signal.SIGTERM, stop)
    clock = RealClock(speed=args.speed, at=(args.epoch, T0))  # dive time: T0 at wall time epoch
    store = NodeStore(args.db, snapshot_interval=5.0, compact=False)  # the test audits the journal
    template = build_dive(minutes=args.minutes, packet_seconds=PACKET_SECONDS, ack_timeout=ACK_TIMEOUT)
    feed = template.feed

    def build() -> Any:
        d = build_dive(minutes=args.minutes, packet_seconds=PACKET_SECONDS, ack_timeout=ACK_TIMEOUT)
        return d.vehicle if args.role == "vehicle" else d.topside

    node = store.restore(build, log=lambda text: print(text, file=sys.stderr))
    transport = open_transport(args.uri)
    runner = Runner(node, {0: transport}, clock, store=store, max_wait=1.0)
    store.set(f"starts_{args.role}", str(int(store.get(f"starts_{args.role}", "0") or 0) + 1))

    def due(now: float) -> None:
        if args.role == "vehicle":
            done = store.count("input")  # the feed items taken so far, in order
            while done < len(feed) and feed[done][0] <= now:
                runner.ingest(feed[done][1], feed[done][2])
                done += 1
        elif now >= T0 + 200.0 and store.get("goal") is None:
            node.receiver("imagery").request_goal(1, "full", now=now)  # type: ignore[attr-defined]
            store.snapshot(node, now)  # the request is in the saved state ...
            store.set("goal", "asked")  # ... before it is marked done

    runner.before_step.append(due)
    try:
        runner.run()
    finally:
        transport.close()
        store.close()


if __name__ == "__main__":
    sys.exit(main())
