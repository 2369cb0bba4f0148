"""`coex demo --gui` serves the live console during the dive and after it."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path


def _get(url: str) -> dict:  # type: ignore[type-arg]
    with urllib.request.urlopen(url, timeout=10) as r:
        return json.loads(r.read())  # type: ignore[no-any-return]


def test_demo_gui_serves_the_console(tmp_path: Path) -> None:
    cmd = [sys.executable, "-m", "coex_core.cli", "demo", "--quick", "--gui", "--http", "127.0.0.1:0",
           "--speed", "5000", "--quiet", "--out", str(tmp_path)]
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
        assert proc.wait(timeout=60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
    assert (tmp_path / "report.html").exists()
