"""One dive of a sweep, as a Dask task: :func:`run_dive` runs ``coex demo`` at a seed in a
scratch directory and returns its row of ``dives.csv`` and its ``metrics.json``; a dive that
raises returns a row with its error instead (and its traceback), never the exception."""

from __future__ import annotations

import math
import statistics
import tempfile
import threading
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .conditions import Condition

__all__ = ["DiveOutcome", "DiveSpec", "error_row", "row_from_metrics", "run_dive", "worker_name"]

#: one dive at a time in a worker process: the imagery codec's scratch files and caches are the
#: process's (start workers with ``--nthreads 1``; a worker with more threads runs its dives in
#: turn instead of side by side)
_ONE_AT_A_TIME = threading.Lock()


@dataclass(frozen=True)
class DiveSpec:
    """What a worker needs to run one dive."""

    condition: Condition
    seed: int


@dataclass
class DiveOutcome:
    """What a dive gives back: its row (:data:`~coex_apps.sweep.results.COLUMNS`, ``goal: NAME``
    per goal), its ``metrics.json`` (``None`` if it raised) and the traceback of its error."""

    row: dict[str, Any]
    metrics: dict[str, Any] | None = None
    traceback: str | None = None


def worker_name() -> str:
    """The Dask worker running this task (its ``--name``, else its address); ``local`` outside
    a worker."""
    try:
        from distributed import get_worker

        w = get_worker()
    except (ImportError, ValueError):
        return "local"
    return str(w.name if w.name is not None else w.address)


def _num(v: Any) -> float | None:
    return None if v is None or (isinstance(v, float) and not math.isfinite(v)) else float(v)


def row_from_metrics(condition: str, seed: int, m: dict[str, Any], wall: float, worker: str) -> dict[str, Any]:
    """A dive's row from its ``metrics.json``: success, each goal, false confirmations, the
    targets (and how many were confirmed), decision time (median and worst over the dive's
    targets, and each target's, ``;``-separated, empty where a target has none), the bytes
    topside received, the wall time and the worker."""
    targets = m.get("targets", [])
    times = [_num(t.get("decision_time_s")) for t in targets]
    have = [t for t in times if t is not None]
    row: dict[str, Any] = {
        "condition": condition, "seed": seed, "success": bool(m["success"]),
        "false_confirmations": len(m.get("false_confirmations", [])),
        "targets": len(targets),
        "targets_confirmed": sum(1 for t in targets if t.get("confirmation") is not None),
        "decision_time_s": statistics.median(have) if have else None,
        "decision_time_worst_s": max(have) if have else None,
        "decision_times_s": ";".join("" if t is None else f"{t:g}" for t in times),
        "bytes_delivered": int(m.get("link", {}).get("delivered_bytes") or 0),
        "wall_s": round(wall, 2), "worker": worker, "error": "",
    }
    for name, goal in m.get("goals", {}).items():
        row[f"goal: {name}"] = bool(goal["met"])
    return row


def error_row(condition: str, seed: int, error: str, wall: float | None = None, worker: str = "") -> dict[str, Any]:
    """The row of a dive that did not finish: its error, no results."""
    return {"condition": condition, "seed": seed, "success": None, "false_confirmations": None,
            "targets": None, "targets_confirmed": None, "decision_time_s": None,
            "decision_time_worst_s": None, "decision_times_s": "", "bytes_delivered": None,
            "wall_s": None if wall is None else round(wall, 2), "worker": worker,
            "error": " ".join(error.split()) or "error"}


def run_dive(spec: DiveSpec) -> DiveOutcome:
    """Run one dive (``coex demo`` at ``spec.seed`` on ``spec.condition``'s scenario, no
    progress output, in a scratch directory removed afterwards). An exception becomes the
    outcome's error row."""
    from coex_apps.demo import DemoConfig, run_demo

    c = spec.condition
    worker = worker_name()
    with _ONE_AT_A_TIME:
        t0 = time.perf_counter()
        try:
            with tempfile.TemporaryDirectory(prefix="coex-sweep-") as tmp:
                # one dive per core: its image coding in its own thread
                result = run_demo(DemoConfig(out=Path(tmp), seed=spec.seed, quick=c.quick, progress=False,
                                             scenario=c.scenario, operator=c.operator, codec_threads=0))
        except Exception as exc:
            wall = time.perf_counter() - t0
            return DiveOutcome(error_row(c.name, spec.seed, f"{type(exc).__name__}: {exc}", wall, worker),
                               traceback=traceback.format_exc())
        wall = time.perf_counter() - t0
    return DiveOutcome(row_from_metrics(c.name, spec.seed, result.metrics, wall, worker), result.metrics)
