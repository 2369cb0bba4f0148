"""``coex topside --store FILE``: a topside console killed at any moment comes back with everything
it had received (map, images, series, vehicle track), its operator's requests and goals, and its
command numbering, and the transfer carries on without the vehicle re-sending what topside has.

In-process, on a simulated clock: a vehicle node (bathymetry, imagery, status) and a topside built
by :func:`build_topside` share a loopback link; topside is abandoned without any shutdown (what a
``kill -9`` leaves: the SQLite file as last committed) and built again from its store on the same
link. A subprocess test does the same to the real command with ``kill -9``.
"""

from __future__ import annotations

import json
import signal
import sqlite3
import subprocess
import sys
import time
import urllib.request
import uuid
from pathlib import Path
from typing import Any

import pytest

from coex_apps.console.cli import TopsideApp, build_topside
from coex_apps.console.testing import survey_points
from coex_core import messages as m
from coex_core.channel import ChannelManager, LinkConfig, Schedule, StreamConfig
from coex_core.errors import ConfigError
from coex_core.node import Node
from coex_core.registry import open_transport
from coex_core.timefmt import to_stamp
from coex_plugins.bathymetry import BathymetryModality, BathymetrySender
from coex_plugins.imagery import ImageInput, ImageryModality
from coex_plugins.imagery.synth import seafloor
from coex_runtime.store import snapshot_text

T0 = 36000.0
SCHEDULE = Schedule.simple([1, 2], 4.0, 0.5)
COEX = str(Path(sys.executable).with_name("coex"))


class Dive:
    """A vehicle and a topside on one loopback link, stepped by hand on a shared clock."""

    def __init__(self, store: Path) -> None:
        self.now = [T0]
        self.uri = f"loopback://store-{uuid.uuid4().hex[:8]}?rate=100000"
        self.store = store
        self.app = self.topside(self.uri)
        self.vtr = open_transport(self.uri)
        manager = ChannelManager(2, [LinkConfig(0, SCHEDULE, rate=5, dst=1)],
                                 queue_status_interval=8.0)
        self.vehicle = Node(manager)
        self.bathy = BathymetrySender({"send_delay": 0.0, "levels": 4})
        self.bathy.ingest(survey_points(), T0)
        self.images = ImageryModality().sender(None)
        self.vehicle.add_sender(BathymetryModality, self.bathy,
                                StreamConfig(3, "map", priority=30, ack_required=True))
        self.vehicle.add_sender(ImageryModality, self.images, StreamConfig(4, "images", priority=20))
        for k in range(3):
            self.images.ingest(ImageInput(seafloor(96, 128, seed=k), time=T0 - 60 + 10 * k,
                                          x=5.0 * k, y=0.0), T0)

    def topside(self, uri: str) -> TopsideApp:
        return build_topside(uri, "127.0.0.1", 0, schedule=SCHEDULE, clock=lambda: self.now[0],
                             store=self.store, snapshot_interval=1e9)

    def run(self, seconds: float, dt: float = 0.25) -> None:
        end = self.now[0] + seconds
        k = 0
        while self.now[0] < end:
            now = self.now[0]
            if k % 40 == 0:
                self.vehicle.push_status(m.VehicleStatus(
                    to_stamp(now), 1.0 + k * 0.01, 2.0, 40.0, 20.0, 90.0, 1.5, 80,
                    m.VehicleMode.SURVEY, 0), now)
            while (f := self.vtr.recv(timeout=0)) is not None:
                self.vehicle.receive(0, f, now)
            for tx in self.vehicle.poll(now):
                for f in tx.frames:
                    self.vtr.send(f)
            self.app.transport.inner.link.clock.advance(dt)  # the loopback's own clock (behind the resilient link)
            self.app.step()
            self.now[0] += dt
            k += 1

    def crash_and_restart(self) -> TopsideApp:
        """Abandon topside as ``kill -9`` would (no shutdown, no last snapshot) and start it
        again from its store on the same link end."""
        old = self.app
        old.server.close()
        old.store.close()  # the file as last committed; nothing else is written (and its lock released)
        self.app = self.topside(f"loopback://spare-{uuid.uuid4().hex[:8]}")
        self.app.transports[0] = old.transports[0]
        return self.app


def _view(app: TopsideApp) -> dict[str, Any]:
    """What the operator sees that must survive a restart."""
    snap = app.hub.snapshot()
    levels = {lv["level"]: lv["subgrids"] for lv in snap["map"]["levels"]}
    images = {im["image_id"]: im["bytes_received"] for im in snap["images"]["items"]}
    commands = [(c["command_id"], c["summary"], c["status"]) for c in snap["commands"]]
    status = dict(snap["vehicle"]["status"] or {})
    status.pop("age", None)  # it grows with the clock
    return {"levels": levels, "images": images, "commands": commands,
            "track": len(snap["vehicle"]["track"]), "status": status}


