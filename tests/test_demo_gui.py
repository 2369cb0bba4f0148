"""`coex demo --gui` serves the live console during the dive and after it."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import time
import urllib.request
from pathlib import Path

import pytest

from ._dives import coex_command, quick_short_file

# a whole demo dive behind the web console
pytestmark = pytest.mark.slow


def _get(url: str) -> dict:  # type: ignore[type-arg]
    with urllib.request.urlopen(url, timeout=10) as r:
        return json.loads(r.read())  # type: ignore[no-any-return]


def test_demo_gui_serves_the_console(tmp_path: Path, tmp_path_factory: pytest.TempPathFactory) -> None:
    # the quick site, not the small one: with nobody operating, the vehicle's own camera
    # transect on the small site takes twice the frames (20 against 10). Its frames are those of
    # test_demo_truth.py's NOT MET dive (the same site and seed, nobody operating): coded once
    # for both (``tests/_dives.py`` ``coex_command``)
    # (a 20-minute dive: ``tests/_dives.py`` ``quick_short``, as that one)
    cmd = coex_command(tmp_path_factory, "demo", "--quick", "--scenario", str(quick_short_file(tmp_path / "quick.toml")),
                       "--gui", "--http", "127.0.0.1:0",
                       "--speed", "5000", "--threads", "0", "--quiet", "--out", str(tmp_path / "out"))
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        url = None
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and url is None:
            line = proc.stderr.readline()
            m = re.search(r"web console at (http://\S+)", line)
            if m:
                url = m.group(1).rstrip("/")
        assert url, "the demo did not announce its console"
        first = _get(url + "/api/state")
        assert isinstance(first, dict) and first
        # a person asks for the 1 m map of a corner: it goes to the vehicle and into the decisions
        body = json.dumps({"action": "request_region",
                           "args": {"level": 0, "x_min": 0, "y_min": 0, "x_max": 20, "y_max": 20}}).encode()
        req = urllib.request.Request(url + "/api/action", data=body, method="POST",
                                     headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(req, timeout=10) as r:
            assert json.loads(r.read())["ok"] is True
        over = False
        while time.monotonic() < deadline + 300 and not over:
            over = "the dive is over" in proc.stderr.readline()
        assert over, "the dive did not finish"
        state = _get(url + "/api/state")
        text = json.dumps(state)
        assert "level" in text and "image" in text  # the map and the images reached the console
        with urllib.request.urlopen(url + "/", timeout=10) as r:
            assert b"<html" in r.read().lower()
        proc.send_signal(signal.SIGINT)
        # communicate drains both pipes while it waits: the demo never blocks on a full pipe
        proc.communicate(timeout=180)  # writes the report and maps first (slow on a loaded machine)
        assert proc.returncode == 0
    finally:
        if proc.poll() is None:
            proc.kill()
    out = tmp_path / "out"
    assert (out / "report.html").exists()
    # with the console and no --operator, a person operates: no scripted decision, theirs logged
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["operator"] == "none"
    rows = (out / "decisions.csv").read_text().splitlines()
    assert not any(",script," in r for r in rows)
    assert any(",person,console action," in r and "request_region" in r for r in rows)
    assert "person" in (out / "report.html").read_text()
