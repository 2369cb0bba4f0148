"""ROS vehicles (issue 44): the ``ros`` input on live topics, the ``ros`` autonomy output (a survey
as a nav_msgs/Path, its progress read back), the topside's products on ROS topics, and the pair
end to end: a real roscore on each side, rospy programs playing the vehicle's nodes, the planner
and rviz, two simulated Micromodems between. Without Debian's ROS 1 (roscore) or rospy in the venv
(`make ros`) the ROS tests are skipped with the reason; the rest runs everywhere."""

from __future__ import annotations

import json
import math
import os
import shlex
import signal
import subprocess
import sys
import threading
import time
import xmlrpc.client
from collections.abc import Callable, Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from coex import Image, InputContext, Nav, Points, Samples
from coex_core.errors import ConfigError
from coex_core.messages import SurveyKind, SurveyReason, SurveyState
from coex_plugins.autonomy.ros import RosAutonomy, parse_progress
from coex_plugins.inputs.ros import RosInput
from coex_plugins.inputs.rosmsg import FrameMap, frame_problems, nav_of, points_of
from coex_plugins.survey.plan import SurveyPlan

from . import _products as typed
from ._lifecycle import Vehicle
from ._ros import Roscore, kill, peer, ros_entry_points, ros_env, why_no_ros

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples" / "ros"
NO_ROS = why_no_ros()
needs_ros = pytest.mark.skipif(NO_ROS is not None, reason=NO_ROS or "")
pytestmark = pytest.mark.filterwarnings("ignore:notifyAll:DeprecationWarning")  # rospy's threads


def _wait(what: str, cond: Callable[[], Any], timeout: float = 30.0, procs: dict[str, Any] | None = None) -> Any:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        for name, p in (procs or {}).items():
            if p.poll() is not None:
                raise AssertionError(f"{name} exited ({p.returncode}) while waiting for {what}")
        got = cond()
        if got:
            return got
        time.sleep(0.1)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


