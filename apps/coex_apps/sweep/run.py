"""Running a sweep on Dask: every (condition, seed) not yet in ``OUT/dives.csv`` is a task;
results are written as they complete (:func:`distributed.as_completed`), with a progress bar
and the Dask dashboard's address."""

from __future__ import annotations

import json
import os
import sys
import time
import uuid
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from coex import ConfigError

from .conditions import Condition, fresh_seeds, is_development_seed
from .dive import DiveOutcome, DiveSpec, error_row, run_dive
from .results import DiveTable, plot, write_summary

__all__ = ["SweepResult", "plan_seeds", "run_sweep"]

#: seconds between redraws of ``sweep.png`` while dives finish (it is drawn at the end too)
PLOT_EVERY = 15.0


@dataclass
class SweepResult:
    """A sweep's outcome: where it is, the seeds, the summary (as in ``summary.json``), every
    row of ``dives.csv``, and the dives run by this call (not skipped as done)."""

    out: Path
    seeds: list[int]
    summary: dict[str, Any]
    rows: list[dict[str, Any]]
    ran: int = 0
    skipped: int = 0
    interrupted: bool = False
    workers: list[str] = field(default_factory=list)


def plan_seeds(out: Path, conditions: Sequence[Condition], dives: int, seeds: Sequence[int] | None) -> list[int]:
    """The sweep's seeds: those given, else those of the sweep already in ``OUT/sweep.json``
    (a resumed sweep), topped up with fresh ones to ``dives``; records the plan in
    ``OUT/sweep.json``. A condition of a name already there must be the same set-up."""
    path = out / "sweep.json"
    plan: dict[str, Any] = json.loads(path.read_text()) if path.exists() else {}
    known: dict[str, str] = dict(plan.get("conditions", {}))
    for c in conditions:
        if c.name in known and known[c.name] != c.fingerprint():
            raise ConfigError(f"{out} holds a sweep whose condition {c.name!r} is another set-up; "
                              "use another --out")
        known[c.name] = c.fingerprint()
    if seeds is not None:
        chosen = list(dict.fromkeys(int(s) for s in seeds))
        if len(chosen) != len(seeds):
            raise ConfigError("seeds must be distinct")
    else:
        chosen = [int(s) for s in plan.get("seeds", [])][:dives]
        chosen += fresh_seeds(dives - len(chosen), avoid=chosen)
    all_seeds = list(dict.fromkeys([*plan.get("seeds", []), *chosen]))
    plan.update({"conditions": known, "seeds": all_seeds})
    tmp = out / "sweep.json.tmp"
    tmp.write_text(json.dumps(plan, indent=2))
    os.replace(tmp, path)
    return chosen


def _connect(stack: ExitStack, scheduler: str | None, workers: int | None) -> Any:
    """A Dask client: on the scheduler at ``scheduler``, or on a local cluster of ``workers``
    processes (default: one per CPU), each running one dive at a time."""
    try:
        from distributed import Client, LocalCluster
    except ImportError as exc:  # the [sweep] extra is not installed
        raise ConfigError(f"coex sweep needs Dask: pip install 'coexploration[sweep]' ({exc})") from exc
    if scheduler is not None:
        try:
            return stack.enter_context(Client(scheduler, timeout=30))  # type: ignore[no-untyped-call]
        except (OSError, TimeoutError) as exc:
            raise ConfigError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from exc
    n = workers or os.cpu_count() or 1
    cluster = stack.enter_context(LocalCluster(  # type: ignore[no-untyped-call]
        n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address="127.0.0.1:8787"))
    return stack.enter_context(Client(cluster))  # type: ignore[no-untyped-call]


def _quiet_dask() -> None:
    import logging

    for name in [n for n in logging.root.manager.loggerDict if n == "distributed" or n.startswith("distributed.")]:
        logging.getLogger(name).setLevel(logging.ERROR)


def _dashboard(client: Any) -> str | None:
    try:
        up = "dashboard" in client.scheduler_info().get("services", {})
    except Exception:
        return None
    return str(client.dashboard_link) if up else None


