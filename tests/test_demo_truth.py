"""The demo's goals against the simulation's truth: scenarios, the referee, candidate ranking,
and whole short dives with decoys and with a target nobody photographs."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from coex_apps.demo import DemoConfig, run_demo
from coex_apps.demo.camera import SandTexture, render_labelled
from coex_apps.demo.config import LAYER_PSNR
from coex_apps.demo.eye import Eye, metres_per_pixel
from coex_apps.demo.operator import measure, target_likeness
from coex_apps.demo.scenario import (
    KINDS,
    PRESETS,
    ObjectSpec,
    Scenario,
    load_scenario,
    preset,
    scenario_from_dict,
)
from coex_apps.demo.truth import MIN_PSNR_DB, MIN_SSIM, fidelity, frame_truth, judge
from coex_core.errors import ConfigError
from coex_plugins.bathymetry.sim import Seafloor, Target
from coex_plugins.imagery.codec import CodingParams, decode_packets, encode_image, split_packets

from ._dives import quick_short

# ---------------------------------------------------------------------------------- scenarios


def test_scenario_file_with_every_key(tmp_path: Path) -> None:
    f = tmp_path / "site.toml"
    f.write_text("""
name = "wreck-field"
area = 200.0
water_depth = 300.0
duration = 5400.0
[survey]
altitude = 25.0
line_spacing = 60.0
speed = 1.2
[camera]
altitude = 4.0
[seafloor]
relief = 1.0
ripple_amplitude = 0.1
random_targets = 1
random_decoys = 1
[[targets]]
x = 50.0
y = 60.0
heading = 30.0
[[decoys]]
x = 120.0
y = 140.0
[modem]
rate = 3
slots = ["topside", "vehicle", "vehicle", "vehicle"]
slot_seconds = 15.0
guard_seconds = 1.5
[loss]
model = "range"
rate = 0.05
range_50 = 800.0
range_width = 150.0
range_max = 0.8
[ship]
x = 100.0
y = -450.0
""")
    s = load_scenario(f)
    assert (s.name, s.area, s.water_depth, s.duration) == ("wreck-field", 200.0, 300.0, 5400.0)
    assert (s.survey_altitude, s.line_spacing, s.survey_speed, s.camera_altitude) == (25.0, 60.0, 1.2, 4.0)
    assert s.targets == (ObjectSpec(50.0, 60.0, heading=30.0),)  # a car by default
    assert s.decoys[0].x == 120.0 and s.decoys[0].width > 2.0  # a rock's default size, not a car's
    assert s.modem_rate == 3 and s.slots == ("topside", "vehicle", "vehicle", "vehicle") and s.cycle == 60.0
    assert s.loss.model == "range" and s.ship == (100.0, -450.0)
    rl = s.loss.range_loss()
    assert rl is not None and rl(400.0) < 0.1 < rl(800.0) < rl(1500.0) <= 0.8
    targets, decoys = s.place(seed=3)
    assert targets == s.targets and [(d.x, d.y) for d in decoys] == [(d.x, d.y) for d in s.decoys]
    assert all(d.shape == "dome" and d.kind == "rock" for d in decoys)  # listed objects win; a boulder by default
    d = s.to_dict()
    assert d["loss"]["model"] == "range" and d["targets"][0]["x"] == 50.0 and "range" in d["loss_description"]


@pytest.mark.parametrize(("text", "key"), [
    ("aera = 100.0", "aera"),
    ("[survey]\naltitud = 20.0", "survey.altitud"),
    ("[loss]\nmodel = 'independent'\nburst = 3", "loss.burst"),
    ("[[targets]]\nx = 10.0\ny = 10.0\ncolour = 'red'", "targets[0].colour"),
    ("[ship]\nz = 3.0", "ship.z"),
])
def test_unknown_scenario_keys_are_named(tmp_path: Path, text: str, key: str) -> None:
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(ConfigError, match=f"{key.replace('[', '.').replace(']', '.')}: unknown key"):
        load_scenario(f)


@pytest.mark.parametrize("data", [
    {"area": 5.0}, {"loss": {"model": "fancy"}}, {"loss": {"rate": 1.2}}, {"modem": {"rate": 9}},
    {"modem": {"slots": ["vehicle", "vehicle"]}}, {"targets": [{"x": 500.0, "y": 1.0}]},
    {"modem": {"rate": 1, "slot_seconds": 2.0, "guard_seconds": 0.5}}, {"survey": {"speed": "fast"}},
])
def test_bad_scenario_values_are_config_errors(data: dict) -> None:  # type: ignore[type-arg]
    with pytest.raises(ConfigError):
        scenario_from_dict(data)


def test_every_scenario_problem_is_reported_together_with_its_key() -> None:
    """The scenario's checker collects (``coex_core.config.Problems``): a wrong type, an unknown
    key and the out-of-range values all in one ConfigError, each with its key and its own words."""
    data = {"area": 5.0, "survey": {"speed": "fast"}, "loss": {"rate": 1.2}, "colour": "red",
            "targets": [{"x": 1.0}]}
    with pytest.raises(ConfigError) as err:
        scenario_from_dict(data)
    keys = [p.key for p in err.value.problems]
    assert sorted(keys) == ["area", "colour", "loss.rate", "survey.speed", "targets[0]"], keys
    text = str(err.value)
    assert text.startswith("5 problems:")
    for words in ("area must be 16-4096 m, got 5.0", "survey.speed: not a finite number, got 'fast'",
                  "loss.rate must be in [0, 1), got 1.2", "colour: unknown key", "targets[0] needs x and y"):
        assert words in text, (words, text)
    with pytest.raises(ConfigError) as err:  # one problem: its sentence alone, as before
        scenario_from_dict({"area": 5.0})
    assert str(err.value) == "area must be 16-4096 m, got 5.0"


def test_presets() -> None:
    assert set(PRESETS) >= {"default", "dive040", "harsh"}
    assert preset("default") == Scenario()
    d040 = preset("dive040")
    assert d040.loss.model == "range"
    # the ship about 1.5 water depths from the site
    assert 1.3 * d040.water_depth <= abs(d040.ship[1]) <= 1.7 * d040.water_depth
    harsh = preset("harsh")
    assert harsh.modem_rate < 5 and harsh.loss.model == "gilbert-elliott"
    with pytest.raises(ConfigError, match="unknown preset"):
        preset("calm")
    assert Scenario().with_loss(0.6, False).loss.rate == 0.6
    assert Scenario().with_loss(0.5, True).loss.model == "gilbert-elliott"


def test_random_targets_and_decoys_draw_kinds_and_sizes_from_ranges() -> None:
    """Random targets are of the scenario's kinds, their lengths within their kind's range and
    ``target_length``; random decoys of ``decoy_kinds``; a listed object takes its kind's shape
    and nominal size."""
    scn = scenario_from_dict({"seafloor": {"random_targets": 3, "random_decoys": 2, "target_length": [2.0, 8.0]}})
    kinds, lengths = set(), []
    for seed in range(12):
        targets, decoys = scn.place(seed)
        for t in targets:
            k = KINDS[t.kind]
            assert k.target and t.shape == k.shape and k.length[0] <= t.length <= k.length[1]
            kinds.add(t.kind)
            lengths.append(t.length)
        assert all(not KINDS[d.kind].target and d.shape == KINDS[d.kind].shape for d in decoys)
    assert kinds == {"car", "container", "hull", "debris"} and min(lengths) < 3.5 and max(lengths) > 6.0
    only = scenario_from_dict({"seafloor": {"target_kinds": ["car"], "target_length": [2.0, 3.0],
                                            "decoy_kinds": ["dark rock"], "random_decoys": 1}})
    targets, decoys = only.place(1)
    assert all(t.kind == "car" and t.length <= 3.0 for t in targets) and decoys[0].kind == "dark rock"
    listed = scenario_from_dict({"targets": [{"kind": "container", "x": 10.0, "y": 20.0}],
                                 "decoys": [{"kind": "biology", "x": 50.0, "y": 50.0}]})
    t, d = listed.targets[0], listed.decoys[0]
    assert (t.length, t.width, t.height, t.shape) == (6.06, 2.44, 2.59, "box")
    assert d.shape == "mound" and not KINDS[d.kind].target
    for bad, key in (({"seafloor": {"target_kinds": ["tank"]}}, "seafloor.target_kinds"),
                     ({"seafloor": {"target_kinds": ["container"], "target_length": [2.0, 4.0]}}, "seafloor.target_length"),
                     ({"targets": [{"kind": "rock", "x": 1.0, "y": 1.0}]}, "targets[0].kind")):
        with pytest.raises(ConfigError) as err:
            scenario_from_dict(bad)
        assert key in [p.key for p in err.value.problems] or key in str(err.value), (bad, str(err.value))


def test_the_container_hull_and_small_car_site() -> None:
    site = preset("container-hull-car")
    assert sorted(t.kind for t in site.targets) == ["car", "container", "hull"]
    car = next(t for t in site.targets if t.kind == "car")
    hull = next(t for t in site.targets if t.kind == "hull")
    assert car.length <= 3.0 and hull.length == 7.0 and site.decoys == ()


def test_a_sweep_never_draws_the_seeds_the_eye_was_developed_on() -> None:
    """Issue 50's development seeds (the demo's own ``DEVELOPMENT_SEEDS``) count as development
    seeds for ``coex sweep`` besides its own (below 1000): never drawn fresh, flagged if given."""
    from coex_apps.demo import DEVELOPMENT_SEEDS
    from coex_apps.sweep.conditions import is_development_seed

    assert 1000 in DEVELOPMENT_SEEDS and 1099 in DEVELOPMENT_SEEDS
    assert all(is_development_seed(s) for s in (0, 999, 1000, 1050, 1099, 2000, 2003, 2015, 2099))
    assert not is_development_seed(1100) and not is_development_seed(123456)


def test_cli_rejects_a_bad_scenario(tmp_path: Path) -> None:
    f = tmp_path / "bad.toml"
    f.write_text("area = 100.0\nwater_dpeth = 3.0\n")
    proc = subprocess.run([sys.executable, "-m", "coex_core.cli", "demo", "--scenario", str(f), "--out",
                           str(tmp_path / "o")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "water_dpeth" in proc.stderr


# ---------------------------------------------------------------------------------- the referee

CAR = Target(50.0, 50.0, heading=20.0)
ROCK = Target(62.0, 50.0, 3.6, 2.6, 1.6, 10.0, "dome", "dark rock", 0.08)
FLOOR = Seafloor(size=100.0, depth=500.0, targets=(CAR, ROCK), seed=1)
ALTITUDE = 6.0


def _frame(x: float, y: float, altitude: float = ALTITUDE) -> tuple[np.ndarray, object]:
    z = float(FLOOR.ground(np.array([x]), np.array([y]))[0]) + altitude
    img, labels = render_labelled(FLOOR.ground, x, y, z, 0.0, targets=[CAR], rocks=[ROCK],
                                  texture=SandTexture(1), rng=np.random.default_rng(0))
    pixel = (2 * altitude * np.tan(np.radians(31.0)) / 640) ** 2
    return img, frame_truth(0.0, x, y, 0.0, img, labels, 1, {1: 4.5 * 1.8, 2: 3.6 * 2.6 * np.pi / 4},
                            {1: pixel, 2: pixel})


def _received(img: np.ndarray, layers: int) -> np.ndarray:
    enc = encode_image(img, CodingParams(layer_psnr=LAYER_PSNR))  # the demo's marks
    return decode_packets(enc.params, enc.width, enc.height,
                          split_packets(enc.body, enc.packet_starts, enc.layer_end(layers)))


def test_the_referee_accepts_a_faithful_image_of_the_target_the_eye_pointed_at() -> None:
    img, truth = _frame(50.0, 50.0)
    assert truth is not None and truth.objects == {1: ("target", 0)}
    sharp, blurry = _received(img, 3), _received(img, 1)
    mpp = metres_per_pixel(ALTITUDE, 640, 62.0)
    sight = next(s for s in Eye().look(sharp, mpp, settled=True) if s.target)
    assert sight.kind == "car"
    assert judge(sharp, truth, sight.box) == [("target", 0)]
    psnr, ssim = fidelity(sharp, truth, 1) or (0.0, 0.0)
    assert psnr >= MIN_PSNR_DB and ssim >= MIN_SSIM
    # the first layer is a smudge: not faithful enough inside the outline
    assert judge(blurry, truth, sight.box) == []
    # a box somewhere else in the frame does not point at the target
    assert judge(sharp, truth, (0, 0, 60, 60)) == []


def test_the_referee_never_counts_a_decoy_and_the_eye_calls_it_natural() -> None:
    img, truth = _frame(62.0, 50.0)
    assert truth is not None and truth.objects == {2: ("decoy", 0)}
    got = _received(img, 3)
    sights = Eye().look(got, metres_per_pixel(ALTITUDE, 640, 62.0), settled=True)
    assert sights and not any(s.target for s in sights), [s.describe() for s in sights]
    assert judge(got, truth, sights[0].box) == [("decoy", 0)]  # shown, but a decoy: never a target


def test_sand_has_no_truth() -> None:
    _img, truth = _frame(85.0, 85.0)
    assert truth is None  # no object in frame: nothing for the referee


# ---------------------------------------------------------------------------------- ranking


def test_target_likeness_ranks_targets_of_2_to_8_m_above_a_spike() -> None:
    """The operator's (and the vehicle's) size prior is a range, 2 to 8 m: a car, a container
    and a hull all score well; a thin pillar taller than anything sought scores low."""
    container = Target(20.0, 25.0, 6.06, 2.44, 2.59, 30.0, "box", "container")
    hull = Target(75.0, 80.0, 7.0, 2.3, 1.4, -60.0, "hull", "hull")
    spike = Target(30.0, 70.0, 1.0, 1.0, 5.0, 0.0)  # a thin pillar taller than anything sought
    ROCK_ = Target(62.0, 50.0, 3.6, 2.6, 1.6, 10.0, "dome", "rock")
    floor = Seafloor(size=100.0, depth=500.0, targets=(CAR, ROCK_, spike, container, hull), seed=2, relief=0.5)
    xs = np.arange(0.5, 100.0, 1.0)
    gx, gy = np.meshgrid(xs, xs)
    grid = floor.elevation(gx, gy)  # row 0 = south, as the receiver holds it
    from coex_plugins.bathymetry import find_targets

    views = {}
    for c in find_targets(grid, cell=1.0, threshold=0.7, min_cells=1, max_area=40.0):
        v = measure(grid, 1.0, 0.0, 0.0, c)
        assert v is not None
        name = min((("car", CAR), ("rock", ROCK_), ("spike", spike), ("container", container), ("hull", hull)),
                   key=lambda o: np.hypot(o[1].x - v.x, o[1].y - v.y))[0]
        views[name] = v
    assert set(views) == {"car", "rock", "spike", "container", "hull"}
    assert abs(views["car"].length - 4.5) < 1.5 and abs(views["car"].width - 1.8) < 1.0
    assert min(views[k].score for k in ("car", "container", "hull")) > 0.5 > views["spike"].score
    assert views["car"].score > views["rock"].score  # a rounded top scores lower
    assert target_likeness(1.5, 4.5, 1.8) == pytest.approx(1.0)
    assert target_likeness(2.6, 6.1, 2.4) == pytest.approx(1.0)
    assert target_likeness(0.3, 1.0, 1.0) < 0.9 and target_likeness(1.0, 14.0, 10.0) < 0.01  # small, or a hummock


# ---------------------------------------------------------------------------------- whole dives


@pytest.mark.slow  # a whole demo dive
@pytest.mark.usefixtures("shared_codestreams")
def test_report_says_not_met_when_a_target_is_never_photographed(tmp_path: Path) -> None:
    """Nobody operates (``--operator none``): the camera crosses the centre of the site only, so
    the cars off it are never photographed; the report must say NOT MET and why. (The quick
    site: on the small one the vehicle's own transect takes twice the frames. Seed 1's quick
    site, whose two cars lie off the centre line, is test_demo_gui.py's dive, where nobody
    operates either: its frames are coded once for both, ``tests/_dives.py``; both end 20 minutes
    into the dive, ``quick_short``: the survey ends at 332 s and nothing after it can change
    the verdict.)"""
    m = run_demo(DemoConfig(out=tmp_path, quick=True, progress=False, codec_threads=0, seed=1,
                            operator="none", scenario=quick_short())).metrics
    assert m["operator"] == "none" and m["images_captured"] > 0  # the camera ran, elsewhere
    goal = m["goals"]["every target confirmed by a received image that shows it, and nothing else confirmed"]
    assert goal["met"] is False and not m["success"]
    assert m["targets"] and all(t["confirmation"] is None for t in m["targets"])
    assert all("never photographed" in t["why_not"] for t in m["targets"])
    html = (tmp_path / "report.html").read_text()
    assert "NOT MET" in html and "never photographed" in html
    assert m["summary"].startswith("NOT MET: every true target confirmed")


# ------------------------------------------------------------------- the map's completeness


def _site_soundings(size: float) -> np.ndarray:
    """A lawnmower's soundings of a ``size`` m site: every 0.5 m from edge to edge."""
    g = np.arange(0.0, size + 0.25, 0.5)
    x, y = np.meshgrid(g, g)
    return np.column_stack([x.ravel(), y.ravel()])


