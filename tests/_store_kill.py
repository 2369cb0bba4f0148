"""The store's kill -9 loop, shared by ``tests/test_store_kill.py`` (a few dozen kills) and
``bench/store_kill.py`` (hundreds).

:func:`work` is a writer process: the fault suite's short dive (``tests/_faults.py``) on a
simulated clock as fast as the machine goes, both nodes with a :class:`NodeStore` used as the
runner uses it (every received frame and every input journaled before the node sees it, a
snapshot before every transmission and after received frames every few seconds, the
topside's map spilling tiles to the store's storage). Started again, it carries on from its
stores (the dive's clock from the newer snapshot, the inputs from the marks journaled with
them), so the dive advances from kill to kill.

:func:`kill_loop` starts it, kills it with ``SIGKILL`` at a random moment, and opens both
stores as a restarted daemon would (:func:`check_store`): every time, each must open (SQLite's
page check included) and restore its node. While the writer runs it also takes a read-only
look at the stores (what ``tests/test_persist.py`` does while its processes run): that must
restore too. Writers start from a forkserver that has the modules loaded, so a kill costs
milliseconds of start-up, not seconds of imports."""

from __future__ import annotations

import multiprocessing
import os
import random
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from coex import AcousticChannel, Node, NodeStore, SimNetwork, SimulatedClock, StoreError
from coex_plugins.bathymetry import BathymetryReceiver

from ._faults import T0, Dive, build_dive, images_complete, map_converged, schedule, series_complete

#: minutes of sensor data in the dive; the dive's clock ends at ``T0 + DIVE_SECONDS``
MINUTES = 3
DIVE_SECONDS = 1500.0
#: the runner's default snapshot interval after received frames (dive seconds)
SNAPSHOT_INTERVAL = 5.0
ROLES = ("vehicle", "topside")


def _small_budget(r: Any) -> Any:
    """The topside map with a tiny tile budget, so its tiles spill to the store's storage."""
    if isinstance(r, BathymetryReceiver):
        return BathymetryReceiver({"levels": 3, "memory_budget": 1, "tile_subgrids": 2})
    return r


def dive() -> Dive:
    return build_dive(minutes=MINUTES, wrap_receiver=_small_budget)


def build(role: str) -> Callable[[], Node]:
    def make() -> Node:
        d = dive()
        return d.vehicle if role == "vehicle" else d.topside
    return make


class _Journaled:
    """A node as :class:`SimNetwork` drives it, through its store as the runner does it."""

    def __init__(self, node: Node, store: NodeStore) -> None:
        self.node, self.store = node, store
        self.node_id = node.node_id

    def receive(self, link: int, frame: bytes, now: float) -> Any:
        self.store.record_rx(link, frame, now)  # committed before the node sees it
        return self.node.receive(link, frame, now)

    def poll(self, now: float) -> Any:
        txs = self.node.poll(now)
        for tx in txs:
            for f in tx.frames:
                self.store.record_tx(tx.link_id, f, now)
        self.store.maybe_snapshot(self.node, now, force=bool(txs))  # before they leave
        return txs

    def next_event(self, now: float) -> float | None:
        return self.node.next_event(now)


def _saved_time(store: NodeStore) -> float:
    row = store.db.execute("SELECT t FROM snapshot WHERE id = 1").fetchone()
    return float(row[0]) if row is not None else T0


class Life:
    """One life of the writer: both nodes restored from their stores in ``folder`` (created
    empty the first time), on a :class:`SimNetwork` over ``channel`` from the newer snapshot's
    time, the vehicle's inputs fed as they fall due and the operator's request for image 1 in
    full made once. :meth:`step` runs it; :meth:`close` closes the stores as they are (what a
    ``kill -9`` leaves: what they committed)."""

    def __init__(self, folder: Path, channel: AcousticChannel) -> None:
        self.stores = {r: NodeStore(folder / f"{r}.sqlite", snapshot_interval=SNAPSHOT_INTERVAL) for r in ROLES}
        try:
            self.nodes = {r: self.stores[r].restore(build(r)) for r in ROLES}
        except BaseException:
            self.close()
            raise
        self.template = dive()
        self.start = max(_saved_time(s) for s in self.stores.values())
        self.fed = len(self.stores["vehicle"].marked("fed:"))
        self.net = SimNetwork({0: channel}, SimulatedClock(start=self.start))
        self.net.add_node(_Journaled(self.nodes["vehicle"], self.stores["vehicle"]), (0.0, 0.0, 500.0))  # type: ignore[arg-type]
        self.net.add_node(_Journaled(self.nodes["topside"], self.stores["topside"]), (100.0, 0.0, 0.0))  # type: ignore[arg-type]
        self.net.every(1.0, self._inputs, start=self.start)

    def _inputs(self, now: float) -> None:
        vehicle, vstore, tstore = self.nodes["vehicle"], self.stores["vehicle"], self.stores["topside"]
        feed = self.template.feed
        while self.fed < len(feed) and feed[self.fed][0] <= now:
            _, name, data = feed[self.fed]
            sender = vehicle.sender(name)
            data = sender.journal_form(data)
            # the input and the mark that it was taken: one transaction
            vstore.record_input(name, data, now, mark=f"fed:{self.fed:06d}")
            sender.ingest(data, now)
            self.fed += 1
        if now >= T0 + 200.0 and tstore.get("goal") is None:
            self.nodes["topside"].receiver("imagery").request_goal(1, "full", now=now)  # type: ignore[attr-defined]
            tstore.snapshot(self.nodes["topside"], now)  # the request is in the saved state ...
            tstore.set("goal", "asked")  # ... before it is marked done

    def step(self, until: float) -> bool:
        """One event of the network (False once its clock reached ``until``), then the
        snapshots the runner takes after received frames."""
        if not self.net.step(until):
            return False
        for r in ROLES:
            self.stores[r].maybe_snapshot(self.nodes[r], self.net.now)
        return True

    def as_dive(self) -> Dive:
        """Both nodes as they are now, as a Dive for the fault suite's checks."""
        return _as_dive(self.nodes["vehicle"], self.nodes["topside"], self.template)

    def close(self) -> None:
        for s in self.stores.values():
            s.close()


