"""The bathymetry plugin's one tile store (plugins/coex_plugins/bathymetry/tilestore.py): the codec
round trip for every kind of array, the formats stored before it (committed in
tests/fixtures/tiles-0.2, written by the code that wrote them), and the cache spilling to a
storage and reading back under its memory budget, for the vehicle's map and the receiver."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from coex_core.state import StateError, dumps, loads
from coex_core.storage import MemoryStorage, Storage
from coex_plugins.bathymetry import BathymetryReceiver, BathymetrySender, QuadtreeMap, tilestore
from coex_plugins.bathymetry.overview import CHUNK, Overview
from coex_plugins.bathymetry.tiles import decode_tile

OLD = Path(__file__).resolve().parent / "fixtures" / "tiles-0.2"


def same(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal type, shape and bytes (NaN, -inf and -0.0 included)."""
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def kinds() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(1)
    f64 = rng.normal(-30, 5, (16, 16))
    f64[0, :4] = [np.nan, np.inf, -np.inf, -0.0]
    return {
        "bool": rng.random((5, 7)) > 0.5,
        "u8": rng.integers(0, 255, 100).astype(np.uint8),
        "u16": rng.integers(0, 60000, 100).astype(np.uint16),
        "u32": np.array([0, 1, 2**32 - 1], np.uint32),
        "u64": np.array([0, 2**64 - 1], np.uint64),
        "i8": np.array([-128, 0, 127], np.int8),
        "i16": np.array([-30000, 5], np.int16),
        "i32": rng.integers(-2**31, 2**31 - 1, 50).astype(np.int32),
        "i64 small": rng.integers(0, 200, (4, 25)),
        "i64 negative": np.array([-5, 70000, 3]),
        "i64 wide": np.array([-2**62, 2**62]),
        "f32": rng.normal(0, 1, (3, 4, 5)).astype(np.float32),
        "f64": f64,
        "empty": np.zeros((0, 3)),
        "scalar": np.array(7.5),
    }


@pytest.mark.parametrize("level", [0, 1, 3])
@pytest.mark.parametrize("shuffle", [True, False])
def test_every_kind_of_array_comes_back_as_it_went(level: int, shuffle: bool) -> None:
    arrays = kinds()
    data = tilestore.encode(arrays, level, shuffle=shuffle)
    assert data[:4] == tilestore.MAGIC
    back = tilestore.decode(data)
    assert list(back) == list(arrays)
    for name, a in arrays.items():
        assert same(back[name], a), name
        assert back[name].flags.writeable, name


def test_integers_are_stored_in_the_smallest_type_that_holds_them() -> None:
    counts = np.random.default_rng(2).integers(0, 200, 4096)
    small = tilestore.encode({"c": counts}, 0)
    wide = tilestore.encode({"c": counts * 10**6}, 0)
    assert len(small) < 4096 + 64 < len(wide)  # one byte a count, not eight
    assert same(tilestore.decode(small)["c"], counts)


def test_damaged_or_foreign_bytes_are_refused() -> None:
    data = tilestore.encode(kinds(), 1)
    for bad in (b"", b"PNG\x00", data[:40], data[:-10], b"CXTS\x09" + data[5:]):
        with pytest.raises(ValueError):
            tilestore.decode(bad)
    with pytest.raises(TypeError):
        tilestore.encode({"s": np.array(["text"])})


# -------------------------------------------------------------- formats stored before the tile store

def expected() -> Any:
    return np.load(OLD / "expected.npz", allow_pickle=False)


@pytest.mark.parametrize("name", ["cxt1-u1", "cxt1-u2"])
def test_the_maps_cxt1_tiles_still_decode(name: str) -> None:
    cells = expected()[name]
    arrays = tilestore.decode((OLD / f"{name}.bin").read_bytes())
    assert np.array_equal(arrays["count"], cells[0])
    assert same(arrays["stats"], cells[1:].copy())


@pytest.mark.parametrize("name", ["cxrt-z0", "cxrt-z1"])
def test_the_receivers_cxrt_tiles_still_decode(name: str) -> None:
    ex = expected()
    t = decode_tile((OLD / f"{name}.bin").read_bytes(), 2, 8, name)
    assert same(t.held, ex["cxrt-held"]) and same(t.stamp, ex["cxrt-stamp"])
    assert same(t.received, ex["cxrt-received"]) and same(t.values, ex["cxrt-values"])
    assert not t.dirty
    with pytest.raises(StateError, match="damaged"):
        decode_tile((OLD / f"{name}.bin").read_bytes(), 2, 4, name)  # another geometry