def test_topside_resumes_from_its_store(tmp_path: Path) -> None:
    dive = Dive(tmp_path / "topside.db")
    try:
        dive.run(40.0)
        before_goal = _view(dive.app)
        assert before_goal["levels"] and before_goal["images"], before_goal
        first = min(before_goal["images"])
        dive.app.hub.act("set_image_goal", {"image_id": first, "kind": "full"})
        dive.app.hub.act("request_region", {"level": 0, "x_min": 0, "y_min": 0,
                                            "x_max": 40, "y_max": 40})
        dive.run(21.0)  # the commands go out; frames keep arriving after the last snapshot
        app = dive.app
        assert app.store.count("rx") > 0
        last_snap = app.store.db.execute("SELECT journal_id FROM snapshot").fetchone()[0]
        after_snap = app.store.db.execute(
            "SELECT COUNT(*) FROM journal WHERE kind = 'rx' AND id > ?", (last_snap,)).fetchone()[0]
        assert after_snap > 0  # the restart must replay the journal, not only load a snapshot
        seen = _view(app)
        held = set(app.node.receiver("imagery").images)
        next_cid = app.node.manager._command_id

        app = dive.crash_and_restart()
        app.step()
        assert _view(app) == seen  # the console shows exactly what it showed
        assert any("resumed from" in e["text"] for e in app.hub.snapshot()["log"])
        assert set(app.node.receiver("imagery").images) == held
        assert app.node.manager._command_id == next_cid
        # the map receiver is the console's region source again (not a copy)
        assert app.hub.actions.map_receiver is app.node.receiver("bathymetry")
        assert app.hub.state.region_source is app.hub.actions.map_receiver

        # the transfer resumes: the goal is met, the map keeps growing, nothing is resent
        sent_before = dive.vehicle.manager.stats["packets"]
        dive.run(400.0)
        assert dive.vehicle.manager.stats["packets"] > sent_before
        final = _view(app)
        imgs = app.hub.snapshot()["images"]["items"]
        goal = next(im for im in imgs if im["image_id"] == first)
        assert goal["fraction"] == 1.0, goal
        assert sum(final["levels"].values()) >= sum(seen["levels"].values())
        # a new command after the restart gets a new id, not one already used
        app.hub.act("link_control", {"link": 0, "enabled": True})
        ids = [c[0] for c in _view(app)["commands"]]
        assert len(ids) == len(set(ids))
    finally:
        dive.app.close()


def test_store_of_another_topside_is_refused(tmp_path: Path) -> None:
    db = tmp_path / "t.db"
    app = build_topside(f"loopback://a-{uuid.uuid4().hex[:6]}", "127.0.0.1", 0, modalities=(),
                        store=db)
    app.step()
    app.close()
    with pytest.raises(ConfigError, match="links"):
        build_topside([f"loopback://b-{uuid.uuid4().hex[:6]}", f"loopback://c-{uuid.uuid4().hex[:6]}"],
                      "127.0.0.1", 0, modalities=(), store=db)
    with pytest.raises(ConfigError, match="node"):
        build_topside(f"loopback://d-{uuid.uuid4().hex[:6]}", "127.0.0.1", 0, modalities=(),
                      store=db, node_id=5)
    bad = tmp_path / "bad.db"
    bad.write_bytes(b"not sqlite at all" * 100)
    r = subprocess.run([COEX, "topside", "--transport", "loopback://x", "--http", "127.0.0.1:0",
                        "--store", str(bad)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "store" in r.stderr, r.stderr


def _state(url: str) -> dict[str, Any]:
    with urllib.request.urlopen(url + "api/state", timeout=5) as r:
        return json.loads(r.read())


def test_coex_topside_store_survives_kill_9(tmp_path: Path) -> None:
    """The real command: operator actions, then ``kill -9``, then the same command again."""
    db = tmp_path / "topside.db"
    cmd = [COEX, "topside", "--transport", "loopback://k9", "--http", "127.0.0.1:0",
           "--slot", "2", "--guard", "0.2", "--packet-seconds", "0.2", "--store", str(db)]

    said: list[str] = []

    def start() -> tuple[subprocess.Popen[str], str]:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line.startswith("CoEx console on http://"), line + (proc.stderr.read() if proc.stderr else "")
        said.append(proc.stdout.readline())
        return proc, line.split()[3]

    proc, url = start()
    try:
        for level in (1, 2):
            body = json.dumps({"action": "request_region", "args": {
                "level": level, "x_min": 0, "y_min": 0, "x_max": 30, "y_max": 30}}).encode()
            req = urllib.request.Request(url + "api/action", data=body,
                                         headers={"Content-Type": "application/json"})
            with urllib.request.urlopen(req, timeout=5) as r:
                assert r.status == 200
        commands = _state(url)["commands"]
        assert len(commands) >= 2
        # the store is saved at once after operator commands: a snapshot holding both appears
        # (looked for in the saved state itself, not by comparing clocks)
        summaries = [json.dumps(c["summary"]).encode() for c in commands]
        deadline = time.monotonic() + 20
        held = False
        while time.monotonic() < deadline and not held:
            with sqlite3.connect(db) as db_:
                text = snapshot_text(db_)
            held = text is not None and all(s in text for s in summaries)
            time.sleep(0.1)
        assert held
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    proc, url = start()
    try:
        again = _state(url)
        assert [(c["command_id"], c["summary"]) for c in again["commands"]] == \
            [(c["command_id"], c["summary"]) for c in commands]
        assert any("resumed from" in e["text"] for e in again["log"])
        assert said[0].startswith(f"store {db}: new") and said[1].startswith(f"store {db}: resumed")
    finally:
        proc.terminate()
        proc.wait(timeout=10)