def work(folder: str, seed: int, until: float = T0 + DIVE_SECONDS, ready: Any = None) -> None:
    """The writer (see the module docstring); returns when the dive's clock reaches ``until``.
    ``ready`` (an event) is set once the dive has advanced by a snapshot in this life."""
    import coex_runtime.store

    coex_runtime.store.GARBAGE_CHUNKS = 64  # chunks no snapshot names are deleted often: killed then too
    life = Life(Path(folder), AcousticChannel(loss=0.1, seed=seed))
    try:
        first = {r: life.stores[r].stats["snapshots"] for r in ROLES}
        while life.step(until):
            if ready is not None and not ready.is_set() and all(
                    life.stores[r].stats["snapshots"] > first[r] for r in ROLES):
                ready.set()  # both stores moved on in this life
        for r in ROLES:
            life.stores[r].snapshot(life.nodes[r], life.net.now)
    finally:
        life.close()


def _work_and_exit(folder: str, seed: int, ready: Any) -> None:
    work(folder, seed, ready=ready)
    ready.set()
    os._exit(0)


def check_store(path: Path, role: str, *, read_only: bool = False) -> Node:
    """Open the store as a restarted daemon would (or for a look) and restore its node: a
    :class:`StoreError` or any other exception is the failure the loop looks for."""
    store = NodeStore(path, read_only=read_only)
    try:
        return store.restore(build(role))
    finally:
        store.close()


@dataclass
class KillReport:
    kills: int = 0
    #: stores opened and restored after a kill (two per kill)
    reopened: int = 0
    #: read-only looks taken while the writer ran
    looks: int = 0
    #: dives the writer finished (each checked: topside holds everything)
    dives: int = 0
    #: what failed: (kill number, role, the error)
    failures: list[tuple[int, str, str]] = field(default_factory=list)
    #: the dive's clock at each kill (how far the writer had got)
    dive_times: list[float] = field(default_factory=list)
    #: for each dive that finished, the number of kills before it finished (where its
    #: successor's clocks begin in ``dive_times``)
    finished: list[int] = field(default_factory=list)
    seconds: float = 0.0


