"""The out-of-core map (issue: a day-long dive, a 100 km² map): tiles leave memory for the node's
storage and come back losing nothing, a request for an evicted region is served, the sender looks
only at changed tiles, a restart restores spilled tiles without counting soundings twice, and an
exhausted budget is reported, never silent."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from coex import ChannelManager, LinkConfig, Node, NodeStore, Schedule, StreamConfig
from coex_core import state, wire
from coex_core.messages import MapMetadata, MapRoiRequest, Subgrid, SubgridMessage
from coex_plugins.bathymetry import BathymetryModality, BathymetrySender
from coex_plugins.bathymetry.quadtree import QuadtreeMap

TILE_BYTES = 4 * 8 * 128 * 128
#: a budget that keeps the minimum of 4 tiles in memory
SMALL = 4 * TILE_BYTES


def survey(n_lines: int = 6, length: float = 900.0, seed: int = 3) -> list[tuple[float, np.ndarray]]:
    """Batches of a lawnmower over ``n_lines`` lines of 100 m swath (about 8 x 5 tiles)."""
    rng = np.random.default_rng(seed)
    out = []
    t = 0.0
    for line in range(n_lines):
        for x0 in np.arange(0.0, length, 50.0):
            x = rng.uniform(x0, x0 + 50.0, 12000)
            y = rng.uniform(line * 100.0, line * 100.0 + 100.0, x.size)
            z = -40.0 + 3.0 * np.sin(x / 80.0) * np.cos(y / 120.0) + rng.normal(0, 0.05, x.size)
            t += 10.0
            out.append((t, np.column_stack([x, y, z])))
    return out


def fed(m: QuadtreeMap, batches: list[tuple[float, np.ndarray]]) -> QuadtreeMap:
    for t, xyz in batches:
        m.add_points(xyz, t)
    m.flush(force=True)
    return m


def test_tiles_spilled_and_reloaded_lose_nothing() -> None:
    batches = survey()
    ref = fed(QuadtreeMap(), batches)
    small = fed(QuadtreeMap(memory_budget=SMALL), batches)
    assert len(ref.tiles) > 20 and small.tiles == ref.tiles
    assert small.resident <= 4 < len(small.tiles), "the budget keeps 4 tiles in memory"
    assert small.spills > 0 and small.loads > 0, "tiles left memory and came back while soundings landed"
    assert (small.accepted, small.rejected, small.dropped) == (ref.accepted, ref.rejected, ref.dropped)
    for level in range(ref.levels):
        a, _, _ = ref.grid(level)
        b, _, _ = small.grid(level)
        np.testing.assert_array_equal(a, b)
    for key in ref.tiles:
        for level in range(ref.levels):
            np.testing.assert_array_equal(ref.subgrid_times(key, level), small.subgrid_times(key, level))
            for x, y in zip(ref.level_stats(key, level), small.level_stats(key, level), strict=True):
                np.testing.assert_array_equal(x, y)
    assert small.resident <= 4


def test_saved_state_holds_the_spilled_tiles() -> None:
    """Without a node store the spilled tiles are in the map's memory storage, saved with it."""
    batches = survey(n_lines=3)
    m = fed(QuadtreeMap(memory_budget=SMALL), batches)
    back = state.loads(state.dumps(m))
    for level in range(m.levels):
        np.testing.assert_array_equal(m.grid(level)[0], back.grid(level)[0])


def _sender(budget: int = SMALL, **cfg: Any) -> BathymetrySender:
    return BathymetrySender({"levels": 5, "memory_budget": budget, "send_delay": 5.0, **cfg})


def _drain(s: BathymetrySender, now: float) -> list[Subgrid]:
    out: list[Subgrid] = []
    while True:
        got = s.fill(4000, now)
        if not got:
            return out
        out.extend(m for m in got if isinstance(m, SubgridMessage))


def test_a_request_for_an_evicted_region_is_served_as_from_memory() -> None:
    batches = survey(n_lines=2, length=300.0)  # 6 tiles for the 4 the budget keeps: tiles are evicted
    ref, small = _sender(512 * 2**20), _sender()
    for s in (ref, small):
        for t, xyz in batches:
            s.ingest(xyz, t)
    now = batches[-1][0] + 100.0
    _drain(ref, now)
    _drain(small, now)
    assert small.map._slots[(0, 0)] not in small.map._res, "the first tile left memory"
    loads = small.map.loads
    req = MapRoiRequest(1, 0, 0, 0, 8, 8, True, (), 0)  # topside holds none of the 64 subgrids
    a = ref.handle(req, now + 1.0)
    b = small.handle(req, now + 1.0)
    assert a == b and b[0].queued == 64
    got_ref, got_small = _drain(ref, now + 2.0), _drain(small, now + 2.0)
    assert got_small == got_ref and len(got_small) == 64
    assert small.map.loads > loads, "the evicted tile was read back to answer"


