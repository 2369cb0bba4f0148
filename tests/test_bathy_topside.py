"""Topside products: level assembly, GeoTIFF and PNG export, candidate targets, `coex bathy roundtrip`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from coex_core import wire
from coex_core.cli import main
from coex_core.messages import Subgrid, SubgridMessage
from coex_plugins.bathymetry import (
    BathymetryReceiver,
    BathymetrySender,
    find_targets,
    write_geotiff,
    write_png,
)
from coex_plugins.bathymetry.export import read_geotiff

from ._bathy_data import small_survey


def _synced() -> tuple[BathymetrySender, BathymetryReceiver, float]:
    _, survey = small_survey(64.0, 400)
    sender = BathymetrySender({"levels": 3, "origin_lat": 33.8, "origin_lon": -118.4})
    for t, xyz in survey.pings(batch=10):
        sender.ingest(xyz, t)
    receiver = BathymetryReceiver({"levels": 3})
    now = float(survey.times[-1]) + 30.0
    for i in range(3000):
        out = sender.fill(240, now + i)
        for m in out:
            receiver.receive(m, now + i)
        if not out:
            break
    return sender, receiver, now


def test_receiver_assembles_every_level_like_the_vehicle_map() -> None:
    sender, receiver, _ = _synced()
    products = {p.key: p for p in receiver.products()}
    assert set(products) == {"level-0", "level-1", "level-2"}
    for k in range(3):
        prod = products[f"level-{k}"]
        grid, x0, y0 = sender.map.grid(k)
        cell = prod.meta["cell_size"]
        assert cell == 2.0**k
        # Compare on the overlap, placing both by their south-west corners.
        r0 = round((prod.meta["y0"] - y0) / cell)
        c0 = round((prod.meta["x0"] - x0) / cell)
        got = prod.data
        ref = np.full(got.shape, np.nan)
        rows = slice(max(r0, 0), min(r0 + got.shape[0], grid.shape[0]))
        cols = slice(max(c0, 0), min(c0 + got.shape[1], grid.shape[1]))
        ref[rows.start - r0:rows.stop - r0, cols.start - c0:cols.stop - c0] = grid[rows, cols]
        ok = np.isfinite(ref)
        assert np.array_equal(ok, np.isfinite(got))
        assert np.abs(got[ok] - ref[ok]).max() <= 0.05 + 1e-9  # quantised to 0.1 m
    assert receiver.origin() == (33.8, -118.4)


def test_geotiff_has_nan_nodata_and_a_local_crs_at_the_origin(tmp_path: Path) -> None:
    grid = np.arange(12.0).reshape(3, 4) - 500.0
    grid[0, 0] = np.nan
    path = write_geotiff(tmp_path / "a.tif", grid, x0=-16.0, y0=8.0, cell=2.0, origin_lat=33.8, origin_lon=-118.4)
    back, geo = read_geotiff(path)
    np.testing.assert_array_equal(np.isnan(back), np.isnan(grid))
    np.testing.assert_allclose(back[1:], grid[1:])
    assert (geo["cell"], geo["x0"], geo["y0"]) == (2.0, -16.0, 8.0)
    assert geo["nodata"] == "nan"
    assert list(geo["geodoubles"]) == pytest.approx([-118.4, 33.8, 0.0, 0.0, 1.0])
    keys = list(geo["geokeys"])
    entries = {keys[i]: keys[i + 3] for i in range(4, len(keys), 4)}
    assert entries[3075] == 1  # transverse Mercator
    assert entries[3076] == 9001  # metres
    assert entries[2048] == 4326  # WGS 84


def test_png_has_colour_hillshade_and_transparent_nodata(tmp_path: Path) -> None:
    yy, xx = np.mgrid[0:40, 0:50]
    grid = -500 + 0.2 * xx + 2.0 * np.sin(yy / 4.0)
    grid[:5, :5] = np.nan
    img = np.asarray(Image.open(write_png(tmp_path / "a.png", grid, 1.0)))
    assert img.shape == (40, 50, 4)
    assert (img[-5:, :5, 3] == 0).all() and (img[:-5, 5:, 3] == 255).all()  # south rows at the bottom
    assert len({tuple(p) for p in img[:, :, :3].reshape(-1, 3)}) > 50  # shaded colours, not flat


def test_candidate_targets_are_the_cars_not_single_cell_spikes() -> None:
    floor, _ = small_survey(64.0, 400)
    _, receiver, _ = _synced()
    prod = receiver.level_product(0)
    grid = prod.data.copy()
    finite = np.argwhere(np.isfinite(grid))
    r, c = finite[len(finite) // 3]
    grid[r, c] += 4.0  # a single-cell spike like a swath-edge outlier
    cands = find_targets(grid, cell=1.0, x0=prod.meta["x0"], y0=prod.meta["y0"])
    assert all(k.cells >= 2 for k in cands)
    # Inside the surveyed square (full coverage) the candidates are exactly the two cars.
    inside = [k for k in cands if 0 <= k.x <= floor.size and 0 <= k.y <= floor.size]
    assert len(inside) == 2
    for target in floor.targets:
        best = min(inside, key=lambda k: np.hypot(k.x - target.x, k.y - target.y))
        assert np.hypot(best.x - target.x, best.y - target.y) < 1.5
        assert best.height == pytest.approx(1.5, abs=0.4)


def test_coex_bathy_roundtrip_writes_messages_levels_and_summary(tmp_path: Path) -> None:
    _, survey = small_survey(48.0, 128)
    pts = tmp_path / "points.npy"
    np.save(pts, survey.points)
    out = tmp_path / "out"
    assert main(["bathy", "roundtrip", str(pts), "--out", str(out), "--loss", "0.2", "--seed", "4"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] is True
    assert summary["points"] == len(survey)
    assert summary["ratio_vs_2022"] < 0.6
    lines = [json.loads(line) for line in (out / "messages.jsonl").read_text().splitlines()]
    assert lines and all({"type", "level", "hex"} <= set(rec) for rec in lines)
    subgrids = [rec for rec in lines if rec["type"] in ("Subgrid", "PredictedSubgrid")]
    assert subgrids
    for rec in subgrids[:50]:
        msg = wire.decode(bytes.fromhex(rec["hex"]))
        assert isinstance(msg, SubgridMessage) and type(msg).__name__ == rec["type"] and msg.level == rec["level"]
    # frame acks tell the sender what topside holds: most subgrids are predicted from their parents
    parent = [rec for rec in subgrids if rec.get("context") == "PARENT"]
    assert len(parent) > len(subgrids) / 3
    for level in summary["levels"]:
        k = level["level"]
        grid, geo = read_geotiff(out / f"level_{k}.tif")
        assert geo["cell"] == 2.0**k and np.isfinite(grid).any()


def test_coex_bathy_roundtrip_reports_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y\n1,2\n")
    assert main(["bathy", "roundtrip", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "bad.csv" in capsys.readouterr().err


def test_a_far_away_subgrid_does_not_blow_up_the_mosaic() -> None:
    """A far-away (or bogus) subgrid is held and drawn: the level's drawn array turns into a
    decimated overview within ``max_mosaic_cells``, where both subgrids show."""
    receiver = BathymetryReceiver({"levels": 1})
    base = {"level": 0, "stamp": 100, "resolution": 1.0, "vertical_resolution": 0.1, "side": 8,
            "encoding": 0, "z_base": -5000, "width": 0, "mask": None, "values": ()}
    near = Subgrid(ix=0, iy=0, **base)  # type: ignore[arg-type]
    far = Subgrid(ix=-8192, iy=8191, **base)  # type: ignore[arg-type]
    receiver.receive(near, 200.0)
    (prod,) = receiver.receive(far, 200.0)
    assert prod.data.size <= 16 * 1024 * 1024
    assert prod.meta["step"] > 1 and prod.meta["cell_size"] == prod.meta["step"] * 1.0
    assert receiver.holdings(0) == {(0, 0): 100, (-8192, 8191): 100}
    cell, x0, y0 = prod.meta["cell_size"], prod.meta["x0"], prod.meta["y0"]
    for ix, iy in ((0, 0), (-8192, 8191)):
        r, c = int((iy * 8 + 4 - y0) // cell), int((ix * 8 + 4 - x0) // cell)
        assert prod.data[r, c] == pytest.approx(-500.0)
    assert np.isfinite(prod.data).sum() == 2


def test_a_region_outside_the_wire_s_index_range_is_refused_and_nothing_is_asked() -> None:
    """A MapRoiRequest carries 14-bit subgrid indices: a region beyond them is refused when it
    is asked, not left to fail (and be retried) every time the receiver polls."""
    from coex_core.errors import RequestRejected
    from coex_plugins.bathymetry import BathymetryReceiver

    rx = BathymetryReceiver()
    with pytest.raises(RequestRejected, match="index range"):
        rx.request_region(0, 8190, 0, 4, 1)
    with pytest.raises(RequestRejected, match="index range"):
        rx.request_area(0, 0.0, -1e6, 10.0, 10.0)
    assert rx.regions == [] and rx.poll(0.0) == []
    assert len(rx.request_region(0, 8184, -8192, 8, 8)) == 1  # the edges themselves are fine
