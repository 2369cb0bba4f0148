"""The ``lcm`` input over real LCM (udpm on loopback, ttl=0, unique channels): coex.points_t,
coex.nav_t and a vehicle's own lcm-gen types mapped field by field."""

from __future__ import annotations

import logging
import math
import os
import subprocess
import time
from collections.abc import Iterator
from typing import Any

import pytest

from coex import InputContext, Item, Nav, Points, Samples, check_options
from coex_core.errors import ConfigError
from coex_plugins.inputs.lcm import LcmInput, compile_path, make_nav_t

lcm = pytest.importorskip("lcm")

from coex_transports.lcm import points_t, regen  # noqa: E402
from coex_transports.lcm.testing import TEST_UDPM_URL, ensure_multicast_route, unique_channel  # noqa: E402

OWN_LCM = """
package testveh;

struct pose_t
{
    int64_t utime;
    double  pos[3];
    float   yaw;
}

struct ctd_t
{
    int64_t stamp_us;
    float   temp;
    float   sal;
}

struct state_t
{
    int64_t utime;
    testveh.pose_t pose;
    int32_t n;
    double  east[n];
    double  north[n];
    double  down[n];
}
"""


@pytest.fixture(scope="module")
def multicast() -> Iterator[None]:
    undo = ensure_multicast_route()
    yield
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        undo()