def test_the_sender_looks_only_at_changed_tiles(monkeypatch: pytest.MonkeyPatch) -> None:
    s = _sender(512 * 2**20)
    batches = survey(n_lines=2, length=400.0)  # 8 tiles, among them (2, 1), where soundings land below
    for t, xyz in batches:
        s.ingest(xyz, t)
    now = batches[-1][0] + 100.0
    _drain(s, now)
    looked: list[int] = []
    orig = BathymetrySender._tile_found

    def spy(self: BathymetrySender, level: int, n: int, now: float, quiet: bool) -> Any:
        looked.append(n)
        return orig(self, level, n, now, quiet)

    monkeypatch.setattr(BathymetrySender, "_tile_found", spy)
    assert all(isinstance(m, MapMetadata) for m in s.fill(240, now + 10.0))
    assert looked == [], "nothing changed: no tile is looked at"
    # new soundings on one tile: only that tile is looked at
    s.ingest(np.column_stack([np.full(50, 300.5), np.full(50, 250.5), np.full(50, -40.0)]), now + 20.0)
    got = _drain(s, now + 60.0)
    assert {(m.level, m.ix // (16 >> m.level), m.iy // (16 >> m.level)) for m in got} <= {
        (lv, 2, 1) for lv in range(5)}
    assert got and set(looked) == {s.map._slots[(2, 1)]}


def _build(**cfg: Any) -> Node:
    node = Node(ChannelManager(2, [LinkConfig(0, Schedule.simple([1, 2], 20.0, 2.0), rate=5, dst=1)]))
    node.add_sender(BathymetryModality, _sender(**cfg), StreamConfig(3, "map", priority=30))
    return node


def test_a_restart_restores_spilled_tiles_without_counting_soundings_twice(tmp_path: Path) -> None:
    """Tiles spilled after the last snapshot are discarded on restore; the journal replayed after
    the snapshot rebuilds them (the hazard: counting their soundings twice)."""
    batches = survey()
    ref = fed(QuadtreeMap(), batches)
    db = tmp_path / "vehicle.db"
    store = NodeStore(db)
    node = store.restore(_build)
    half = len(batches) // 2
    for i, (t, xyz) in enumerate(batches):
        store.record_input("bathymetry", xyz, t)  # as the runner does, before the sender takes it
        node.sender("bathymetry").ingest(xyz, t)
        if i == half:
            store.snapshot(node, t)
    spills_after = node.sender("bathymetry").map.spills
    assert spills_after > 0
    store.close()  # killed: no snapshot since the middle of the survey
    store = NodeStore(db)
    node = store.restore(_build)
    m = node.sender("bathymetry").map
    m.flush(force=True)
    assert m.accepted == ref.accepted
    for level in range(ref.levels):
        np.testing.assert_array_equal(ref.grid(level)[0], m.grid(level)[0])
    # and once more from a snapshot at the end: nothing replayed, the same map
    store.snapshot(node, batches[-1][0] + 1.0)
    store.close()
    store = NodeStore(db)
    node = store.restore(_build)
    assert store.stats["replayed"] == 0
    np.testing.assert_array_equal(ref.grid(0)[0], node.sender("bathymetry").map.grid(0)[0])
    store.close()


def test_an_exhausted_budget_is_reported_not_silent(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    store = NodeStore(tmp_path / "vehicle.db")
    node = store.restore(lambda: _build(disk_budget=3 * 2**20))
    s = node.sender("bathymetry")
    batches = survey()
    for t, xyz in batches:
        s.ingest(xyz, t)
    s.map.flush(force=True)
    assert s.map.dropped > 0 and s.map.overflow is not None and "disk budget" in s.map.overflow
    with caplog.at_level(logging.WARNING, logger="coex_plugins.bathymetry.sender"):
        out = s.fill(240, batches[-1][0] + 100.0)
    assert any("disk budget" in r.getMessage() for r in caplog.records), "logged"
    meta = [m for m in out if isinstance(m, MapMetadata)]
    assert meta and meta[0].dropped_k == -(-s.map.dropped // 1000)
    assert wire.decode(wire.encode(meta[0])).dropped_k == meta[0].dropped_k, "topside gets it"
    store.close()


def test_max_tiles_cap_is_reported() -> None:
    s = _sender(max_tiles=2)
    batches = survey(n_lines=2)
    for t, xyz in batches:
        s.ingest(xyz, t)
    s.map.flush(force=True)
    assert len(s.map.tiles) == 2 and s.map.dropped > 0 and "max_tiles" in (s.map.overflow or "")
    meta = [m for m in s.fill(240, batches[-1][0] + 100.0) if isinstance(m, MapMetadata)]
    assert meta[0].dropped_k > 0
