"""The console's operator stays served under a flood from other machines (issue 52): the load
and attack suite of ``bench/console_flood.py``, short, on loopback (addresses 127.0.x.y stand
for other machines). All at once: 300 idle sockets from one address (re-opened when closed), a
viewer's 100 event streams, a viewer's 40 map windows of 4 Mpx, 50 addresses guessing ana's
password, 100 pollers of /api/state; meanwhile ana, in the browser she signed in with before,
signs in, reads the state and sends an action every 2 s, each answered within 3 s. The
console runs in a process of its own, the attackers in another."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[1]
BOUND = 3.0


def _bench() -> ModuleType:
    path = ROOT / "bench" / "console_flood.py"
    spec = importlib.util.spec_from_file_location("console_flood", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["console_flood"] = module
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_the_operator_is_served_within_3_s_under_every_flood_at_once(tmp_path: Path) -> None:
    flood = _bench()
    result = flood.run_flood(seconds=14.0, every=2.0, workdir=tmp_path, settle=15.0)
    rounds = result["rounds"]
    assert len(rounds) >= 3, result
    for what, want in (("sign_in", 303), ("state", 200), ("action", 200)):
        codes, slowest = flood.worst(rounds, what)
        assert codes == [want] * len(rounds) and slowest <= BOUND, (what, codes, slowest, result)
    # the attacks happened, and each met its limit (how much of the viewer's work got done
    # depends on the machine's load: a loaded one may draw none of its windows in 14 s)
    got = result["attackers"]
    assert got["idle"]["opened"] >= 300, got
    assert got["streams"].get("200", 0) <= 8 and got["streams"].get("429", 0) > 20, got
    assert got["windows"].get("429", 0) > 20, got
    assert got["guessers"].get("429", 0) > 20 and got["guessers"].get("401", 0) <= 60, got
    assert got["pollers"].get("200", 0) > 100, got
    # memory stays bounded under the flood and goes back after it
    rss = result["rss_mb"]
    assert rss["peak_during"] < 600, rss
    assert rss["after"] < rss["before"] + 60, rss