class _Out:
    """A peer's JSON lines, read in a thread."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.events: list[dict[str, Any]] = []
        self.bad: list[str] = []
        self.t = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self.t.start()

    def _read(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            try:
                self.events.append(json.loads(line))
            except ValueError:
                self.bad.append(line)  # not JSON: said in a failure's message

    def find(self, **match: Any) -> list[dict[str, Any]]:
        return [e for e in list(self.events) if all(e.get(k) == v for k, v in match.items())]


# ============================================================================ without ROS
def _msg(frame: str, **fields: Any) -> Any:
    return SimpleNamespace(header=SimpleNamespace(frame_id=frame, stamp=SimpleNamespace(sec=5, nanosec=0)), **fields)


def _cloud(frame: str, xyz: np.ndarray) -> Any:
    fields = [SimpleNamespace(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")]
    data = np.ascontiguousarray(xyz, dtype="<f4").tobytes()  # bytes, as rospy gives it
    return _msg(frame, fields=fields, is_bigendian=False, point_step=12, width=len(xyz), height=1,
                row_step=12 * len(xyz), data=data)


def _pose(frame: str, x: float, y: float, z: float, yaw: float) -> Any:
    q = SimpleNamespace(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))
    return _msg(frame, pose=SimpleNamespace(position=SimpleNamespace(x=x, y=y, z=z), orientation=q))


def test_frames_map_points_and_poses_to_the_local_grid() -> None:
    frames = FrameMap({"map": "enu", "world_ned": "ned", "odom": {"x": 100.0, "y": -50.0, "yaw": 90.0}})
    pts = np.array([[1.0, 2.0, -30.0], [np.nan, 0.0, 0.0]])
    assert points_of(_cloud("map", pts), frames).tolist() == [[1.0, 2.0, -30.0]]  # NaN row dropped
    # NED: x north, y east, z down
    assert points_of(_cloud("/world_ned", np.array([[2.0, 1.0, 30.0]])), frames).tolist() == [[1.0, 2.0, -30.0]]
    # odom: turned 90 degrees counter-clockwise, its origin at (100, -50)
    np.testing.assert_allclose(points_of(_cloud("odom", np.array([[1.0, 0.0, -5.0]])), frames),
                               [[100.0, -49.0, -5.0]], atol=1e-9)
    with pytest.raises(ValueError, match="frame 'base_link' is not mapped"):
        points_of(_cloud("base_link", pts), frames)
    nav = nav_of("geometry_msgs/PoseStamped", _pose("world_ned", 10.0, 30.0, 25.0, math.pi / 2), 5.0, frames)
    assert nav is not None and (nav.x, nav.y, nav.depth) == (30.0, 10.0, 25.0)
    assert nav.heading == pytest.approx(90.0)  # NED yaw 90 degrees = east
    nav = nav_of("geometry_msgs/PoseStamped", _pose("odom", 0.0, 0.0, -2.0, 0.0), 5.0, frames)
    assert nav is not None and (nav.x, nav.y, nav.depth) == (100.0, -50.0, 2.0)
    assert nav.heading == pytest.approx(0.0)  # odom's x axis points north
    # without `frames`: points as given, poses in nav_frame, whatever their frame id
    assert nav_of("geometry_msgs/PoseStamped", _pose("anything", 10.0, 30.0, 25.0, 0.0), 5.0,
                  FrameMap(None, "ned")) == Nav(5.0, x=30.0, y=10.0, depth=25.0, heading=0.0, speed=None)
    assert frame_problems("ros", {"frames": {"a": "nde", "b": {"axes": "enu", "roll": 1}, "c": {"x": "1"}},
                                  "nav_frame": "xyz"}) == [
        "input 'ros': option 'nav_frame' must be one of 'enu', 'ned', not 'xyz'",
        "input 'ros': option 'frames.a.axes' must be 'enu' or 'ned', not 'nde'",
        "input 'ros': option 'frames.b.roll' is not one of axes, x, y, z, yaw",
        "input 'ros': option 'frames.c.x' must be a number, not '1'",
    ]


def test_the_ros_adapters_check_their_options_without_ros() -> None:
    ctx = InputContext()
    with pytest.raises(ConfigError, match="needs at least one of the options"):
        RosInput({}, ctx)
    with pytest.raises(ConfigError, match=r"option 'master' must be an http:// URI"):
        RosInput({"nav_topic": "/odom", "master": "localhost:11311"}, ctx)
    with pytest.raises(ConfigError, match=r"'series\[0\].channels.t': 'temp\[' is not a field path"):
        RosInput({"series": [{"topic": "/ctd", "channels": {"t": "temp["}}]}, ctx)
    with pytest.raises(ConfigError, match=r"'series\[0\].scale.s' scales nothing"):
        RosInput({"series": [{"topic": "/ctd", "channels": {"t": "temperature"}, "scale": {"s": 2}}]}, ctx)
    with pytest.raises(ConfigError, match=r"queue: 0 is outside 1\.\.10000"):
        RosInput({"nav_topic": "/odom", "queue": 0}, ctx)
    RosInput({"series": [{"topic": "/ctd", "channels": {"t": "temperature"}}]}, ctx)  # builds, opens nothing
    RosInput({"altitude_topic": "/altimeter"}, ctx)  # an altimeter alone is enough
    with pytest.raises(ConfigError, match=r"option 'altitude_field': 'range\[' is not a field path"):
        RosInput({"altitude_topic": "/dvl", "altitude_field": "range["}, ctx)
    with pytest.raises(ConfigError, match="answer_timeout"):
        RosAutonomy({"answer_timeout": -1}, ctx)
    with pytest.raises(ConfigError, match="autonomy 'ros': silence: not a finite number, got '10'"):
        RosAutonomy({"silence": "10"}, ctx)
    with pytest.raises(ConfigError, match="unknown option 'topic'"):
        RosAutonomy({"topic": "/x"}, ctx)


def test_progress_answers() -> None:
    assert parse_progress("7 started 2") == (7, SurveyState.STARTED, SurveyReason.NONE, 2, None)
    assert parse_progress("started") == (None, SurveyState.STARTED, SurveyReason.NONE, 0, None)
    assert parse_progress("  Completed ") == (None, SurveyState.COMPLETED, SurveyReason.NONE, None, None)
    assert parse_progress("3 refused speed above 1.5 m/s") == (
        3, SurveyState.REJECTED, SurveyReason.AUTONOMY_REFUSED, None, "speed above 1.5 m/s")
    assert parse_progress("aborted leak in the pressure housing")[1:] == (
        SurveyState.ABORTED, SurveyReason.AUTONOMY_STOPPED, None, "leak in the pressure housing")
    assert parse_progress("4 aborted manual pilot took over")[1:] == (
        SurveyState.ABORTED, SurveyReason.MANUAL_OVERRIDE, None, "pilot took over")
    assert parse_progress("aborted all_stop")[2] == SurveyReason.ALL_STOP
    assert parse_progress("aborted restarted planner crashed")[2] == SurveyReason.AUTONOMY_RESTARTED
    for bad in ("", "7", "flying", "started two"):
        with pytest.raises(ValueError):
            parse_progress(bad)


def test_topside_ros_table_is_checked() -> None:
    from coex_apps.vehicle.config import check_mapping

    base: dict[str, Any] = {"node": {"role": "topside", "id": 1}, "modems": [{"uri": "loopback://t"}],
                            "modalities": {"survey": {}}}
    cfg, problems = check_mapping({**base, "ros": {"prefix": "coex", "interval": 0, "topic": "/x"}}, ROOT / "t.toml", None)
    assert problems == ["ros.topic: unknown key (known: frame, grid_max, grid_min, interval, master, node, prefix, "
                        "series_samples, track, vehicle_frame)",
                        "ros.prefix: a global namespace starting with '/', got 'coex'",
                        "ros.interval: seconds from 0.05 to 3600, got 0"]
    _, problems = check_mapping({**base, "ros": {"grid_min": -30.0, "series_samples": 0}}, ROOT / "t.toml", None)
    assert problems == ["ros.series_samples: an integer from 1 to 1000000, got 0",
                        "ros.grid_max: give grid_min and grid_max together"]
    _, problems = check_mapping({**base, "ros": {"grid_min": -30.0, "grid_max": -40}}, ROOT / "t.toml", None)
    assert problems == ["ros.grid_max: above grid_min (-30.0), got -40"]
    cfg, problems = check_mapping({**base, "ros": {"master": "http://ship:11311"}}, ROOT / "t.toml", None)
    assert problems == [] and cfg is not None and cfg.ros == {"master": "http://ship:11311"}
    vehicle = {**base, "node": {"role": "vehicle", "id": 2}, "ros": {}}
    _, problems = check_mapping(vehicle, ROOT / "v.toml", None)
    assert any(p.startswith("ros: only a topside node publishes its products on ROS") for p in problems)


def test_the_ship_s_grids_share_one_depth_scale() -> None:
    """OccupancyGrid values are elevations on one scale for every message (not each level's own
    deepest..shallowest): the configured one, or the first level's widened to whole 10 m."""
    from coex_apps.console.ros import grid_scale, topic_name
    from coex_transports.ros.msgs import grid_values

    a = np.array([[-31.0, np.nan], [-28.0, -30.0]])
    assert grid_values(a, -40.0, -20.0).tolist() == [[45, -1], [60, 50]]
    assert grid_values(a + 5.0, -40.0, -20.0).tolist() == [[70, -1], [85, 75]]  # shallower: higher
    assert grid_values(np.array([[-100.0, 0.0]]), -40.0, -20.0).tolist() == [[0, 100]]  # clipped
    assert grid_scale(a) == (-40.0, -20.0) and grid_scale(np.array([[-30.0]])) == (-30.0, -20.0)
    assert grid_values(a).tolist() == [[0, -1], [100, 33]]  # without a scale: the grid's own
    with pytest.raises(ValueError):
        grid_scale(np.full((2, 2), np.nan))
    assert [topic_name(n) for n in ("methane", "CTD temp (C)", "2nd", "")] == [
        "methane", "CTD_temp__C_", "ch_2nd", "ch"]