def run_sweep(conditions: Sequence[Condition], dives: int, out: Path, *, seeds: Sequence[int] | None = None,
              scheduler: str | None = None, workers: int | None = None, retry_failed: bool = False,
              progress: bool = True, client: Any = None, stream: TextIO | None = None,
              dive: Callable[[DiveSpec], DiveOutcome] = run_dive, quiet_dask: bool = True) -> SweepResult:
    """Run ``dives`` dives of every condition on Dask (``client``, else the scheduler at
    ``scheduler``, else a local cluster of ``workers`` processes), writing ``OUT/dives.csv``,
    ``OUT/metrics.jsonl``, ``OUT/summary.json`` and ``OUT/sweep.png`` as dives finish. Dives
    already in ``OUT/dives.csv`` are skipped (those that raised too, unless ``retry_failed``).
    A dive that raises is a row with its error; a dive whose worker dies is run again on
    another (the scheduler's ``allowed_failures``), and is a row with the error only when that
    fails too. Ctrl+C stops the sweep where it is (``interrupted``): run it again to resume.
    ``quiet_dask`` turns Dask's loggers down to errors (its INFO lines and closing chatter)."""
    from tqdm import tqdm

    stream = stream or sys.stderr
    if not conditions:
        raise ConfigError("a sweep needs at least one condition")
    if dives < 1 and seeds is None:
        raise ConfigError("a sweep needs at least one dive per condition")
    out.mkdir(parents=True, exist_ok=True)
    chosen = plan_seeds(out, conditions, dives, seeds)
    dev = [s for s in chosen if is_development_seed(s)]
    print(f"coex sweep: {len(conditions)} condition(s) x {len(chosen)} dive(s); seeds "
          f"{', '.join(str(s) for s in chosen)}", file=stream)
    if dev:
        print(f"coex sweep: warning: seed(s) {', '.join(map(str, dev))} are development seeds: "
              "not for reporting", file=stream)
    table = DiveTable(out)
    mine = {(c.name, s) for c in conditions for s in chosen}
    if retry_failed:
        table.forget([k for r in table.failed() if (k := (str(r["condition"]), int(r["seed"]))) in mine])
    names = {c.name: c.describe() for c in conditions}
    todo = [DiveSpec(c, s) for c in conditions for s in chosen if not table.done(c.name, s)]
    skipped = len(conditions) * len(chosen) - len(todo)
    if skipped:
        print(f"coex sweep: {skipped} dive(s) already in {out / 'dives.csv'}: skipped", file=stream)

    def rows() -> list[dict[str, Any]]:
        return [r for r in table.rows if (r["condition"], r["seed"]) in mine]

    extra = {"dives_per_condition": len(chosen)}
    title = f"coex sweep: {len(chosen)} dive(s) per condition" + (" (quick)" if any(c.quick for c in conditions) else "")
    summary = write_summary(out, names, rows(), chosen, extra)
    result = SweepResult(out, chosen, summary, rows(), skipped=skipped)
    if not todo:
        plot(summary, result.rows, out / "sweep.png", title)
        return result

    with ExitStack() as stack:
        from distributed import as_completed

        if quiet_dask:
            _quiet_dask()
        client = client if client is not None else _connect(stack, scheduler, workers)
        link = _dashboard(client)
        if link:
            print(f"coex sweep: Dask dashboard at {link}", file=stream)
        token = uuid.uuid4().hex[:8]
        futures = {}
        for i, spec in enumerate(todo):
            key = f"coex-dive-{token}-{i}"
            futures[key] = (client.submit(dive, spec, key=key, pure=False), spec)
        bar = stack.enter_context(tqdm(total=len(todo), unit="dive", file=stream, disable=not progress,
                                       dynamic_ncols=True))
        failed = 0
        last_plot = time.monotonic()
        seen_workers: set[str] = set()

        def postfix() -> None:
            try:  # a worker runs as many dives as it has threads; the scheduler may have sent it more
                threads = {a: int(w.get("nthreads", 1)) for a, w in client.scheduler_info()["workers"].items()}
                busy = sum(min(sum(1 for k in keys if k in futures), threads.get(a, 1))
                           for a, keys in client.processing().items())
            except Exception:
                busy = -1
            rates = []
            for name in names:
                rs = [r for r in table.rows if r["condition"] == name and (name, r["seed"]) in mine]
                if rs:
                    rates.append(f"{name}: {sum(1 for r in rs if r.get('success') is True)}/{len(rs)}")
            bar.set_postfix_str(f"running {busy if busy >= 0 else '?'}, failed {failed}"
                                + ("; " + "; ".join(rates) if rates else ""), refresh=True)

        postfix()
        try:
            for fut in as_completed([f for f, _ in futures.values()]):  # type: ignore[no-untyped-call]
                _, spec = futures[fut.key]
                if fut.status == "error":  # the worker died too often, or the task could not run
                    exc = fut.exception()
                    outcome = DiveOutcome(error_row(spec.condition.name, spec.seed,
                                                    f"{type(exc).__name__}: {exc}"))
                else:
                    outcome = fut.result()
                fut.release()
                table.add(outcome)
                row = outcome.row
                seen_workers.add(str(row.get("worker") or ""))
                if row.get("error"):
                    failed += 1
                    verdict = f"ERROR {row['error']}"
                else:
                    verdict = "ok" if row["success"] else "FAIL"
                    if row.get("false_confirmations"):
                        verdict += f", {row['false_confirmations']} false confirmation(s)"
                bar.write(f"  {row['condition']} seed {row['seed']}: {verdict} "
                          f"({row.get('wall_s') or '-'} s on {row.get('worker') or '?'})", file=stream)
                bar.update(1)
                result.ran += 1
                summary = write_summary(out, names, rows(), chosen, extra)
                if time.monotonic() - last_plot > PLOT_EVERY:
                    plot(summary, rows(), out / "sweep.png", title)
                    last_plot = time.monotonic()
                postfix()
        except KeyboardInterrupt:
            result.interrupted = True
            client.cancel([f for f, _ in futures.values()])
            print(f"\ncoex sweep: interrupted; run it again with --out {out} to resume "
                  f"({result.ran + skipped} of {len(conditions) * len(chosen)} dives done)", file=stream)
    result.rows = rows()
    result.summary = write_summary(out, names, result.rows, chosen, extra)
    result.workers = sorted(w for w in seen_workers if w)
    plot(result.summary, result.rows, out / "sweep.png", title)
    return result
