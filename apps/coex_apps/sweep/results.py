"""A sweep's results as data, written as dives finish: ``dives.csv`` (one row per dive),
``metrics.jsonl`` (each dive's ``metrics.json``, one line), ``errors/`` (the traceback of each
dive that raised), ``summary.json`` (per condition: n, successes, the success rate with its
Wilson 95 % interval, false confirmations, decision time) and ``sweep.png``."""

from __future__ import annotations

import csv
import json
import math
import os
import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from coex import ConfigError

from .dive import DiveOutcome

__all__ = ["COLUMNS", "DiveTable", "plot", "summarise", "wilson_interval", "write_summary"]

#: the columns of dives.csv, in order; each goal of the demo follows ``success`` as ``goal: NAME``
COLUMNS = ("condition", "seed", "success", "false_confirmations", "targets", "targets_confirmed",
           "decision_time_s", "decision_time_worst_s", "decision_times_s", "bytes_delivered", "wall_s",
           "worker", "error")
_INTS = {"seed", "false_confirmations", "targets", "targets_confirmed", "bytes_delivered"}
_FLOATS = {"decision_time_s", "decision_time_worst_s", "wall_s"}
#: z of a two-sided 95 % interval
Z95 = 1.959963984540054


def wilson_interval(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """The Wilson score interval of a success rate (``successes`` of ``n``; 95 % by default):
    centre ``(p + z²/2n) / (1 + z²/n)``, half-width ``z·sqrt(p(1-p)/n + z²/4n²) / (1 + z²/n)``.
    8 of 8 gives (0.676, 1.0). No dives: (0, 1)."""
    if n <= 0:
        return 0.0, 1.0
    if not 0 <= successes <= n:
        raise ValueError(f"{successes} successes of {n}")
    p = successes / n
    d = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / d
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    lo = 0.0 if successes == 0 else max(0.0, centre - half)  # exact at the ends (no rounding dust)
    hi = 1.0 if successes == n else min(1.0, centre + half)
    return lo, hi


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    return str(v)


def _parse(col: str, text: str) -> Any:
    if text == "":
        return "" if col in ("error", "worker", "decision_times_s", "condition") else None
    if col in _INTS:
        return int(text)
    if col in _FLOATS:
        return float(text)
    if col == "success" or col.startswith("goal: "):
        if text not in ("true", "false"):
            raise ValueError(f"{col}: {text!r}")
        return text == "true"
    return text


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9.=-]+", "_", text).strip("_")[:80] or "condition"