def test_the_example_rviz_configuration_shows_what_the_examples_publish() -> None:
    """examples/ros/coex.rviz (tried in rviz 1.14 under xvfb-run: docs/deploy.md) subscribes only
    to topics the example topside publishes (or the vehicle's survey path), in the fixed frame the
    topside's messages carry, with each display's type the one its topic carries."""
    import tomllib

    import yaml

    from coex_apps.vehicle.config import expand

    rviz = yaml.safe_load((EXAMPLES / "coex.rviz").read_text())
    topside = tomllib.loads(expand((EXAMPLES / "topside.toml").read_text()))["ros"]
    vehicle = tomllib.loads(expand((EXAMPLES / "vehicle.toml").read_text()))
    prefix, frame = topside["prefix"], topside["frame"]
    manager = rviz["Visualization Manager"]
    assert manager["Global Options"]["Fixed Frame"] == frame
    published = {**{f"{prefix}/map/level_{k}": "rviz/PointCloud2" for k in range(8)},
                 **{f"{prefix}/map/level_{k}/grid": "rviz/Map" for k in range(8)},
                 f"{prefix}/image": "rviz/Image", f"{prefix}/vehicle/odometry": "rviz/Odometry",
                 f"{prefix}/vehicle/track": "rviz/Path"}
    path_topic = next(v["path_topic"] for v in _tables(vehicle) if "path_topic" in v)
    published[path_topic] = "rviz/Path"
    shown = {d.get("Topic") or d.get("Image Topic"): d["Class"] for d in manager["Displays"]
             if d["Class"] != "rviz/Grid"}
    assert shown and all(published.get(t) == c for t, c in shown.items()), shown
    assert {c for c in shown.values()} == {"rviz/PointCloud2", "rviz/Map", "rviz/Image", "rviz/Odometry", "rviz/Path"}


def _tables(doc: dict[str, Any]) -> list[dict[str, Any]]:
    """Every table of a TOML document, nested ones included."""
    out = [doc]
    for v in doc.values():
        if isinstance(v, dict):
            out.extend(_tables(v))
    return out


# ============================================================================ with a roscore
@pytest.fixture(scope="session")
def roscore(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Roscore]:
    """One roscore per test process (rospy: one master per process), killed at the end; this
    process's rospy talks to it on loopback."""
    if NO_ROS is not None:
        pytest.skip(NO_ROS)
    core = Roscore()
    core.start()
    home = tmp_path_factory.mktemp("ros-home")
    os.environ.update({k: v for k, v in ros_env(core.uri, home).items() if k.startswith("ROS_")})
    yield core
    core.close()


def _items(inp: RosInput, want: Callable[[list[Any]], bool], timeout: float = 30.0) -> list[Any]:
    got: list[Any] = []

    def enough() -> bool:
        got.extend(inp.poll(time.time()))
        return want(got)

    _wait("items from the ros input", enough, timeout)
    return got


def _kinds(items: list[Any]) -> set[type]:
    return {type(i) for i in items}


@needs_ros
def test_the_ros_input_reads_live_topics_and_survives_a_roscore_restart(roscore: Roscore, tmp_path: Path) -> None:
    inp = RosInput({"master": roscore.uri, "points_topic": "/t1/points", "image_topic": "/t1/image",
                    "nav_topic": "/t1/odom", "frames": {"world_ned": "ned", "map": "enu"},
                    "series": [{"topic": "/ctd/temperature", "channels": {"water_temperature": "temperature"},
                                "scale": {"water_temperature": 10.0}}], "altitude_topic": "/altimeter"},
                   InputContext())
    inp.open()
    args = ["--publish", "--every", "0.3", "--swaths", "1000", "--images", "1000", "--image", "raw",
            "--points-topic", "/t1/points", "--image-topic", "/t1/image", "--nav-topic", "/t1/odom",
            "--points-frame", "ned", "--points-frame-id", "world_ned", "--nav-frame", "ned",
            "--nav-frame-id", "world_ned"]
    first = peer(["--name", "stack_a", *args], roscore.env(), tmp_path / "stack_a.log")
    second = None
    try:
        items = _items(inp, lambda got: _kinds(got) >= {Points, Image, Nav, Samples})
        pts = next(i for i in items if isinstance(i, Points))
        # NED points of the seafloor 30 m down come out east, north, up
        assert pts.xyz.shape == (400, 3) and -31.5 < pts.xyz[:, 2].min() and pts.xyz[:, 2].max() < -28.5
        assert -20.5 < pts.xyz[:, 0].min() and pts.xyz[:, 0].max() < 20.5
        img = next(i for i in items if isinstance(i, Image))
        assert img.pixels is not None and img.pixels.shape == (96, 128) and img.pixels.dtype == np.uint8
        nav = next(i for i in items if isinstance(i, Nav) and i.x is not None)
        assert (nav.x, nav.y, nav.depth, nav.speed) == (30.0, 10.0, 25.0, 1.0) and nav.heading == pytest.approx(90.0)
        # the altimeter: altitude alone (a ping without a bottom gives none)
        items += _items(inp, lambda got: inp.counts["no_altitude"] >= 1 and inp.counts["altitude"] >= 1)
        alts = [i for i in items if isinstance(i, Nav) and i.altitude is not None]
        assert alts and {(i.x, i.altitude) for i in alts} == {(None, 5.0)}
        assert abs(nav.time - time.time()) < 60  # the header stamp
        series = next(i for i in items if isinstance(i, Samples))
        assert series.channel == "water_temperature" and 39.9 < series.values[0] < 45.0  # scaled by 10
        assert inp.state == "up"

        # the master dies: what is connected goes on flowing, polls never wait
        roscore.stop()
        _wait("the master seen lost", lambda: inp.state == "master lost", 20)
        _items(inp, lambda got: Points in _kinds(got))
        # a new master; the vehicle's nodes are restarted with it (ROS 1 nodes do not register again)
        roscore.start()
        kill(first)
        _wait("the input registered again", lambda: inp.state == "up" and inp._node.counts["reregistered"] >= 1, 20)
        inp.poll(time.time())  # what the old publisher sent last
        second = peer(["--name", "stack_b", *args], roscore.env(), tmp_path / "stack_b.log")
        items = _items(inp, lambda got: _kinds(got) >= {Points, Image, Nav, Samples})
        assert inp._node.counts["outages"] >= 1
        assert inp.counts["skipped"] == 0
    finally:
        kill(first)
        kill(second)
        inp.close()


