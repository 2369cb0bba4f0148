"""``coex sweep``: many simulated dives on Dask (see docs/demo.md, "Sweeps")."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from coex import ConfigError


def _list(kind: type, what: str) -> Any:
    def parse(text: str) -> list[Any]:
        try:
            values = [kind(v.strip()) for v in text.split(",") if v.strip()]
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what}: expected comma-separated values, got {text!r}") from None
        if not values:
            raise argparse.ArgumentTypeError(f"{what}: no value given")
        return values
    return parse


def register(sub: Any) -> None:
    p = sub.add_parser(
        "sweep",
        help="run many simulated dives (coex demo) on Dask: success rates with 95 %% intervals, decision times",
        description="Runs N dives of coex demo per condition on a Dask cluster (a local one by default, "
        "or the scheduler at --scheduler), each at a fresh seed, and writes OUT/dives.csv (one row per "
        "dive), OUT/metrics.jsonl (each dive's metrics.json), OUT/summary.json (per condition: n, "
        "successes, success rate with its Wilson 95 % interval, decision time median and p90) and "
        "OUT/sweep.png as dives finish. Run it again with the same --out to resume. Conditions: each "
        "--preset and --scenario under every combination of the override lists (comma-separated).",
    )
    p.add_argument("--preset", type=_list(str, "--preset"), default=[], metavar="NAME[,NAME...]",
                   help="built-in scenarios (coex demo --preset); default: default (unless --scenario)")
    p.add_argument("--scenario", type=Path, action="append", default=[], metavar="FILE.toml",
                   help="a scenario file (repeat for more)")
    p.add_argument("--rate", type=_list(int, "--rate"), default=[], metavar="R[,R...]",
                   help="Micromodem packet rates (modem.rate)")
    p.add_argument("--loss-model", type=_list(str, "--loss-model"), default=[], metavar="M[,M...]",
                   help="loss models: independent, gilbert-elliott, range (loss.model)")
    p.add_argument("--loss", type=_list(float, "--loss"), default=[], metavar="P[,P...]",
                   help="loss levels in [0, 1) (loss.rate: independent or mean burst loss, floor of range loss)")
    p.add_argument("--slots", action="append", default=[], metavar="OWNER,OWNER,...",
                   help="a TDMA cycle, one owner per slot (topside, vehicle, camera), e.g. "
                        "topside,vehicle,vehicle,topside,vehicle,vehicle; repeat for more")
    p.add_argument("--vehicles", type=_list(int, "--vehicles"), default=[], metavar="N[,N...]",
                   help="1, or 2 (a mapping AUV and a camera vehicle: the second vehicle slot becomes "
                        "the camera vehicle's)")
    p.add_argument("--operator", type=_list(str, "--operator"), default=[], metavar="WHO[,WHO...]",
                   help="script (the scripted operator, default) or none")
    p.add_argument("--quick", action="store_true", help="the short dive (coex demo --quick) in every condition")
    p.add_argument("--dives", type=int, default=8, metavar="N", help="dives per condition (default 8)")
    p.add_argument("--seeds", type=_list(int, "--seeds"), default=None, metavar="S[,S...]",
                   help="these seeds instead of fresh ones (to reproduce dives; development seeds are "
                        "flagged, not for reporting)")
    p.add_argument("--out", type=Path, default=Path("coex-sweep-out"), help="output directory (default ./coex-sweep-out)")
    p.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                   help="an existing Dask scheduler (default: a local cluster on this machine)")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="local cluster: worker processes (default: one per CPU)")
    p.add_argument("--retry-failed", action="store_true",
                   help="run again the dives of --out that raised (otherwise a resumed sweep skips them)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from .conditions import Overrides, grid
    from .run import run_sweep

    if args.workers is not None and args.workers < 1:
        raise ConfigError("--workers must be at least 1")
    if args.dives < 1:
        raise ConfigError("--dives must be at least 1")
    slots = [[s.strip() for s in text.split(",") if s.strip()] for text in args.slots]
    bases = [*args.preset, *(str(s) for s in args.scenario)]
    for s in args.scenario:
        if not str(s).endswith(".toml"):
            raise ConfigError(f"--scenario {s}: a scenario file ends in .toml")
    conditions = grid(bases or ["default"],
                      Overrides(rate=args.rate, loss_model=args.loss_model, loss=args.loss, slots=slots,
                                vehicles=args.vehicles, operator=args.operator), quick=args.quick)
    result = run_sweep(conditions, args.dives, args.out, seeds=args.seeds, scheduler=args.scheduler,
                       workers=args.workers, retry_failed=args.retry_failed, progress=not args.quiet,
                       quiet_dask=not getattr(args, "verbose", 0))
    print(table(result.summary))
    print(f"outputs in {result.out}/ (dives.csv, summary.json, sweep.png); {result.ran} dive(s) run, "
          f"{result.skipped} skipped as done" + (f"; workers: {', '.join(result.workers)}" if result.workers else ""))
    return 130 if result.interrupted else 0


def table(summary: dict[str, Any]) -> str:
    """The summary as a Markdown table: n, successes, the rate and its Wilson 95 % interval,
    false confirmations, errors, decision time median and p90."""
    lines = ["| condition | n | successes | success rate (Wilson 95 %) | false conf. | errors "
             "| decision time median / p90 (min) |", "|---|---|---|---|---|---|---|"]
    for name, s in summary["conditions"].items():
        lo, hi = s["success_wilson95"]
        rate = "-" if s["success_rate"] is None else f"{s['success_rate']:.0%} [{lo:.2f}, {hi:.2f}]"
        d = s["decision_time_s"]
        dt = "-" if d["median"] is None else f"{d['median'] / 60:.1f} / {d['p90'] / 60:.1f}"
        lines.append(f"| {name} | {s['n']} | {s['successes']} | {rate} | {s['false_confirmations']} "
                     f"| {s['errors']} | {dt} |")
    return "\n".join(lines)

