"""`coex sweep`: conditions and seeds, the results table (resume, torn lines), Wilson
intervals, and a sweep on a real Dask scheduler with two worker processes, one of them killed
mid-sweep: every dive is in the table once, a dive that raised is a row with its error."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from coex import ConfigError
from coex_apps.demo.scenario import preset
from coex_apps.sweep import (
    Condition,
    DiveOutcome,
    DiveSpec,
    DiveTable,
    Overrides,
    fresh_seeds,
    grid,
    is_development_seed,
    run_sweep,
    summarise,
    wilson_interval,
)
from coex_apps.sweep import conditions as conditions_module
from coex_apps.sweep.dive import error_row, row_from_metrics

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "tests" / "fixtures" / "sweep-tiny.toml"


# ---------------------------------------------------------------------------- statistics

def test_wilson_interval_matches_the_reference() -> None:
    lo, hi = wilson_interval(8, 8)  # ../shared/reference/evaluation-coding-scale.md: [0.68, 1.00]
    assert round(lo, 2) == 0.68 and hi == 1.0
    lo, hi = wilson_interval(0, 3)
    assert lo == 0.0 and round(hi, 3) == 0.561
    lo, hi = wilson_interval(5, 10)
    assert round(lo, 3) == 0.237 and round(hi, 3) == 0.763
    assert wilson_interval(0, 0) == (0.0, 1.0)
    with pytest.raises(ValueError):
        wilson_interval(4, 3)


def test_summary_counts_errors_as_dives_that_did_not_succeed() -> None:
    ok = row_from_metrics("c", 1001, _metrics(True, [300.0, 600.0]), 1.0, "w1")
    bad = row_from_metrics("c", 1002, _metrics(False, [900.0, None]), 1.0, "w2")
    err = error_row("c", 1003, "RuntimeError: boom")
    s = summarise([ok, bad, err])
    assert (s["n"], s["successes"], s["errors"]) == (3, 1, 1)
    assert s["success_wilson95"] == [round(x, 4) for x in wilson_interval(1, 3)]
    assert s["decision_time_s"] == {"median": 600.0, "p90": 840.0, "targets": 3, "missing": 1}
    assert s["false_confirmations"] == 1 and s["dives_with_false_confirmation"] == 1


# ---------------------------------------------------------------------------- conditions, seeds

def test_fresh_seeds_are_distinct_and_never_development_seeds(monkeypatch: pytest.MonkeyPatch) -> None:
    seeds = fresh_seeds(200)
    assert len(set(seeds)) == 200 and not any(is_development_seed(s) for s in seeds)
    drawn = iter([5, 101, 5000, 5000, 1, 7777])  # development seeds and a repeat are drawn again
    monkeypatch.setattr(conditions_module.secrets, "randbelow", lambda n: next(drawn))
    assert fresh_seeds(2) == [5000, 7777]
    assert is_development_seed(1) and is_development_seed(101) and not is_development_seed(123456)


def test_grid_expands_presets_and_files_by_the_overrides() -> None:
    conds = grid(["default", str(TINY)], Overrides(rate=[1, 5], loss=[0.3, 0.6], vehicles=[1, 2]))
    assert len(conds) == 16
    names = [c.name for c in conds]
    assert names[0] == "default rate=1 loss=0.3 vehicles=1" and "sweep-tiny rate=5 loss=0.6 vehicles=2" in names
    c = next(c for c in conds if c.name == "default rate=1 loss=0.6 vehicles=2")
    assert c.scenario.modem_rate == 1 and c.scenario.loss.rate == 0.6
    assert c.scenario.slots == preset("fleet").slots  # two vehicles on the NUI cycle: preset fleet's
    one = grid(["fleet"], Overrides(vehicles=[1]))[0]
    assert "camera" not in one.scenario.slots and not one.scenario.fleet
    g = grid(["lowrate"], Overrides(loss_model=["gilbert-elliott"], operator=["none"],
                                    slots=[["topside", "vehicle", "vehicle", "vehicle"]]), quick=True)[0]
    assert g.name == "lowrate model=gilbert-elliott slots=topside,vehicle,vehicle,vehicle operator=none"
    assert g.scenario.loss.model == "gilbert-elliott" and g.operator == "none" and g.quick
    assert len(g.scenario.slots) == 4
    assert grid(["default"])[0].name == "default"
    for bad in (Overrides(loss=[1.5]), Overrides(vehicles=[3]), Overrides(loss_model=["fog"]),
                Overrides(slots=[["topside", "ship"]]), Overrides(operator=["robot"])):
        with pytest.raises(ConfigError):
            grid(["default"], bad)
    with pytest.raises(ConfigError):
        grid(["nosuchpreset"])
    with pytest.raises(ConfigError):
        grid(["default", "default"])  # two conditions of one name


# ---------------------------------------------------------------------------- the table

def _metrics(success: bool, times: list[float | None]) -> dict[str, Any]:
    return {"success": success, "false_confirmations": [] if success else [{"x": 1}],
            "targets": [{"decision_time_s": t, "confirmation": {} if t is not None else None} for t in times],
            "link": {"delivered_bytes": 1234},
            "goals": {"g one": {"met": success}, "g two": {"met": True}}}


def test_table_resumes_and_drops_a_torn_line(tmp_path: Path) -> None:
    t = DiveTable(tmp_path)
    t.add(DiveOutcome(row_from_metrics("a b", 11, _metrics(True, [60.0]), 2.0, "w1"), _metrics(True, [60.0])))
    t.add(DiveOutcome(error_row("a b", 12, "ValueError: no\nmore"), traceback="Traceback ...\n"))
    with (tmp_path / "dives.csv").open("a") as fh:  # an interrupted write
        fh.write("a b,13,tr")
    again = DiveTable(tmp_path)
    assert again.dropped == 1 and again.done("a b", 11) and again.done("a b", 12) and not again.done("a b", 13)
    rows = list(csv.DictReader((tmp_path / "dives.csv").open()))
    assert [r["seed"] for r in rows] == ["11", "12"]
    assert rows[0]["goal: g one"] == "true" and rows[0]["success"] == "true" and rows[0]["worker"] == "w1"
    assert rows[1]["error"] == "ValueError: no more" and rows[1]["success"] == ""
    assert (tmp_path / "errors" / "a_b_12.txt").read_text().startswith("Traceback")
    assert list(again.metrics()) == [("a b", 11)]
    assert again.rows[0]["success"] is True and again.rows[0]["decision_time_s"] == 60.0
    again.forget([("a b", 12)])
    assert [r["seed"] for r in DiveTable(tmp_path).rows] == [11]


# ---------------------------------------------------------------------------- a sweep in-process

def fake_dive(spec: DiveSpec) -> DiveOutcome:
    """A stand-in dive: succeeds on even seeds; seed 1003 raises (outside the dive's own guard,
    as a task that fails on its worker would)."""
    if spec.seed == 1003:
        raise RuntimeError("worker-side failure")
    m = _metrics(spec.seed % 2 == 0, [120.0, 240.0])
    return DiveOutcome(row_from_metrics(spec.condition.name, spec.seed, m, 0.1, "fake"), m)


def test_sweep_writes_as_it_goes_and_resumes(tmp_path: Path) -> None:
    distributed = pytest.importorskip("distributed")
    conds = [Condition("one", preset("default")), Condition("two", preset("lowrate"))]
    out = tmp_path / "out"
    with distributed.Client(processes=False, n_workers=1, threads_per_worker=1, dashboard_address=None) as client:
        r = run_sweep(conds, 0, out, seeds=[1002, 1003, 1004], client=client, progress=False, dive=fake_dive)
        assert (r.ran, r.skipped) == (6, 0)
        rows = list(csv.DictReader((out / "dives.csv").open()))
        assert sorted((x["condition"], x["seed"]) for x in rows) == sorted(
            (c, s) for c in ("one", "two") for s in ("1002", "1003", "1004"))
        failed = [x for x in rows if x["error"]]
        assert [x["seed"] for x in failed] == ["1003", "1003"] and "worker-side failure" in failed[0]["error"]
        summary = json.loads((out / "summary.json").read_text())
        one = summary["conditions"]["one"]
        assert (one["n"], one["successes"], one["errors"]) == (3, 2, 1)
        assert one["success_wilson95"] == [round(x, 4) for x in wilson_interval(2, 3)]
        assert one["decision_time_s"]["median"] == 180.0 and summary["seeds"] == [1002, 1003, 1004]
        assert (out / "sweep.png").stat().st_size > 0
        # run again: everything is done (the failed dives too), nothing runs
        again = run_sweep(conds, 0, out, seeds=[1002, 1003, 1004], client=client, progress=False, dive=fake_dive)
        assert (again.ran, again.skipped) == (0, 6)
        # a resumed sweep without seeds takes the stored ones, topped up with fresh ones
        more = run_sweep(conds[:1], 4, out, client=client, progress=False, dive=fake_dive)
        assert more.seeds[:3] == [1002, 1003, 1004] and not is_development_seed(more.seeds[3])
        assert (more.ran, more.skipped) == (1, 3)
        # failed dives run again on request: still one row each
        retried = run_sweep(conds[:1], 4, out, client=client, progress=False, retry_failed=True, dive=fake_dive)
        assert retried.ran == 1
        rows = list(csv.DictReader((out / "dives.csv").open()))
        assert len(rows) == 7 and len({(x["condition"], x["seed"]) for x in rows}) == 7
        # the same name for another set-up is refused
        with pytest.raises(ConfigError):
            run_sweep([replace(conds[0], quick=True)], 1, out, client=client, progress=False, dive=fake_dive)


# ---------------------------------------------------------------------------- a real scheduler

def _start(args: list[str], log: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen(args, stdout=log.open("w"), stderr=subprocess.STDOUT, start_new_session=True)


def _wait(what: str, cond: Any, timeout: float, procs: list[subprocess.Popen[bytes]]) -> Any:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        for p in procs:
            if p.poll() is not None:
                raise AssertionError(f"{p.args} exited ({p.returncode}) while waiting for {what}")
        got = cond()
        if got:
            return got
        time.sleep(0.2)
    raise AssertionError(f"gave up waiting for {what} after {timeout:.0f} s")


@pytest.mark.slow
def test_sweep_on_a_real_scheduler_survives_a_killed_worker(tmp_path: Path) -> None:
    """`dask scheduler` and two `dask worker` processes (no nanny: a killed worker stays dead) on
    loopback; `coex sweep --scheduler` runs four tiny dives and two that raise; one worker is
    killed while it runs a dive. Every dive is in dives.csv once, the killed worker's dive ran
    again on the other, the raising ones are rows with their error."""
    distributed = pytest.importorskip("distributed")
    dask = Path(sys.executable).with_name("dask")
    if not dask.exists():
        pytest.skip("the dask command is not installed (the [sweep] extra)")
    bad = tmp_path / "crowded.toml"  # 40 objects cannot be placed apart on a 16 m site: the dive raises
    bad.write_text('name = "crowded"\narea = 16.0\nduration = 600.0\n[seafloor]\nrandom_targets = 20\n'
                   'random_decoys = 20\n')
    sched_file = tmp_path / "scheduler.json"
    procs: list[subprocess.Popen[bytes]] = []
    try:
        procs.append(_start([str(dask), "scheduler", "--host", "127.0.0.1", "--port", "0", "--dashboard-address", "127.0.0.1:0",
                             "--scheduler-file", str(sched_file)], tmp_path / "scheduler.log"))
        address = _wait("the scheduler", lambda: sched_file.exists() and json.loads(sched_file.read_text() or "{}")
                        .get("address"), 60, procs)
        workers = {}
        for name in ("w1", "w2"):
            workers[name] = _start([str(dask), "worker", address, "--nthreads", "1", "--name", name,
                                    "--no-nanny", "--no-dashboard", "--host", "127.0.0.1"],
                                   tmp_path / f"{name}.log")
            procs.append(workers[name])
        with distributed.Client(address, timeout=30) as client:
            client.wait_for_workers(2, timeout=60)
            out = tmp_path / "out"
            sweep = _start([sys.executable, "-m", "coex_core.cli", "sweep", "--scheduler", address, "--scenario",
                            str(TINY), "--scenario", str(bad), "--dives", "3", "--out", str(out), "--quiet"],
                           tmp_path / "sweep.log")
            by_name = {info["name"]: addr for addr, info in client.scheduler_info()["workers"].items()}

            def w1_busy() -> bool:
                return any(str(k).startswith("coex-dive-") for k in client.processing().get(by_name["w1"], ()))
            _wait("a dive on w1", w1_busy, 120, [sweep])
            os.killpg(workers["w1"].pid, signal.SIGKILL)  # the worker dies with its dive
            workers["w1"].wait(30)
            rc = sweep.wait(300)
        log = (tmp_path / "sweep.log").read_text()
        assert rc == 0, log
        rows = list(csv.DictReader((out / "dives.csv").open()))
        seeds = json.loads((out / "sweep.json").read_text())["seeds"]
        assert len(seeds) == 3 and len(set(seeds)) == 3 and not any(is_development_seed(s) for s in seeds)
        assert sorted((r["condition"], int(r["seed"])) for r in rows) == sorted(
            (c, s) for c in ("sweep-tiny", "crowded") for s in seeds), log
        tiny = [r for r in rows if r["condition"] == "sweep-tiny"]
        assert all(r["error"] == "" and r["success"] in ("true", "false") for r in tiny), tiny
        assert {r["worker"] for r in rows} <= {"w1", "w2"} and "w2" in {r["worker"] for r in rows}
        crowded = [r for r in rows if r["condition"] == "crowded"]
        assert all(r["error"].startswith("ConfigError: cannot place") for r in crowded), crowded
        summary = json.loads((out / "summary.json").read_text())["conditions"]
        assert summary["sweep-tiny"]["n"] == 3 and summary["crowded"]["errors"] == 3
        assert len(summary["sweep-tiny"]["success_wilson95"]) == 2
    finally:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(30)