@needs_ros
def test_a_topic_of_another_type_is_skipped_and_counted(roscore: Roscore, tmp_path: Path) -> None:
    inp = RosInput({"master": roscore.uri, "image_topic": "/t2/odom", "nav_topic": "/t2/odom2"}, InputContext())
    inp.open()
    p = peer(["--name", "stack_t2", "--publish", "--every", "0.2", "--nav-topic", "/t2/odom"], roscore.env(),
             tmp_path / "t2.log")
    try:
        _wait("a skipped message", lambda: not inp.poll(time.time()) and inp.counts["skipped"] >= 2, 30)
        assert inp.counts["image"] == 0
    finally:
        kill(p)
        inp.close()


def _reports(out: RosAutonomy, n: int = 1) -> list[Any]:
    """The output's reports once it has ``n`` (a few more polls for what comes with them)."""
    got: list[Any] = []
    _wait(f"{n} report(s)", lambda: got.extend(out.poll(time.time())) or len(got) >= n, 30)
    for _ in range(5):
        time.sleep(0.05)
        got.extend(out.poll(time.time()))
    return got


LAWN = SurveyPlan(7, SurveyKind.LAWNMOWER, ((10.0, -20.0), (70.0, -20.0), (70.0, -30.0), (10.0, -30.0)),
                  depth=20.0, speed=2.0, heading=90.0, length=60.0, width=10.0, spacing=10.0, centre=(40.0, -25.0))


@needs_ros
def test_a_survey_goes_out_as_a_path_and_its_progress_comes_back(roscore: Roscore, tmp_path: Path) -> None:
    ctx = InputContext(41.5, -70.6)
    out = RosAutonomy({"master": roscore.uri, "answer_timeout": 30.0}, ctx)
    out.open()
    # the path's publisher and the progress subscriber registered before the planner starts (the
    # node makes them in its own thread: under load the planner could otherwise start first)
    _wait("the output's topics registered", lambda: _registered(roscore.uri, out._path.topic, 0)
          and _registered(roscore.uri, out._sub.topic, 1), 30)
    planner = peer(["--name", "planner_fly", "--planner", "fly", "--leg", "0.1"], roscore.env(), tmp_path / "fly.log")
    lines = _Out(planner)
    try:
        _wait("the planner connected both ways",
              lambda: out._path.connections() > 0 and out._sub.connections() > 0, 30)
        out.submit(LAWN, time.time())
        reports: list[Any] = []

        def done() -> bool:
            reports.extend(out.poll(time.time()))
            return bool(reports) and reports[-1].state == SurveyState.COMPLETED

        _wait("the survey flown", done, 30)
        # the planner said "started 0" .. "started 3", "completed"; any it said may be superseded
        # by a newer one before CoEx reads it (a loaded machine): what comes is in order, once each,
        # ending completed
        started = [r.index for r in reports if r.state == SurveyState.STARTED]
        assert started == sorted(set(started)) and set(started) <= {0, 1, 2, 3}, reports
        assert [r.state for r in reports][-1] == SurveyState.COMPLETED
        assert [r.state for r in reports].count(SurveyState.COMPLETED) == 1
        [path] = lines.find(event="path")
        assert path["frame"] == "coex_local"
        assert path["poses"] == [[x, y, -20.0] for x, y in LAWN.waypoints]  # z = -depth
        assert path["stamps"][1] - path["stamps"][0] == pytest.approx(30.0, abs=1e-3)  # 60 m at 2 m/s
        assert path["plan"] == {"survey_id": 7, "kind": "lawnmower", "waypoints": 4, "altitude": None,
                                "depth": 20.0, "speed": 2.0, "frame": "coex_local", "stamp": path["plan"]["stamp"],
                                "ended": False}
    finally:
        kill(planner)
    out.end(7, time.time())  # as the daemon's lifecycle does: the next planner is not handed survey 7
    fresh = _new_peers(out)  # the killed planner's connections may linger: wait for the refuser's
    refuser = peer(["--name", "planner_refuse", "--planner", "refuse"], roscore.env(), tmp_path / "refuse.log")
    try:
        _wait("the refusing planner connected both ways", fresh, 30)
        plan = SurveyPlan(8, SurveyKind.GOTO, ((5.0, 5.0),), altitude=3.0)
        out.submit(plan, time.time())
        got = _reports(out)
        assert [(r.survey_id, r.state, r.reason, r.detail) for r in got] == [
            (8, SurveyState.REJECTED, SurveyReason.AUTONOMY_REFUSED, "no thrusters")]
    finally:
        kill(refuser)

    # answers from the planner's topic: aborted with reasons; an answer about the previous survey
    # (handed over by this output) is reported as that survey's, for the daemon's lifecycle to
    # record as a late answer; one about a survey never handed over is dropped
    # three answers published at once: a queue that holds them all (at the default 2 a loaded
    # machine's publisher thread dropped the first before it sent it)
    answer = out.node.publisher("/coex/survey/progress", "std_msgs/String", queue=10)
    _wait("the answer topic connected", lambda: answer.connections() > 0, 30)
    for sid, text, want in ((9, "9 aborted manual pilot took over", SurveyReason.MANUAL_OVERRIDE),
                            (10, "aborted all_stop MissingDecVars:depth", SurveyReason.ALL_STOP),
                            (11, "11 aborted restarted", SurveyReason.AUTONOMY_RESTARTED)):
        out.submit(SurveyPlan(sid, SurveyKind.GOTO, ((1.0, 1.0),)), time.time())
        answer.publish(out.node.message("std_msgs/String", data=f"{sid - 1} started 0"))  # the previous survey's
        answer.publish(out.node.message("std_msgs/String", data="500 started 0"))  # never handed over
        answer.publish(out.node.message("std_msgs/String", data=text))
        got = _reports(out, 2)
        assert sorted((r.survey_id, r.state, r.reason) for r in got) == [
            (sid - 1, SurveyState.STARTED, SurveyReason.NONE), (sid, SurveyState.ABORTED, want)], got
    assert [r.detail for r in got if r.survey_id == 11] == [None]
    out.close()


