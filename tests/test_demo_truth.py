"""The demo's goals against the simulation's truth: scenarios, the operator's eye, the referee,
candidate ranking, and whole short dives with a decoy and with a target nobody photographs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from coex_apps.demo import DemoConfig, run_demo
from coex_apps.demo.camera import SandTexture, render_labelled
from coex_apps.demo.config import LAYER_PSNR
from coex_apps.demo.operator import car_likeness, measure
from coex_apps.demo.scenario import (
    PRESETS,
    ObjectSpec,
    Scenario,
    load_scenario,
    preset,
    scenario_from_dict,
)
from coex_apps.demo.truth import Eye, frame_truth, judge
from coex_core.errors import ConfigError
from coex_plugins.bathymetry.sim import Seafloor, Target
from coex_plugins.imagery.codec import CodingParams, decode_packets, encode_image, split_packets

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
    assert s.targets == (ObjectSpec(50.0, 60.0, heading=30.0),)
    assert s.decoys[0].x == 120.0 and s.decoys[0].width > 2.0  # a rock's default size, not a car's
    assert s.modem_rate == 3 and s.slots == ("topside", "vehicle", "vehicle", "vehicle") and s.cycle == 60.0
    assert s.loss.model == "range" and s.ship == (100.0, -450.0)
    rl = s.loss.range_loss()
    assert rl is not None and rl(400.0) < 0.1 < rl(800.0) < rl(1500.0) <= 0.8
    targets, decoys = s.place(seed=3)
    assert targets == s.targets and [(d.x, d.y) for d in decoys] == [(d.x, d.y) for d in s.decoys]
    assert all(d.shape == "dome" for d in decoys)  # listed objects win over random ones; decoys are boulders
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
    with pytest.raises(ConfigError, match=f"unknown scenario key {key.replace('[', '.').replace(']', '.')}"):
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
    for words in ("area must be 16-4096 m, got 5.0", "survey.speed must be a number, got 'fast'",
                  "loss.rate must be in [0, 1), got 1.2", "unknown scenario key colour", "targets[0] needs x and y"):
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


def test_cli_rejects_a_bad_scenario(tmp_path: Path) -> None:
    f = tmp_path / "bad.toml"
    f.write_text("area = 100.0\nwater_dpeth = 3.0\n")
    proc = subprocess.run([sys.executable, "-m", "coex_core.cli", "demo", "--scenario", str(f), "--out",
                           str(tmp_path / "o")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "water_dpeth" in proc.stderr


# ---------------------------------------------------------------------------------- the eye

CAR = Target(50.0, 50.0, heading=20.0)
ROCK = Target(62.0, 50.0, 3.6, 2.6, 1.6, 10.0, "dome")
FLOOR = Seafloor(size=100.0, depth=500.0, targets=(CAR, ROCK), seed=1)


def _frame(x: float, y: float, altitude: float = 5.0) -> tuple[np.ndarray, object]:
    z = float(FLOOR.ground(np.array([x]), np.array([y]))[0]) + altitude
    img, labels = render_labelled(FLOOR.ground, x, y, z, 0.0, targets=[CAR], rocks=[ROCK],
                                  texture=SandTexture(1), rng=np.random.default_rng(0))
    hf = np.tan(np.radians(31.0))
    pixel = {1: (2 * (altitude - 1.5) * hf / 640) ** 2, 2: (2 * (altitude - 1.07) * hf / 640) ** 2}
    return img, frame_truth(0.0, x, y, 0.0, img, labels, 1, {1: 4.5 * 1.8, 2: 3.6 * 2.6 * np.pi / 4}, pixel)


def _received(img: np.ndarray, layers: int) -> np.ndarray:
    enc = encode_image(img, CodingParams(layer_psnr=LAYER_PSNR))  # the demo's marks
    return decode_packets(enc.params, enc.width, enc.height,
                          split_packets(enc.body, enc.packet_starts, enc.layer_end(layers)))


def test_eye_needs_a_sharp_enough_image_to_see_a_car() -> None:
    img, truth = _frame(50.0, 50.0)
    assert truth is not None and truth.objects == {1: ("target", 0)}
    eye = Eye()
    blurry = eye.look(_received(img, 1), truth)  # the first quality mark, 20 dB
    sharp = eye.look(_received(img, 3), truth)  # 30 dB
    assert [s.kind for s in blurry] == ["unclear"]  # a dark smudge: ask for more
    assert [s.kind for s in sharp] == ["car"]
    # the referee agrees that the sharp image shows target 1, and not the first layers
    assert judge(_received(img, 3), truth) == [("target", 0)]
    assert judge(_received(img, 1), truth) == []


def test_eye_never_takes_a_boulder_for_a_car() -> None:
    img, truth = _frame(62.0, 50.0)
    assert truth is not None and truth.objects == {2: ("decoy", 0)}
    for layers in (2, 6, 10, 14, 22):
        kinds = {s.kind for s in Eye().look(_received(img, layers), truth)}
        assert "car" not in kinds, layers
    assert {s.kind for s in Eye().look(img, truth)} == {"rock"}
    assert judge(img, truth) == [("decoy", 0)]


def test_sand_shows_nothing() -> None:
    _img, truth = _frame(85.0, 85.0)
    assert truth is None  # no object in frame: nothing for the eye or the referee


# ---------------------------------------------------------------------------------- ranking


def test_car_likeness_ranks_a_car_above_a_boulder_and_a_spike() -> None:
    spike = Target(30.0, 70.0, 1.2, 1.2, 3.5, 0.0)
    floor = Seafloor(size=100.0, depth=500.0, targets=(CAR, ROCK, spike), seed=2, relief=0.5)
    xs = np.arange(0.5, 100.0, 1.0)
    gx, gy = np.meshgrid(xs, xs)
    grid = floor.elevation(gx, gy)  # row 0 = south, as the receiver holds it
    from coex_plugins.bathymetry import find_targets

    views = {}
    for c in find_targets(grid, cell=1.0, threshold=0.7, min_cells=1, max_area=40.0):
        v = measure(grid, 1.0, 0.0, 0.0, c)
        assert v is not None
        name = min((("car", CAR), ("rock", ROCK), ("spike", spike)),
                   key=lambda o: np.hypot(o[1].x - v.x, o[1].y - v.y))[0]
        views[name] = v
    assert set(views) == {"car", "rock", "spike"}
    assert abs(views["car"].length - 4.5) < 1.5 and abs(views["car"].width - 1.8) < 1.0
    assert views["car"].score > views["rock"].score > views["spike"].score
    assert car_likeness(1.5, 4.5, 1.8) == pytest.approx(1.0)


# ---------------------------------------------------------------------------------- whole dives


def _quick(tmp: Path, scenario: Scenario, **kw: object) -> dict:  # type: ignore[type-arg]
    return run_demo(DemoConfig(out=tmp, quick=True, progress=False, scenario=scenario, **kw)).metrics  # type: ignore[arg-type]


@pytest.mark.slow  # a whole demo dive
def test_a_decoy_is_looked_at_and_never_confirmed(tmp_path: Path) -> None:
    """A car-sized boulder near the car: the operator visits it (it is car-like enough in the
    map) and sees a boulder; only the car is confirmed."""
    scn = Scenario(area=96.0, targets=(ObjectSpec(30.0, 40.0, heading=10.0),),
                   decoys=(ObjectSpec(65.0, 55.0, 3.6, 2.6, 1.6, 40.0),))
    m = _quick(tmp_path, scn, seed=4)
    assert m["false_confirmations"] == []
    assert m["decoys"][0]["visited"], "the decoy must be visited for this test to mean anything"
    at_decoy = [c for c in m["candidates"] if c["truth"] == "decoy 1 (rock)"]
    assert at_decoy and all(c["verdict"] != "car" for c in at_decoy)
    assert m["targets"][0]["confirmation"] is not None and m["success"]
    truth = json.loads((tmp_path / "truth.json").read_text())
    assert [d["kind"] for d in truth["decoys"]] == ["rock"]


@pytest.mark.slow  # a whole demo dive
def test_report_says_not_met_when_a_target_is_never_photographed(tmp_path: Path) -> None:
    """Nobody operates (``--operator none``): the camera crosses the centre of the site only, so
    the car in the corner is never photographed; the report must say NOT MET and why."""
    scn = Scenario(area=96.0, targets=(ObjectSpec(22.0, 75.0),))
    m = _quick(tmp_path, scn, seed=2, operator="none")
    assert m["operator"] == "none"
    goal = m["goals"]["every target confirmed by a received image that shows it, and nothing else confirmed"]
    assert goal["met"] is False and not m["success"]
    assert m["targets"][0]["confirmation"] is None
    assert "never photographed" in m["targets"][0]["why_not"]
    html = (tmp_path / "report.html").read_text()
    assert "NOT MET" in html and "never photographed" in html
    assert m["summary"].startswith("NOT MET: every true target confirmed")