def test_the_receivers_cxov_overview_chunks_still_decode() -> None:
    ex = expected()
    assert int(ex["chunk"][0]) == CHUNK
    ov = Overview(1)
    ov.include(0, CHUNK, 0, CHUNK)
    ov.paste_chunk(0, 0, (OLD / "cxov-step1.bin").read_bytes(), "step1")
    assert same(ov.mean[:16, :16], ex["cxov-step1-mean"][:16, :16].copy())
    coarse = Overview(4)
    coarse.include(0, 4, 0, 4)
    coarse.paste_chunk(0, 0, (OLD / "cxov-step4.bin").read_bytes(), "step4")
    n = ex["cxov-step4-mean"].shape
    assert same(coarse.mean[:n[0], :n[1]], ex["cxov-step4-mean"].copy())
    assert same(coarse.count[:n[0], :n[1]], ex["cxov-step4-count"].copy())  # type: ignore[index]
    with pytest.raises(StateError, match="damaged"):
        Overview(2).paste_chunk(0, 0, (OLD / "cxov-step4.bin").read_bytes(), "step4")  # wrong step


def test_a_map_reads_its_old_cxt1_tiles_back_and_writes_the_new_form() -> None:
    """A version-2 map's storage holds CXT1 tiles: the map reads them (same statistics) and
    writes the tile store's form when they change."""
    m = QuadtreeMap(subgrid_side=2, levels=2, outlier_rejection=False, memory_budget=0)
    assert m.tile == 4
    m.add_points(np.array([[0.5, 0.5, -30.0]]), 1.0)
    m.sync()
    cells = expected()["cxt1-u1"]
    m.storage.put("tile/0/0", (OLD / "cxt1-u1.bin").read_bytes())  # as version 2 left it
    m._res.clear()
    m._cache.nbytes = 0
    cnt, sm, ss, tm = m.level_stats((0, 0), 0)
    assert np.array_equal(cnt.ravel(), cells[0]) and np.array_equal(sm.ravel(), cells[1])
    assert np.array_equal(ss.ravel(), cells[2]) and np.array_equal(tm.ravel(), cells[3])
    m.add_points(np.array([[1.5, 0.5, -31.0]]), 2.0)
    m.sync()
    data = m.storage.get("tile/0/0")
    assert data is not None and data[:4] == tilestore.MAGIC


# ----------------------------------------------------------------------------------- the cache

class Recording(MemoryStorage):
    def __init__(self, fail: bool = False) -> None:
        super().__init__()
        self.puts: list[str] = []
        self.fail = fail

    def put(self, key: str, data: bytes) -> None:
        if self.fail:
            raise OSError("disk full")
        self.puts.append(key)
        super().put(key, data)


def cache(storage: Storage | None, budget: int, **kw: Any) -> tilestore.TileCache[int, np.ndarray]:
    return tilestore.TileCache(
        name=lambda k: f"t/{k}", encode=lambda k, a: tilestore.encode({"a": a}),
        decode=lambda k, d: tilestore.decode(d)["a"], nbytes=lambda a: int(a.nbytes),
        budget=budget, storage=storage, **kw)


def test_the_cache_spills_beyond_its_budget_and_reads_back() -> None:
    st = Recording()
    c = cache(st, budget=3 * 800)
    tiles = {k: np.full(100, float(k)) for k in range(10)}
    for k, a in tiles.items():
        c.add(k, a.copy())
        assert c.nbytes <= c.budget and c.nbytes == sum(v.nbytes for v in c.resident.values())
    assert list(c.resident) == [7, 8, 9] and st.puts == [f"t/{k}" for k in range(7)]
    assert c.dirty == {7, 8, 9}
    back = c.get(0)  # read back; the least recently used (7) leaves, written as it goes
    assert same(back, tiles[0]) and list(c.resident) == [8, 9, 0] and "t/7" in st.puts
    assert 0 not in c.dirty
    c.get(8)  # used: now the most recent
    c.get(1)
    assert list(c.resident) == [0, 8, 1]  # 9 left, not 8
    n = len(st.puts)
    c.get(2)
    c.get(3)
    assert list(c.resident) == [1, 2, 3]
    assert st.puts[n:] == ["t/8"]  # 8 was dirty (written); 0 was clean (not written again)
    c.touch(3)
    c.resident[3][:] = -1.0
    c.sync()
    assert 3 not in c.dirty and same(tilestore.decode(st.get("t/3") or b"")["a"], np.full(100, -1.0))
    n = len(st.puts)
    c.sync()
    assert len(st.puts) == n  # nothing changed since: nothing written


def test_the_cache_keeps_what_is_protected_and_the_last_tiles() -> None:
    st = Recording()
    c = cache(st, budget=0, min_resident=1)
    c.add(1, np.zeros(10))
    c.add(2, np.ones(10))
    assert list(c.resident) == [2]  # one stays, whatever the budget
    c.get(1, protect=[2])
    assert list(c.resident) == [2, 1]  # nothing else to evict
    c.evict()
    assert list(c.resident) == [1]


def test_a_failed_write_keeps_the_tile_in_memory_when_the_owner_says_so() -> None:
    told: list[Exception] = []
    c = cache(Recording(fail=True), budget=800, failed=told.append, min_resident=0)
    c.add(1, np.zeros(100))
    c.add(2, np.zeros(100))
    assert list(c.resident) == [2, 1] and len(told) == 1 and isinstance(told[0], OSError)
    raising = cache(Recording(fail=True), budget=800)
    raising.add(1, np.zeros(100))
    with pytest.raises(OSError):
        raising.add(2, np.zeros(100))


