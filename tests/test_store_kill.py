"""The store fails safe: killed at any moment (``kill -9``), or refused a write at any of its
write points (a full disk, an I/O error), it leaves a file that opens and restores the node as
it was at a committed point, and a node that carries on writes everything once the disk takes
writes again. ``bench/store_kill.py`` runs the kill loop hundreds of times."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from coex import AcousticChannel, Node, NodeStore, StoreError
from coex.messages import SubgridMessage
from coex_core.acoustic import Arrival
from coex_core.wire import unpack_frame

from ._faults import (
    T0,
    VEHICLE,
    FaultyDb,
    build_dive,
    map_converged,
    run_sim,
    schedule,
    sqlite_full,
    sqlite_ioerr,
)
from ._store_kill import Life, kill_loop
from .test_store_fixture import digest

#: kills in CI (``COEX_STORE_KILLS`` for more; the benchmark runs hundreds)
KILLS = int(os.environ.get("COEX_STORE_KILLS", "24"))


def test_kill_9_at_random_moments_never_leaves_an_unreadable_store(tmp_path: Path) -> None:
    """A writer process (both nodes of a dive, journaling, snapshotting, spilling map tiles)
    killed with SIGKILL at random moments: after every kill both stores open (SQLite's page
    check) and restore, and read-only looks taken while it ran restored too."""
    report = kill_loop(tmp_path, KILLS, seed=7, max_alive=1.0)
    assert report.failures == [], report
    assert report.kills == KILLS and report.reopened == 2 * KILLS
    assert report.looks > 0
    # the dive advanced from kill to kill (the writer resumed from its stores): its clock at the
    # first dive's last kill is later than at its first (a finished dive's successor starts at 0)
    first = report.dive_times[:report.finished[0]] if report.finished else report.dive_times
    assert len(first) >= 2 and first[-1] > first[0], report.dive_times


class _LoseTheLastChildFrame(AcousticChannel):
    """Once ``on``: the last frame of a vehicle packet is lost when it carries a subgrid of the
    finest level (the packet's other frames arrive, so topside's ack names them and not it: the
    vehicle learns that frame's fate only at its ack timeout or a later packet's ack)."""

    def __init__(self, **kw: Any) -> None:
        super().__init__(**kw)
        self.on = False
        self.lost = 0

    def poll(self, now: float) -> list[Arrival]:
        out = []
        for a in super().poll(now):
            last = a.frames[-1] if a.frames else None
            if self.on and a.src == VEHICLE and last is not None and any(
                    isinstance(m, SubgridMessage) and m.level == 0 for m in unpack_frame(last).messages):
                a = dataclasses.replace(a, frames=[*a.frames[:-1], None])
                self.lost += 1
            out.append(a)
        return out


def test_a_kill_between_a_parents_ack_and_its_childs_loss_loses_no_subgrid(tmp_path: Path) -> None:
    """The kill loop's finished dive whose map did not converge (issue 51), at the exact step.
    The survey's last soundings go out as new versions of parents and children in one packet
    (the children coded on their own: the new parents are not acknowledged yet); the packet's
    last frame, with children, is lost. The writer is killed after the vehicle saved a snapshot
    holding the ack of the parents' frames (so its children are now predicted from them, other
    messages than the lost ones) and before it knew the children's frame was lost. Restarted,
    the vehicle learns the loss from the frame record it saved and must send those children
    again: within ten TDMA cycles of a loss-free link (the loss is known one cycle, its ack
    timeout, after the frame left; the re-sends go in the next vehicle slots) topside's map
    equals the vehicle's. Before the fix the loss was taken for an old version's and the map
    never converged (60 cycles tried)."""
    channel = _LoseTheLastChildFrame(loss=0.0, seed=1)
    life = Life(tmp_path, channel)
    try:
        last_ping = max(t for t, name, _ in life.template.feed if name == "bathymetry")
        life.net.at(last_ping, lambda now: setattr(channel, "on", True))
        vstore = life.stores["vehicle"]
        heard: int | None = None  # frames the vehicle had received when the first frame was lost
        saved: int | None = None  # its snapshots when it received the next frame (topside's ack)
        while life.step(T0 + 600.0):
            if channel.lost and heard is None:
                heard = vstore.stats["rx"]
            if heard is not None and saved is None and vstore.stats["rx"] > heard:
                saved = vstore.stats["snapshots"]
            if saved is not None and vstore.stats["snapshots"] > saved:
                break  # kill -9: the stores hold what they committed
        assert channel.lost and saved is not None, "the step was not reached"
    finally:
        life.close()
    life = Life(tmp_path, AcousticChannel(loss=0.0, seed=2))
    try:
        start = life.start
        assert 0 < start - last_ping < 30.0  # killed right after the last soundings went out
        cycles = 0
        while not map_converged(life.as_dive()) and cycles < 10:
            cycles += 1
            while life.step(start + schedule().cycle * cycles):
                pass
        converged = map_converged(life.as_dive())
        assert converged, f"the map did not converge within {cycles} cycles of the restart"
    finally:
        life.close()


# ------------------------------------------------------------------ fault injection
def _frames() -> list[tuple[int, bytes, float]]:
    """What topside received in the first 200 s of the fault suite's dive."""
    dive = build_dive(minutes=2)
    got: list[tuple[int, bytes, float]] = []
    inner = dive.topside.receive

    def recorder(link: int, frame: bytes, now: float) -> Any:
        got.append((link, frame, now))
        return inner(link, frame, now)

    dive.topside.receive = recorder  # type: ignore[method-assign]
    run_sim(dive, AcousticChannel(loss=0.1, seed=4), T0 + 200.0)
    return got


