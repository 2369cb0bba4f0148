"""A dive that fails releases everything it held (the link log, the pseudo-terminals, the
console's server), and a dive's failures are counted in ``metrics.json`` (``failures``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from coex_apps.demo import DemoConfig
from coex_apps.demo import run as run_module
from coex_apps.demo.failures import failure_counts
from coex_apps.demo.run import DiveRun


class _FakeServer:
    """What the dive needs of the console's server, and whether it was closed."""

    def __init__(self) -> None:
        self.closed = False

        class Hub:
            import threading

            lock = threading.Lock()

            class state:  # the console's state: the dive hands it topside's navigation (issue 56)
                navigation: Any = None

            def update(self, fn: Any) -> None:
                pass
        self.hub = Hub()
        self.url = "http://127.0.0.1:0/"

    def close(self) -> None:
        self.closed = True


def test_a_failing_dive_releases_the_link_log_the_ptys_and_the_console(tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    server = _FakeServer()
    monkeypatch.setattr(run_module, "_start_gui", lambda cfg, topside, vehicle, log: server)
    dive = DiveRun(DemoConfig(out=tmp_path, quick=True, seed=1, progress=False, gui=True, linger=False,
                              operator="script"))
    hosts = list(dive.net._hosts)
    assert hosts and all(h.master is not None for h in hosts)  # pseudo-terminals open

    def boom(end: float) -> None:
        raise RuntimeError("the simulated modem caught fire")
    monkeypatch.setattr(dive.loop, "run", boom)
    with pytest.raises(RuntimeError, match="caught fire"):
        dive.run()
    assert dive.link_log.closed
    assert all(h.master is None and h.slave is None for h in hosts)
    assert server.closed
    dive.close()  # closing again is harmless


def test_a_dive_that_cannot_be_set_up_releases_what_it_opened(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    opened: list[Any] = []
    real = DiveRun._build_link

    def build_then_fail(self: DiveRun) -> None:
        real(self)
        opened.extend([self.link_log, *self.net._hosts])
        raise ValueError("no camera")
    monkeypatch.setattr(DiveRun, "_build_link", build_then_fail)
    with pytest.raises(ValueError, match="no camera"):
        DiveRun(DemoConfig(out=tmp_path, quick=True, seed=1, progress=False))
    log, *hosts = opened
    assert log.closed and hosts and all(h.master is None for h in hosts)


def test_failure_counts_add_up_per_node() -> None:
    class Node:
        def __init__(self, bad: int, fails: int) -> None:
            self.stats = {"bad_frames": bad, "unauthenticated": 1, "rejected": 2}

            class Mgr:
                stats = {"sender_failures": fails}
                sender_failures_by_stream = {"images": fails}
            self.manager = Mgr()

    class Runner:
        def __init__(self, node: Node, errors: int) -> None:
            self.node, self.error_count = node, errors
    got = failure_counts({1: Runner(Node(0, 0), 0), 2: Runner(Node(3, 2), 1)})  # type: ignore[dict-item]
    assert (got["rejected_frames"], got["rejected_messages"], got["sender_failures"], got["runner_errors"]) == (5, 4, 2, 1)
    assert got["nodes"]["2"]["sender_failures_by_stream"] == {"images": 2}