@pytest.fixture(scope="module")
def own_types(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    """A vehicle's own LCM package, generated with the wheel's lcm-gen and importable."""
    import importlib
    import sys

    root = tmp_path_factory.mktemp("owntypes")
    (root / "testveh.lcm").write_text(OWN_LCM)
    subprocess.run([regen.find_lcm_gen(), "-p", "--ppath", str(root), str(root / "testveh.lcm")],
                   check=True, capture_output=True, timeout=60)
    sys.path.insert(0, str(root))
    try:
        yield importlib.import_module("testveh")
    finally:
        sys.path.remove(str(root))
        for name in [m for m in sys.modules if m == "testveh" or m.startswith("testveh.")]:
            del sys.modules[name]


def collect(adapter: LcmInput, now: float, want: int, timeout: float = 3.0) -> list[Item]:
    got: list[Item] = []
    deadline = time.monotonic() + timeout
    while len(got) < want and time.monotonic() < deadline:
        got += adapter.poll(now)
        if len(got) < want:
            time.sleep(0.01)
    return got


def test_compile_path() -> None:
    class M:
        pos = [1.0, 2.0, 3.0]

        class pose:
            class position:
                x = 7.5

    get, first = compile_path("-pos[2]")
    assert get(M) == -3.0 and first == "pos"
    assert compile_path("pose.position.x")[0](M) == 7.5
    assert compile_path("- pos")[0](M).tolist() == [-1.0, -2.0, -3.0]
    for bad in ("pos[", "2pos", "pos[-1]", "a..b", "pos[1]x", ""):
        with pytest.raises(ValueError):
            compile_path(bad)


def test_options_are_checked_and_named() -> None:
    assert "needs at least one of the options 'points_channel'" in check_options(LcmInput, {})[0]
    problems = check_options(LcmInput, {"own": [
        {"channel": "POSE", "type": "pose_t", "feeds": "status", "fields": {"x": "pos[0]", "depht": "pos[2]"}},
        {"channel": "CTD", "type": "a.ctd_t", "feeds": "timeseries", "channels": {"t": "temp["},
         "scale": {"s": 2}},
        {"channel": "S", "type": "a.b", "feeds": "bathymetry", "fields": {"x": "e", "y": "n"}},
        {"channel": "C", "feeds": "mood"},
        "not a table",
    ]})
    assert problems == [
        "input 'lcm': option 'own[0].type' must be 'package.Class' or 'package.module.Class', not 'pose_t'",
        "input 'lcm': option 'own[0].fields.depht': not one of x, y, lat, lon, depth, altitude, heading, speed",
        "input 'lcm': option 'own[1].channels.t': 'temp[' is not a field path (name, name[index], a.b, optional leading -)",
        "input 'lcm': option 'own[1].scale.s' scales nothing (not in 'own[1].channels')",
        "input 'lcm': option 'own[2].fields' needs x, y and z for bathymetry",
        "input 'lcm': option 'own[3].type' is required (a string)",
        "input 'lcm': option 'own[3].feeds' must be one of 'status', 'timeseries', 'bathymetry', not 'mood'",
        "input 'lcm': option 'own[4]' must be a table",
    ]
    with pytest.raises(ConfigError, match=r"own\[0\]\.type"):
        LcmInput({"own": [{"channel": "P", "type": "nowhere_pkg.pose_t", "feeds": "status",
                           "fields": {"x": "x"}}]}, InputContext()).open()


def test_points_and_nav(multicast: None) -> None:
    points_ch, nav_ch = unique_channel("PTS"), unique_channel("NAV")
    adapter = LcmInput({"url": TEST_UDPM_URL, "points_channel": points_ch, "nav_channel": nav_ch},
                       InputContext())
    adapter.open()
    pub = lcm.LCM(TEST_UDPM_URL)
    msg = points_t()
    msg.utime, msg.n = 1_700_000_000_500_000, 3
    msg.x, msg.y, msg.z = [1.0, 2.0, float("nan")], [3.0, 4.0, 5.0], [-30.0, -31.5, -32.0]
    pub.publish(points_ch, msg.encode())
    pub.publish(nav_ch, make_nav_t(0, x=12.0, y=-4.0, depth=55.5, heading=270.0).encode())
    pub.publish(nav_ch, b"garbage that is not a nav_t")
    pub.publish(unique_channel("OTHER"), make_nav_t(0, x=1.0).encode())
    items = collect(adapter, 42.0, 2)
    time.sleep(0.05)
    items += adapter.poll(42.0)  # the garbage, nothing more
    pts = next(i for i in items if isinstance(i, Points))
    nav = next(i for i in items if isinstance(i, Nav))
    assert len(items) == 2
    assert pts.time == pytest.approx(1_700_000_000.5) and pts.xyz.tolist() == [[1, 3, -30], [2, 4, -31.5]]
    assert nav.time == 42.0  # utime 0: when received
    assert (nav.x, nav.y, nav.depth, nav.heading) == (12.0, -4.0, 55.5, 270.0)
    assert nav.lat is None and nav.altitude is None and nav.speed is None  # NaN: unknown
    assert adapter.counts == {"messages": 2, "skipped": 1}
    adapter.close()


def test_own_types_status_timeseries_bathymetry(multicast: None, own_types: Any,
                                                caplog: pytest.LogCaptureFixture) -> None:
    pose_ch, ctd_ch, state_ch = unique_channel("POSE"), unique_channel("CTD"), unique_channel("STATE")
    adapter = LcmInput({"url": TEST_UDPM_URL, "own": [
        {"channel": pose_ch, "type": "testveh.pose_t", "feeds": "status",
         "fields": {"x": "pos[1]", "y": "pos[0]", "depth": "pos[2]", "heading": "yaw"},
         "scale": {"heading": 180 / math.pi}},
        {"channel": ctd_ch, "type": "testveh.ctd_t.ctd_t", "feeds": "timeseries", "time": "stamp_us",
         "channels": {"temperature": "temp", "salinity": "sal"}},
        {"channel": state_ch, "type": "testveh.state_t", "feeds": "bathymetry",
         "fields": {"x": "east", "y": "north", "z": "-down"}},
    ]}, InputContext())
    adapter.open()
    pub = lcm.LCM(TEST_UDPM_URL)
    pose = own_types.pose_t()
    pose.utime, pose.pos, pose.yaw = 5_000_000, [100.0, 20.0, 7.5], math.pi / 2  # NED
    pub.publish(pose_ch, pose.encode())
    for i in range(3):
        ctd = own_types.ctd_t()
        ctd.stamp_us, ctd.temp, ctd.sal = (10 + i) * 1_000_000, 4.0 + i, 35.0
        pub.publish(ctd_ch, ctd.encode())
    state = own_types.state_t()
    state.utime, state.pose, state.n = 9_000_000, pose, 2
    state.east, state.north, state.down = [1.0, 2.0], [3.0, 4.0], [40.0, 41.0]
    pub.publish(state_ch, state.encode())
    items = collect(adapter, 99.0, 4)
    time.sleep(0.05)
    items += adapter.poll(99.0)
    (nav,) = [i for i in items if isinstance(i, Nav)]
    assert nav.time == 5.0 and (nav.x, nav.y, nav.depth) == (20.0, 100.0, 7.5)
    assert nav.heading == pytest.approx(90.0) and nav.lat is None
    samples = {s.channel: s for s in items if isinstance(s, Samples)}
    assert set(samples) == {"temperature", "salinity"}
    assert samples["temperature"].times.tolist() == [10.0, 11.0, 12.0]
    assert samples["temperature"].values.tolist() == [4.0, 5.0, 6.0]
    assert samples["salinity"].values.tolist() == [35.0] * 3
    (pts,) = [i for i in items if isinstance(i, Points)]
    assert pts.time == 9.0 and pts.xyz.tolist() == [[1, 3, -40], [2, 4, -41]]

    # a pose_t on the CTD channel does not decode as a ctd_t: skipped, logged once
    with caplog.at_level(logging.WARNING):
        pub.publish(ctd_ch, pose.encode())
        pub.publish(ctd_ch, pose.encode())
        time.sleep(0.1)
        assert adapter.poll(100.0) == []
    assert sum("skipped" in r.getMessage() for r in caplog.records) == 1
    assert adapter.counts["skipped"] == 2
    adapter.close()


def test_own_type_field_names_are_checked_at_open(own_types: Any) -> None:
    adapter = LcmInput({"url": "memq://", "own": [
        {"channel": "P", "type": "testveh.pose_t", "feeds": "status", "fields": {"x": "position[0]"}}]},
        InputContext())
    with pytest.raises(ConfigError, match=r"'own\[0\].fields.x': testveh.pose_t has no field 'position'"):
        adapter.open()
