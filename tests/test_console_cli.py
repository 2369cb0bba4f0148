"""``coex topside``: the command serves the console over a transport URI; bad options fail cleanly."""

from __future__ import annotations

import json
import subprocess
import sys
import urllib.request
from pathlib import Path

COEX = str(Path(sys.executable).with_name("coex"))


def test_coex_topside_serves_the_console() -> None:
    proc = subprocess.Popen([COEX, "topside", "--transport", "loopback://cli-test",
                             "--http", "127.0.0.1:0", "--slot", "5"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line.startswith("CoEx console on http://127.0.0.1:"), line + proc.stderr.read()
        url = line.split()[3]
        with urllib.request.urlopen(url, timeout=5) as r:
            assert r.status == 200 and b"CoEx topside" in r.read()
        with urllib.request.urlopen(url + "api/state", timeout=5) as r:
            state = json.loads(r.read())
        (sched,) = state["link"]["schedules"]
        assert [s["owner"] for s in sched["slots"]] == [1, 2, 2, 1, 2, 2]
        assert {s["duration"] for s in sched["slots"]} == {5.0}
        assert state["queues"]["streams"] == []  # nothing from a vehicle yet
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_coex_topside_bad_options() -> None:
    r = subprocess.run([COEX, "topside", "--transport", "nosuch://x", "--http", "127.0.0.1:0"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "nosuch" in r.stderr
    r = subprocess.run([COEX, "topside", "--transport", "loopback://x", "--http", "nowhere"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "HOST:PORT" in r.stderr
    r = subprocess.run([COEX, "topside", "--transport", "loopback://y", "--http", "127.0.0.1:0",
                        "--schedule", "{bad json"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "--schedule" in r.stderr