def test_a_cache_without_its_storage_says_so() -> None:
    c = cache(None, budget=10**6, owner="a map")
    c.add(1, np.zeros(4))
    with pytest.raises(StateError, match=r"a map: .*not attached"):
        c.get(2)
    with pytest.raises(StateError, match="missing"):
        cache(MemoryStorage(), budget=10**6).get(5)


# ------------------------------------------------------------- both users, under a small budget

def survey(seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 300, (40_000, 2))
    z = -30 + 0.01 * xy[:, 0] + rng.normal(0, 0.05, len(xy))
    return np.column_stack([xy, z])


def test_the_map_under_a_small_budget_holds_what_a_big_one_does() -> None:
    pts = survey()
    big = QuadtreeMap(outlier_rejection=False)
    small = QuadtreeMap(outlier_rejection=False, memory_budget=1)  # 4 tiles resident
    for m in (big, small):
        m.add_points(pts, 10.0)
        m.flush(force=True)
    assert small.resident <= 4 < len(small.tiles) and small.spills > 0
    for key in big.tiles:
        for a, b in zip(big.level_stats(key, 0), small.level_stats(key, 0), strict=True):
            assert same(a, b)
    assert small.loads > 0 and small.disk_bytes() > 0
    back = loads(dumps(small))
    for key in big.tiles:
        assert same(big.level_stats(key, 1)[1], back.level_stats(key, 1)[1])


def everything(sender: BathymetrySender) -> list[Any]:
    out: list[Any] = []
    while batch := sender.fill(1 << 22, 200.0):
        out += batch
    return out


def test_the_receiver_under_a_small_budget_holds_what_a_big_one_does() -> None:
    sender = BathymetrySender({"levels": 3})
    sender.ingest(survey(), 100.0)
    sender.map.flush(force=True)
    tile_bytes = (16 * 8) ** 2 * 8 + 16 * 16 * 17
    big = BathymetryReceiver({"auto_fill": False})
    small = BathymetryReceiver({"auto_fill": False, "memory_budget": 2 * tile_bytes})
    for msg in everything(sender):
        big.receive(msg, 200.0)
        small.receive(msg, 200.0)
        assert small.resident_bytes() <= 2 * tile_bytes
    assert small.disk_bytes() > 0 and len(small._tiles) == 2
    for rx in (small, loads(dumps(small))):
        for level in big.levels():
            a, b = big.held_subgrids(level), rx.held_subgrids(level)
            order_a, order_b = np.lexsort(a[0].T), np.lexsort(b[0].T)
            for x, y in zip(a, b, strict=True):
                assert same(x[order_a], y[order_b])
            ext = big.level_summary(level)["extent"]  # type: ignore[index]
            cell, side = big.geometry(level)  # type: ignore[misc]
            box = (ext[0] * cell * side, ext[1] * cell * side, ext[2] * cell * side, ext[3] * cell * side)
            assert same(big.window(level, *box)[0], rx.window(level, *box)[0])


def test_the_receiver_tiles_its_state_saved_dirty_are_written_after_a_restore() -> None:
    """With its own storage the resident tiles are saved in the state with whether the storage
    lacks them; restored, a storage attached gets them."""
    sender = BathymetrySender({"levels": 2})
    sender.ingest(survey(), 100.0)
    sender.map.flush(force=True)
    rx = BathymetryReceiver({"auto_fill": False})
    for msg in everything(sender):
        rx.receive(msg, 200.0)
    back = loads(dumps(rx))
    assert back._cache.dirty == set(back._tiles) and back._tiles
    st = MemoryStorage()
    back.attach_storage(st)
    back.sync_storage()
    assert not back._cache.dirty
    assert sorted(st.keys("tile/")) == sorted(f"tile/{lv}/{tx}/{ty}" for lv, tx, ty in back._tiles)
    for key in back._tiles:
        t = decode_tile(st.get(f"tile/{key[0]}/{key[1]}/{key[2]}") or b"", 16, 8, "t")
        assert same(t.values, back._tiles[key].values) and same(t.held, back._tiles[key].held)


def test_a_storage_says_whether_another_holds_the_same_keys() -> None:
    """``Storage.same_keys`` (declared on the base: the same object; a child: the same part of
    the same storage): what the receiver asks before moving its tiles to a storage attached
    again."""
    from coex_plugins.bathymetry.tiles import same_storage

    root, other = MemoryStorage(), MemoryStorage()
    a, again = root.child("bathymetry/"), root.child("bathymetry/")
    assert a is not again and a.same_keys(again) and same_storage(a, again)
    assert root.child("x/").child("y/").same_keys(root.child("x/y/"))
    assert not a.same_keys(root.child("imagery/")) and not a.same_keys(other.child("bathymetry/"))
    assert not a.same_keys(root) and not root.same_keys(a) and not a.same_keys(None)
    assert root.same_keys(root) and not root.same_keys(other)
    assert same_storage(None, None) and not same_storage(None, root) and not same_storage(root, None)