@needs_ros
def test_an_ended_survey_is_never_handed_to_a_planner_started_later(roscore: Roscore, tmp_path: Path) -> None:
    """Issue 51: a survey completed, refused or unanswered leaves the ended form latched (an empty
    path, the plan's JSON with "ended": true), so a planner started (or respawned) after it flies
    nothing; an answer after the end is kept in the survey's record; a planner killed mid-survey
    is reported aborted, AUTONOMY_SILENT, within `silence`."""
    ns = "/t6/survey"
    silence = 3.0
    out = RosAutonomy({"master": roscore.uri, "path_topic": f"{ns}/path", "plan_topic": f"{ns}/plan",
                       "progress_topic": f"{ns}/progress", "answer_timeout": 4.0, "silence": silence},
                      InputContext(41.5, -70.6))
    out.open()
    v = Vehicle(out, name="ros")
    _wait("the output's topics registered", lambda: _registered(roscore.uri, f"{ns}/path", 0)
          and _registered(roscore.uri, f"{ns}/progress", 1), 30)
    env = roscore.env()

    def planner(name: str, kind: str, leg: float = 0.1) -> tuple[subprocess.Popen[str], _Out]:
        p = peer(["--name", name, "--planner", kind, "--leg", str(leg), "--survey-ns", ns], env,
                 tmp_path / f"{name}.log")
        return p, _Out(p)

    def connected() -> bool:
        return out._path.connections() > 0 and out._sub.connections() > 0

    def gets_only_the_ended_form(name: str, sid: int) -> None:
        """A planner started now gets survey ``sid``'s ended form and flies nothing."""
        p, lines = planner(name, "fly")
        try:
            [ended] = _wait(f"{name} given the ended form", lambda: lines.find(event="ended"), 30)
            _wait(f"{name} given the ended plan", lambda: [e for e in lines.find(event="ended")
                                                         if e["plan"].get("survey_id") == sid], 10)
            assert ended["frame"] == "coex_local"
            for _ in range(10):  # a while later: still nothing flown, nothing answered
                v.step()
                time.sleep(0.1)
            assert lines.find(event="path") == [] and lines.find(event="started") == [], lines.events
        finally:
            kill(p)

    # completed, then a planner started later
    fly, lines = planner("p6_fly", "fly")
    try:
        _wait("the planner connected both ways", connected, 30)
        v.ask(1, x=0.0, kind=SurveyKind.LINE, depth=5.0)
        v.until("survey 1 completed", lambda: v.state(1) == SurveyState.COMPLETED)
        _wait("the flying planner told it ended", lambda: lines.find(event="ended"), 30)
    finally:
        kill(fly)
    gets_only_the_ended_form("p6_after_completed", 1)

    # refused, then a planner started later
    fresh = _new_peers(out)
    refuser, _ = planner("p6_refuse", "refuse")
    try:
        _wait("the refusing planner connected both ways", fresh, 30)
        v.ask(2, x=10.0, kind=SurveyKind.LINE, depth=5.0)
        v.until("survey 2 refused", lambda: v.state(2) == SurveyState.REJECTED)
    finally:
        kill(refuser)
    gets_only_the_ended_form("p6_after_refused", 2)

    # no planner at all: no answer; one that starts later does not fly it either
    _wait("no planner left", lambda: out._sub.connections() == 0, 30)
    v.ask(3, x=20.0, kind=SurveyKind.LINE, depth=5.0)
    v.until("survey 3 unanswered", lambda: v.state(3) == SurveyState.REJECTED, 30)
    [r] = [r for r in v.reports if r.survey_id == 3]
    assert (r.reason, r.value) == (SurveyReason.AUTONOMY_NO_ANSWER, None) and r.detail.endswith(
        f"no planner subscribed to {ns}/path"), r
    gets_only_the_ended_form("p6_after_no_answer", 3)

    # an answer after the end is the survey's late answer: kept in its record, never applied
    answer = out.node.publisher(f"{ns}/progress", "std_msgs/String")
    _wait("the answer topic connected", lambda: answer.connections() > 0, 30)
    answer.publish(out.node.message("std_msgs/String", data="3 started 0"))
    v.until("the late answer recorded", lambda: v.sender.late(3))
    assert v.state(3) == SurveyState.REJECTED and v.sender.late(3)[0][1:3] == ("STARTED", 0)
    answer.close()
    _wait("the test's publisher gone", lambda: out._sub.connections() == 0, 30)

    # a planner killed mid-survey: aborted, autopilot silent, within the bound
    slow, lines = planner("p6_slow", "fly", leg=60.0)
    try:
        _wait("the slow planner connected both ways", connected, 30)
        v.ask(4, x=30.0, kind=SurveyKind.LINE, depth=5.0)
        v.until("survey 4 started", lambda: v.state(4) == SurveyState.STARTED)
    finally:
        killed = time.time()
        kill(slow)
    v.until("survey 4 aborted", lambda: v.state(4) == SurveyState.ABORTED, 60)
    took = time.time() - killed
    print(f"planner killed: survey aborted {took:.1f} s later (silence {silence:g} s)")
    [r] = [r for r in v.reports if r.survey_id == 4 and r.state == SurveyState.ABORTED]
    assert (r.reason, r.detail) == (SurveyReason.AUTONOMY_SILENT, f"no planner on {ns}/progress"), r
    assert silence <= r.value and took < silence + 5.0, (r.value, took)  # the bound, plus the test's polling
    gets_only_the_ended_form("p6_after_silent", 4)
    out.close()


