"""The operator's map reading over simulated maps (issue 50): which targets of a quick dive's
site the scripted operator can identify in the received 1 m map, without running whole dives.

For each development seed and scene it builds the 1 m map topside holds at the end of the survey
the way ``bench/navigation_map.py``'s ``one()`` does (the site's seafloor and objects, the
lawnmower survey, the vehicle's drifting dead reckoning, topside's navigation; the whole map
delivered without loss, no aiding), then reads it with the operator's own ``operator.map_bumps``
(what ``run.py`` judges "identifiable at 1 m" on): a target is **identifiable** when a bump
scoring at least ``operator.MIN_SCORE`` lies within ``failures.identify_radius`` of it. It counts
per scene and kind the targets identifiable, the decoys with a candidate (the eye has to reject
those) and the **candidates with no object** (scoring bumps inside the survey box more than
``max(6, length / 2 + 3)`` m from every object: camera lines over bare sand).

Scenes (the ``--quick`` site, 96 m): ``default`` (the default preset: two random targets of every
kind), ``debris-decoys`` (two debris patches of 2-5 m and two random decoys,
``bench/scenarios/debris-decoys.toml``) and ``container-hull-car`` (the preset's three listed
targets). The survey is the quick dive's by default (a 120 s descent, 20 s turns:
they set the track and so the drift at each pass; ``--descent 300 --turn 60`` is
``navigation_map.py``'s); the map is not the dive's (the whole map delivered without loss, at
the end of the survey, navigation simulated as ``navigation_map.py`` does): it is the map
reading that is compared, on what such a map shows. Its absolute rates are not the dives'
(with the quick timing it misses containers and hulls the fresh-seed dives found, with
``navigation_map.py``'s it finds patches a development dive did not): compare rules with it,
not conditions.

Prints a table and writes ``bench/results/map_targets.json``. Development seeds only (1000-1099).

    python bench/map_targets.py [--seeds N] [--first-seed S] [--scenes default,debris-decoys,container-hull-car]
                                [--descent S --turn S] [--verbose]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

from navigation_map import one  # noqa: E402

from coex_apps.demo.config import DEVELOPMENT_SEEDS  # noqa: E402
from coex_apps.demo.failures import identify_radius  # noqa: E402
from coex_apps.demo.operator import MIN_SCORE, map_bumps  # noqa: E402
from coex_apps.demo.scenario import Scenario, load_scenario, preset  # noqa: E402
from coex_plugins.navigation import CorrectedMap  # noqa: E402

VEHICLE = 2
#: the quick dive's descent and turns (s; ``run.py``): they set the survey's track and so the
#: dead reckoning's drift at each pass
QUICK_DESCENT = 120.0
QUICK_TURN = 20.0


def scenes() -> dict[str, Scenario]:
    return {"default": preset("default").quick(),
            "debris-decoys": load_scenario(HERE / "scenarios" / "debris-decoys.toml").quick(),
            "container-hull-car": preset("container-hull-car").quick()}


def read_map(scn: Scenario, seed: int, descent: float = QUICK_DESCENT, turn: float = QUICK_TURN) -> dict[str, Any]:
    """One scene's map as the operator reads it: per target whether it is identifiable (and the
    best score near it), per decoy whether it has a candidate, and the candidates with no object."""
    keep: dict[str, Any] = {}
    one(seed, False, scn, keep=keep, descent=descent, turn_time=turn)
    targets, decoys = scn.place(seed)
    views = [v for v in map_bumps(CorrectedMap(keep["rx"], keep["nav"], VEHICLE))
             if 3.0 <= v.x <= scn.area - 3.0 and 3.0 <= v.y <= scn.area - 3.0 and v.score >= MIN_SCORE]

    def near(o: Any) -> list[Any]:
        return [v for v in views if math.hypot(v.x - o.x, v.y - o.y) <= identify_radius(o)]
    objs = targets + decoys
    alone = [v for v in views if all(math.hypot(v.x - o.x, v.y - o.y) > max(6.0, o.length / 2 + 3.0) for o in objs)]
    return {"seed": seed,
            "targets": [{"kind": t.kind, "length": t.length, "height": t.height, "identifiable": bool(near(t)),
                         "score": max((v.score for v in near(t)), default=None)} for t in targets],
            "decoys": [{"kind": d.kind, "length": d.length, "candidate": bool(near(d))} for d in decoys],
            "no_object": [{"x": v.x, "y": v.y, "height": v.height, "cells": v.cells, "score": v.score} for v in alone]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=30)
    ap.add_argument("--first-seed", type=int, default=DEVELOPMENT_SEEDS[0])
    ap.add_argument("--scenes", default="default,debris-decoys,container-hull-car")
    ap.add_argument("--descent", type=float, default=QUICK_DESCENT,
                    help="seconds of descent before the survey (the quick dive's 120; navigation_map.py's 300)")
    ap.add_argument("--turn", type=float, default=QUICK_TURN,
                    help="seconds per turn between survey lines (the quick dive's 20; navigation_map.py's 60)")
    ap.add_argument("--verbose", action="store_true")
    args = ap.parse_args()
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    if any(s not in DEVELOPMENT_SEEDS for s in seeds):
        print(f"note: seeds {seeds[0]}..{seeds[-1]} are not all development seeds")
    every = scenes()
    rows: dict[str, list[dict[str, Any]]] = {}
    summary: dict[str, Any] = {}
    for name in args.scenes.split(","):
        rows[name] = [read_map(every[name], s, args.descent, args.turn) for s in seeds]
        kinds: dict[str, list[int]] = {}
        for r in rows[name]:
            for t in r["targets"]:
                k = kinds.setdefault(t["kind"], [0, 0])
                k[0] += t["identifiable"]
                k[1] += 1
                if args.verbose and not t["identifiable"]:
                    print(f"  {name} {r['seed']}: {t['kind']} {t['length']} m long, {t['height']} m high: not identifiable")
            if args.verbose and r["no_object"]:
                print(f"  {name} {r['seed']}: candidates with no object {r['no_object']}")
        decoys = [d for r in rows[name] for d in r["decoys"]]
        summary[name] = {"dives": len(rows[name]), "identifiable": {k: f"{a}/{n}" for k, (a, n) in sorted(kinds.items())},
                         "decoys_with_candidate": f"{sum(d['candidate'] for d in decoys)}/{len(decoys)}",
                         "candidates_with_no_object": sum(len(r["no_object"]) for r in rows[name])}
        print(f"{name} (seeds {seeds[0]}-{seeds[-1]}): " + json.dumps(summary[name]), flush=True)
    out = HERE / "results"
    out.mkdir(exist_ok=True)
    (out / "map_targets.json").write_text(json.dumps({"seeds": [seeds[0], seeds[-1]], "descent": args.descent,
                                                      "turn": args.turn, "summary": summary,
                                                      "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