class DiveTable:
    """``OUT/dives.csv`` and ``OUT/metrics.jsonl``, kept as dives finish: :meth:`add` appends a
    dive (and rewrites the file whole, atomically, when a row brings a column the header lacks,
    e.g. a goal). Opening it reads what an earlier, interrupted run of the same sweep wrote (a
    torn last line is dropped), so that run's dives are :meth:`done`."""

    def __init__(self, out: Path) -> None:
        self.out = out
        self.csv = out / "dives.csv"
        self.jsonl = out / "metrics.jsonl"
        self.rows: list[dict[str, Any]] = []
        self.columns: list[str] = list(COLUMNS)
        self._index: dict[tuple[str, int], int] = {}
        self.dropped = 0
        self._load()

    # ------------------------------------------------------------------ reading
    def _load(self) -> None:
        if not self.csv.exists():
            return
        with self.csv.open(newline="") as fh:
            reader = csv.reader(fh)
            header = next(reader, None)
            if header is None:
                return
            if header[:2] != ["condition", "seed"]:
                raise ConfigError(f"{self.csv} is not a sweep's dives.csv (its header is {header[:3]})")
            self.columns = list(header)
            for cells in reader:
                try:
                    if len(cells) != len(header):
                        raise ValueError("torn row")
                    row = {col: _parse(col, text) for col, text in zip(header, cells, strict=True)}
                except ValueError:
                    self.dropped += 1
                    continue
                self._put(row)
        if self.dropped:  # a torn line of an interrupted run: rewrite the table without it
            self._rewrite()

    def _put(self, row: dict[str, Any]) -> None:
        key = (str(row["condition"]), int(row["seed"]))
        if key in self._index:
            self.rows[self._index[key]] = row
        else:
            self._index[key] = len(self.rows)
            self.rows.append(row)

    def done(self, condition: str, seed: int) -> bool:
        return (condition, seed) in self._index

    def failed(self) -> list[dict[str, Any]]:
        return [r for r in self.rows if r.get("error")]

    def forget(self, keys: Iterable[tuple[str, int]]) -> None:
        """Drop these dives (to run them again), and rewrite the table without them."""
        drop = set(keys)
        self.rows = [r for r in self.rows if (r["condition"], r["seed"]) not in drop]
        self._index = {(r["condition"], r["seed"]): i for i, r in enumerate(self.rows)}
        self._rewrite()

    def metrics(self) -> dict[tuple[str, int], dict[str, Any]]:
        """Each finished dive's ``metrics.json`` (from ``metrics.jsonl``; the last of a dive run
        twice), for the dives in the table."""
        out: dict[tuple[str, int], dict[str, Any]] = {}
        if not self.jsonl.exists():
            return out
        with self.jsonl.open() as fh:
            for line in fh:
                try:
                    rec = json.loads(line)
                    key = (str(rec["condition"]), int(rec["seed"]))
                except (ValueError, KeyError, TypeError):
                    continue  # a torn last line
                if key in self._index:
                    out[key] = rec["metrics"]
        return out

    # ------------------------------------------------------------------ writing
    def add(self, outcome: DiveOutcome) -> None:
        row = outcome.row
        for col in row:
            if col not in self.columns:
                grow = True
                break
        else:
            grow = False
        if grow:
            goals = [c for c in row if c.startswith("goal: ") and c not in self.columns]
            at = self.columns.index("success") + 1
            while at < len(self.columns) and self.columns[at].startswith("goal: "):
                at += 1
            self.columns[at:at] = goals
            self.columns += [c for c in row if c not in self.columns]
        replaced = self.done(str(row["condition"]), int(row["seed"]))
        self._put(row)
        if grow or replaced or not self.csv.exists():
            self._rewrite()
        else:
            with self.csv.open("a", newline="") as fh:
                csv.writer(fh).writerow([_cell(row.get(c)) for c in self.columns])
        if outcome.metrics is not None:
            with self.jsonl.open("a") as fh:
                fh.write(json.dumps({"condition": row["condition"], "seed": row["seed"],
                                     "metrics": outcome.metrics}, separators=(",", ":"), default=str) + "\n")
        if outcome.traceback:
            errors = self.out / "errors"
            errors.mkdir(exist_ok=True)
            (errors / f"{_slug(str(row['condition']))}_{row['seed']}.txt").write_text(outcome.traceback)

    def _rewrite(self) -> None:
        tmp = self.csv.with_suffix(".csv.tmp")
        with tmp.open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(self.columns)
            for r in self.rows:
                w.writerow([_cell(r.get(c)) for c in self.columns])
        os.replace(tmp, self.csv)


# ---------------------------------------------------------------------------- summary

def _percentile(values: Sequence[float], q: float) -> float | None:
    return None if not values else round(float(np.percentile(np.asarray(values, float), q)), 1)


