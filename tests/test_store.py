"""NodeStore in process: a snapshot plus the journal after it gives the node exactly as it was;
the journal is compacted at each snapshot (what a snapshot holds is not kept twice)."""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

from coex import AcousticChannel, NodeStore

from ._faults import T0, build_dive, run_sim
from .test_store_fixture import digest


class Recorder:
    """Topside's receive path through a store, as the runner does it: journal, then the node."""

    def __init__(self, node: Any, store: NodeStore) -> None:
        self.node, self.store = node, store
        self.inner = node.receive

    def __call__(self, link: int, frame: bytes, now: float) -> Any:
        self.store.record_rx(link, frame, now)
        return self.inner(link, frame, now)


def _dive_with_store(db: Path, *, compact: bool, snapshot_at: float, until: float) -> tuple[Any, NodeStore]:
    dive = build_dive(minutes=3)
    store = NodeStore(db, snapshot_interval=1e9, compact=compact)
    dive.topside.receive = Recorder(dive.topside, store)  # type: ignore[method-assign]

    def snapshot(now: float) -> None:
        recorder = dive.topside.__dict__.pop("receive")  # the test's hook is not node state
        try:
            store.snapshot(dive.topside, now)
        finally:
            dive.topside.receive = recorder  # type: ignore[method-assign]

    dive.inputs.append((snapshot_at, snapshot))
    run_sim(dive, AcousticChannel(loss=0.1, seed=4), until)
    return dive, store


def test_store_restores_a_node_exactly(tmp_path: Path) -> None:
    db = tmp_path / "topside.sqlite"
    dive, store = _dive_with_store(db, compact=True, snapshot_at=T0 + 150.0, until=T0 + 400.0)
    live = digest(dive.topside, products_only=True)
    assert any(k.startswith("bathymetry/") for k in live) and any(k.startswith("imagery/") for k in live)
    (last,) = store.db.execute("SELECT journal_id FROM snapshot").fetchone()
    after = store.count("rx")
    assert last > 0 and after > 0  # a snapshot, and frames after it that the restore replays
    store.close()

    store = NodeStore(db)
    try:
        del dive.topside.receive  # the instance attribute; pickling a Recorder is not the point
        node = store.restore(lambda: build_dive(minutes=3).topside)
    finally:
        store.close()
    assert store.stats["replayed"] == after
    assert digest(node, products_only=True) == live


def test_the_journal_is_compacted_at_each_snapshot(tmp_path: Path) -> None:
    kept, compacted = tmp_path / "kept.sqlite", tmp_path / "compacted.sqlite"
    _, s1 = _dive_with_store(kept, compact=False, snapshot_at=T0 + 150.0, until=T0 + 300.0)
    _, s2 = _dive_with_store(compacted, compact=True, snapshot_at=T0 + 150.0, until=T0 + 300.0)
    try:
        last = s2.db.execute("SELECT journal_id FROM snapshot").fetchone()[0]
        assert last > 0
        rows = [r.id for r in s2.journal()]
        assert rows and min(rows) > last  # nothing the snapshot holds is kept twice
        assert s1.count("rx") == s2.count("rx") + last  # the record-keeping store kept all
        # what the snapshots wrote is counted (one snapshot here: the one in the file)
        size = s2.db.execute("SELECT length(state) FROM snapshot").fetchone()[0]
        size += s2.db.execute("SELECT SUM(length(data)) FROM chunk").fetchone()[0]
        assert s2.stats["snapshots"] == 1 and s2.stats["snapshot_bytes"] == size
    finally:
        s1.close()
        s2.close()


def test_store_is_in_wal_mode(tmp_path: Path) -> None:
    store = NodeStore(tmp_path / "n.sqlite")
    try:
        assert store.db.execute("PRAGMA journal_mode").fetchone()[0].lower() == "wal"
    finally:
        store.close()


