"""A store that cannot be written is named, never a traceback, and the node keeps its link.

* ``coex vehicle`` and ``coex topside`` on a damaged store (a page corrupted in the middle of
  the file), a read-only one or one in a folder that does not exist exit with one sentence
  that names the file and the remedy;
* a vehicle whose disk fills up mid-dive (SQLite's ``max_page_count``, which refuses a write
  as a full disk does) keeps its link and answers commands, tells topside (``VehicleStatus``
  faults) and its log, holds the image it could not journal, takes it once the disk has room
  again, and a restart after that takes no file twice.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import subprocess
import sys
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image as PILImage

from coex import ChannelManager, CommandResult, LinkConfig, Node, Schedule, StoreError
from coex.messages import AckStatus, QueueConfig, VehicleStatus
from coex.registry import open_transport
from coex_apps.vehicle.config import load
from coex_apps.vehicle.daemon import FAULT_STORE, TAKEN_PREFIX, VehicleApp
from coex_plugins.imagery import ImageryModality
from coex_plugins.imagery.synth import seafloor
from coex_runtime.runner import STORE_RECOVERY

from ._faults import FaultyDb

COEX = [sys.executable, "-m", "coex_core.cli"]
T = 1_800_000_000.0

VEHICLE = """
[node]
role = "vehicle"
id = 2
peer = 1
store = "{store}"
snapshot_interval = 1
[[modems]]
uri = "{uri}"
packet_seconds = 0.2
[tdma]
slots = ["topside", "vehicle"]
slot_seconds = 1.0
guard = 0.1
[modalities.imagery]
stream = 4
options = {{ default_goal = "layer:1" }}
[status]
interval = 1
[[inputs]]
type = "directory"
path = "images"
existing = true
settle = 0
interval = 0.1
nav = true
"""


def _image(folder: Path, name: str, seed: int) -> None:
    folder.mkdir(exist_ok=True)
    PILImage.fromarray(seafloor(96, 128, seed=seed)).save(folder / name)


class Dive:
    """The vehicle daemon (in process, on a hand-driven clock) and a topside node on one
    loopback link."""

    def __init__(self, tmp: Path, store: str = "vehicle.sqlite") -> None:
        self.tmp = tmp
        self.now = [T]
        self.uri = f"loopback://disk-{uuid.uuid4().hex[:8]}?rate=100000"
        (tmp / "v.toml").write_text(VEHICLE.format(store=store, uri=self.uri))
        self.events: list[Any] = []
        self.statuses: list[VehicleStatus] = []
        self.vtr = open_transport(self.uri)  # end a: the vehicle's
        self.ttr = open_transport(self.uri)  # end b: topside's
        sched = Schedule.simple([1, 2], 1.0, 0.1)
        self.topside = Node(ChannelManager(1, [LinkConfig(0, sched, rate=5, dst=2, packet_seconds=0.2)]))
        self.topside.add_receiver(ImageryModality, ImageryModality().receiver(None))
        self.app = self.start()

    def start(self) -> VehicleApp:
        app = VehicleApp(load(self.tmp / "v.toml", "vehicle"), clock=lambda: self.now[0],
                         transports={0: self.vtr})
        app.open()
        app.nav.update(x=1.0, y=2.0)  # a position, so that the vehicle sends its status
        return app

    def run(self, seconds: float, dt: float = 0.1, *, topside_sends: bool = True) -> None:
        end = self.now[0] + seconds
        while self.now[0] < end:
            now = self.now[0]
            self.app.runner.step()
            while (f := self.ttr.recv(timeout=0)) is not None:
                self.topside.receive(0, f, now)
            for tx in self.topside.poll(now):
                for f in tx.frames:
                    if topside_sends:
                        self.ttr.send(f)
            for e in self.topside.events():
                self.events.append(e)
                msg = getattr(e, "message", None)
                if isinstance(msg, VehicleStatus):
                    self.statuses.append(msg)
            self.vtr.link.clock.advance(dt)
            self.now[0] += dt

    def command(self) -> int:
        """A channel command to the vehicle (a queue setting); its id."""
        cid = self.topside.manager.next_command_id()
        return self.topside.manager.send_command(QueueConfig(cid, 4, False, True, 40, None, None, None), self.now[0])

    def answered(self, cid: int) -> bool:
        return any(isinstance(e, CommandResult) and e.command_id == cid and e.status == AckStatus.ACCEPTED
                   for e in self.events)

    def images_topside(self) -> int:
        return len(self.topside.receiver("imagery").images)  # type: ignore[attr-defined]


def _fill(store: Any) -> None:
    """The disk is nearly full from now on: the file may not grow by a page (SQLite's
    ``max_page_count``: a write that needs a new page is refused as on a full disk; one that
    fits in the pages the file has free still goes, as on a real disk)."""
    pages = int(store.db.execute("PRAGMA page_count").fetchone()[0])
    store.db.execute(f"PRAGMA max_page_count = {pages}")


def _room(store: Any) -> None:
    store.db.execute("PRAGMA max_page_count = 1073741823")


def _no_room(store: Any) -> FaultyDb:
    full = FaultyDb(store.db, full=True)
    store.db = full
    store.storage().db = full
    return full


def test_a_full_disk_keeps_the_link_and_commands_and_takes_no_file_twice(tmp_path: Path,
                                                                          caplog: pytest.LogCaptureFixture) -> None:
    _image(tmp_path / "images", "a.png", 1)
    dive = Dive(tmp_path)
    try:
        dive.run(4.0)
        assert dive.app.counts["images"] == 1 and dive.images_topside() == 1
        assert dive.statuses and dive.statuses[-1].faults == 0
        # the disk fills; a new image comes (its journal row does not fit), and a command
        full = _no_room(dive.app.store)
        _image(tmp_path / "images", "b.png", 2)
        cid = dive.command()
        seen = len(dive.statuses)
        with caplog.at_level("WARNING", logger="coex.vehicle"):
            dive.run(6.0)
        assert dive.app.runner.store_problem is not None and dive.app.runner.store_problem.kind == "full"
        text = caplog.text
        assert "the disk is full" in text and str(tmp_path / "vehicle.sqlite") in text
        assert "images wait in their folder" in text and "Traceback" not in text
        assert text.count("the disk is full") == 1  # said once, not at every refused write
        assert dive.answered(cid)  # the link and the commands run on
        assert dive.app.counts["images"] == 1 and len(dive.app._held) == 1  # b.png held, not taken
        assert len(dive.statuses) > seen and dive.statuses[-1].faults & FAULT_STORE  # topside is told
        # room again: the held image is taken (once), topside gets it, the fault clears
        full.full = False
        caplog.clear()
        with caplog.at_level("INFO", logger="coex.vehicle"):
            dive.run(STORE_RECOVERY + 6.0)
        assert dive.app.runner.store_problem is None
        assert dive.app.counts["images"] == 2 and dive.images_topside() == 2
        assert dive.statuses[-1].faults == 0
        assert "writing again" in caplog.text and "store writes again: 1 held item(s) taken now" in caplog.text
        assert len(dive.app.store.marked(TAKEN_PREFIX)) == 2
        dive.app.store.db = full.real
        dive.app.store.storage().db = full.real
        dive.app.close()
        # a restart (existing = true: the folder is read again) takes neither file again
        dive.app = dive.start()
        dive.run(3.0)
        assert dive.app.counts["images"] == 0
        assert len(dive.app.node.sender("imagery").images) == 2  # type: ignore[attr-defined]
    finally:
        dive.app.close()


def test_a_nearly_full_disk_and_a_restart_take_each_file_once(tmp_path: Path) -> None:
    """A disk with a few free pages left in the file (SQLite's ``max_page_count``): some writes
    go, some are refused; killed meanwhile (nothing saved since) and started again still
    nearly full, then with room: every file is taken once, none twice."""
    _image(tmp_path / "images", "a.png", 1)
    dive = Dive(tmp_path)
    try:
        dive.run(3.0)
        _fill(dive.app.store)
        for k in range(3):
            _image(tmp_path / "images", f"b{k}.png", 2 + k)
        dive.run(3.0)
        assert dive.app.runner.store_problem is not None
        dive.app.store.close()  # kill -9: no shutdown, no last snapshot
        dive.app.store = None
        dive.app = dive.start()
        _fill(dive.app.store)
        dive.run(3.0)
        _room(dive.app.store)
        dive.run(STORE_RECOVERY + 5.0)
        assert dive.app.runner.store_problem is None
        names = sorted(k[len(TAKEN_PREFIX):].split("|")[0].rsplit("/", 1)[-1]
                       for k in dive.app.store.marked(TAKEN_PREFIX))
        assert names == ["a.png", "b0.png", "b1.png", "b2.png"]  # each once
        ids = dive.app.node.sender("imagery").images  # type: ignore[attr-defined]
        assert len(ids) == 4
    finally:
        dive.app.close()


# ------------------------------------------------------------------ at start: named, no traceback
def _a_store(tmp: Path) -> Path:
    """A vehicle store with a few snapshots in it."""
    _image(tmp / "images", "a.png", 1)
    dive = Dive(tmp)
    dive.run(3.0)
    dive.app.close()
    return tmp / "vehicle.sqlite"


def _corrupt_a_middle_page(db: Path) -> None:
    """Overwrite a page of a table in the middle of the file (a bad flash block)."""
    con = sqlite3.connect(db)
    size = int(con.execute("PRAGMA page_size").fetchone()[0])
    count = int(con.execute("PRAGMA page_count").fetchone()[0])
    try:
        pages = sorted(int(r[0]) for r in con.execute("SELECT pageno FROM dbstat WHERE name = 'chunk'"))
    except sqlite3.Error:
        pages = [count // 2]
    con.close()
    assert not Path(f"{db}-wal").exists()  # closed cleanly: everything is in the file
    page = pages[len(pages) // 2]
    with db.open("r+b") as f:
        f.seek((page - 1) * size + 8)
        f.write(np.random.default_rng(5).integers(0, 256, size - 16, dtype=np.uint8).tobytes())


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(COEX + args, cwd=cwd, capture_output=True, text=True, timeout=120)


def _read_only(path: Path) -> Any:
    """Make ``path``'s folder's files read-only for the daemon: as a plain user, the mode
    bits; as root (who ignores them), a read-only bind mount of the folder. None if neither
    can be done here."""
    if os.geteuid() != 0:
        path.chmod(0o444)
        return lambda: path.chmod(0o644)
    folder = path.parent
    r = subprocess.run(["mount", "--bind", "-o", "ro", str(folder), str(folder)], capture_output=True)
    if r.returncode != 0:
        return None
    return lambda: subprocess.run(["umount", str(folder)], check=True)


def test_damaged_read_only_and_missing_stores_are_named_at_start_without_a_traceback(tmp_path: Path) -> None:
    db = _a_store(tmp_path)
    good = tmp_path / "good.sqlite"
    shutil.copy(db, good)
    # damaged: a page in the middle of the file overwritten
    _corrupt_a_middle_page(db)
    with pytest.raises(StoreError) as err:
        from coex import NodeStore

        NodeStore(db)
    assert err.value.kind == "damaged"
    out = _run(["vehicle", "--config", "v.toml"], tmp_path)
    assert out.returncode == 2, out
    assert "Traceback" not in out.stderr and str(db) in out.stderr and "is damaged" in out.stderr
    assert "move it away" in out.stderr
    # a folder that does not exist: the check and the daemon say the same
    (tmp_path / "v.toml").write_text((tmp_path / "v.toml").read_text().replace('store = "vehicle.sqlite"',
                                                                             'store = "nowhere/v.sqlite"'))
    check = _run(["config", "check", "v.toml"], tmp_path)
    out = _run(["vehicle", "--config", "v.toml"], tmp_path)
    assert check.returncode == 1 and "node.store" in check.stdout and "nowhere" in check.stdout
    assert out.returncode == 2 and "Traceback" not in out.stderr and "nowhere" in out.stderr
    # read-only
    sub = tmp_path / "ro"
    sub.mkdir()
    shutil.copy(good, sub / "v.sqlite")
    (tmp_path / "v.toml").write_text((tmp_path / "v.toml").read_text().replace('store = "nowhere/v.sqlite"',
                                                                             'store = "ro/v.sqlite"'))
    undo = _read_only(sub / "v.sqlite")
    if undo is None:
        pytest.skip("cannot make a file read-only here (root without a mount)")
    try:
        out = _run(["vehicle", "--config", "v.toml"], tmp_path)
        from coex import NodeStore

        with pytest.raises(StoreError) as err:
            NodeStore(sub / "v.sqlite")  # the store's own refusal, past the check
        assert err.value.kind == "read-only" and str(sub / "v.sqlite") in str(err.value)
    finally:
        undo()
    assert out.returncode == 2, out
    assert "Traceback" not in out.stderr and "is read-only" in out.stderr and str(sub / "v.sqlite") in out.stderr