@needs_ros
def test_no_planner_is_no_answer(roscore: Roscore) -> None:
    out = RosAutonomy({"master": roscore.uri, "path_topic": "/t4/path", "progress_topic": "/t4/progress",
                       "plan_topic": "", "answer_timeout": 10.0}, InputContext())
    out.open()
    try:
        out.submit(SurveyPlan(12, SurveyKind.GOTO, ((1.0, 1.0),)), 1000.0)
        assert out.poll(1009.0) == []
        [r] = out.poll(1010.5)
        # the seconds waited in words ("no answer from the vehicle's autonomy: 10.5 s, no planner
        # ..."): a value would read as tries
        assert (r.state, r.reason, r.value, r.detail) == (SurveyState.REJECTED, SurveyReason.AUTONOMY_NO_ANSWER, None,
                                                          "10.5 s, no planner subscribed to /t4/path")
        assert out.poll(1100.0) == []  # once
    finally:
        out.close()


@needs_ros
def test_topside_products_appear_on_ros_topics(roscore: Roscore, tmp_path: Path) -> None:
    """The ship's ROS view (issue 51): map levels as clouds and grids on one fixed depth scale,
    the newest image (an older one refined later does not replace it) raw and compressed, the
    vehicle's odometry, track and TF, each time series, the surveys' states; all in coex_local."""
    from coex_apps.console.ros import RosProducts
    from coex_core.channel.events import ProductUpdated, Received
    from coex_core.messages import VehicleMode, VehicleStatus

    listeners: list[Callable[[list[Any]], Any]] = []
    coex_node = SimpleNamespace(subscribe=lambda f: listeners.append(f) or (lambda: listeners.remove(f)))
    lock = threading.Lock()
    products = RosProducts({"master": roscore.uri, "prefix": "/t5", "interval": 0.2, "grid_min": -40.0,
                            "grid_max": -20.0}, lock=lock).attach(coex_node)
    topics = ["/t5/map/level_1", "/t5/map/level_1/grid", "/t5/map/grid_range", "/t5/image", "/t5/image/compressed",
              "/t5/vehicle/odometry", "/t5/vehicle/track", "/t5/series/methane_2", "/t5/surveys", "/tf"]
    spy = peer(["--name", "rviz_like", "--listen", *topics], roscore.env(), tmp_path / "listen.log")
    lines = _Out(spy)
    try:
        # the listener subscribes before the publishers exist, so that each latched message
        # reaches it once, by the master's publisherUpdate (the order does not depend on load)
        _wait("the listener subscribed", lambda: all(_subscribed(roscore.uri, t, "/rviz_like") for t in topics), 60)
        level = np.full((4, 6), np.nan)
        level[1, 2], level[3, 5], level[0, 0] = -30.0, -28.0, -31.0
        now = time.time()
        status = VehicleStatus(int(now) % 2**18, 30.0, 10.0, 25.0, 5.0, 90.0, 1.0, 80, VehicleMode.SURVEY, 0)
        pixels = (np.arange(96 * 128) % 256).astype(np.uint8).reshape(96, 128)
        older = np.zeros((48, 64), np.uint8)
        series = SimpleNamespace(times=np.array([now - 2.0, now - 1.0]), values=np.array([3.5, 4.25]),
                                 bounds=np.array([0.1, np.inf]))
        survey = typed.survey(7, "started", now, 2, text="heading for waypoint 1", index=1, survey_kind="line",
                                 waypoints=[[0.0, 0.0], [20.0, 0.0]])
        events = [
            ProductUpdated(now, "bathymetry", typed.map_level(1, level, 3, cell_size=2.0, x0=-10.0, y0=20.0,
                                                                 newest=now)),
            ProductUpdated(now, "imagery", typed.image(4, pixels, now - 5)),
            ProductUpdated(now, "imagery", typed.image(3, older, now - 100, 9)),
            ProductUpdated(now, "timeseries", typed.series("methane-2", series)),
            ProductUpdated(now, "survey", survey),
            Received(now, 0, 2, status),
        ]
        for f in listeners:
            f(events)
        want = {"sensor_msgs/PointCloud2", "nav_msgs/OccupancyGrid", "sensor_msgs/Image", "nav_msgs/Odometry",
                "nav_msgs/Path", "sensor_msgs/CompressedImage", "std_msgs/String", "std_msgs/Float64MultiArray",
                "tf2_msgs/TFMessage"}

        def heard_all() -> bool:
            if not lines.find(type="tf2_msgs/TFMessage"):  # /tf is not latched: a status until one is heard
                for f in listeners:
                    f([Received(time.time(), 0, 2, status)])
            return {e["type"] for e in lines.find(event="message")} >= want

        try:
            _wait("every product on its topic", heard_all, 90)
        except AssertionError as exc:
            heard = sorted({e["type"] for e in lines.find(event="message")})
            state = _system_state(roscore.uri) or [[], []]
            pubs = {t: ns for t, ns in state[0] if t.startswith("/t5")}
            conns = {t: (p.connections(), p.counts) for t, p in products._pubs.items()}
            raise AssertionError(f"{exc}; heard {heard}; ROS node {products.node.state!r}, counts "
                                 f"{products.counts}; the master's publishers {pubs}; connections {conns}; "
                                 f"lines not JSON: {lines.bad[-5:]}; listener: {(tmp_path / 'listen.log').read_text()[-1500:]}") from None
        assert {e["frame"] for e in lines.find(event="message") if e["frame"] is not None} == {"coex_local"}
        [cloud] = lines.find(type="sensor_msgs/PointCloud2")[:1]
        assert cloud["points"] == 3 and cloud["z"] == [-31.0, -28.0]
        # absolute depths: 0 = -40 m, 100 = -20 m, in every message alike
        [grid] = lines.find(type="nav_msgs/OccupancyGrid")[:1]
        assert (grid["width"], grid["height"], grid["resolution"], grid["known"]) == (6, 4, 2.0, 3)
        assert grid["values"] == [45, 50, 60]
        [rng] = lines.find(topic="/t5/map/grid_range")
        assert rng["data"] == {"min": -40.0, "max": -20.0, "unknown": -1, "frame": "coex_local"}
        # the newest image (4), not the older one refined after it
        images = lines.find(type="sensor_msgs/Image")
        assert [(i["width"], i["height"], i["encoding"]) for i in images] == [(128, 96, "mono8")]
        assert images[0]["stamp"] == pytest.approx(now - 5, abs=1e-3)
        [png] = lines.find(type="sensor_msgs/CompressedImage")
        assert png["format"] == "mono8; png compressed mono8" and png["shape"] == [96, 128]
        assert png["sum"] == int(pixels.astype(np.int64).sum())  # lossless
        [odom] = lines.find(type="nav_msgs/Odometry")[:1]
        assert (odom["x"], odom["y"], odom["z"]) == (30.0, 10.0, -25.0)
        tf = lines.find(type="tf2_msgs/TFMessage")[0]
        assert tf["transforms"] == [["coex_local", "coex_vehicle", 30.0, 10.0, -25.0]]
        [ts] = lines.find(type="std_msgs/Float64MultiArray")
        assert ts["topic"] == "/t5/series/methane_2" and ts["dims"] == [["time,value,bound", 3, 6], ["sample", 2, 2]]
        assert ts["data"][:4] == [pytest.approx(now - 2.0), pytest.approx(now - 1.0), 3.5, 4.25]
        assert ts["data"][4] == 0.1 and ts["data"][5] == math.inf
        [sv] = lines.find(topic="/t5/surveys")
        assert sv["data"]["surveys"] == [dict(survey.meta)]  # its description, as JSON
        assert products.counts["failed"] == 0 and products.counts["image"] == 1
    finally:
        kill(spy)
        products.close()
    assert listeners == []


