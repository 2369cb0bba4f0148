"""Camera lines after drift correction (issue 56): how far a camera line sent through topside's
:class:`~coex_plugins.navigation.VehicleFrameSurveys` passes from the point it was aimed at, with
the map taken as perfect (the target's true position is the aim), so that only the navigation
(topside's estimate, its prediction along the way, the vehicle's drift) is measured; no whole dive.

For each seed: the default dive's lawnmower (as ``bench/navigation.py``: 256 m site at 30 m altitude
and 1 m/s after a 300 s descent; drift 0.005, heading bias 0.5 deg, 2 m at the bottom; the ship's
USBL 200 m south of the site, 1 % of the slant range, 2 % wild, every 10 s), statuses at the
vehicle's 4 of 6 TDMA slots of 20 s with 30 % lost. At the survey's end the operator has
``--lines`` aim points (drawn at random in the site, 20 m from its edges, each with a random
heading) and sends one 30 m camera line through each (0.3 m/s, transit 1 m/s, ``append``) by one
of two policies:

* ``all``: every line at once at the survey's end (the demo's operator until issue 56's third pass);
* ``ahead``: a line only when topside expects the vehicle to be done with the lines it was sent
  within ``--ahead`` seconds (its own estimate of when each line is flown: its transit at 1 m/s
  and the line's length at its speed, from the vehicle's reports of reaching each line's start).

A command reaches the vehicle at the end of topside's next slot (slots 0 and 3 of the cycle), or
a later one when lost (30 %). The vehicle flies its queue in its own frame
(``DeadReckoning.true_path``). Per line: how long it waited between being sent and flown, the miss
of its first point (the prediction against the vehicle's true error then) and ``cross_m``, the
closest distance of the true camera line to the aim point (what ``camera_pass_m`` measures with a
perfect map); and, to find where a miss comes from, ``live_m`` (topside's estimate against the
truth when the line was sent), ``true_change`` (how the vehicle's error changed from then to the
line's start) and ``pred_change`` (how the prediction moved the line's start from the estimate).
Written to ``bench/results/navigation_lines.json``.

Usage: ``python bench/navigation_lines.py [--seeds N] [--first S] [--policy all|ahead]
[--ahead S] [--lines K]`` (development seeds: 1000-1099 and 2000 and up).
"""

from __future__ import annotations

import argparse
import json
import math
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from navigation import survey_track  # bench/navigation.py: the same survey's true track

from coex.messages import SurveyCommand, VehicleMode, VehicleStatus
from coex_apps.demo.navigation import DeadReckoning, UsblTracker, track_positions
from coex_apps.demo.world import Leg
from coex_core.timefmt import to_stamp
from coex_plugins.navigation import LocalFrame, Navigation, VehicleFrameSurveys

VEHICLE = 2
CYCLE = 120.0
SLOT = 20.0
HALF = 15.0
LINE_SPEED = 0.3
TRANSIT = 1.0
LOSS = 0.3


@dataclass
class _Rx:
    """A stand-in survey receiver: it only numbers the commands."""

    sent: list[SurveyCommand] = field(default_factory=list)

    def request(self, kind: Any, x: float, y: float, now: float, *, points: Any = (), **kw: Any) -> SurveyCommand:
        cmd = SurveyCommand(command_id=len(self.sent) + 1, survey_id=len(self.sent) + 1, kind=kind, x=x, y=y,
                            heading=kw.get("heading"), length=kw.get("length"), altitude=kw.get("altitude"), speed=kw.get("speed"), append=True)
        self.sent.append(cmd)
        return cmd


def _status(t: float, x: float, y: float, heading: float) -> VehicleStatus:
    return VehicleStatus(stamp=to_stamp(t), x=x, y=y, depth=470.0, altitude=10.0, heading=heading % 360.0,
                         speed=1.0, battery=90, mode=VehicleMode(1), faults=0)


