"""The soak with faults (``bench/soak_faults.py``), short and light: the vehicle daemon and the
topside console over simulated Micromodems on one simulated clock, the vehicle's modem stream cut
once and topside killed (as by ``kill -9``) and restarted from its store; after a drain,
everything the vehicle sent is held topside, both ends counted the outage, and the daemons logged
a handful of lines."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]


def _bench() -> Any:
    path = ROOT / "bench" / "soak_faults.py"
    spec = importlib.util.spec_from_file_location("soak_faults", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["soak_faults"] = module
    spec.loader.exec_module(module)
    return module


def test_a_cut_and_a_topside_kill_lose_nothing(tmp_path: Path) -> None:
    sf = _bench()
    faults = sf.Faults(cuts=[(600.0, 180.0)], kills=[(1200.0, 60.0)])
    r = sf.Soak(tmp_path, 0.5, faults, light=True, drain=sf.HOUR, progress=lambda _: None).run()
    assert r["converged"] == {"map": True, "images": True, "series": True}, r["converged"]
    assert r["images_taken"] >= 5 and r["images_missing"] == []
    assert r["vehicle_link"]["outages"] == 1 and r["topside_heard"]["outages"] == 1
    assert r["topside_restarts"] == 1
    # a state change is a line; nothing is logged per read, send or retry
    assert 0 < r["log_records"] <= 20, r["log_by_logger"]
    assert r["ok"]
