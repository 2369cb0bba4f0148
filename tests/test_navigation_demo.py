"""The demo's navigation (issue 56): ``[navigation] drift = 0`` is today's dive, byte for byte
(and so the same seed gives the same dive); a dive whose vehicle drifts is corrected topside and
judged against the truth."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from coex_apps.demo import DemoConfig, run_demo
from coex_apps.demo import run as run_module
from coex_apps.demo.navigation import DiveNavigation
from coex_apps.demo.scenario import scenario_from_dict

# SMALL: a small, short dive (a 64 m site, one car, 25 minutes): the navigation's every path, quickly
from ._dives import SMALL, shared_dive, small


class _NoNavigation(DiveNavigation):
    """No navigation code at all in the dive: every hook gives back what it got."""

    def __init__(self, run: Any) -> None:
        from coex_apps.demo.config import VEHICLE

        self.active = False
        self.camera_vehicle = VEHICLE
        self.aid_sender = self.aid_receiver = None

    def model(self, vehicle: int) -> Any:
        return None

    def metrics(self, *args: Any) -> dict[str, Any]:
        return {}

    def close(self) -> None:
        pass


@pytest.mark.slow
@pytest.mark.usefixtures("shared_codestreams")
def test_drift_zero_is_todays_dive(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                  tmp_path_factory: pytest.TempPathFactory) -> None:
    """With ``drift = 0`` the dive is the one without any navigation code: the same decisions,
    link log and time series, byte for byte; nothing drifted, no fix was drawn."""
    # the dive with the navigation code is shared (test_demo.py's spare-traffic test compares
    # its own dive with it); the one without runs here
    a_out, a = shared_dive(tmp_path_factory, DemoConfig(seed=1, progress=False, scenario=small(
        navigation={"drift": 0.0}), codec_threads=0))
    monkeypatch.setattr(run_module, "DiveNavigation", _NoNavigation)
    run_demo(DemoConfig(out=tmp_path, seed=1, progress=False, scenario=small(navigation={"drift": 0.0}),
                        codec_threads=0))
    for name in ("decisions.csv", "link.jsonl", "timeseries.csv", "truth.json"):
        assert (a_out / name).read_bytes() == (tmp_path / name).read_bytes(), name
    b = json.loads((tmp_path / "metrics.json").read_text())
    nav = a["navigation"]
    assert nav["drift_at_end_m"] == 0.0 and nav["active"] is False and "usbl" not in nav
    assert all(t["camera_pass_m"] is not None for t in nav["targets"])
    assert a["success"] == b["success"]
    # the same seed, the same dive (``coex demo --seed S`` is deterministic; this was a second
    # quick dive in test_demo.py): every metric but the navigation's own, the wall time, the
    # configuration's echo and the modems' pty names
    strip = ("wall_seconds", "config", "modems", "navigation")
    assert {k: v for k, v in a.items() if k not in strip} == {k: v for k, v in b.items() if k not in strip}


@pytest.mark.slow
@pytest.mark.usefixtures("shared_codestreams")
def test_a_drifting_dive_is_corrected_and_judged_against_the_truth(tmp_path: Path) -> None:
    """The default drift and USBL: the vehicle really drifts, every fix went through the USBL
    input, the wild ones are found, the estimate follows the true drift, and the camera still
    passes over every target; metrics.json says all of it (``navigation``)."""
    result = run_demo(DemoConfig(out=tmp_path, seed=2, progress=False, scenario=scenario_from_dict(SMALL),
                                 codec_threads=0))
    m = json.loads((tmp_path / "metrics.json").read_text())
    nav = m["navigation"]
    assert nav["active"] and nav["correction"] == "on" and nav["drift_at_end_m"] > 1.0
    usbl = nav["usbl"]
    assert usbl["fixes"] == usbl["fixes_read"] > 100 and usbl["input_counts"]["bad"] == 0
    est = nav["estimate"]["2"]
    # a wild fix only 4 sigmas off may pass for a good one; no more than one is used
    assert est["wild_used"] <= 1 and est["flagged"] <= est["wild_fixes"] + 3 and est["fixes_used"] > 80
    assert est["error_p95_m"] < 2.0, est
    assert len(nav["targets"]) == len(m["targets"])
    for t in nav["targets"]:
        assert set(t) == {"x", "y", "map_error_m", "camera_pass_m"}
        assert t["camera_pass_m"] is not None and t["camera_pass_m"] <= 3.0, t
        assert t["map_error_m"] is not None and t["map_error_m"] <= 3.5, t
    assert result.metrics["success"]
    # the report shows it too (the navigation's metrics reach the report, not only metrics.json)
    assert "<h3>Navigation</h3>" in (tmp_path / "report.html").read_text()