def kill_loop(folder: Path, kills: int, *, seed: int = 1, max_alive: float = 1.2,
              log: Callable[[str], None] | None = None) -> KillReport:
    """Run the writer ``kills`` times into ``folder``, each killed with SIGKILL a random 0 to
    ``max_alive`` seconds after it has moved its dive on by a snapshot (one in four: that long
    after it started, while it opens its stores, replays its journal, takes its first snapshot),
    a look at its stores at a random moment before, and check the stores after each kill. A dive that finishes is checked whole (topside holds the vehicle's
    map, images and series) and the next one starts in a fresh folder."""
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(["tests._store_kill"])
    rng = random.Random(seed)
    report = KillReport()
    started = time.monotonic()
    dive_no = 0
    first_kill = 0  # index in ``dive_times`` of this dive's first kill
    here = folder / f"dive{dive_no}"
    here.mkdir(parents=True, exist_ok=True)
    while report.kills < kills:
        ready = ctx.Event()
        p = ctx.Process(target=_work_and_exit, args=(str(here), rng.randrange(1 << 30), ready), daemon=True)
        p.start()
        # most kills come after the writer has moved its dive on by a snapshot (so the dive
        # advances whatever the machine's load), a random time later; one in four at a random
        # moment of its start (the stores opening, the journal replayed, the first snapshot)
        if report.kills % 4 != 3:
            ready.wait(300.0)
        alive = rng.uniform(0.0, max_alive)
        look_at = rng.uniform(0.0, alive)
        time.sleep(look_at)
        if p.is_alive() and all((here / f"{r}.sqlite").exists() for r in ROLES):
            for r in ROLES:
                try:
                    check_store(here / f"{r}.sqlite", r, read_only=True)
                    report.looks += 1
                except Exception as exc:
                    report.failures.append((report.kills, f"{r} (look)", f"{type(exc).__name__}: {exc}"))
        time.sleep(max(0.0, alive - look_at))
        if p.is_alive():
            assert p.pid is not None
            os.kill(p.pid, signal.SIGKILL)
            p.join()
            report.kills += 1
            for r in ROLES:
                try:
                    check_store(here / f"{r}.sqlite", r)
                    report.reopened += 1
                except Exception as exc:
                    report.failures.append((report.kills, r, f"{type(exc).__name__}: {exc}{_holders(here / f'{r}.sqlite')}"))
                    if isinstance(exc, StoreError) and exc.kind == "damaged":
                        raise AssertionError(f"kill {report.kills}: {r} store unreadable: {exc}") from exc
            report.dive_times.append(round(_dive_clock(here), 1))
            if log is not None and report.kills % 25 == 0:
                log(f"{report.kills} kills, {report.failures[-1:] or 'no failure'}")
            continue
        p.join()
        if p.exitcode != 0:
            report.failures.append((report.kills, "writer", f"exit code {p.exitcode}"))
            break
        # the dive finished: topside must hold everything the vehicle sent
        d = restored_dive(here)
        missing = [what for what, ok in (("map", map_converged(d)), ("images", images_complete(d)),
                                         ("series", series_complete(d))) if not ok]
        if missing:  # which part topside lacks, the dive's clock at each kill of this dive, and
            # whether the dive, run on, converges (a margin) or not (something lost for good)
            report.failures.append((report.kills, "topside", f"the finished dive did not converge: "
                                    f"{', '.join(missing)} incomplete (kills at {report.dive_times[first_kill:]}; "
                                    f"{_run_on(here, rng.randrange(1 << 30))})"))
        report.dives += 1
        report.finished.append(report.kills)
        first_kill = len(report.dive_times)
        dive_no += 1
        here = folder / f"dive{dive_no}"
        here.mkdir(parents=True, exist_ok=True)
    report.seconds = round(time.monotonic() - started, 1)
    return report


#: TDMA cycles a finished dive that did not converge is run on, to tell a margin from a loss
RUN_ON_CYCLES = 20


def _run_on(folder: Path, seed: int) -> str:
    """A finished dive that did not converge, run on from a copy of its stores (the same lossy
    link) for up to :data:`RUN_ON_CYCLES` TDMA cycles: what it then lacks, in words."""
    import shutil
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        for r in ROLES:
            for suffix in ("", "-wal"):
                src = folder / f"{r}.sqlite{suffix}"
                if src.exists():
                    shutil.copy(src, Path(tmp) / src.name)
        life = Life(Path(tmp), AcousticChannel(loss=0.1, seed=seed))
        try:
            cycle = schedule().cycle
            for k in range(1, RUN_ON_CYCLES + 1):
                while life.step(life.start + cycle * k):
                    pass
                d = life.as_dive()
                if map_converged(d) and images_complete(d) and series_complete(d):
                    return f"run on, it converged within {k} TDMA cycles"
        finally:
            life.close()
    return f"run on for {RUN_ON_CYCLES} TDMA cycles, it still did not converge"


def _holders(path: Path) -> str:
    """" (open in: pid cmdline, ...)": the processes that have ``path`` open (for a failure's
    text; Linux /proc, what this user may read)."""
    out = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            if any(Path(os.readlink(fd)) == path for fd in (proc / "fd").iterdir()):
                cmd = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode()
                out.append(f"{proc.name} {cmd[:80]}")
        except OSError:
            continue
    return f" (open in: {'; '.join(out)})" if out else ""


def _dive_clock(folder: Path) -> float:
    store = NodeStore(folder / "topside.sqlite", read_only=True)
    try:
        return _saved_time(store) - T0
    finally:
        store.close()


def restored_dive(folder: Path) -> Dive:
    """Both nodes as their stores in ``folder`` have them, as a Dive for the fault suite's checks."""
    v = check_store(folder / "vehicle.sqlite", "vehicle", read_only=True)
    t = check_store(folder / "topside.sqlite", "topside", read_only=True)
    return _as_dive(v, t, dive())


def _as_dive(v: Node, t: Node, template: Dive) -> Dive:
    return Dive(v, t, v.sender("bathymetry"), v.sender("imagery"), v.sender("timeseries"),  # type: ignore[arg-type]
                t.receiver("bathymetry"), t.receiver("imagery"), t.receiver("timeseries"),  # type: ignore[arg-type]
                series_data=template.series_data)