def _held(placed: np.ndarray, cell: float, x0: float, y0: float, n: int) -> np.ndarray:
    """The topside grid of a map that reached topside whole: every cell holding a sounding."""
    grid = np.full((n, n), np.nan)
    col = np.floor((placed[:, 0] - x0) / cell).astype(int)
    row = np.floor((placed[:, 1] - y0) / cell).astype(int)
    grid[row, col] = -500.0
    return grid


def test_map_completeness_is_judged_in_the_frame_the_vehicle_sent_the_map() -> None:
    """Issue 54: a map that reached topside whole is complete however far the vehicle's
    dead-reckoning put it off the truth; a cell that never arrived is missing at every level
    it belongs to. The site's true cells against the received map (``area_fraction``) mix the
    frames: the same whole map, placed 3 m south-west, lacks the site's northern and eastern
    strips there."""
    from coex_apps.demo.world import SurveyedCells, area_fraction

    floor = Seafloor(size=32.0, relief=0.0)
    true = _site_soundings(32.0)
    placed = true + np.array([-3.0, -3.2])  # where a drifting vehicle put them
    cells = SurveyedCells(floor, resolution=1.0)
    cells.add(true, placed)
    cells.add(true + 40.0, placed + 40.0)  # soundings beyond the site are not the site's cells
    grid = _held(placed, 1.0, -8.0, -8.0, 48)
    assert cells.fraction(grid, 1.0, (-8.0, -8.0)) == 1.0
    assert area_fraction(grid, 1.0, (-8.0, -8.0), floor) < 0.9  # the old measure: 29 x 28 of 32 x 32
    # perfect navigation: the same as the site's cells
    still = SurveyedCells(floor, resolution=1.0)
    still.add(true, true)
    whole = _held(true, 1.0, -8.0, -8.0, 48)
    assert still.fraction(whole, 1.0, (-8.0, -8.0)) == area_fraction(whole, 1.0, (-8.0, -8.0), floor) == 1.0
    # one 1 m cell and one 8 x 8 subgrid never arrived: missing at 1 m, the subgrid at 2 m too
    grid[20, 20] = np.nan
    grid[8:16, 16:24] = np.nan
    n0 = np.count_nonzero(cells.cells(1.0))
    assert cells.fraction(grid, 1.0, (-8.0, -8.0)) == pytest.approx((n0 - 65) / n0)
    coarse = _held(placed, 2.0, -8.0, -8.0, 24)
    coarse[4:8, 8:12] = np.nan
    n1 = np.count_nonzero(cells.cells(2.0))
    assert cells.fraction(coarse, 2.0, (-8.0, -8.0)) == pytest.approx((n1 - 16) / n1)
    # nothing surveyed yet: nothing complete
    assert SurveyedCells(floor).fraction(grid, 1.0, (-8.0, -8.0)) == 0.0


