"""Navigation in whole dives (issue 56): the same ``coex demo`` dive with the correction on and
off (``--no-correction``), and what ``metrics.json`` ``navigation`` says of it against the truth.

For each preset and seed it runs ``coex demo --preset P --seed S [--quick] --quiet`` twice (the
correction on, then off) into ``bench/results/navigation_dives/<preset>-<seed>-<on|off>/``,
skipping a dive whose ``metrics.json`` is already there (so an interrupted run resumes, and dives
run by hand into that layout are collected), and writes one row per dive to
``bench/results/navigation_dives.json``: the preset, seed and correction; the dive's success; the
drift at the end; per true target ``map_error_m`` and ``camera_pass_m``; the estimate against the
truth (median, 95th percentile, worst; wild fixes used); per camera line the miss of its first
point (``lines[].start_miss_m``); and the issue's targets judged per dive (every target's map
error and camera pass at most 2.0 m, the dive a success). ``--collect DIR ...`` adds dives run
elsewhere (each a demo output directory, its name ``<label>-<seed>-<on|off>``) without running
anything.

Development seeds only (the project's navigation seeds are 2000 and up; never the reported ones).
The dives run one at a time (``--jobs`` for more): a full dive takes 5-15 minutes on the 2-core
machine.

Usage: ``python bench/navigation_dives.py [--seeds 2003,2008] [--presets default,lowrate]
[--quick] [--jobs 1] [--collect DIR ...]``
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "bench" / "results"
#: the issue's bound on every target's map error and camera pass (m)
BOUND = 2.0


def run(preset: str, seed: int, correction: bool, quick: bool, base: Path) -> Path:
    """One dive into ``base/<preset>-<seed>-<on|off>`` unless it is there already."""
    out = base / f"{preset}-{seed}-{'on' if correction else 'off'}"
    if (out / "metrics.json").exists():
        return out
    exe = Path(sys.executable).with_name("coex")  # the console script beside this interpreter
    cmd = [str(exe), "demo", "--preset", preset, "--seed", str(seed), "--out", str(out), "--quiet"]
    if quick:
        cmd.append("--quick")
    if not correction:
        cmd.append("--no-correction")
    subprocess.run(cmd, check=False, cwd=ROOT)
    return out


def row(out: Path) -> dict[str, Any] | None:
    """What a dive's ``metrics.json`` says of its navigation (None: no metrics there)."""
    path = out / "metrics.json"
    if not path.exists():
        return None
    m = json.loads(path.read_text())
    nav = m.get("navigation") or {}
    label, seed, mode = out.name.rsplit("-", 2)
    targets = nav.get("targets") or []
    maps = [t.get("map_error_m") for t in targets]
    cams = [t.get("camera_pass_m") for t in targets]
    est: dict[str, Any] = next(iter((nav.get("estimate") or {}).values()), {})
    lines = nav.get("lines") or []

    def within(values: list[float | None]) -> bool:
        return bool(values) and all(v is not None and v <= BOUND for v in values)

    return {"dive": out.name, "preset": label, "seed": int(seed), "correction": mode == "on",
            "quick": bool((m.get("config") or {}).get("quick", False)), "success": bool(m.get("success")),
            "drift_at_end_m": nav.get("drift_at_end_m"), "map_error_m": maps, "camera_pass_m": cams,
            "estimate_median_m": est.get("error_median_m"), "estimate_p95_m": est.get("error_p95_m"),
            "estimate_max_m": est.get("error_max_m"), "wild_used": est.get("wild_used"),
            "line_start_miss_m": [ln.get("start_miss_m") for ln in lines],
            "map_within_2m": within(maps), "camera_within_2m": within(cams),
            "targets_met": bool(m.get("success")) and within(maps) and within(cams)}


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--seeds", default="", help="comma-separated development seeds (2000 and up)")
    ap.add_argument("--presets", default="default")
    ap.add_argument("--quick", action="store_true", help="the demo's short scenario")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--collect", nargs="*", type=Path, default=[], help="demo output directories to add")
    ap.add_argument("--json", type=Path, default=OUT / "navigation_dives.json")
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    if any(s < 2000 for s in seeds):
        ap.error("development seeds are 2000 and up")
    base = OUT / "navigation_dives"
    jobs = [(p, s, c) for p in args.presets.split(",") for s in seeds for c in (True, False)]
    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        dirs = list(pool.map(lambda j: run(j[0], j[1], j[2], args.quick, base), jobs))
    rows = [r for r in (row(d) for d in [*dirs, *args.collect]) if r is not None]
    for r in rows:
        print(json.dumps(r), flush=True)
    on = [r for r in rows if r["correction"]]
    summary = {"dives": len(rows), "with_correction": len(on),
               "targets_met_with_correction": sum(r["targets_met"] for r in on),
               "map_within_2m_with_correction": sum(r["map_within_2m"] for r in on),
               "camera_within_2m_with_correction": sum(r["camera_within_2m"] for r in on)}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"bound_m": BOUND, "rows": rows, "summary": summary}, indent=2))
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