@needs_ros
def test_topside_logs_the_ros_master_lost_and_back(tmp_path: Path) -> None:
    """``coex topside --config`` with a ``[ros]`` table: the ship's roscore killed and started
    again; the topside's log says it was lost and that it is back (issue 51: only the loss was
    logged, the ROS node's thread having put back the logging level of before the CLI's set-up)."""
    from ._procs import start

    core = Roscore()
    proc = None
    try:
        core.start()
        (tmp_path / "t.toml").write_text(f"""
[node]
role = "topside"
id = 1
store = false
[[modems]]
uri = "loopback://ship"
[console]
http = "127.0.0.1:0"
[ros]
master = "{core.uri}"
node = "coex_topside_t7"
prefix = "/t7"
""")
        env = ros_env(core.uri, tmp_path / "ros-home")
        proc, out = start(["topside", "--config", str(tmp_path / "t.toml")], env, tmp_path / "topside.log")
        procs = {"topside": proc}
        _wait("the topside's ROS node up", lambda: out.has("coex_topside_t7") and out.has("): up"), 60, procs)
        core.stop()
        _wait("the master's loss logged", lambda: out.has("the ROS master does not answer"), 30, procs)
        core.start()
        _wait("the master's return logged", lambda: out.has("a new ROS master (pid"), 30, procs)
    finally:
        kill(proc)  # type: ignore[arg-type]
        core.close()


# ============================================================================ the pair
def _system_state(uri: str) -> Any:
    try:
        return xmlrpc.client.ServerProxy(uri).getSystemState("/coex_test")[2]
    except OSError:
        return None


def _peers(topic: Any) -> set[str]:
    """The peers a CoEx publisher or subscriber (``coex_transports.ros.node``) is connected to
    now, by rospy's endpoint id (a subscriber's caller id; a publisher's XML-RPC URI)."""
    handle = topic.handle
    return set() if handle is None else {str(c.endpoint_id) for c in list(handle.impl.connections)}


def _new_peers(out: Any) -> Callable[[], bool]:
    """Whether the output's path publisher and progress subscriber are both connected to a peer
    they were not connected to when this was called: a planner started after a killed one
    (whose connections rospy may still count, or reconnect to, for a while) is connected both
    ways only when both are connected to *it*."""
    before = (_peers(out._path), _peers(out._sub))
    return lambda: bool(_peers(out._path) - before[0]) and bool(_peers(out._sub) - before[1])


def _registered(uri: str, topic: str, kind: int) -> bool:
    """Whether some node publishes (``kind`` 0) or subscribes to (1) ``topic`` on the master."""
    state = _system_state(uri)
    return bool(state) and any(t == topic and nodes for t, nodes in state[kind])


def _subscribed(uri: str, topic: str, node: str) -> bool:
    state = _system_state(uri)
    return bool(state) and any(t == topic and node in nodes for t, nodes in state[1])


def _console(http: str) -> dict[str, Any]:
    from ._procs import state

    return state(http)


