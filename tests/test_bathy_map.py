"""QuadtreeMap: vectorised ingest, statistics, growth, outlier rejection and point-file inputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from coex_core.errors import CoexError
from coex_plugins.bathymetry import (
    InputError,
    QuadtreeMap,
    iter_points,
    load_points,
    write_pointcloud_bag,
)

from ._bathy_data import small_survey


def _reference(xyz: np.ndarray, res: float) -> dict[tuple[int, int], np.ndarray]:
    cells: dict[tuple[int, int], list[float]] = {}
    for x, y, z in xyz:
        cells.setdefault((int(np.floor(x / res)), int(np.floor(y / res))), []).append(z)
    return {k: np.array(v) for k, v in cells.items()}


def test_cell_mean_count_and_std_match_a_direct_computation() -> None:
    rng = np.random.default_rng(0)
    xyz = np.column_stack([rng.uniform(-40, 40, 3000), rng.uniform(-20, 60, 3000), rng.normal(-50, 0.2, 3000)])
    m = QuadtreeMap(resolution=2.0, outlier_rejection=False)
    m.add_points(xyz[:1000], 1.0)
    m.add_points(xyz[1000:], 2.0)
    ref = _reference(xyz, 2.0)
    for (ci, cj), zs in list(ref.items())[:200]:
        # level 0 cell (ci, cj) lies in subgrid (ci // 8, cj // 8) at position (cj % 8, ci % 8)
        blk = m.block(0, ci // 8, cj // 8)
        assert blk is not None
        r, c = cj % 8, ci % 8
        assert blk.count[r, c] == zs.size
        assert blk.mean[r, c] == pytest.approx(zs.mean(), abs=1e-9)
        assert blk.std[r, c] == pytest.approx(zs.std(), abs=1e-6)
    assert m.accepted == 3000 and m.rejected == 0


def test_coarser_levels_aggregate_children_weighted_by_count() -> None:
    xyz = np.array([[0.5, 0.5, -10.0], [1.5, 0.5, -12.0], [1.5, 0.5, -12.0], [0.5, 1.5, -14.0]])
    m = QuadtreeMap(outlier_rejection=False)
    m.add_points(xyz, 5.0)
    blk = m.block(1, 0, 0)
    assert blk is not None
    assert blk.count[0, 0] == 4
    assert blk.mean[0, 0] == pytest.approx(-12.0)
    assert np.isnan(blk.mean[0, 1])
    assert blk.updated == 5.0


def test_tree_grows_a_new_root_and_memory_follows_area_not_points() -> None:
    m = QuadtreeMap(outlier_rejection=False)
    rng = np.random.default_rng(1)
    patch = np.column_stack([rng.uniform(1, 99, 20000), rng.uniform(1, 99, 20000), rng.normal(-30, 0.1, 20000)])
    m.add_points(patch, 1.0)
    m.flush()
    assert m.root_level == 0 or m.root_origin is not None
    level_before, mem_before = m.root_level, m.nbytes()
    for i in range(10):  # ten times more soundings on the same area: no new memory
        m.add_points(patch + rng.normal(0, 0.01, patch.shape), 2.0 + i)
    m.flush()
    assert m.nbytes() == mem_before
    far = np.array([[-5000.0, 7000.0, -40.0]] * 5)
    m.add_points(far, 20.0)
    m.flush()
    assert m.root_level > level_before
    ox, oy = m.root_origin  # type: ignore[misc]
    size = 1 << m.root_level
    for tx, ty in m.tiles:
        assert ox <= tx < ox + size and oy <= ty < oy + size
    assert m.nbytes() <= 2 * mem_before  # one more tile, not a dense grid spanning 7 km


@pytest.mark.parametrize("bad", [np.zeros((5, 2)), np.zeros(3), np.array([["a", "b", "c"]])])
def test_bad_input_raises_a_typed_error_and_loses_nothing(bad: np.ndarray) -> None:
    m = QuadtreeMap()
    good = np.array([[1.0, 1.0, -5.0], [1.2, 1.3, -5.2], [1.4, 1.1, -5.1]])
    m.add_points(good, 1.0)
    with pytest.raises(InputError) as info:
        m.add_points(bad, 2.0)
    assert isinstance(info.value, CoexError)
    m.flush()
    assert m.accepted == 3


def test_non_finite_and_out_of_range_soundings_are_dropped_and_counted() -> None:
    m = QuadtreeMap()
    pts = np.array([[1.0, 1.0, np.nan], [1e9, 0.0, -5.0], [2.0, 2.0, -5.0]])
    m.add_points(pts, 1.0)
    m.flush()
    assert (m.dropped, m.accepted, m.pending) == (2, 0, 1)  # a lone sounding waits for neighbours
    m.flush(force=True)
    assert (m.dropped, m.accepted, m.pending) == (2, 1, 0)


def test_outlier_rejection_removes_swath_edge_spikes_and_keeps_targets() -> None:
    floor, survey = small_survey(64.0, 400)
    m = QuadtreeMap()
    m.track_rejections = True
    for t, xyz in survey.pings(batch=1):
        m.add_points(xyz, t)
    m.flush(force=True)
    assert m.accepted + m.rejected == len(survey) and m.pending == 0
    rejected = np.zeros(len(survey), bool)
    rejected[np.concatenate(m.rejected_ids)] = True
    caught = int((rejected & survey.outlier).sum())
    false = int((rejected & ~survey.outlier).sum())
    assert caught >= 0.93 * survey.outlier.sum()
    assert false <= 0.001 * len(survey)
    # The cars survive: the 1 m cell at each car's centre sits ~1.5 m above the bare bottom.
    for target in floor.targets:
        blk = m.block(0, int(target.x // 8), int(target.y // 8))
        assert blk is not None
        val = blk.mean[int(target.y) % 8, int(target.x) % 8]
        assert val - float(floor.ground(target.x, target.y)) == pytest.approx(1.5, abs=0.3)


def test_outlier_rejection_can_be_switched_off() -> None:
    _, survey = small_survey(64.0, 96)
    m = QuadtreeMap(outlier_rejection=False)
    m.add_points(survey.points, 1.0)
    m.flush()
    assert m.rejected == 0 and m.pending == 0 and m.accepted == len(survey)


def test_map_error_against_truth_is_small_with_rejection_and_large_without() -> None:
    floor, survey = small_survey(64.0, 400)
    errors = []
    for rejection in (True, False):
        m = QuadtreeMap(outlier_rejection=rejection)
        for t, xyz in survey.pings(batch=5):
            m.add_points(xyz, t)
        m.flush(force=True)
        grid, x0, y0 = m.grid(0)
        yy, xx = np.mgrid[0:grid.shape[0], 0:grid.shape[1]]
        truth = floor.elevation(x0 + xx + 0.5, y0 + yy + 0.5)
        inside = (x0 + xx >= 0) & (x0 + xx < floor.size) & (y0 + yy >= 0) & (y0 + yy < floor.size)
        ok = np.isfinite(grid) & inside
        errors.append(np.abs(grid - truth)[ok])
    assert np.percentile(errors[0], 99.9) < 1.0 and errors[0].max() < 5.0
    assert errors[1].max() > 2.0  # single-cell spikes without rejection


def test_npy_and_csv_inputs(tmp_path: Path) -> None:
    xyz = np.array([[1.0, 2.0, -3.0], [4.5, -5.5, -6.25]])
    np.save(tmp_path / "p.npy", xyz)
    (tmp_path / "p.csv").write_text("x,y,z\n1,2,-3\n4.5,-5.5,-6.25\n")
    (tmp_path / "q.csv").write_text("z,x,y\n-3,1,2\n-6.25,4.5,-5.5\n")
    for name in ("p.npy", "p.csv", "q.csv"):
        np.testing.assert_allclose(load_points(tmp_path / name), xyz)
    (tmp_path / "bad.csv").write_text("x,y,z\n1,2\n")
    with pytest.raises(InputError):
        load_points(tmp_path / "bad.csv")
    with pytest.raises(InputError):
        load_points(tmp_path / "missing.npy")


@pytest.mark.parametrize("ros1", [False, True])
def test_pointcloud2_bags_with_topic_selection(tmp_path: Path, ros1: bool) -> None:
    rng = np.random.default_rng(3)
    clouds = [(100.0 + i, rng.normal(0, 10, (40, 3))) for i in range(3)]
    path = tmp_path / ("b.bag" if ros1 else "b2")
    write_pointcloud_bag(path, clouds, topic="/mbes/points", ros1=ros1)
    got = list(iter_points(path, topic="/mbes/points"))
    assert [t for t, _ in got] == [100.0, 101.0, 102.0]
    for (_, a), (_, b) in zip(got, clouds, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-5)
    with pytest.raises(InputError, match="no PointCloud2 topic"):
        list(iter_points(path, topic="/other"))


def test_sender_ingests_pointcloud2_messages_and_rejects_other_objects(tmp_path: Path) -> None:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    from coex_plugins.bathymetry import BathymetrySender

    rng = np.random.default_rng(4)
    xyz = np.column_stack([rng.uniform(0, 8, 60), rng.uniform(0, 8, 60), rng.normal(-40, 0.05, 60)])
    write_pointcloud_bag(tmp_path / "b", [(5.0, xyz)])
    sender = BathymetrySender()
    with AnyReader([tmp_path / "b"], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        for conn, _, raw in reader.messages():
            sender.ingest(reader.deserialize(raw, conn.msgtype), 5.0)
    sender.map.flush(force=True)
    assert sender.map.accepted == 60
    with pytest.raises(InputError):
        sender.ingest("survey.npy", 6.0)  # the sender does no file I/O
    assert sender.map.accepted == 60


def test_queries_outside_the_levels_raise_a_typed_error() -> None:
    m = QuadtreeMap(levels=3)
    m.add_points(np.array([[1.0, 1.0, -5.0]] * 3), 1.0)
    assert m.block(2, 0, 0) is not None
    assert m.block(0, 50, 50) is None
    for level in (-1, 3):
        with pytest.raises(InputError):
            m.block(level, 0, 0)


def test_memory_guard_drops_soundings_that_need_too_many_tiles() -> None:
    m = QuadtreeMap(max_tiles=2, outlier_rejection=False)
    pts = np.array([[1.0, 1.0, -5.0], [300.0, 1.0, -5.0], [900.0, 900.0, -5.0], [2.0, 2.0, -5.0]])
    m.add_points(pts, 1.0)
    m.flush()
    assert len(m.tiles) == 2 and (m.accepted, m.dropped) == (3, 1)
    m.add_points(np.array([[3.0, 3.0, -5.0], [5000.0, 0.0, -5.0]]), 2.0)
    m.flush()
    assert len(m.tiles) == 2 and (m.accepted, m.dropped) == (4, 2)