def test_a_cell_whose_only_sounding_was_wild_is_not_a_surveyed_cell() -> None:
    """Issue 54: the simulation's wild soundings (``Survey.outlier``) measure nothing, and the
    vehicle's outlier screen refuses them; a cell that only a wild sounding fell in is not in
    the vehicle's map, so it is not counted as surveyed (and missing) either. A cell with a
    valid sounding beside the wild one still is."""
    from coex_apps.demo.world import SurveyedCells

    floor = Seafloor(size=32.0, relief=0.0)
    true = _site_soundings(32.0)
    placed = true + np.array([-3.0, -3.2])
    wild = np.array([[40.5, 40.5], [41.5, 40.5], [41.7, 40.7]])  # placed beyond the site's map ...
    wild_true = np.array([[10.2, 10.2], [11.2, 10.2], [11.4, 10.4]])  # ... truly in the site
    valid = np.array([False, False, True])  # the third, in the second's cell, measured the bottom
    cells = SurveyedCells(floor, resolution=1.0)
    cells.add(np.vstack([true, wild_true]), np.vstack([placed, wild]), np.concatenate([np.ones(len(true), bool), valid]))
    grid = _held(placed, 1.0, -8.0, -8.0, 56)  # topside holds every cell of the valid soundings
    n = np.count_nonzero(cells.cells(1.0))
    assert cells.fraction(grid, 1.0, (-8.0, -8.0)) == pytest.approx((n - 1) / n)  # the valid one's cell
    assert np.count_nonzero(SurveyedCells(floor).cells(1.0)) == 0
    every = SurveyedCells(floor, resolution=1.0)
    every.add(np.vstack([true, wild_true]), np.vstack([placed, wild]))  # without ``valid``: all count
    assert np.count_nonzero(every.cells(1.0)) == n + 1
