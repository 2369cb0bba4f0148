"""CoEx commands as processes for end-to-end tests: start one with its output collected in a
thread (and written to a log file), wait for a condition while checking that none of them died,
read the console's state and act through its HTTP API."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
COEX = [sys.executable, "-m", "coex_core.cli"]

__all__ = ["COEX", "ROOT", "Lines", "act", "start", "state", "wait_for"]


def wait_for(what: str, cond: Callable[[], Any], timeout: float,
             procs: dict[str, subprocess.Popen[str]] | None = None, every: float = 0.5) -> Any:
    """``cond()`` once it is true; AssertionError when ``timeout`` seconds pass first or one of
    ``procs`` exits meanwhile."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        for name, p in (procs or {}).items():
            if p.poll() is not None:
                raise AssertionError(f"{name} exited ({p.returncode}) while waiting for {what}")
        got = cond()
        if got:
            return got
        time.sleep(every)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


class Lines:
    """A process's output, read in a thread (the test looks for lines; nothing blocks)."""

    def __init__(self, proc: subprocess.Popen[str], sink: Path) -> None:
        self.lines: list[str] = []
        self.sink = sink.open("a")
        self.t = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self.t.start()

    def _read(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            self.lines.append(line.rstrip("\n"))
            self.sink.write(line)
            self.sink.flush()

    def has(self, text: str) -> bool:
        return any(text in line for line in self.lines)

    def count(self, text: str) -> int:
        return sum(text in line for line in self.lines)


def start(args: list[str], env: dict[str, str], log: Path, cwd: Path = ROOT) -> tuple[subprocess.Popen[str], Lines]:
    """``coex ARGS`` with stdout and stderr collected (and appended to ``log``)."""
    p = subprocess.Popen([*COEX, *args], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                         cwd=cwd)
    return p, Lines(p, log)


def state(http: str) -> dict[str, Any]:
    """The console's state (``GET /api/state``), or {} while it does not answer."""
    try:
        with urllib.request.urlopen(f"http://{http}/api/state", timeout=5) as r:
            return json.loads(r.read())  # type: ignore[no-any-return]
    except OSError:
        return {}


def act(http: str, action: str, args: dict[str, Any]) -> Any:
    """An operator's action through the console's HTTP API."""
    req = urllib.request.Request(f"http://{http}/api/action",
                                 data=json.dumps({"action": action, "args": args}).encode(),
                                 headers={"Content-Type": "application/json"}, method="POST")
    with urllib.request.urlopen(req, timeout=10) as r:
        return json.loads(r.read())