@pytest.mark.slow
@needs_ros
def test_a_ros_vehicle_and_ship_through_two_micromodems(tmp_path: Path) -> None:
    """examples/ros: the vehicle (started with the command line roslaunch gives for
    vehicle.launch) reads the vehicle's topics; map, image and status reach the console and the
    ship's ROS topics; a survey from the console goes out as a Path, the planner flies it, and
    its progress comes back to the console."""
    from ._modemsim import free_tcp_base
    from ._procs import COEX, Lines, act, start

    vcore, score = Roscore(), Roscore()
    procs: dict[str, subprocess.Popen[str]] = {}
    peers: list[subprocess.Popen[str]] = []
    try:
        for core in (vcore, score):
            core.start()
        tcp, http = free_tcp_base(2), f"127.0.0.1:{free_tcp_base(1)}"
        env = ros_env(vcore.uri, tmp_path / "ros-home")
        env.update({
            "COEX_VEHICLE_MODEM": f"micromodem:socket://127.0.0.1:{tcp + 1}?src=2&dest=1&rate=5",
            "COEX_TOPSIDE_MODEM": f"micromodem:socket://127.0.0.1:{tcp}?src=1&dest=2&rate=5",
            "COEX_SLOT_SECONDS": "4", "COEX_GUARD_SECONDS": "0.5", "COEX_STATUS_INTERVAL": "4",
            "COEX_VEHICLE_STORE": str(tmp_path / "vehicle.sqlite"), "COEX_TOPSIDE_STORE": str(tmp_path / "topside.sqlite"),
            "COEX_TOPSIDE_IMAGES": str(tmp_path / "received"), "COEX_HTTP": http,
            "COEX_SHIP_ROS_MASTER": score.uri, "ROS_PACKAGE_PATH": str(EXAMPLES),
        })
        for f in ("vehicle.toml", "topside.toml"):
            check = subprocess.run([*COEX, "config", "check", str(EXAMPLES / f)], env=env, capture_output=True,
                                   text=True, timeout=120, cwd=ROOT)
            assert check.returncode == 0 and ": ok: " in check.stdout, check.stdout + check.stderr
        # the vehicle as roslaunch would start it beside the vehicle's nodes
        launch = subprocess.run(["roslaunch", "--args", "coex_vehicle", str(EXAMPLES / "coex_ros/launch/vehicle.launch"),
                                 f"coex:={sys.executable} -m coex_core.cli"], env=env, capture_output=True,
                                text=True, timeout=60, cwd=tmp_path)
        assert launch.returncode == 0, launch.stdout + launch.stderr
        words = shlex.split(launch.stdout.strip().splitlines()[-1])
        n = 0
        while "=" in words[n].split("/")[0]:  # NAME=value before the command
            n += 1
        assigned, argv = words[:n], words[n:]
        assert argv[0].endswith("coex_ros/scripts/coex_vehicle") and "__name:=coex_vehicle" in argv, argv
        venv = {**env, **dict(w.split("=", 1) for w in assigned)}
        assert venv["ROS_MASTER_URI"].rstrip("/") == vcore.uri

        sim, _ = start(["modem-sim", "--nodes", "1,2", "--tcp-base", str(tcp)], env, tmp_path / "modem-sim.log")
        procs["modem-sim"] = sim
        time.sleep(1.5)
        top, top_out = start(["topside", "--config", str(EXAMPLES / "topside.toml")], env, tmp_path / "topside.log")
        procs["topside"] = top
        veh = subprocess.Popen(argv, env=venv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT)
        procs["vehicle"] = veh
        veh_out = Lines(veh, tmp_path / "vehicle.log")
        _wait("the vehicle subscribed to its topics",
              lambda: _subscribed(vcore.uri, "/multibeam/points", "/coex_vehicle"), 60, procs)
        ship = peer(["--name", "rviz_on_ship", "--listen", *[f"/coex/map/level_{k}" for k in range(5)],
                     "/coex/map/level_2/grid", "/coex/image", "/coex/vehicle/odometry", "/coex/vehicle/track"],
                    ros_env(score.uri, tmp_path / "ros-home"), tmp_path / "ship.log")
        peers.append(ship)
        ship_out = _Out(ship)
        stack = peer(["--name", "vehicle_stack", "--publish", "--planner", "fly", "--leg", "0.5"], env,
                     tmp_path / "stack.log")
        peers.append(stack)
        stack_out = _Out(stack)

        def arrived() -> dict[str, Any] | None:
            s = _console(http)
            levels = (s.get("map") or {}).get("levels") or []
            status = (s.get("vehicle") or {}).get("status")
            imgs = [i for i in (s.get("images") or {}).get("items", []) if i.get("bytes_received")]
            # a status sent before the altimeter's first reading reached the vehicle has no
            # altitude: wait for one that has (none ever is a failure: the wait times out)
            return s if levels and status and status.get("altitude") is not None and imgs else None

        s = _wait("map, image and vehicle status (with the altimeter's altitude) topside", arrived, 240, procs)
        status = s["vehicle"]["status"]
        assert abs(status["x"] - 30.0) < 0.2 and abs(status["y"] - 10.0) < 0.2 and abs(status["depth"] - 25.0) < 0.2
        assert status["altitude"] == 5.0, status  # from the altimeter's sensor_msgs/Range
        [img] = [i for i in s["images"]["items"] if i.get("bytes_received")][:1]
        assert (img["width"], img["height"]) == (128, 96) and abs(img["x"] - 30.0) < 1.0, img  # placed by nav

        def on_ship(kind: str) -> list[dict[str, Any]]:
            return ship_out.find(event="message", type=kind)

        _wait("products on the ship's topics",
              lambda: all(on_ship(k) for k in ("sensor_msgs/PointCloud2", "sensor_msgs/Image", "nav_msgs/Odometry")),
              60, procs)
        cloud = on_ship("sensor_msgs/PointCloud2")[-1]
        assert cloud["points"] > 0 and -31.5 < cloud["z"][0] <= cloud["z"][1] < -28.5, cloud
        image = on_ship("sensor_msgs/Image")[-1]
        assert (image["width"], image["height"]) == (128, 96)
        odom = on_ship("nav_msgs/Odometry")[-1]
        assert (odom["x"], odom["y"], odom["z"]) == (30.0, 10.0, -25.0)

        # a survey from the console: a Path for the planner, its progress back to the console
        act(http, "survey", {"kind": "lawnmower", "x": 40.0, "y": -30.0, "heading": 90.0, "length": 60.0,
                             "width": 20.0, "spacing": 10.0, "altitude": 5.0, "speed": 1.5})

        def survey_state() -> str | None:
            items = (_console(http).get("surveys") or {}).get("items") or []
            return items[0]["state"] if items else None

        _wait("the survey completed on the console", lambda: survey_state() == "completed", 240, procs)
        [path] = stack_out.find(event="path")
        assert path["poses"] == [[10.0, -20.0, 0.0], [70.0, -20.0, 0.0], [70.0, -30.0, 0.0], [10.0, -30.0, 0.0],
                                 [10.0, -40.0, 0.0], [70.0, -40.0, 0.0]], path
        assert (path["plan"]["kind"], path["plan"]["altitude"], path["plan"]["speed"]) == ("lawnmower", 5.0, 1.5)
        assert veh_out.has("survey") and top_out.has("CoEx console")
    finally:
        for p in peers:
            kill(p)
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in procs.values():
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        vcore.close()
        score.close()


def test_entry_points_shim_is_only_needed_for_an_old_install() -> None:
    shim = ros_entry_points()
    from importlib import metadata

    assert "ros" in {ep.name for ep in metadata.entry_points(group="coex.inputs")}
    assert shim is None or Path(shim).is_dir()
