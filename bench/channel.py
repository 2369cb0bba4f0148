"""Channel manager benchmark: packet fill, operator-request latency, utilisation, replay speed.

Scenario (the NUI 2022 layout): one Micromodem rate-5 link (8 x 256 B frames, ~3.0 s per
packet), a TDMA cycle of 6 x 20 s slots with a 2 s guard, topside owning slots 0 and 3 and
the vehicle 1, 2, 4 and 5; vehicle 300 m across and 1000 m below the ship. The vehicle sends a
status every 10 s, a queue status every cycle, and three modalities with data always waiting,
served by pulls ("at most N bytes"):

* ``bathy``: fixed-size pieces (80 or 144 B, like the original 8x8 subgrids), not acked;
* ``image``: fragments cut to whatever fits (up to 245 B), acked;
* ``series``: 40..100 B chunks, not acked.

Topside makes an operator request at seeded random times; the requested modality answers with
tagged messages. Measured:

* **fill**: useful (message) bytes / offered bytes (full packets) of vehicle transmissions;
  target >= 97 %;
* **latency**: from the request arriving subsea to the start of the first vehicle transmission
  that carries the answer, and whether that is the next vehicle transmit opportunity (target:
  every request);
* **utilisation**: useful bytes delivered per cycle against the physical limit of the link
  (the vehicle transmitting at rate 5 for all of its slot time) and against the TDMA limit
  (whole packets that fit before each slot's guard); the original system's configuration
  (one 17 s packet per slot) is given for comparison;
* a lossy run (10 % independent frame loss) for goodput, and replay speed (simulated s per s);
* spare capacity: a mostly idle link (20 B/s of new data per modality, spare work always
  available) with spare traffic on and off, and on at 60 % frame loss: vehicle link use over
  the packets sent while work was ready (target >= 90 %), spare and redundant bytes (0 with spare
  off), and request to the first answer byte delivered topside, in vehicle slots (target: the
  next vehicle slot in the median at 60 % loss).

    python bench/channel.py [--cycles N] [--seed S] [--quick]

Prints the numbers and writes ``bench/results/channel.json``.
"""

from __future__ import annotations

import argparse
import json
import random
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

from coex import SimNetwork
from coex_core import wire
from coex_core.acoustic import RATES, AcousticChannel
from coex_core.channel import ChannelManager, LinkConfig, Schedule, StreamConfig
from coex_core.errors import ConfigError
from coex_core.messages import Message, Opaque, VehicleMode, VehicleStatus
from coex_core.modality import Modality, ModalityReceiver, ModalitySender, Product
from coex_core.node import Node

ROOT = Path(__file__).resolve().parents[1]
VEHICLE, TOPSIDE = 2, 1
DATA, REQUEST = 100, 120
SLOT, GUARD = 20.0, 2.0
OWNERS = [TOPSIDE, VEHICLE, VEHICLE, TOPSIDE, VEHICLE, VEHICLE]


class BenchSender(ModalitySender):
    """Endless data of one size policy; a request makes the next two messages carry its tag."""

    def __init__(self, kind: int, policy: str, rng: random.Random) -> None:
        self.kind, self.policy, self.rng = kind, policy, rng
        self.urgent: list[int] = []
        self.handled: list[tuple[int, float]] = []
        self.n = 0

    def ingest(self, data: Any, now: float) -> None:
        pass

    def _size(self, room: int) -> int:
        if self.policy == "fixed":
            size = 144 if self.n % 2 else 80
            return size if size <= room else (80 if room >= 80 else 0)
        if self.policy == "fit":
            return min(room, 245) if room >= 12 else 0
        size = self.rng.randint(40, 100)
        return size if size <= room else (room if room >= 40 else 0)

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        out: list[Message] = []
        room = max_bytes
        while True:
            size = self._size(room)
            if size < 8:
                break
            tag = self.urgent.pop(0) if self.urgent else 0
            self.n += 1
            # Opaque encodes as type (1 B) + length (1 or 2 B) + body
            overhead = 2 if size - 2 < 128 else 3
            body = bytes([self.kind, tag]) + bytes(size - overhead - 2)
            out.append(Opaque(DATA, body))
            room -= size
        return out

    def handle(self, message: Message, now: float) -> list[Message]:
        assert isinstance(message, Opaque)
        tag = message.body[1]
        self.handled.append((tag, now))
        self.urgent.extend([tag, tag])
        return []