def one(seed: int, policy: str, ahead: float, n_lines: int) -> list[dict[str, Any]]:
    track, _ = survey_track(seed)
    end_survey = float(track.samples[-1][0])
    end = 7200.0
    dr = DeadReckoning(track, 0.0, 300.0, end, drift=0.005, heading_bias=0.5, seed_offset=2.0,
                       rng=np.random.default_rng([seed, 56]))
    usbl = UsblTracker((128.0, -200.0), LocalFrame(0.0, 0.0), sigma=0.01, outliers=0.02,
                       rng=np.random.default_rng([seed, 57]))
    rng = np.random.default_rng([seed, 59])
    aims = [(float(rng.uniform(20, 236)), float(rng.uniform(20, 236)), float(rng.uniform(0, 180)))
            for _ in range(n_lines)]
    nav = Navigation()
    nav.estimator(VEHICLE)
    rx = _Rx()
    view = VehicleFrameSurveys(rx, nav, VEHICLE)
    lost = np.random.default_rng([seed, 58])
    # the vehicle: commands arrived and not flown; what it flies now (until when)
    inbox: deque[tuple[SurveyCommand, float]] = deque()  # (command, arrival)
    flying: list[tuple[float, float, int]] = []  # (reached start, done, survey id)
    pending: list[tuple[SurveyCommand, float]] = []  # sent, not arrived: (command, sent)
    busy_until = -math.inf
    pos = (track.samples[-1][1], track.samples[-1][2])
    to_send = list(aims)
    sent_at: dict[int, tuple[float, float, float, FloatPair]] = {}
    reached: dict[int, float] = {}
    live: dict[int, Any] = {}
    planned_done = -math.inf  # topside's estimate of when the vehicle is done with its queue
    planned_pos: FloatPair | None = None
    rows = []
    heading = 0.0
    for now in np.arange(0.0, end, 10.0):
        now = float(now)
        # the vehicle
        if now > end_survey:
            if now >= busy_until and inbox:
                cmd, _ = inbox.popleft()
                if busy_until < now:  # held since its last line ended
                    track.legs.append(Leg(busy_until, now, pos, pos, 50.0))
                h = math.radians(float(cmd.heading or 0.0))
                wps = [(cmd.x, cmd.y), (cmd.x + 2 * HALF * math.sin(h), cmd.y + 2 * HALF * math.cos(h))]
                true = dr.true_path(now, pos, wps, [TRANSIT, LINE_SPEED])
                t1 = now + math.hypot(true[0][0] - pos[0], true[0][1] - pos[1]) / TRANSIT
                t2 = t1 + math.hypot(true[1][0] - true[0][0], true[1][1] - true[0][1]) / LINE_SPEED
                track.legs.append(Leg(now, t1, pos, true[0], 10.0))
                track.legs.append(Leg(t1, t2, true[0], true[1], 8.7, camera=True))
                flying.append((t1, t2, int(cmd.survey_id)))
                reached[int(cmd.survey_id)] = t1
                pos, busy_until = true[1], t2
            elif now >= busy_until:
                track.legs.append(Leg(busy_until if busy_until > end_survey else now, now + 10.0, pos, pos, 50.0))
                busy_until = now + 10.0 - 1e-6
        x, y = track_positions(track, np.array([now]))[0]
        e = dr.error(now)
        usbl.fix(now, VEHICLE, x, y, 470.0)
        nav.estimator(VEHICLE).add_fix(now, *usbl.log[-1][4:6])
        slot = int(now // SLOT) % 6
        if slot in (1, 2, 4, 5) and lost.random() > LOSS:
            p0 = track_positions(track, np.array([now - 10.0]))[0]  # the heading over the last 10 s
            if math.hypot(x - p0[0], y - p0[1]) > 0.5:
                heading = math.degrees(math.atan2(x - p0[0], y - p0[1])) + 0.5
            nav.status(VEHICLE, _status(now, x + e[0], y + e[1], heading), now)
        # commands arriving at the end of a topside slot (0, 3), each lost 30 %
        if slot in (0, 3) and now % SLOT == 10.0:
            for item in list(pending):
                if lost.random() > LOSS:
                    pending.remove(item)
                    inbox.append((item[0], now))
        # topside
        if now < end_survey + 30.0 or not to_send:
            continue
        # when the vehicle is done with what it was sent, as topside would know it
        if policy == "ahead":
            if planned_done - now > ahead:
                continue
        while to_send:
            ax, ay, hd = to_send.pop(0)
            h = math.radians(hd)
            start = (ax - HALF * math.sin(h), ay - HALF * math.cos(h))
            cmd = view.request("line", start[0], start[1], now, heading=hd, length=2 * HALF, altitude=8.7,
                               speed=LINE_SPEED, append=True)
            pending.append((cmd, now))
            c = view.sent[-1][2]
            sent_at[int(cmd.survey_id)] = (now, ax, ay, c)
            live[int(cmd.survey_id)] = (np.asarray(nav.estimate(VEHICLE, now)), dr.error(now))
            if planned_pos is None or planned_done < now:
                tr = nav.track(VEHICLE)
                planned_pos = nav.corrected(VEHICLE, float(tr[-1, 0]), float(tr[-1, 1]), float(tr[-1, 2]))
                planned_done = now + CYCLE / 4
            planned_done += math.hypot(start[0] - planned_pos[0], start[1] - planned_pos[1]) / TRANSIT
            planned_done += 2 * HALF / LINE_SPEED
            planned_pos = (start[0] + 2 * HALF * math.sin(h), start[1] + 2 * HALF * math.cos(h))
            if policy == "ahead":
                break
    legs = [leg for leg in track.legs if leg.camera]
    by_sid = {sid: legs[i] for i, (_, _, sid) in enumerate(flying)}
    for sid, (at, ax, ay, c) in sent_at.items():
        leg = by_sid.get(sid)
        if leg is None:
            continue
        (px, py), (qx, qy) = leg.p0, leg.p1
        dx, dy = qx - px, qy - py
        f = min(max(((ax - px) * dx + (ay - py) * dy) / (dx * dx + dy * dy), 0.0), 1.0)
        cross = math.hypot(px + f * dx - ax, py + f * dy - ay)
        e = dr.error(reached[sid])
        rows.append({"seed": seed, "survey_id": sid, "wait_s": round(reached[sid] - at, 1),
                     "start_miss_m": round(float(math.hypot(e[0] - c[0], e[1] - c[1])), 2),
                     "cross_m": round(cross, 2),
                     "live_m": round(float(np.hypot(*(live[sid][0] - live[sid][1]))), 2),
                     "true_change": [round(float(v), 2) for v in e - live[sid][1]],
                     "pred_change": [round(float(v), 2) for v in np.asarray(c) - live[sid][0]]})
    return rows


FloatPair = tuple[float, float]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--first", type=int, default=1000)
    ap.add_argument("--policy", choices=("all", "ahead"), default="all")
    ap.add_argument("--ahead", type=float, default=240.0)
    ap.add_argument("--lines", type=int, default=6)
    args = ap.parse_args()
    rows = [r for s in range(args.first, args.first + args.seeds) for r in one(s, args.policy, args.ahead, args.lines)]
    for r in rows:
        print(r)
    cross = np.array([r["cross_m"] for r in rows])
    miss = np.array([r["start_miss_m"] for r in rows])
    summary = {"policy": args.policy, "ahead": args.ahead, "lines": len(rows),
               "cross_median_m": round(float(np.median(cross)), 2), "cross_p90_m": round(float(np.percentile(cross, 90)), 2),
               "cross_max_m": round(float(cross.max()), 2), "cross_over_2m": int((cross > 2.0).sum()),
               "start_miss_median_m": round(float(np.median(miss)), 2),
               "wait_median_s": round(float(np.median([r["wait_s"] for r in rows])), 1)}
    print(json.dumps(summary))
    out = Path(__file__).parent / "results"
    out.mkdir(exist_ok=True)
    (out / "navigation_lines.json").write_text(json.dumps({"args": vars(args), "rows": rows, "summary": summary},
                                                          indent=2))


if __name__ == "__main__":
    main()
