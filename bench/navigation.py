"""Navigation benchmark (issue 56): how well topside's drift estimate follows the truth, and what
it costs, without running whole dives.

For each seed: the default dive's lawnmower (``simulate_survey`` over a 256 m site at 30 m
altitude and 1 m/s, after a 300 s descent), then two camera lines and a hold to 7200 s; the
vehicle dead-reckons with the demo's model (``coex_apps.demo.navigation.DeadReckoning``: drift
0.005, heading bias 0.5 deg, 2 m at the bottom), the ship's USBL (``UsblTracker``: 1 % of the
slant range from 200 m south of the site, 2 % wild) fixes it every 10 s, and topside receives the
vehicle's believed position at its TDMA slots (4 of 6 slots of 20 s) with 30 % of them lost.
The estimator (``DriftEstimator``, defaults) gets the fixes as they come and the statuses, solving
after each new point as the console would. Printed and written to ``bench/results/navigation.json``:

* the smoothed correction against the true drift over the dive (median, 95th percentile, worst);
* the live estimate (the filter at the newest data) at the end of the survey, when the demo's
  operator sends its camera lines;
* wild fixes drawn, flagged, and used;
* the CPU time of all the solves.

Usage: ``python bench/navigation.py [--seeds N] [--first S]`` (development seeds: 2000 and up).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

from coex_apps.demo.navigation import DeadReckoning, UsblTracker, track_positions
from coex_apps.demo.world import Leg, Track
from coex_plugins.bathymetry.sim import Seafloor, simulate_survey
from coex_plugins.navigation import DriftEstimator, LocalFrame


def survey_track(seed: int) -> tuple[Track, float]:
    """The true track of a 256 m lawnmower survey at 30 m altitude after a 300 s descent (the
    benches' vehicle), and the survey's end (s). ``bench/navigation_lines.py`` flies its camera
    lines after the same survey."""
    floor = Seafloor(size=256.0, depth=500.0, relief=2.0, ripple_amplitude=0.15, targets=(), seed=seed)
    track = Track(floor)
    survey = simulate_survey(floor, altitude=30.0, speed=1.0, ping_rate=2.0, beams=256, t0=300.0, turn_time=60.0,
                             seed=seed + 1)
    for t, xyz in survey.pings(batch=20):
        track.add_sample(float(t), float(np.mean(xyz[:, 0])), float(np.mean(xyz[:, 1])), 30.0)
    track.samples.sort()
    track.legs.append(Leg(0.0, 300.0, (0.0, 0.0), (0.0, 0.0), 30.0))
    return track, float(survey.times[-1])


def one(seed: int) -> dict[str, float]:
    track, end_survey = survey_track(seed)
    t, p = end_survey, (track.samples[-1][1], track.samples[-1][2])
    for a, b in (((100.0, 70.0), (100.0, 130.0)), ((180.0, 40.0), (180.0, 100.0))):
        d = math.hypot(a[0] - p[0], a[1] - p[1])
        track.legs.append(Leg(t, t + d, p, a, 10.0))
        track.legs.append(Leg(t + d, t + d + 120.0, a, b, 5.0, camera=True))
        t, p = t + d + 120.0, b
    track.legs.append(Leg(t, 7200.0, p, p, 50.0))
    dr = DeadReckoning(track, 0.0, 300.0, 7200.0, drift=0.005, heading_bias=0.5, seed_offset=2.0,
                       rng=np.random.default_rng([seed, 56]))
    usbl = UsblTracker((128.0, -200.0), LocalFrame(0.0, 0.0), sigma=0.01, outliers=0.02,
                       rng=np.random.default_rng([seed, 57]))
    est = DriftEstimator()
    lost = np.random.default_rng([seed, 58])
    times = np.arange(0.0, 7200.0, 10.0)
    truth = np.zeros((len(times), 2))
    live = math.nan
    cpu = 0.0
    for k, now in enumerate(times):
        x, y = track_positions(track, np.array([now]))[0]
        truth[k] = dr.error(now)
        usbl.fix(now, 2, x, y, 470.0)
        est.add_fix(now, *usbl.log[-1][4:6])
        if int(now // 20) % 6 in (1, 2, 4, 5) and lost.random() > 0.3:
            est.add_track(now, x + truth[k][0], y + truth[k][1])
        c0 = time.process_time()
        est.solution()
        cpu += time.process_time() - c0
        if math.isnan(live) and now >= end_survey + 30.0:
            live = float(np.hypot(*(est.correction(now) - truth[k])))
    miss = np.hypot(*(est.correction(times) - truth).T)
    sol = est.solution()
    assert sol is not None
    wild = {round(r[0], 3) for r in usbl.log if r[6]}
    flagged = {round(float(r[0]), 3) for r in sol.fixes if r[4] > 0}
    used = {round(float(r[0]), 3) for r in sol.fixes if r[3] > 0}
    return {"seed": seed, "drift_at_end_m": round(float(np.hypot(*truth[-1])), 2),
            "smoothed_median_m": round(float(np.median(miss)), 2),
            "smoothed_p95_m": round(float(np.percentile(miss, 95)), 2), "smoothed_max_m": round(float(miss.max()), 2),
            "live_at_camera_pass_m": round(live, 2), "wild": len(wild), "wild_flagged": len(wild & flagged),
            "wild_used": len(wild & used), "flagged": len(flagged), "fix_sigma_m": round(sol.fix_sigma, 2),
            "solves": len(times), "cpu_s": round(cpu, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--first", type=int, default=2000)
    args = ap.parse_args()
    rows = [one(s) for s in range(args.first, args.first + args.seeds)]
    keys = list(rows[0])
    print(" ".join(f"{k:>14}" for k in keys))
    for r in rows:
        print(" ".join(f"{r[k]!s:>14}" for k in keys))
    out = Path(__file__).parent / "results"
    out.mkdir(exist_ok=True)
    summary = {k: {"median": float(np.median([r[k] for r in rows])), "worst": float(max(r[k] for r in rows))}
               for k in ("smoothed_median_m", "smoothed_p95_m", "smoothed_max_m", "live_at_camera_pass_m", "cpu_s")}
    (out / "navigation.json").write_text(json.dumps({"rows": rows, "summary": summary}, indent=2))
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
