"""Soak benchmark: a simulated 24-hour dive with bounded memory.

A vehicle and a topside node (the NUI layout: rate 5, 6 x 20 s TDMA slots, 20 % frame loss) run
for 24 simulated hours with steady inputs all day: the vehicle surveys a 256 m site with a
96-beam multibeam again and again (a pass every ~15 minutes), takes a camera image every 5
minutes, samples two sensor channels every second and reports its status every 10 s; topside asks
every hour for the newest image in full. Every simulated hour the benchmark samples the
process's resident memory and what the nodes hold (their whole state as a store would save it,
images on each side, series samples topside); it prints peak RSS (``ru_maxrss``), memory over
time and the slope of the second half (MB per hour), and writes ``bench/results/soak.json``.
What may grow is what the dive produced and the operator keeps: images up to the imagery
modality's ``max_images`` (64 vehicle, 256 topside) and the received series; the channel
manager, queues, acks, map and caches stay flat.

    python bench/soak.py [--hours 24] [--quick] [--seed S]

``--quick`` runs 2 simulated hours.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from coex import SimNetwork, SimulatedClock
from coex_core.acoustic import AcousticChannel
from coex_core.channel import ChannelManager, LinkConfig, Schedule, StreamConfig
from coex_core.messages import VehicleMode, VehicleStatus
from coex_core.node import Node
from coex_plugins.bathymetry import BathymetryModality
from coex_plugins.bathymetry.sim import Seafloor, simulate_survey
from coex_plugins.imagery import ImageInput, ImageryModality
from coex_plugins.imagery.synth import seafloor
from coex_plugins.timeseries import TimeSeriesModality
from coex_plugins.timeseries import synth as ts_synth

ROOT = Path(__file__).resolve().parents[1]
VEHICLE, TOPSIDE = 2, 1
T0 = 0.0


def rss_mb() -> float:
    """Resident memory now (Linux /proc; falls back to the peak elsewhere)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return peak_mb()


def peak_mb() -> float:
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 1024 if sys.platform != "darwin" else kb / 2**20


def survey_passes(seed: int, size: float = 256.0, beams: int = 96) -> tuple[list[tuple[float, np.ndarray]], float]:
    """One pass over the site (256 m) with a multibeam (96 beams, 1 ping/s, 1.5 m/s): ``(seconds
    from the pass's start, N x 3 soundings)`` in batches of 10 pings, and the pass's length in
    seconds with its turn."""
    floor = Seafloor.default(size=size, seed=seed, relief=1.0)
    survey = simulate_survey(floor, beams=beams, ping_rate=1.0, speed=1.5, seed=seed + 1)
    passes = [(t, xyz) for t, xyz in survey.pings(batch=10)]
    return passes, max(t for t, _ in passes) + 30.0


def camera_image(k: int, shape: tuple[int, int] = (120, 160)) -> np.ndarray:
    """The ``k``-th camera image of the day (one of 50 seafloor frames)."""
    return seafloor(shape[0], shape[1], seed=k % 50)


def sensor_series(duration: float, seed: int, t0: float) -> list[Any]:
    """Two sensor channels (methane, temperature) at 1 Hz for ``duration`` seconds from ``t0``."""
    return list(ts_synth.dataset(duration=duration, period=1.0, seed=seed, t0=t0))


def build(hours: float, seed: int) -> tuple[SimNetwork, dict[str, Any]]:
    sched = Schedule.simple([TOPSIDE, VEHICLE, VEHICLE, TOPSIDE, VEHICLE, VEHICLE], 20.0, 2.0)
    vehicle = Node(
        ChannelManager(
            VEHICLE, [LinkConfig(0, sched, rate=5, dst=TOPSIDE)], queue_status_interval=120.0
        )
    )
    topside = Node(ChannelManager(TOPSIDE, [LinkConfig(0, sched, rate=5, dst=VEHICLE)]))
    duration = hours * 3600.0
    series = sensor_series(duration, seed, T0)
    bathy = BathymetryModality().sender({"send_delay": 20.0})
    images = ImageryModality().sender(None)
    ts = TimeSeriesModality().sender({"channels": [s.channel() for s in series]})
    vehicle.add_sender(
        BathymetryModality, bathy, StreamConfig(3, "map", priority=40, ack_required=True)
    )
    vehicle.add_sender(ImageryModality, images, StreamConfig(4, "images", priority=30))
    vehicle.add_sender(TimeSeriesModality, ts, StreamConfig(5, "series", priority=20))
    map_rx, image_rx, ts_rx = (
        BathymetryModality().receiver(None),
        ImageryModality().receiver(None),
        TimeSeriesModality().receiver(None),
    )
    topside.add_receiver(BathymetryModality, map_rx)
    topside.add_receiver(ImageryModality, image_rx)
    topside.add_receiver(TimeSeriesModality, ts_rx)
    net = SimNetwork(
        {0: AcousticChannel(loss=0.2, seed=seed)}, SimulatedClock(start=T0), keep_transmissions=100
    )
    net.add_node(vehicle, (0.0, 0.0, 500.0))
    net.add_node(topside, (300.0, 400.0, 0.0))

    passes, pass_seconds = survey_passes(seed)

    def survey_pass(now: float) -> None:
        for t, xyz in passes:
            net.at(now + t, lambda at, xyz=xyz: bathy.ingest(xyz, at))
        if now + pass_seconds < duration:
            net.at(now + pass_seconds, survey_pass)

    net.at(T0 + 10.0, survey_pass)
    k = [0]

    def photo(now: float) -> None:
        k[0] += 1
        images.ingest(ImageInput(camera_image(k[0]), time=now, x=0.0, y=0.0), now)

    net.every(300.0, photo, start=T0 + 60.0)

    def samples(now: float) -> None:
        ts.ingest(
            {
                s.name: (
                    s.times[(s.times >= now - 60.0) & (s.times < now)],
                    s.values[(s.times >= now - 60.0) & (s.times < now)],
                )
                for s in series
            },
            now,
        )

    net.every(60.0, samples, start=T0 + 60.0)
    net.every(
        10.0,
        lambda now: vehicle.push_status(
            VehicleStatus(
                int(now) % 262144, 10.0, 20.0, 480.0, 20.0, 90.0, 1.0, 80, VehicleMode.SURVEY, 0
            ),
            now,
        ),
    )

    def ask(now: float) -> None:
        if images.images:
            image_rx.request_goal(max(images.images), "full", now=now)

    net.every(3600.0, ask, start=T0 + 1800.0)
    return net, {
        "vehicle": vehicle,
        "topside": topside,
        "images": images,
        "map_rx": map_rx,
        "image_rx": image_rx,
        "ts_rx": ts_rx,
        "pass_seconds": pass_seconds,
        "photos": k,
    }


