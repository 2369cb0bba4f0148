"""``coex demo --preset fleet`` (issue 43): a mapping AUV (node 2) and a camera vehicle (node 3)
with topside (node 1) on one simulated acoustic network of Micromodems on pseudo-terminals. The
quick dive meets its goals, the camera vehicle confirms a target while the mapper's survey still
runs, and no survey command meant for the camera vehicle is ever executed by the mapper."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from coex_apps.demo import DemoConfig
from coex_apps.demo.config import CAMERA, TOPSIDE, VEHICLE
from coex_apps.demo.run import DiveRun
from coex_apps.demo.scenario import preset, scenario_from_dict
from coex_apps.demo.world import dive_schedule
from coex_core.errors import ConfigError

from ._dives import codestreams_shared

# a whole two-vehicle demo dive
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def dive(tmp_path_factory: pytest.TempPathFactory) -> tuple[DiveRun, dict[str, Any], Path]:
    """One quick fleet dive, its survey slowed and its lines closer (the quick site is small: at
    full speed its survey is over in four minutes, before any camera line could be flown)."""
    out = tmp_path_factory.mktemp("fleet")
    scn = scenario_from_dict({"survey": {"speed": 0.5, "line_spacing": 24.0}}, base=preset("fleet"))
    run = DiveRun(DemoConfig(out=out, quick=True, seed=1, progress=False, scenario=scn))
    with codestreams_shared(tmp_path_factory):
        result = run.run()
    return run, result.metrics, out


def test_fleet_preset_schedule() -> None:
    scn = preset("fleet")
    assert scn.fleet and not preset("default").fleet
    owners = [s.owner for s in dive_schedule(scn).slots]
    assert set(owners) == {TOPSIDE, VEHICLE, CAMERA}
    assert owners == [1, 2, 3, 1, 2, 2]
    with pytest.raises(ConfigError, match="camera"):
        scenario_from_dict({"modem": {"slots": ["topside", "vehicle", "boat"]}})


def test_fleet_quick_dive_meets_its_goals(dive: tuple[DiveRun, dict[str, Any], Path]) -> None:
    _, m, out = dive
    assert m["success"], m["summary"]
    assert all(g["met"] for g in m["goals"].values()), m["goals"]
    assert not m["false_confirmations"]
    # three modems on pseudo-terminals, one schedule giving slots to all three
    assert set(m["modems"]["nmea_over"]) == {"1", "2", "3"}
    assert "camera vehicle slots 2" in m["modems"]["tdma"]
    # decision time per target and its summary
    for t in m["targets"]:
        assert t["decision_time_s"] == pytest.approx(t["confirmation"]["confirmed_at_s"] - t["identifiable_at_1m_s"])
    assert m["decision_time_s"]["missing"] == 0 and m["decision_time_s"]["worst"] is not None
    # one report section per vehicle
    roles = [(v["node"], v["role"]) for v in m["vehicles"]]
    assert roles == [(VEHICLE, "mapping AUV (multibeam)"), (CAMERA, "camera vehicle")]
    report = (out / "report.html").read_text()
    assert "Vehicle 2: mapping AUV" in report and "Vehicle 3: camera vehicle" in report
    assert "decision time (s)" in report
    assert json.loads((out / "metrics.json").read_text())["vehicles"] == m["vehicles"]


def test_camera_confirms_a_target_before_the_survey_ends(dive: tuple[DiveRun, dict[str, Any], Path]) -> None:
    run, m, _ = dive
    confirmed = [t["confirmation"]["confirmed_at_s"] for t in m["targets"] if t["confirmation"]]
    assert confirmed and min(confirmed) < m["survey_end_s"], (confirmed, m["survey_end_s"])
    # the camera vehicle took the images, the mapper none; the mapper kept mapping meanwhile
    # (its pings went on to the survey's end, and the 1 m map is complete)
    cam, mapper = m["vehicles"][1], m["vehicles"][0]
    assert cam["images_captured"] > 0 and mapper["images_captured"] == 0
    assert all(leg.t0 >= run.camera_start - 1e-6 for leg in run.autonomy.camera_legs())
    assert not any(leg.camera for leg in run.track.legs)  # the mapper never flew a camera line
    assert m["map_coverage"]["0"] >= 0.99
    assert min(s["sent_at_s"] for s in m["surveys"]) < m["survey_end_s"]


def test_no_command_for_the_camera_vehicle_is_executed_by_the_mapper(
        dive: tuple[DiveRun, dict[str, Any], Path]) -> None:
    run, m, _ = dive
    assert run.fleet is not None
    camera_surveys = run.fleet.camera_senders["survey"].surveys
    mapper_surveys = run.fleet.mapper_senders["survey"].surveys
    assert len(camera_surveys) >= 2  # the camera lines reached the camera vehicle ...
    assert mapper_surveys == {}  # ... and never the mapper, which has a survey sender of its own
    assert run.mapper_autonomy is not None and run.mapper_autonomy.truth == {}
    mapper, cam = m["vehicles"]
    assert mapper["survey_commands_received"] == mapper["survey_commands_flown"] == 0
    assert cam["survey_commands_flown"] >= 2
    # the mapper's modem heard topside's frames for the camera vehicle and handled none of them
    assert mapper["frames_overheard_for_others"] > 0
    # every survey command topside sent went to node 3, and was answered by node 3 alone
    assert all(s["final_state"] in ("completed", "started", "accepted") for s in m["surveys"])
    assert run.fleet.receivers["mapper_survey"].surveys == {}
