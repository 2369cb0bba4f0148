"""Map benchmark of the navigation (issue 56): where does the car sit in topside's corrected 1 m
map at the end of the survey, with and without aiding the vehicle's navigation, without running
whole dives.

For each seed, the default preset's survey as the demo flies it (its seafloor, cars and lawnmower;
``simulate_survey`` after a 300 s descent), the vehicle's dead reckoning with the demo's draws for
that seed (``DeadReckoning``, ``rng_for(seed, 560)``: the same drift as ``coex demo --seed S``),
the ship's USBL (``UsblTracker``, 1 % of the slant range, 2 % wild, every 10 s), and a link that
keeps the demo's TDMA cycle (6 x 20 s: topside in slots 0 and 3, the vehicle in the others) and
loses 30 % of the messages each way: the vehicle's newest status goes up in each of its slots;
topside's position fixes (aiding) go down in its slots and their answers come up in the
vehicle's. The vehicle's soundings, in its believed frame, go into the vehicle's real map
(``BathymetrySender``); at the end of the survey the whole map is handed to topside's real
``BathymetryReceiver`` without loss, topside's ``Navigation`` corrects it (``CorrectedMap``), and
the scripted operator's bump finder (``operator.map_bumps``: measured in the level as received,
placed by the map's correction) measures every bump: the **map error** of each target is the
distance from its true centre to the nearest target-like bump within 25 m, as ``metrics.json``
``navigation.targets[].map_error_m`` has it (the operator's candidates there also come from the
vehicle's detections). ``--scenario FILE`` runs a scenario file instead of a preset (issue 56's
fourth pass: debris patches, ``target_kinds = ["debris"]``).

Printed per seed and mode (``off``: no aiding, the first pass's correction alone; ``on``: topside
aids the vehicle during its survey as the demo does), and written to
``bench/results/navigation_map.json``. Development seeds only (2000 and up).

Usage: ``python bench/navigation_map.py [--seeds N] [--first S] [--modes off,on] [--scenario FILE]``
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from coex.messages import CommandAck, PositionFix
from coex_apps.demo.config import EPOCH, VEHICLE
from coex_apps.demo.navigation import (
    AID_BLEND,
    AID_DELAY,
    AID_INTERVAL,
    DeadReckoning,
    UsblTracker,
    believed_soundings,
)
from coex_apps.demo.operator import MIN_SCORE, map_bumps
from coex_apps.demo.scenario import Scenario, load_scenario, preset
from coex_apps.demo.world import Leg, Track, rng_for, vehicle_status
from coex_core.loopback import RoundTrip
from coex_plugins.bathymetry import BathymetryModality
from coex_plugins.bathymetry.relief import bumps
from coex_plugins.bathymetry.sim import Seafloor, simulate_survey
from coex_plugins.navigation import AidConfig, CorrectedMap, LocalFrame, Navigation
from coex_plugins.survey import SurveyModality

CYCLE = 120.0
TOPSIDE_SLOTS = (0.0, 60.0)
LOSS = 0.3


def one(seed: int, aiding: bool, scenario: str | Scenario = "default", swath: float | None = 135.0,
        keep: dict[str, Any] | None = None, descent: float = 300.0, turn_time: float = 60.0) -> dict[str, Any]:
    scn = preset(scenario) if isinstance(scenario, str) else scenario
    cars, rocks = scn.place(seed)
    floor = Seafloor(size=scn.area, depth=scn.water_depth, relief=scn.relief, ripple_amplitude=scn.ripple_amplitude,
                     targets=cars + rocks, seed=seed)
    survey = simulate_survey(floor, altitude=scn.survey_altitude, line_spacing=scn.line_spacing or None,
                             speed=scn.survey_speed, ping_rate=2.0, beams=256, t0=EPOCH + descent, turn_time=turn_time,
                             seed=seed + 1)
    end = float(survey.times[-1])
    track = Track(floor)
    batches = []
    off = 0
    for t, xyz in survey.pings(batch=20):
        track.add_sample(float(t), float(np.mean(xyz[:, 0])), float(np.mean(xyz[:, 1])), scn.survey_altitude)
        batches.append((float(t), xyz, slice(off, off + len(xyz))))
        off += len(xyz)
    track.samples.sort()
    track.legs.append(Leg(EPOCH, EPOCH + descent, (0.0, 0.0), (0.0, 0.0), scn.survey_altitude))
    dr = DeadReckoning(track, EPOCH, EPOCH + descent, EPOCH + scn.duration, drift=scn.drift,
                       heading_bias=scn.heading_bias, seed_offset=scn.seed_offset, rng=rng_for(seed, 560))
    usbl = UsblTracker(scn.ship, LocalFrame(0.0, 0.0), sigma=scn.usbl_sigma, outliers=scn.usbl_outliers,
                       rng=rng_for(seed, 562))
    nav = Navigation(swath=swath)
    nav.estimator(VEHICLE)
    sender = SurveyModality().sender({"aiding": aiding, "aid_delay": AID_DELAY})
    receiver = SurveyModality().receiver(None)
    if aiding:
        nav.aiding[VEHICLE] = AidConfig(delay=AID_DELAY, blend=AID_BLEND, interval=AID_INTERVAL, until=end)
    bathy = BathymetryModality().sender({"send_delay": 20.0})
    lost = np.random.default_rng([seed, 5601])
    down: list[tuple[float, Any]] = []  # (arrives, message) topside -> vehicle
    up: list[tuple[float, Any]] = []  # vehicle -> topside
    cpu = time.process_time()
    k = 0
    t = EPOCH
    taken = 0
    while t <= end + 60.0:
        # the vehicle: position fixes due, then the soundings up to now in its believed frame
        for a in sender.take_aids(t):
            dr.aid(a.time, a.x, a.y, a.time + AID_DELAY, AID_BLEND)
            taken += 1
        while k < len(batches) and batches[k][0] <= t:
            bt, xyz, rows = batches[k]
            bathy.ingest(believed_soundings(dr, xyz, survey.ping[rows], survey.times[rows]), bt)
            k += 1
        x, y, depth, _alt, _h = track.position(t)
        fx, fy, _ = usbl.fix(t, VEHICLE, x, y, depth)
        nav.estimator(VEHICLE).add_fix(t, fx, fy)
        phase = (t - EPOCH) % CYCLE
        slot = int(phase // 20.0)
        for arrive, msg in [m for m in down if m[0] <= t]:
            down.remove((arrive, msg))
            for ack in sender.handle(msg, arrive):
                up.append((arrive, ack))
        if slot in (1, 2, 4, 5) and phase % 20.0 == 10.0:  # the vehicle's slot: its newest status, answers
            status = vehicle_status(track, t)
            bx, by = dr.believed(t, status.x, status.y)
            status = replace(status, x=round(bx, 1), y=round(by, 1), heading=round(dr.heading(status.heading) % 359.9, 1))
            if lost.random() > LOSS:
                nav.status(VEHICLE, status, t)
            answers, up[:] = list(up), []
            for _sent, ack in answers:
                if isinstance(ack, CommandAck) and lost.random() > LOSS:
                    receiver.receive(ack, t)
        if phase in TOPSIDE_SLOTS:  # topside's slot: an aid when it is time, the fixes due
            nav.aid(VEHICLE, receiver, t)
            for msg in receiver.poll(t):
                if isinstance(msg, PositionFix) and lost.random() > LOSS:
                    down.append((t + 2.0, msg))
        t += 10.0
    cpu = time.process_time() - cpu
    # the whole map to topside (no loss: where the map sits is the question here, not the link)
    rx = BathymetryModality().receiver(None)
    bathy.map.flush(force=True)
    link = RoundTrip(bathy, rx, mtu=1 << 16, round_seconds=5.0, now=end + 60.0)
    for _ in range(400):
        link.step()
        if not link.last_fill and bathy.pending_bytes() == 0:
            break
    rows: dict[str, Any] = {"seed": seed, "aiding": aiding, "drift_at_end_m": round(float(np.hypot(*dr.error(end))), 2),
                            "aids_taken": taken, "aids_sent": len(nav.aids.get(VEHICLE, [])), "cpu_s": round(cpu, 1)}
    if keep is not None:
        keep.update(nav=nav, rx=rx, cars=cars, dr=dr, track=track)
    views = {"raw": rx, "corrected": CorrectedMap(rx, nav, VEHICLE)}
    rows["targets"] = [f"{car.kind} {car.length:.1f} m" for car in cars]
    for name, view in views.items():
        # the scripted operator's own measure of the received 1 m map (map_bumps)
        found = [(v.x, v.y, v.score) for v in map_bumps(view)]
        errs = []
        for car in cars:
            near = [math.hypot(bx - car.x, by - car.y) for bx, by, score in found if score >= MIN_SCORE]
            best = min(near, default=math.inf)
            errs.append(round(best, 2) if best <= 25.0 else None)
        rows[f"map_{name}_m"] = errs
    # the estimate against the truth over the survey; the vehicle's error (truth) and topside's
    # estimate of it at each pass over each car (the swath's centre line nearest the car)
    ts = np.arange(EPOCH + descent + 60.0, end, 10.0)
    truth = np.array([dr.error(float(x)) for x in ts])
    est = nav.estimate(VEHICLE, ts)
    miss = np.hypot(*(est - truth).T)
    rows["estimate_median_m"] = round(float(np.median(miss)), 2)
    rows["estimate_p95_m"] = round(float(np.percentile(miss, 95)), 2)
    st = np.array([s_[0] for s_ in track.samples])
    sxy = np.array([(s_[1], s_[2]) for s_ in track.samples])
    passes = []
    for car in cars:
        near = (np.abs(sxy[:, 0] - car.x) <= 70.0) & (np.abs(sxy[:, 1] - car.y) <= 5.0)
        seen: list[float] = []
        for tt in st[near]:
            if not seen or tt - seen[-1] > 60.0:
                seen.append(float(tt))
        offs = [float(abs(sxy[int(np.argmin(np.abs(st - tt))), 0] - car.x)) for tt in seen]
        passes.append([[round(tt - EPOCH), [round(v, 1) for v in dr.error(tt)],
                        [round(float(v), 1) for v in nav.estimate(VEHICLE, tt)], round(u, 1)]
                       for tt, u in zip(seen, offs, strict=True)])
    rows["passes"] = passes
    # the bump of the raw map (the vehicle's frame) nearest where the vehicle saw each car, placed
    # by the estimate at its first pass, at its last pass, and at their mean
    p = rx.level_product(0)
    grid = np.asarray(p.data, float)
    raw = [(b.x, b.y) for _c, b in bumps(grid, cell=float(p.meta["cell_size"]), x0=float(p.meta["x0"]),
                                          y0=float(p.meta["y0"]), threshold=0.7, min_cells=2, max_area=40.0)]
    rules: dict[str, list[float | None]] = {"first": [], "last": [], "mean": [], "nadir": [], "cos2": [],
                                             "cos4": []}
    for car, ps in zip(cars, passes, strict=True):
        if not ps or not raw:
            for r in rules.values():
                r.append(None)
            continue
        seen = np.array([car.x, car.y]) + np.mean([q[1] for q in ps], axis=0)
        bx, by = min(raw, key=lambda b: math.hypot(b[0] - seen[0], b[1] - seen[1]))
        rows.setdefault("bump_offset", []).append([round(bx - car.x, 1), round(by - car.y, 1)])
        cs = np.array([q[2] for q in ps])
        u = np.array([q[3] for q in ps])
        w = 30.0**2 / (30.0**2 + u**2)
        for name, c in (("first", cs[0]), ("last", cs[-1]), ("mean", cs.mean(axis=0)),
                        ("nadir", cs[int(np.argmin(u))]), ("cos2", (w[:, None] * cs).sum(0) / w.sum()),
                        ("cos4", (w[:, None] ** 2 * cs).sum(0) / (w**2).sum())):
            rules[name].append(round(math.hypot(bx - c[0] - car.x, by - c[1] - car.y), 2))
    rows["rule_m"] = rules
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--first", type=int, default=2000)
    ap.add_argument("--modes", default="off,on")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--scenario", default=None, help="a scenario file instead of --preset (e.g. debris patches)")
    ap.add_argument("--swath", type=float, default=135.0, help="topside's idea of the swath (0: stamps only)")
    args = ap.parse_args()
    rows = []
    for s in range(args.first, args.first + args.seeds):
        for mode in args.modes.split(","):
            scn = load_scenario(args.scenario) if args.scenario else args.preset
            r = one(s, mode == "on", scn, args.swath or None)
            rows.append(r)
            print(json.dumps(r), flush=True)
    out = Path(__file__).parent / "results"
    out.mkdir(exist_ok=True)
    summary: dict[str, Any] = {}
    for mode in args.modes.split(","):
        errs = [e for r in rows if r["aiding"] == (mode == "on") for e in r["map_corrected_m"]]
        got = [e for e in errs if e is not None]
        summary[mode] = {"targets": len(errs), "found": len(got),
                         "median_m": float(np.median(got)) if got else None, "worst_m": max(got, default=None),
                         "over_2m": sum(1 for e in errs if e is None or e > 2.0)}
    (out / "navigation_map.json").write_text(json.dumps({"rows": rows, "summary": summary}, indent=2))
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