def k_photos(parts: dict[str, Any]) -> int:
    return int(parts["photos"][0])


def held(parts: dict[str, Any]) -> dict[str, float]:
    """What the nodes hold: their whole sans-I/O state as a store would save it (its saved state: Node.export_state),
    images kept on each side, and series samples kept topside (bounded by the modalities'
    documented limits, or by the dive itself for the series)."""
    ts = parts["ts_rx"]
    series = sum(b.count for ch in ts._channels.values() for b in ch.blocks.values())
    return {
        "vehicle_state_mb": round(len(parts["vehicle"].export_state()) / 2**20, 2),
        "topside_state_mb": round(len(parts["topside"].export_state()) / 2**20, 2),
        "images_vehicle": float(len(parts["images"].images)),
        "images_topside": float(len(parts["image_rx"].images)),
        "series_samples_topside": float(series),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--hours", type=float, default=24.0)
    p.add_argument("--quick", action="store_true", help="2 simulated hours")
    p.add_argument("--seed", type=int, default=1)
    args = p.parse_args(argv)
    hours = 2.0 if args.quick else args.hours
    wall0 = time.perf_counter()
    net, parts = build(hours, args.seed)
    samples: list[dict[str, float]] = [{"hour": 0.0, "rss_mb": round(rss_mb(), 1), "wall_s": 0.0}]
    print(f"soak: {hours:g} simulated hours; a survey pass every {parts['pass_seconds']:.0f} s")
    for h in range(1, int(hours) + 1):
        net.run(T0 + 3600.0 * h)
        for node in (parts["vehicle"], parts["topside"]):
            node.events()  # a real runner hands events on; nobody keeps them here
        s = {
            "hour": float(h),
            "rss_mb": round(rss_mb(), 1),
            "wall_s": round(time.perf_counter() - wall0, 1),
            **held(parts),
        }
        samples.append(s)
        print(
            f"  hour {h:3d}: RSS {s['rss_mb']:7.1f} MB, node state {s['vehicle_state_mb']:5.1f} + "
            f"{s['topside_state_mb']:5.1f} MB, images {s['images_vehicle']:3.0f} vehicle / "
            f"{s['images_topside']:3.0f} topside, series {s['series_samples_topside']:6.0f} samples "
            f"(wall {s['wall_s']:6.1f} s)",
            flush=True,
        )
    half = [s for s in samples if s["hour"] >= hours / 2]
    slope = (
        float(np.polyfit([s["hour"] for s in half], [s["rss_mb"] for s in half], 1)[0])
        if len(half) >= 2
        else 0.0
    )
    state_slope = (
        float(
            np.polyfit(
                [s["hour"] for s in half],
                [s["vehicle_state_mb"] + s["topside_state_mb"] for s in half],
                1,
            )[0]
        )
        if len(half) >= 2
        else 0.0
    )
    vm = parts["vehicle"].manager
    result = {
        "hours": hours,
        "peak_rss_mb": round(max(peak_mb(), *(s["rss_mb"] for s in samples)), 1),
        "rss_start_mb": samples[1]["rss_mb"] if len(samples) > 1 else samples[0]["rss_mb"],
        "rss_end_mb": samples[-1]["rss_mb"],
        "second_half_slope_mb_per_hour": round(slope, 2),
        "second_half_state_slope_mb_per_hour": round(state_slope, 2),
        "wall_seconds": round(time.perf_counter() - wall0, 1),
        "vehicle_packets": vm.stats["packets"],
        "fill": round(vm.fill_ratio(), 4),
        "images_taken": k_photos(parts),
        "max_images_vehicle": parts["images"].max_images,
        "max_images_topside": parts["image_rx"].max_images,
        "samples": samples,
    }
    print(
        f"peak RSS {result['peak_rss_mb']} MB; RSS {result['rss_start_mb']} MB after hour 1, "
        f"{result['rss_end_mb']} MB at the end; second-half slope {result['second_half_slope_mb_per_hour']} MB/h "
        f"(node state {result['second_half_state_slope_mb_per_hour']} MB/h); "
        f"{result['vehicle_packets']} vehicle packets, fill {result['fill']}; wall {result['wall_seconds']} s"
    )
    out = ROOT / "bench" / "results"
    out.mkdir(parents=True, exist_ok=True)
    (out / "soak.json").write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