def test_a_damaged_or_pickled_snapshot_is_a_clear_error(tmp_path: Path) -> None:
    import pickle
    import shutil
    import sqlite3

    import pytest

    from coex import ConfigError

    from .test_store_fixture import FIXTURES, MINUTES

    def with_state(name: str, blob: bytes) -> Path:
        db = tmp_path / name
        shutil.copy(FIXTURES / "store-v1-topside.sqlite", db)
        con = sqlite3.connect(db)
        con.execute("UPDATE snapshot SET state = ?", (blob,))
        con.commit()
        con.close()
        return db

    good = sqlite3.connect(FIXTURES / "store-v1-topside.sqlite").execute(
        "SELECT state FROM snapshot").fetchone()[0]
    cases = {
        "truncated.sqlite": (good[: len(good) // 2], "unreadable snapshot"),
        "renamed.sqlite": (good.replace(b'"bathymetry.Receiver"', b'"bathymetry.Receivex"'),
                           "does not know"),
        "pickled.sqlite": (pickle.dumps({"node": 1}, protocol=5), "pickled snapshot"),
    }
    for name, (blob, why) in cases.items():
        store = NodeStore(with_state(name, blob))
        try:
            with pytest.raises(ConfigError, match=why) as err:
                store.restore(lambda: build_dive(minutes=MINUTES).topside)
            assert name in str(err.value)
        finally:
            store.close()


def test_a_wrapped_sender_keeps_its_wrapper_and_gets_the_saved_state() -> None:
    """An application that wraps a sender (here a recorder) saves the sender inside; restored,
    the node's wrapper is still the one it built, around the saved sender."""
    from coex import ChannelManager, LinkConfig, Node, Schedule, StreamConfig
    from coex_apps.console.testing import RecordingSender, survey_points
    from coex_plugins.bathymetry import BathymetryModality, BathymetrySender

    def build() -> tuple[Node, RecordingSender]:
        node = Node(ChannelManager(2, [LinkConfig(0, Schedule.simple([1, 2], 5.0, 0.5), dst=1)]))
        wrapper = RecordingSender(BathymetrySender({"send_delay": 0.0, "levels": 3}))
        node.add_sender(BathymetryModality, wrapper, StreamConfig(3, "map"))
        return node, wrapper

    node, wrapper = build()
    wrapper.ingest(survey_points(), 10.0)
    saved = node.export_state()
    fresh, fresh_wrapper = build()
    fresh.restore_state(saved)
    assert fresh.sender("bathymetry") is fresh_wrapper  # the application's own wrapper
    assert fresh_wrapper.inner is not wrapper.inner  # around the restored sender
    assert fresh_wrapper.inner.map.tiles == wrapper.inner.map.tiles != []
    assert fresh.manager._streams[3].sender is fresh_wrapper  # packets are filled through it


def test_snapshots_are_incremental(tmp_path: Path, monkeypatch: Any) -> None:
    """A snapshot writes only the chunks the file does not hold: a second one of an unchanged
    node writes its manifest alone, one after a little more of the dive writes a small part of
    the state, and the chunks no snapshot uses any more are deleted (at once here: they are
    deleted together once there are ``GARBAGE_CHUNKS`` of them); the node comes back whole."""
    import coex_runtime.store
    from coex_runtime.store import chunk_text

    monkeypatch.setattr(coex_runtime.store, "GARBAGE_CHUNKS", 1)

    db = tmp_path / "topside.sqlite"
    dive, store = _dive_with_store(db, compact=True, snapshot_at=T0 + 150.0, until=T0 + 300.0)
    try:
        del dive.topside.receive
        node = dive.topside
        store.snapshot(node, T0 + 300.0)
        first = store.stats["snapshot_bytes"]
        store.snapshot(node, T0 + 300.0)
        again = store.stats["snapshot_bytes"] - first
        (manifest,) = store.db.execute("SELECT length(state) FROM snapshot").fetchone()
        assert again == manifest  # nothing changed: nothing but the list of chunks is written
        run_sim(dive, AcousticChannel(loss=0.1, seed=4), T0 + 330.0)
        before, saved = store.stats["snapshot_bytes"], store.stats["state_bytes"]
        store.snapshot(node, T0 + 330.0)
        changed = store.stats["snapshot_bytes"] - before
        size = store.stats["state_bytes"] - saved
        assert 0 < changed < size / 4, (changed, size)
        text = store.saved_text()
        assert text is not None
        used = {bytes(r[0]) for r in store.db.execute("SELECT hash FROM chunk")}
        assert len(used) == len(set(used))
        assert store.db.execute("SELECT COUNT(*) FROM chunk WHERE dtype IS NULL").fetchone()[0] == \
            len({hash(c) for c in chunk_text(text)})  # only the text's chunks of this snapshot
        live = digest(node, products_only=True)
    finally:
        store.close()
    store = NodeStore(db)
    try:
        back = store.restore(lambda: build_dive(minutes=3).topside)
        assert digest(back, products_only=True) == live
    finally:
        store.close()


def test_content_defined_chunks_resynchronise() -> None:
    """An insertion changes the chunks around it; the others are cut as before."""
    import numpy as np

    from coex_runtime.store import chunk_text

    rng = np.random.default_rng(1)
    data = rng.integers(32, 127, 200_000, dtype=np.uint8).tobytes()
    edited = data[:100_000] + b"a few more bytes" + data[100_000:]
    a, b = chunk_text(data), chunk_text(edited)
    assert b"".join(a) == data and b"".join(b) == edited
    assert all(128 <= len(c) <= 4096 for c in a[:-1])
    assert len(set(a) - set(b)) <= 2 and len(a) > 100


def test_chunks_no_snapshot_names_are_deleted_together_and_never_while_named(tmp_path: Path, monkeypatch: Any) -> None:
    """Chunks the newest snapshot no longer names stay until there are ``GARBAGE_CHUNKS`` of
    them, then go in one snapshot's transaction (deleting each at the snapshot that dropped it
    rewrote as many pages every time); a chunk named again meanwhile is kept; the file always
    restores."""
    import coex_runtime.store
    from coex_runtime.store import chunk_text

    monkeypatch.setattr(coex_runtime.store, "GARBAGE_CHUNKS", 40)
    db = tmp_path / "topside.sqlite"
    dive, store = _dive_with_store(db, compact=True, snapshot_at=T0 + 100.0, until=T0 + 120.0)
    del dive.topside.receive
    unnamed = []
    try:
        for k in range(12):
            run_sim(dive, AcousticChannel(loss=0.1, seed=4), T0 + 120.0 + 15.0 * (k + 1))
            store.snapshot(dive.topside, T0 + 120.0 + 15.0 * (k + 1))
            text = store.saved_text()
            assert text is not None
            named = {coex_runtime.store._digest(c) for c in chunk_text(text)}
            held = {bytes(r[0]) for r in store.db.execute("SELECT hash FROM chunk WHERE dtype IS NULL")}
            assert named <= held  # never a chunk the snapshot names deleted
            unnamed.append(len(held - named))
        live = digest(dive.topside, products_only=True)
    finally:
        store.close()
    assert max(unnamed) < 40 + 40 and any(b < a for a, b in itertools.pairwise(unnamed)), unnamed
    assert max(unnamed) > 0  # kept for a while, not deleted at once
    store = NodeStore(db)
    try:
        assert digest(store.restore(lambda: build_dive(minutes=3).topside), products_only=True) == live
    finally:
        store.close()
