"""The topside map at scale (issue 27): the receiver holds its levels as tiles within a memory
budget (spilled to storage and read back losing nothing), draws a big level as a bounded,
decimated overview, reads what is on screen with ``window``, streams GeoTIFF exports from its
tiles, and restores from a NodeStore with spilled tiles."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from coex import AcousticChannel, NodeStore
from coex_core import state
from coex_core.messages import Subgrid
from coex_core.storage import MemoryStorage
from coex_plugins.bathymetry import BathymetryReceiver, encode_subgrid, write_level_geotiff
from coex_plugins.bathymetry.export import read_geotiff

from ._faults import T0, build_dive, run_sim
from .test_store_fixture import digest

SIDE = 8


def _subgrid(level: int, ix: int, iy: int, stamp: int, seed: int, holes: bool = True) -> Subgrid:
    """A subgrid of a smooth slope plus noise (0.1 m units); some cells missing when ``holes``."""
    rng = np.random.default_rng(abs(seed))
    yy, xx = np.mgrid[0:SIDE, 0:SIDE]
    q = -5000 + (ix * SIDE + xx) + 2 * (iy * SIDE + yy) + rng.integers(-20, 20, (SIDE, SIDE))
    present = np.ones((SIDE, SIDE), bool)
    if holes and seed % 3 == 0:
        present[rng.random((SIDE, SIDE)) < 0.4] = False
    return encode_subgrid(q, present, level=level, ix=ix, iy=iy, stamp=stamp, resolution=1.0,
                          vertical_resolution=0.1)


def _survey(nx: int, ny: int, levels: int = 2, x0: int = -3, y0: int = -2, stamp: int = 100,
            skip: int = 7) -> list[Subgrid]:
    """Subgrids of a ``nx x ny`` block at level 0 (every ``skip``-th one missing) and the
    coarser levels over the same area."""
    out = []
    for level in range(levels):
        n = 1 << level
        for iy in range(y0 // n, (y0 + ny - 1) // n + 1):
            for ix in range(x0 // n, (x0 + nx - 1) // n + 1):
                if (ix * 31 + iy * 17) % skip == 0:
                    continue
                out.append(_subgrid(level, ix, iy, stamp, seed=ix * 1000 + iy * 7 + level))
    return out


def _feed(rx: BathymetryReceiver, msgs: list[Subgrid], now: float = 1000.0) -> None:
    for m in msgs:
        rx.receive(m, now)


def _full(rx: BathymetryReceiver, level: int) -> tuple[np.ndarray, tuple[float, float, float]]:
    """The whole level at full resolution, from ``window`` over its extent."""
    summary = rx.level_summary(level)
    assert summary is not None
    ix0, iy0, ix1, iy1 = summary["extent"]
    span = SIDE * summary["cell"]
    grid, geo = rx.window(level, ix0 * span, iy0 * span, ix1 * span, iy1 * span,
                          max_cells=10**9)
    assert geo[2] == summary["cell"]
    return grid, geo


def _fingerprint(rx: BathymetryReceiver) -> list[Any]:
    """Everything the receiver tells of its levels, in a comparable form."""
    out: list[Any] = [rx.levels()]
    for level in rx.levels():
        keys, stamps, received = rx.held_subgrids(level)
        order = np.lexsort((keys[:, 1], keys[:, 0]))
        grid, geo = _full(rx, level)
        p = rx.level_product(level, 2000.0)
        span, ckeys, oldest = rx.coverage(level, 8)
        out.append((keys[order].tolist(), stamps[order].tolist(), received[order].tolist(),
                    rx.holdings(level), np.nan_to_num(grid, nan=1e9).tolist(), geo,
                    np.nan_to_num(p.data, nan=1e9).tolist(), p.version, p.meta,
                    rx.level_summary(level), span, ckeys.tolist(), oldest.tolist()))
    return out


def _assert_same(a: BathymetryReceiver, b: BathymetryReceiver) -> None:
    assert _fingerprint(a) == _fingerprint(b)


def test_tiles_spilled_and_read_back_lose_nothing() -> None:
    msgs = _survey(40, 30)
    newer = [dataclasses.replace(m, stamp=m.stamp + 50) for m in msgs[::5]]
    big = BathymetryReceiver({"levels": 2})
    tiny = BathymetryReceiver({"levels": 2, "memory_budget": 1, "tile_subgrids": 4})
    for rx in (big, tiny):
        _feed(rx, msgs)
        _feed(rx, newer, 1100.0)  # newer versions of spilled subgrids replace them
        _feed(rx, msgs[:40], 1200.0)  # older copies: duplicates, nothing changes
        assert rx.duplicates == 40
    assert len(tiny._tiles) == 1 and tiny.disk_bytes() > 0 and big.disk_bytes() == 0
    _assert_same(big, tiny)
    m = newer[3]
    assert tiny.age(m.level, m.ix, m.iy, 1500.0) == big.age(m.level, m.ix, m.iy, 1500.0) == 1500.0 - 150
    assert tiny.region_stamps(0, -3, -2, 9, 9) == big.region_stamps(0, -3, -2, 9, 9)
    # a spilled subgrid forgotten is gone from both the tiles and the drawn level
    k = msgs[0]
    assert tiny.forget(k.level, k.ix, k.iy) and big.forget(k.level, k.ix, k.iy)
    assert (k.ix, k.iy) not in tiny.holdings(k.level)
    _assert_same(big, tiny)


def test_resident_tiles_stay_within_the_budget_on_a_map_far_larger() -> None:
    n = 4  # 4 x 4 subgrids a tile: 32 x 32 cells
    tile_bytes = (n * SIDE) ** 2 * 8 + n * n * (8 + 8 + 1)
    budget = 5 * tile_bytes
    rx = BathymetryReceiver({"levels": 3, "memory_budget": budget, "tile_subgrids": n})
    msgs = _survey(64, 64, levels=3, x0=0, y0=0)  # 256 tiles at level 0 alone
    for i, m in enumerate(msgs):
        rx.receive(m, 1000.0 + i)
        assert rx.resident_bytes() <= budget
        assert rx.resident_bytes() == len(rx._tiles) * tile_bytes
    tiles = sum(ix.n for ix in rx._index.values())
    assert tiles > 50 * 5  # the map is over 50 times the budget
    assert rx.disk_bytes() > 0
    assert rx.overview_bytes() <= 3 * 16 * 1024 * 1024 * 8
    # every subgrid is there, read back from storage
    for level in range(3):
        want = {(m.ix, m.iy) for m in msgs if m.level == level}
        assert set(rx.holdings(level)) == want
        assert rx.resident_bytes() <= budget


def test_a_level_too_big_to_draw_is_a_decimated_overview_with_nothing_left_out() -> None:
    msgs = _survey(48, 40, levels=1)
    cap = 4096  # cells: the level is 384 x 320
    rx = BathymetryReceiver({"levels": 1, "max_mosaic_cells": cap})
    ref = BathymetryReceiver({"levels": 1})
    for r in (rx, ref):
        _feed(r, msgs)
        _feed(r, [dataclasses.replace(m, stamp=200) for m in msgs[::4]], 1100.0)
        assert r.forget(0, msgs[1].ix, msgs[1].iy)
    p = rx.level_product(0)
    k = p.meta["step"]
    assert k > 1 and p.data.size <= cap and p.meta["cell_size"] == k * 1.0
    assert p.meta["subgrids"] == len(ref.holdings(0)) and p.meta["level_cell"] == 1.0
    full = ref.level_product(0)
    assert full.meta["step"] == 1
    # the overview is the mean of each k x k block of the full-resolution level
    z = full.data
    fx0, fy0 = int(full.meta["x0"]), int(full.meta["y0"])
    ox0, oy0 = int(p.meta["x0"]), int(p.meta["y0"])
    pad = np.full((p.data.shape[0] * k, p.data.shape[1] * k), np.nan)
    r0, c0 = fy0 - oy0, fx0 - ox0
    h, w = min(z.shape[0], pad.shape[0] - r0), min(z.shape[1], pad.shape[1] - c0)
    pad[r0:r0 + h, c0:c0 + w] = z[:h, :w]
    blocks = pad.reshape(p.data.shape[0], k, p.data.shape[1], k)
    fin = np.isfinite(blocks).sum(axis=(1, 3))
    with np.errstate(invalid="ignore"):
        want = np.where(fin > 0, np.nansum(blocks, axis=(1, 3)) / np.maximum(fin, 1), np.nan)
    np.testing.assert_allclose(p.data, want, rtol=1e-5, atol=1e-3)
    # every held subgrid shows in its block
    for ix, iy in ref.holdings(0):
        r, c = (iy * SIDE - oy0) // k, (ix * SIDE - ox0) // k
        if np.isfinite(z[iy * SIDE - fy0:(iy + 1) * SIDE - fy0, ix * SIDE - fx0:(ix + 1) * SIDE - fx0]).any():
            assert np.isfinite(p.data[r:r + max(1, SIDE // k), c:c + max(1, SIDE // k)]).any()
    # window at full resolution is the same on both
    np.testing.assert_array_equal(_full(rx, 0)[0], _full(ref, 0)[0])


def test_window_matches_the_level_on_a_small_map_and_decimates_a_large_one() -> None:
    rx = BathymetryReceiver({"levels": 2, "tile_subgrids": 4, "memory_budget": 20_000})
    _feed(rx, _survey(30, 20))
    p = rx.level_product(0)
    assert p.meta["step"] == 1
    x0, y0 = p.meta["x0"], p.meta["y0"]
    # the whole drawn level, and a part of it not aligned on subgrids
    grid, geo = rx.window(0, x0, y0, x0 + p.data.shape[1], y0 + p.data.shape[0])
    assert geo == (x0, y0, 1.0)
    np.testing.assert_array_equal(grid, p.data)
    grid, geo = rx.window(0, x0 + 13.5, y0 + 7.2, x0 + 101.0, y0 + 55.9)
    assert geo == (x0 + 13, y0 + 7, 1.0) and grid.shape == (49, 88)
    np.testing.assert_array_equal(grid, p.data[7:56, 13:101])
    # empty where nothing is held; a level never received has the level's geometry
    grid, geo = rx.window(0, 5000.0, 5000.0, 5010.0, 5004.0)
    assert grid.shape == (4, 10) and np.isnan(grid).all()
    grid, geo = rx.window(3, 0.0, 0.0, 64.0, 64.0)
    assert geo[2] == 8.0 and grid.shape == (8, 8) and np.isnan(grid).all()
    # too large: block means of 2^j x 2^j cells, blocks aligned on the level's grid
    full = p.data
    for max_cells in (2000, 300, 40):
        grid, (gx, gy, cell) = rx.window(0, x0, y0, x0 + full.shape[1], y0 + full.shape[0],
                                         max_cells=max_cells)
        s = int(cell)
        assert s > 1 and grid.size <= max_cells and gx % s == 0 and gy % s == 0
        pad = np.full((grid.shape[0] * s, grid.shape[1] * s), np.nan)
        r0, c0 = int(y0 - gy), int(x0 - gx)
        pad[r0:r0 + full.shape[0], c0:c0 + full.shape[1]] = full
        blocks = pad.reshape(grid.shape[0], s, grid.shape[1], s)
        fin = np.isfinite(blocks).sum(axis=(1, 3))
        want = np.where(fin > 0, np.nansum(blocks, axis=(1, 3)) / np.maximum(fin, 1), np.nan)
        np.testing.assert_allclose(grid, want, rtol=1e-12)
    # decimated from the tiles (finer than the overview's step) gives the same means
    small = BathymetryReceiver({"levels": 2, "max_mosaic_cells": 1024, "tile_subgrids": 4,
                                "memory_budget": 20_000})
    _feed(small, _survey(30, 20))
    assert small.level_product(0).meta["step"] >= 4
    a, ga = small.window(0, x0, y0, x0 + full.shape[1], y0 + full.shape[0], max_cells=20_000)
    b, gb = rx.window(0, x0, y0, x0 + full.shape[1], y0 + full.shape[0], max_cells=20_000)
    assert ga == gb and ga[2] == 2.0
    np.testing.assert_allclose(a, b, rtol=1e-12)


def test_the_streamed_geotiff_is_the_level(tmp_path: Path) -> None:
    import tifffile

    rx = BathymetryReceiver({"levels": 2, "memory_budget": 1, "tile_subgrids": 4,
                             "origin_lat": 43.5, "origin_lon": 16.2})
    _feed(rx, _survey(70, 45))
    for level in (0, 1):
        path = write_level_geotiff(tmp_path / f"l{level}.tif", rx, level, tile=64)
        grid, geo = read_geotiff(path)
        want, (x0, y0, cell) = _full(rx, level)
        np.testing.assert_array_equal(grid, want.astype(np.float32))
        assert (geo["x0"], geo["y0"], geo["cell"]) == (x0, y0, cell)
        assert geo["geodoubles"] == (16.2, 43.5, 0.0, 0.0, 1.0) and geo["nodata"] == "nan"
        with tifffile.TiffFile(path) as tif:
            page = tif.pages[0]
            assert page.is_tiled and page.tilewidth == 64 and page.compression == 8  # deflate
    with pytest.raises(ValueError, match="nothing held"):
        write_level_geotiff(tmp_path / "none.tif", rx, 4)


def test_the_saved_state_holds_the_tiles_only_without_a_storage() -> None:
    msgs = _survey(20, 20)
    rx = BathymetryReceiver({"levels": 2, "memory_budget": 1, "tile_subgrids": 4})
    _feed(rx, msgs)
    # the receiver's own MemoryStorage: everything is in its saved state, no sync needed
    back = state.loads(state.dumps(rx))
    _assert_same(rx, back)
    # a storage attached: the state is the index, the tiles and overviews are in the storage
    store = MemoryStorage()
    rx.attach_storage(store)
    rx.sync_storage()
    assert rx.disk_bytes() == store.nbytes() > 0  # tiles and overview chunks
    blob = state.dumps(rx)
    assert len(blob) < store.nbytes() / 4
    again = state.loads(blob)
    with pytest.raises(state.StateError, match="not attached"):
        again.level_product(0)
    copy = MemoryStorage()
    copy.data = dict(store.data)  # the storage as it was at that state (a snapshot's)
    again.attach_storage(copy)
    _assert_same(rx, again)
    # and it goes on: more subgrids, a sync, another restore
    more = [dataclasses.replace(m, stamp=300) for m in msgs[::3]]
    _feed(rx, more, 1300.0)
    _feed(again, more, 1300.0)
    assert again.level_summary(0)["newest"] == 300.0
    rx.sync_storage()
    third = state.loads(state.dumps(rx))
    third.attach_storage(store)
    _assert_same(again, third)


def _small_budget(r: Any) -> Any:
    if isinstance(r, BathymetryReceiver):
        return BathymetryReceiver({"levels": 3, "memory_budget": 1, "tile_subgrids": 2})
    return r


def test_a_receiver_with_spilled_tiles_restores_from_a_node_store(tmp_path: Path) -> None:
    """A dive's topside with a tiny tile budget (tiles spill to the store's file): snapshot
    mid-dive, frames after it journaled, the process gone; the restored node holds exactly what
    the live one does."""
    db = tmp_path / "topside.sqlite"
    dive = build_dive(minutes=3, wrap_receiver=_small_budget)
    store = NodeStore(db, snapshot_interval=1e9)
    dive.topside.attach_storage(store.storage())
    inner = dive.topside.receive

    def recorder(link: int, frame: bytes, now: float) -> Any:
        store.record_rx(link, frame, now)
        return inner(link, frame, now)

    def snapshot(now: float) -> None:
        dive.topside.__dict__.pop("receive")  # the test's hook is not node state
        try:
            store.snapshot(dive.topside, now)
        finally:
            dive.topside.receive = recorder  # type: ignore[method-assign]

    dive.topside.receive = recorder  # type: ignore[method-assign]
    dive.inputs.append((T0 + 150.0, snapshot))
    run_sim(dive, AcousticChannel(loss=0.1, seed=4), T0 + 400.0)
    live = dive.topside.receiver("bathymetry")
    assert isinstance(live, BathymetryReceiver) and live.disk_bytes() > 0
    assert len(live._tiles) == 1 and sum(ix.n for ix in live._index.values()) > 10
    held = _fingerprint(live)
    text = store.saved_text()
    assert text is not None
    classes = json.loads(text)["classes"]
    # the snapshot holds the tile index, not the tiles (those are the store's storage rows)
    assert "bathymetry.LevelIndex" in classes and "bathymetry.Tile" not in classes
    assert store.count("rx") > 0  # frames after the snapshot, to replay
    del dive.topside.receive
    expected = digest(dive.topside, products_only=True)
    store.close()  # what was spilled after the snapshot is not committed: discarded on open

    store = NodeStore(db)
    try:
        node = store.restore(lambda: build_dive(minutes=3, wrap_receiver=_small_budget).topside)
        assert digest(node, products_only=True) == expected
        restored = node.receiver("bathymetry")
        assert isinstance(restored, BathymetryReceiver)
        assert _fingerprint(restored) == held
    finally:
        store.close()


def test_the_console_shows_a_big_level_bounded_and_what_is_on_screen(monkeypatch: pytest.MonkeyPatch) -> None:
    """The console's map section of a level too big to draw whole: a bounded picture (the
    decimated overview, placed on its extent), the coverage in a bounded number of blocks,
    and, through the server, the part on screen at a finer step, read from the tiles."""
    import io
    import urllib.error
    import urllib.request

    from PIL import Image

    from coex_apps.console import ConsoleState, serve
    from coex_apps.console import mapview as console_map

    monkeypatch.setattr(console_map, "MAP_BLOCKS", 16)
    rx = BathymetryReceiver({"levels": 1, "max_mosaic_cells": 4096, "tile_subgrids": 4,
                             "memory_budget": 1})
    st = ConsoleState(receivers={"bathymetry": rx})
    for msg in _survey(48, 40, levels=1):
        for p in rx.receive(msg, 1000.0):
            st.apply_product("bathymetry", p, 1000.0)
    (lv,) = st.snapshot()["map"]["levels"]
    assert lv["subgrids"] == len(rx.holdings(0)) > 16 and lv["step"] > 1
    assert lv["tile_span"] >= 4 and len(lv["tiles"]) <= 16  # blocks of tiles, not every subgrid
    covered = {(ix // lv["tile_span"], iy // lv["tile_span"]) for ix, iy in rx.holdings(0)}
    assert {(bx, by) for bx, by, _ in lv["tiles"]} == covered
    z, x0, y0, cell = st.level_grid(0)  # type: ignore[misc]
    assert z.size <= 4096 and cell == lv["step"]
    assert lv["image"] == [x0, y0, x0 + z.shape[1] * cell, y0 + z.shape[0] * cell]
    assert lv["x0"] >= lv["image"][0] and lv["x1"] <= lv["image"][2]
    with serve(st, "127.0.0.1", 0) as srv:
        box = "x0=-16&y0=0&x1=112&y1=64"
        with urllib.request.urlopen(srv.url + f"map/0/window.png?{box}&step=2", timeout=5) as r:
            img = np.asarray(Image.open(io.BytesIO(r.read())))
        assert img.shape == (32, 64, 4)  # 128 x 64 m at 2 m a pixel
        want, _ = rx.window(0, -16.0, 0.0, 112.0, 64.0, max_cells=32 * 64)
        assert ((img[::-1, :, 3] > 0) == np.isfinite(want)).all()  # north up, empty transparent
        for bad in ("x0=0&y0=0&x1=0&y1=10", "x0=0&y0=0&x1=1e9&y1=1e9", "x0=nan&y0=0&x1=1&y1=1"):
            with pytest.raises(urllib.error.HTTPError):
                urllib.request.urlopen(srv.url + f"map/0/window.png?{bad}&step=1", timeout=5)


def test_an_overview_coarsened_between_snapshots_restores_from_its_storage() -> None:
    cfg = {"levels": 1, "max_mosaic_cells": 16384, "memory_budget": 1, "tile_subgrids": 4}
    rx = BathymetryReceiver(cfg)
    store = MemoryStorage()
    rx.attach_storage(store)
    _feed(rx, _survey(10, 10, levels=1))
    rx.sync_storage()
    first = rx.level_product(0).meta["step"]
    _feed(rx, _survey(60, 50, levels=1, x0=-20, y0=-20), 1100.0)  # the level outgrows its array
    rx.sync_storage()
    assert rx.level_product(0).meta["step"] > first
    assert rx.disk_bytes() == store.nbytes()  # chunks of the finer step emptied
    back = state.loads(state.dumps(rx))
    back.attach_storage(store)
    _assert_same(rx, back)


def test_attaching_the_same_storage_again_moves_nothing() -> None:
    rx = BathymetryReceiver({"levels": 1, "memory_budget": 1, "tile_subgrids": 4})
    _feed(rx, _survey(12, 12, levels=1))
    base = MemoryStorage()
    rx.attach_storage(base.child("rx/bathymetry/"))
    puts: list[str] = []
    put = base.put
    base.put = lambda key, data: (puts.append(key), put(key, data))[1]  # type: ignore[method-assign]
    rx.attach_storage(base.child("rx/bathymetry/"))  # what a node attaching again gives
    assert puts == []
    assert set(rx.holdings(0)) == {(m.ix, m.iy) for m in _survey(12, 12, levels=1)}