class BenchReceiver(ModalityReceiver):
    def __init__(self) -> None:
        self.bytes = 0
        self.first_seen: dict[int, float] = {}

    def receive(self, message: Message, now: float) -> list[Product]:
        assert isinstance(message, Opaque)
        self.bytes += wire.encoded_size(message)
        tag = message.body[1]
        if tag and tag not in self.first_seen:
            self.first_seen[tag] = now
        return []

    def poll(self, now: float) -> list[Message]:
        return []

    def products(self) -> list[Product]:
        return []


def _modality(kind: int) -> type[Modality]:
    class Bench(Modality):
        name = f"bench{kind}"
        message_ids: ClassVar[tuple[int, ...]] = (DATA,)
        request_ids: ClassVar[tuple[int, ...]] = (REQUEST + kind,)

        # only its message ids matter here: the benchmark drives the streams itself
        def sender(self, config: Mapping[str, Any] | None = None) -> ModalitySender:
            raise ConfigError(f"{self.name} is a benchmark stand-in without a sender")

        def receiver(self, config: Mapping[str, Any] | None = None) -> ModalityReceiver:
            raise ConfigError(f"{self.name} is a benchmark stand-in without a receiver")

    return Bench


def run(cycles: int, seed: int, loss: float = 0.0, requests: bool = True,
        cut_to_fit: bool = True) -> dict[str, Any]:
    rng = random.Random(seed)
    schedule = Schedule.simple(OWNERS, SLOT, GUARD)
    link = LinkConfig(0, schedule, rate=5)
    vmgr = ChannelManager(VEHICLE, [link], queue_status_interval=schedule.cycle,
                          clock=time.perf_counter)
    vehicle = Node(vmgr)
    senders = {
        0: BenchSender(0, "fixed", random.Random(seed + 1)),
        1: BenchSender(1, "fit", random.Random(seed + 2)),
        2: BenchSender(2, "random", random.Random(seed + 3)),
    }
    streams = {
        0: StreamConfig(5, "bathy", priority=30),
        1: StreamConfig(6, "image", priority=30, ack_required=True),
        2: StreamConfig(7, "series", priority=20),
    }
    if not cut_to_fit:  # only fixed-size and random-size pieces: no sender cuts to fit
        del senders[1]
    for k, s in senders.items():
        vehicle.add_sender(_modality(k), s, streams[k])
    tmgr = ChannelManager(TOPSIDE, [link])
    topside = Node(tmgr)
    receiver = BenchReceiver()
    topside.add_receiver(_modality(0), receiver)
    channel = AcousticChannel(loss=loss, seed=seed)
    log: list[dict[str, Any]] = []
    net = SimNetwork({0: channel}, link_log=log.append)
    net.add_node(vehicle, (0.0, 0.0, 1000.0))
    net.add_node(topside, (300.0, 0.0, 0.0))
    net.every(10.0, lambda now: vehicle.push_status(
        VehicleStatus(int(now), 1.0, 2.0, 1000.0, 10.0, 0.0, 1.0, 90, VehicleMode.SURVEY, 0), now))

    # operator requests: at random times, mostly outside topside slots (they wait for one)
    issued: dict[int, tuple[int, float]] = {}
    if requests:
        t, tag = 200.0, 1
        end = cycles * schedule.cycle - 2 * schedule.cycle
        while t < end and tag < 256:
            kind = rng.choice(sorted(senders))
            issued[tag] = (kind, t)
            net.at(t, lambda now, k=kind, g=tag: topside.request(Opaque(REQUEST + k, bytes([k, g])), now))
            t += rng.uniform(150.0, 400.0)
            tag += 1

    vehicle_tx: list[tuple[float, Any]] = []
    answered: dict[int, float] = {}
    backlog: list[int] = []  # queued bytes not awaiting an ack, after each vehicle packet

    def on_tx(node_id: int, tx: Any) -> None:
        if node_id != VEHICLE:
            return
        vehicle_tx.append((tx.start, tx))
        backlog.append(sum(e.size for q in vmgr.streams if q.id >= 3 for e in q.entries
                           if not e.pending))
        waiting = {g for s in senders.values() for g, _ in s.handled} - set(answered)
        if not waiting:
            return
        for f in tx.frames:
            for m in wire.unpack(f):
                if isinstance(m, Opaque) and m.type_id == DATA and m.body[1] in waiting:
                    answered.setdefault(m.body[1], tx.start)

    net.on_transmit = on_tx
    t0 = time.perf_counter()
    net.run(cycles * schedule.cycle)
    wall = time.perf_counter() - t0

    txs = [tx for _, tx in vehicle_tx]
    used = sum(tx.used for tx in txs)
    offered = sum(tx.capacity for tx in txs)
    fills = [tx.used / tx.capacity for tx in txs]

    lat: list[float] = []
    next_ok = 0
    n_req = 0
    starts = sorted(t for t, _ in vehicle_tx)
    first_arrival: dict[int, float] = {}
    for s in senders.values():  # a request re-sent after a lost frame ack counts once
        for tag, arrived in s.handled:
            first_arrival.setdefault(tag, arrived)
    for tag, arrived in sorted(first_arrival.items()):
        n_req += 1
        nxt = next((t for t in starts if t > arrived), None)
        ans = answered.get(tag)
        if ans is None or nxt is None:
            continue
        lat.append(ans - arrived)
        next_ok += ans == nxt

    veh_log = [r for r in log if r["src"] == VEHICLE and r["dst"] == TOPSIDE]
    delivered_frames = sum(sum(r["delivered"]) for r in veh_log)
    useful_delivered = sum(r["delivered_bytes"] for r in veh_log) - 3 * delivered_frames
    n_cycles = cycles
    info = RATES[5]
    vehicle_time = sum(s.duration for s in schedule.slots if s.owner == VEHICLE)
    airtime_limit = vehicle_time * info.max_bytes / info.airtime()
    per_slot = int((SLOT - GUARD) // link.packet_time)
    tdma_limit = per_slot * info.max_bytes * sum(1 for s in schedule.slots if s.owner == VEHICLE)
    nui_limit = 1 * info.max_bytes * 4  # 17 s packet length: one packet per 20 s slot
    per_cycle = useful_delivered / n_cycles
    lat_sorted = sorted(lat)
    return {
        "cycles": cycles,
        "simulated_s": cycles * schedule.cycle,
        "wall_s": round(wall, 3),
        "replay_speed": round(cycles * schedule.cycle / wall, 1),
        "loss": loss,
        "vehicle_packets": len(txs),
        "fill": round(used / offered, 5) if offered else 0.0,
        "fill_min_packet": round(min(fills), 5) if fills else 0.0,
        "fill_max_possible": round((256 - 3) / 256, 5),
        "requests": n_req,
        "requests_answered": len(lat),
        "requests_next_opportunity": next_ok,
        "latency_s": {
            "min": round(lat_sorted[0], 2) if lat else None,
            "median": round(lat_sorted[len(lat) // 2], 2) if lat else None,
            "max": round(lat_sorted[-1], 2) if lat else None,
        },
        "useful_bytes_per_cycle": round(per_cycle, 1),
        "useful_bytes_per_s": round(per_cycle / schedule.cycle, 1),
        "airtime_limit_per_cycle": round(airtime_limit, 1),
        "tdma_limit_per_cycle": tdma_limit,
        "nui2022_limit_per_cycle": nui_limit,
        "utilisation_vs_airtime": round(per_cycle / airtime_limit, 4),
        "utilisation_vs_tdma": round(per_cycle / tdma_limit, 4),
        "vs_nui2022_config": round(per_cycle / nui_limit, 2),
        "sender_failures": vmgr.stats["sender_failures"],
        "max_backlog_bytes": max(backlog, default=0),
        "max_backlog_packets": round(max(backlog, default=0) / info.max_bytes, 2),
    }


class SpareBenchSender(BenchSender):
    """A mostly idle modality: a trickle of background data (``rate`` B/s of new pieces), spare
    work always available (refinements), and a request answered by tagged pieces."""

    def __init__(self, kind: int, rng: random.Random, rate: float) -> None:
        super().__init__(kind, "fit", rng)
        self.rate = rate
        self.credit = 0.0
        self.last: float | None = None

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        if self.last is not None:
            self.credit += (now - self.last) * self.rate
        self.last = now
        room = int(min(max_bytes, self.credit))
        if self.urgent:
            room = max(room, min(max_bytes, 245))  # an answer goes whatever the trickle
        out = super().fill(room, now)
        self.credit -= sum(wire.encoded_size(m) for m in out)
        return out

    def spare(self, max_bytes: int, now: float) -> list[Message]:
        out: list[Message] = []
        room = max_bytes
        while room >= 12:
            size = min(room, 245)
            overhead = 2 if size - 2 < 128 else 3
            out.append(Opaque(DATA, bytes([self.kind, 0]) + bytes(size - overhead - 2)))
            room -= size
        return out

    def spare_bytes(self) -> int:
        return 10**6


def run_spare(cycles: int, seed: int, loss: float, spare: bool) -> dict[str, Any]:
    """A mostly idle link (a 20 B/s trickle of background data per modality) with spare work:
    vehicle link use over packets sent while work was ready, spare bytes, and request to first
    answer byte delivered topside, in vehicle slots (1: the next vehicle slot)."""
    rng = random.Random(seed)
    schedule = Schedule.simple(OWNERS, SLOT, GUARD)
    link = LinkConfig(0, schedule, rate=5, spare=1.0 if spare else 0.0)
    vmgr = ChannelManager(VEHICLE, [link], queue_status_interval=schedule.cycle, clock=time.perf_counter)
    vehicle = Node(vmgr)
    senders = {k: SpareBenchSender(k, random.Random(seed + k), 20.0) for k in range(3)}
    for k, snd in senders.items():
        vehicle.add_sender(_modality(k), snd, StreamConfig(5 + k, f"m{k}", priority=30))
    topside = Node(ChannelManager(TOPSIDE, [LinkConfig(0, schedule, rate=5)]))
    receiver = BenchReceiver()
    topside.add_receiver(_modality(0), receiver)
    net = SimNetwork({0: AcousticChannel(loss=loss, seed=seed)})
    net.add_node(vehicle, (0.0, 0.0, 1000.0))
    net.add_node(topside, (300.0, 0.0, 0.0))
    net.every(10.0, lambda now: vehicle.push_status(
        VehicleStatus(int(now), 1.0, 2.0, 1000.0, 10.0, 0.0, 1.0, 90, VehicleMode.SURVEY, 0), now))
    issued: dict[int, float] = {}
    t, tag = 200.0, 1
    while t < cycles * schedule.cycle - 2 * schedule.cycle and tag < 256:
        kind = rng.choice(sorted(senders))
        issued[tag] = t
        net.at(t, lambda now, k=kind, g=tag: topside.request(Opaque(REQUEST + k, bytes([k, g])), now))
        t += rng.uniform(150.0, 400.0)
        tag += 1
    txs: list[Any] = []
    net.on_transmit = lambda node_id, tx: txs.append(tx) if node_id == VEHICLE else None
    net.run(cycles * schedule.cycle)

    def vehicle_slots(t0: float, t1: float) -> int:
        n, t = 0, t0 + 1e-6
        while True:
            w = schedule.next_window(t, VEHICLE)
            if w is None or w.start > t1:
                return n
            n += w.start > t0
            t = w.end + 1e-6

    # a request's clock starts when it first leaves topside (the next topside slot)
    slots = []
    for g, t_req in issued.items():
        w = schedule.next_window(t_req, TOPSIDE)
        sent = t_req if w is None else max(t_req, w.start)
        got = receiver.first_seen.get(g)
        slots.append(vehicle_slots(sent, got) if got is not None else 10**6)
    slots.sort()
    work = [tx for tx in txs if tx.backlog > 0]
    return {
        "loss": loss, "spare": spare, "cycles": cycles, "vehicle_packets": len(txs),
        "link_use_with_work": round(sum(tx.used for tx in work) / sum(tx.capacity for tx in work), 4) if work else None,
        "link_use_all": round(sum(tx.used for tx in txs) / sum(tx.capacity for tx in txs), 4) if txs else None,
        "spare_bytes": vmgr.stats["spare_bytes"], "redundant_bytes": vmgr.stats["redundant_bytes"],
        "requests": len(slots),
        "first_answer_vehicle_slots_median": slots[len(slots) // 2] if slots else None,
        "first_answer_at_next_vehicle_slot": round(sum(s <= 1 for s in slots) / len(slots), 3) if slots else None,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cycles", type=int, default=60, help="TDMA cycles of 120 s (default 60 = 2 h)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="8 cycles")
    args = ap.parse_args(argv)
    cycles = 8 if args.quick else args.cycles
    clean = run(cycles, args.seed)
    lossy = run(max(4, cycles // 2), args.seed + 1, loss=0.1)
    fixed = run(max(4, cycles // 2), args.seed + 2, cut_to_fit=False)
    spare_cycles = max(4, cycles // 2)
    idle_on = run_spare(spare_cycles, args.seed, 0.0, True)
    idle_off = run_spare(spare_cycles, args.seed, 0.0, False)
    lossy_on = run_spare(spare_cycles, args.seed + 3, 0.6, True)
    result = {
        "scenario": "rate 5 (8x256 B), 6 x 20 s slots, guard 2 s, vehicle slots 1,2,4,5",
        "clean": clean,
        "lossy_10pct": lossy,
        "no_cut_to_fit_sender": fixed,
        "spare_idle_link": idle_on,
        "spare_off_idle_link": idle_off,
        "spare_60pct_loss": lossy_on,
        "targets": {
            "link use >= 90 % while work is ready (spare on)": (idle_on["link_use_with_work"] or 0) >= 0.90
            and (lossy_on["link_use_with_work"] or 0) >= 0.90,
            "no spare bytes with spare traffic off": idle_off["spare_bytes"] == 0 and idle_off["redundant_bytes"] == 0,
            "60 % loss: first answer byte at the next vehicle slot (median)":
                lossy_on["first_answer_vehicle_slots_median"] is not None
                and lossy_on["first_answer_vehicle_slots_median"] <= 1,
            "fill>=0.97": clean["fill"] >= 0.97,
            "every request served at the next vehicle opportunity":
                clean["requests"] > 0 and clean["requests_next_opportunity"] == clean["requests"],
        },
    }
    c = clean
    print(f"channel bench: {c['cycles']} cycles ({c['simulated_s']:.0f} s simulated) in {c['wall_s']:.1f} s "
          f"wall ({c['replay_speed']:.0f}x real time)")
    print(f"  fill (useful/offered bytes): {c['fill']:.2%} (min packet {c['fill_min_packet']:.2%}, "
          f"header-limited max {c['fill_max_possible']:.2%}); target >= 97%")
    print(f"  requests: {c['requests']} answered {c['requests_answered']}, at the next vehicle opportunity "
          f"{c['requests_next_opportunity']}; latency arrival->answer leaves s: {c['latency_s']}")
    print(f"  useful bytes/cycle {c['useful_bytes_per_cycle']:.0f} ({c['useful_bytes_per_s']:.0f} B/s): "
          f"{c['utilisation_vs_airtime']:.1%} of the rate-5 airtime limit "
          f"({c['airtime_limit_per_cycle']:.0f} B), {c['utilisation_vs_tdma']:.1%} of the TDMA limit "
          f"({c['tdma_limit_per_cycle']} B), {c['vs_nui2022_config']:.1f}x the 2022 configuration "
          f"({c['nui2022_limit_per_cycle']} B)")
    lo = lossy
    print(f"  10% frame loss: {lo['useful_bytes_per_s']:.0f} B/s useful delivered "
          f"({lo['utilisation_vs_tdma']:.1%} of the TDMA limit), fill {lo['fill']:.2%}, "
          f"requests at next opportunity {lo['requests_next_opportunity']}/{lo['requests']}")
    print(f"  manager queues stay shallow: at most {c['max_backlog_bytes']} B "
          f"({c['max_backlog_packets']} packets) queued and not awaiting an ack")
    print(f"  without a sender that cuts to fit (80/144 B pieces + 40..100 B chunks only): fill "
          f"{fixed['fill']:.2%}")
    for name, r in (("spare on, idle link", idle_on), ("spare off, idle link", idle_off),
                    ("spare on, 60% loss", lossy_on)):
        print(f"  {name}: link use {_pct(r['link_use_all'])} overall, {_pct(r['link_use_with_work'])} while "
              f"work was ready; spare {r['spare_bytes']} B, redundant {r['redundant_bytes']} B; request to "
              f"first answer delivered: median {r['first_answer_vehicle_slots_median']} vehicle slots, "
              f"{_pct(r['first_answer_at_next_vehicle_slot'])} at the next one")
    out = ROOT / "bench" / "results"
    out.mkdir(parents=True, exist_ok=True)
    (out / "channel.json").write_text(json.dumps(result, indent=2) + "\n")
    print(f"  targets: {result['targets']}")
    return 0 if all(result["targets"].values()) else 1


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{v:.1%}"


if __name__ == "__main__":
    sys.exit(main())
