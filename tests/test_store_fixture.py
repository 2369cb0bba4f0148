"""Stores written by an earlier version must load: committed fixtures (tests/fixtures/) of a
vehicle's and a topside's store, and what their nodes held when they were written.

Made with ``python -m tests.test_store_fixture --write`` (only when the state format gains a
version: a new fixture beside the old ones, never a replacement).
"""

from __future__ import annotations

import hashlib
import json
import shutil
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from coex import AcousticChannel, ConfigError, NodeStore
from coex_runtime.store import SCHEMA_VERSION

from ._faults import T0, build_dive, run_sim

FIXTURES = Path(__file__).resolve().parent / "fixtures"
VERSIONS = ["v1", "v2", "v3"]  # v2: incremental snapshots (store schema 2, state in parts); v3: chunks by id (schema 3)
MINUTES = 2


def digest(node: Any, products_only: bool = False) -> dict[str, Any]:
    """What the node holds, in a form a later version can compare with: per product, its
    version and a hash of its data (and, unless ``products_only``, the manager's and senders'
    counters)."""
    out: dict[str, Any] = {}
    for name, rx in node.receivers():
        for p in rx.products():
            data = p.data
            if isinstance(data, np.ndarray):
                raw = np.nan_to_num(np.asarray(data, float), nan=-9999.0).round(4).tobytes()
            else:
                raw = repr(data).encode()
            out[f"{name}/{p.key}"] = [int(p.version), hashlib.sha256(raw).hexdigest()[:16]]
    if products_only:
        return out
    mgr = node.manager
    out["manager"] = {"command_id": mgr._command_id, "queued": sum(len(q) for q in mgr.streams),
                      "packets": mgr.stats["packets"]}
    for name, tx in ((s.name, s.sender) for s in node._senders):
        out[f"sender/{name}"] = tx.pending_bytes()
    return out


def write(version: str) -> None:
    FIXTURES.mkdir(exist_ok=True)
    dive = build_dive(minutes=MINUTES)
    run_sim(dive, AcousticChannel(loss=0.2, seed=5), T0 + 200.0)
    expected = {}
    for role in ("vehicle", "topside"):
        node = getattr(dive, role)
        path = FIXTURES / f"store-{version}-{role}.sqlite"
        path.unlink(missing_ok=True)
        store = NodeStore(path)
        store.snapshot(node, T0 + 200.0)
        store.db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        store.close()
        expected[role] = digest(node)
    (FIXTURES / f"store-{version}.json").write_text(json.dumps(expected, indent=1, sort_keys=True))


@pytest.mark.parametrize("version", VERSIONS)
@pytest.mark.parametrize("role", ["vehicle", "topside"])
def test_a_store_of_an_earlier_version_loads(tmp_path: Path, version: str, role: str) -> None:
    source = FIXTURES / f"store-{version}-{role}.sqlite"
    db = tmp_path / source.name  # SQLite writes to an opened file: never open the fixture itself
    shutil.copy(source, db)
    expected = json.loads((FIXTURES / f"store-{version}.json").read_text())[role]
    store = NodeStore(db)
    again = NodeStore(tmp_path / "again.sqlite")
    try:
        # the 0.1 file never set a schema version: it is migrated to the present one
        assert store.schema_found == (0 if version == "v1" else store.schema_found)
        assert store.db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
        node = store.restore(lambda: getattr(build_dive(minutes=MINUTES), role))
        assert digest(node) == expected
        # and it goes on working: moved to another store (its modalities' out-of-core storage
        # too, while the first store is open), another snapshot of it loads too
        node.attach_storage(again.storage())
    finally:
        store.close()
    try:
        again.snapshot(node, T0 + 300.0)
        twin = again.restore(lambda: getattr(build_dive(minutes=MINUTES), role))
    finally:
        again.close()
    assert digest(twin) == expected


def test_a_store_of_a_newer_schema_is_refused_not_written(tmp_path: Path) -> None:
    path = tmp_path / "future.sqlite"
    NodeStore(path).close()
    import sqlite3

    with sqlite3.connect(path) as db:
        db.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    with pytest.raises(ConfigError, match="written by a newer CoEx"):
        NodeStore(path)
    fresh = NodeStore(tmp_path / "new.sqlite")
    try:
        assert fresh.schema_found == 0 and fresh.db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
    finally:
        fresh.close()


if __name__ == "__main__" and "--write" in sys.argv:
    write(VERSIONS[-1])