FRAMES: list[tuple[int, bytes, float]] = []


def _topside_ops() -> list[Callable[[Node, NodeStore], None]]:
    """Topside's writes, as the runner makes them: each frame journaled then received (the
    map's tiles spill to the store's storage), a snapshot after every quarter of them."""
    if not FRAMES:
        FRAMES.extend(_frames())
    frames = FRAMES[:16]

    def receive(link: int, f: bytes, t: float) -> Callable[[Node, NodeStore], None]:
        def op(node: Node, store: NodeStore) -> None:
            try:
                store.record_rx(link, f, t)
            finally:  # the runner gives the frame to the node even when the journal fails
                node.receive(link, f, t)
        return op

    ops: list[Callable[[Node, NodeStore], None]] = []
    quarter = max(1, len(frames) // 4)
    for i, (link, f, t) in enumerate(frames):
        ops.append(receive(link, f, t))
        if i % quarter == quarter - 1:
            ops.append(lambda node, store, t=t: store.snapshot(node, t))
    return ops


def _vehicle_ops() -> list[Callable[[Node, NodeStore], None]]:
    """The vehicle's writes: inputs journaled with their marks, snapshots between them."""
    feed = build_dive(minutes=2).feed[:30]

    def take(i: int) -> Callable[[Node, NodeStore], None]:
        t, name, data = feed[i]

        def op(node: Node, store: NodeStore) -> None:
            sender = node.sender(name)
            store.record_input(name, sender.journal_form(data), t, mark=f"fed:{i:04d}")
            sender.ingest(data, t)
        return op

    ops: list[Callable[[Node, NodeStore], None]] = []
    for i in range(len(feed)):
        ops.append(take(i))
        if i % 10 == 9:
            ops.append(lambda node, store, t=feed[i][0]: store.snapshot(node, t))
    return ops


def _topside() -> Node:
    """The fault suite's topside (``build_dive``'s, without building the whole dive), its map
    with a tiny tile budget so that its tiles spill to the store's storage."""
    from coex import ChannelManager, LinkConfig
    from coex_plugins.bathymetry import BathymetryModality, BathymetryReceiver
    from coex_plugins.imagery import ImageryModality
    from coex_plugins.timeseries import TimeSeriesModality

    from ._faults import TOPSIDE

    node = Node(ChannelManager(TOPSIDE, [LinkConfig(0, schedule(), rate=5, dst=VEHICLE)]))
    node.add_receiver(BathymetryModality, BathymetryReceiver({"levels": 3, "memory_budget": 1, "tile_subgrids": 2}))
    node.add_receiver(ImageryModality, ImageryModality().receiver({"retry": 10.0, "max_tries": 1000}))
    node.add_receiver(TimeSeriesModality, TimeSeriesModality().receiver(None))
    return node


def _build(role: str) -> Callable[[], Node]:
    if role == "topside":
        return _topside
    return lambda: build_dive(minutes=2).vehicle


def _state(node: Node, role: str, store: NodeStore | None = None) -> Any:
    if role == "topside":
        return digest(node, products_only=True)
    return (digest(node)["manager"]["queued"], sorted((s.name, s.sender.pending_bytes()) for s in node._senders),
            None if store is None else len(store.marked("fed:")))


@pytest.mark.parametrize("role", ["topside", "vehicle"])
def test_a_write_refused_at_any_write_point_leaves_a_store_that_restores(tmp_path: Path, role: str,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """Every statement a node's store runs (journal rows, marks, snapshots: chunks, manifest,
    journal compaction, the storage's rows and generation) refused in turn, as by a full disk
    or an I/O error: the store raises :class:`StoreError` naming the file (never an
    sqlite3 error); a process that dies there leaves a file that restores the node as after
    the last operation that committed (or the one that failed, when what failed was a spilled
    tile kept in memory); a node that carries on writes it all with its next snapshot."""
    import coex_runtime.store

    monkeypatch.setattr(coex_runtime.store, "GARBAGE_CHUNKS", 1)  # unnamed chunks deleted at every snapshot
    ops = _topside_ops() if role == "topside" else _vehicle_ops()
    # the states the restored node may be in: before and after each operation
    ref_store = NodeStore(tmp_path / "ref.sqlite")
    node = ref_store.restore(_build(role))
    counter = FaultyDb(ref_store.db)
    ref_store.db = counter  # type: ignore[assignment]
    ref_store.storage().db = counter  # type: ignore[assignment]
    states = [_state(node, role)]
    for op in ops:
        op(node, ref_store)
        states.append(_state(node, role))
    ref_store.close()
    writes = [i + 1 for i, q in enumerate(counter.sql) if not q.startswith("SELECT")]
    kinds = {q for q in counter.sql if not q.startswith("SELECT")}
    assert len(writes) > 30 and len(kinds) >= 10, kinds
    if role == "topside":  # the map's spilled tiles, their generation's commit, chunks no snapshot names
        assert {"INSERT OR REPLACE INTO storage (key, gen, data) VALUES (?, ?, ?)",
                "INSERT OR REPLACE INTO meta (key, value) VALUES ('storage_gen', ?)",
                "DELETE FROM chunk WHERE id = ?"} <= kinds, kinds
    else:  # an input and its mark, in one transaction
        assert "INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)" in kinds, kinds
    # every kind of write (and the reads inside a snapshot's transaction), the first and the
    # last time each is run
    first: dict[str, int] = {}
    last: dict[str, int] = {}
    for i, q in enumerate(counter.sql, 1):
        first.setdefault(q, i)
        last[q] = i
    points = sorted({*first.values(), *last.values()})
    for k in points:
        for carry_on in (False, True):
            db = tmp_path / f"k{k}-{int(carry_on)}.sqlite"
            store = NodeStore(db)
            node = store.restore(_build(role))
            faulty = FaultyDb(store.db, k, sqlite_full() if k % 2 else sqlite_ioerr())
            store.db = faulty  # type: ignore[assignment]
            store.storage().db = faulty  # type: ignore[assignment]
            failed_op = None
            for j, op in enumerate(ops):
                try:
                    op(node, store)
                except StoreError as exc:
                    assert str(db) in str(exc) and exc.kind in ("full", "io"), exc
                    failed_op = j
                    if not carry_on:
                        break
                if faulty.failed and failed_op is None:
                    failed_op = j  # a spilled tile refused: kept in memory, no error raised
                    if not carry_on:
                        break
            assert faulty.failed, k
            if carry_on:
                store.snapshot(node, 1e10)  # the disk takes writes again: everything is written
                live = _state(node, role, store)
            store.db = faulty.real  # type: ignore[assignment]
            store.close()  # (kill -9: what was not committed is not in the file)
            again = NodeStore(db)
            try:
                back = again.restore(_build(role))
                got = _state(back, role, again)
            finally:
                again.close()
            if carry_on:
                assert got == live, (k, failed_op)
            else:
                assert failed_op is not None
                if role == "vehicle":
                    got = got[:2]
                    allowed = [s[:2] for s in states[failed_op:failed_op + 2]]
                else:
                    allowed = states[failed_op:failed_op + 2]
                assert got in allowed, (k, failed_op)