def summarise(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """One condition's dives: ``n`` (every dive run, those that raised included: a dive that
    did not finish is not a success), ``successes``, ``errors``, ``success_rate`` and its Wilson
    95 % interval ``success_wilson95`` ``[low, high]``, false confirmations (in all and dives
    with one), each goal's count, decision time over every target of the dives that has one
    (median and p90, s, with the targets without one), and the dives' wall time."""
    n = len(rows)
    ok = sum(1 for r in rows if r.get("success") is True)
    lo, hi = wilson_interval(ok, n)
    times = [float(t) for r in rows for t in str(r.get("decision_times_s") or "").split(";") if t != ""]
    missing = sum(1 for r in rows for t in str(r.get("decision_times_s") or "").split(";")
                  if t == "" and r.get("targets"))
    walls = [float(r["wall_s"]) for r in rows if r.get("wall_s") is not None and not r.get("error")]
    goals = sorted({c for r in rows for c in r if c.startswith("goal: ")})
    return {
        "n": n, "successes": ok, "errors": sum(1 for r in rows if r.get("error")),
        "success_rate": round(ok / n, 4) if n else None,
        "success_wilson95": [round(lo, 4), round(hi, 4)],
        "false_confirmations": sum(int(r.get("false_confirmations") or 0) for r in rows),
        "dives_with_false_confirmation": sum(1 for r in rows if (r.get("false_confirmations") or 0) > 0),
        "goals": {g[len("goal: "):]: sum(1 for r in rows if r.get(g) is True) for g in goals},
        "decision_time_s": {"median": _percentile(times, 50), "p90": _percentile(times, 90),
                            "targets": len(times), "missing": missing},
        "wall_s": {"median": _percentile(walls, 50), "mean": round(sum(walls) / len(walls), 1) if walls else None},
        "seeds": sorted(int(r["seed"]) for r in rows),
    }


def write_summary(out: Path, conditions: dict[str, dict[str, Any]], rows: Sequence[dict[str, Any]],
                  seeds: Sequence[int], extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """``OUT/summary.json``: per condition (in the sweep's order) its :func:`summarise` and
    what it is; the seeds; how the interval is computed. Written whole, atomically."""
    by: dict[str, list[dict[str, Any]]] = {name: [] for name in conditions}
    for r in rows:
        by.setdefault(str(r["condition"]), []).append(r)
    summary = {
        "interval": "Wilson score interval, 95 % (z = 1.96); n counts every dive run, a dive that "
                    "raised as not a success",
        "decision_time": "from a target identifiable at 1 m topside to its confirming image, over every "
                         "target of the condition's dives that has one (median and p90, s)",
        "seeds": list(seeds),
        **(extra or {}),
        "conditions": {name: {**summarise(rs), "condition": conditions.get(name)} for name, rs in by.items()},
    }
    tmp = out / "summary.json.tmp"
    tmp.write_text(json.dumps(summary, indent=2, default=str))
    os.replace(tmp, out / "summary.json")
    return summary


def plot(summary: dict[str, Any], rows: Sequence[dict[str, Any]], path: Path, title: str = "") -> None:
    """The sweep's figure: per condition, the success rate with its Wilson 95 % interval (and
    n), and the decision time of every target (each dot one target, the median a bar)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    conds = list(summary["conditions"])
    k = max(len(conds), 1)
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, max(2.4, 1.2 + 0.45 * k)), sharey=True,
                                   gridspec_kw={"width_ratios": [1, 1.3]})
    y = np.arange(len(conds))[::-1]
    for yi, name in zip(y, conds, strict=True):
        s = summary["conditions"][name]
        lo, hi = s["success_wilson95"]
        rate = s["success_rate"]
        if rate is not None:
            ax1.errorbar([rate], [yi], xerr=[[rate - lo], [hi - rate]], fmt="o", color="tab:blue", capsize=4)
            ax1.annotate(f"{s['successes']}/{s['n']}", (hi, yi), xytext=(6, 0), textcoords="offset points",
                         va="center", fontsize=8)
        times = [float(t) / 60 for r in rows if r["condition"] == name
                 for t in str(r.get("decision_times_s") or "").split(";") if t != ""]
        if times:
            jitter = np.linspace(-0.15, 0.15, len(times)) if len(times) > 1 else np.zeros(1)
            ax2.scatter(times, yi + jitter, s=10, color="tab:orange", alpha=0.7)
            ax2.plot([float(np.median(times))] * 2, [yi - 0.3, yi + 0.3], color="black", lw=2)
    ax1.set_yticks(y, conds, fontsize=8)
    ax1.set_xlim(0, 1.12)
    ax1.set_xlabel("success rate (Wilson 95 % interval)")
    ax1.grid(axis="x", alpha=0.3)
    ax2.set_xlabel("decision time per target (min; bar: median)")
    ax2.set_xlim(left=min(0.0, ax2.get_xlim()[0]))
    ax2.grid(axis="x", alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    tmp = path.with_name(path.stem + ".tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, path)
