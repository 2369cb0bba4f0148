"""The vehicle on MOOS (issue 23, second half): the ``moos`` input (NAV_* and sensor variables),
the ``moos`` autonomy output (the IvP helm's BHV_Waypoint through its ``updates`` variable) and
pCoex (``coex vehicle --moos MISSION.moos``), against a real MOOSDB with pymoos playing the helm
and the navigation."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from coex import InputContext, Nav, Samples
from coex_apps.vehicle.mission import check_mission, read_mission
from coex_core.errors import ConfigError
from coex_core.messages import SurveyKind, SurveyReason, SurveyState
from coex_plugins.autonomy.moos import MoosAutonomy, update_of
from coex_plugins.inputs.moos import MoosInput
from coex_plugins.survey.plan import SurveyPlan

from ._moos import MoosDB, moos_entry_points, unique

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
KEY = "00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff"
SHIM = moos_entry_points()  # the moos input / autonomy entry points, when the install predates them


def _wait(cond: Callable[[], Any], timeout: float = 20.0, what: str = "condition") -> Any:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        got = cond()
        if got:
            return got
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


# ------------------------------------------------------------------ the update strings (no MOOSDB)
def test_update_strings_carry_the_plans_own_waypoints() -> None:
    lawn = SurveyPlan(7, SurveyKind.LAWNMOWER, ((-40.0, 25.5), (40.0, 25.5), (40.0, -0.25), (-40.0, -0.25)),
                      altitude=5.0, speed=1.5, heading=90.0, length=80.0, width=25.75, spacing=25.75,
                      centre=(0.0, 12.6))
    assert update_of(lawn) == "points=-40,25.5:40,25.5:40,-0.25:-40,-0.25#speed=1.5"  # posted after name=
    assert update_of(SurveyPlan(8, SurveyKind.GOTO, ((12.0, -3.0),))) == "point=12,-3"
    line = SurveyPlan(9, SurveyKind.LINE, ((0.0, 0.0), (0.0, 120.0)), speed=None)
    assert update_of(line, "capture_radius=5") == "points=0,0:0,120#capture_radius=5"
    assert update_of(SurveyPlan(1, SurveyKind.WAYPOINTS, ((-0.001, 1e5), (3.14159, 2.0)))) == \
        "points=0,100000:3.14,2"


def test_options_are_checked() -> None:
    ctx = InputContext()
    with pytest.raises(ConfigError, match="server"):
        MoosInput({"server": "nohost"}, ctx)
    with pytest.raises(ConfigError, match=r"nav\.z is not a navigation field"):
        MoosInput({"nav": {"z": "NAV_Z"}}, ctx)
    with pytest.raises(ConfigError, match="channels"):
        MoosInput({"channels": {"CTD T": "t"}}, ctx)
    with pytest.raises(ConfigError, match="activate"):
        MoosAutonomy({"activate": "COEX_SURVEY"}, ctx)
    with pytest.raises(ConfigError, match="unknown option 'updates'"):
        MoosAutonomy({"updates": "X"}, ctx)
    with pytest.raises(ConfigError, match="silence: -2 is below 0 s"):
        MoosAutonomy({"silence": -2}, ctx)


# ------------------------------------------------------------------ the mission file (no MOOSDB)
MISSION = """\
// a test mission
ServerHost = ${{COEX_TEST_MOOS_HOST:-127.0.0.1}}
ServerPort = {port}
Community  = alpha
LatOrigin  = 42.358436
LongOrigin = -71.087448
define: STREAM = 7

ProcessConfig = ANTLER
{{
  Run = MOOSDB @ NewConsole = false
  Run = pCoex  @ NewConsole = false
}}

ProcessConfig = pCoex
{{
  AppTick   = 4
  CommsTick = 4
  config    = base.toml                      // read first, overridden below
  Node.ID   = 2                              // MOOS keys are case-insensitive
  node.command_key_file = k.key
  node.store = false
  modems[0].uri = moos://${{ServerHost}}:${{ServerPort}}?name=pCoex_modem   // a URI is not a comment
  modems[0].rate = 3
  modems[0].packet_seconds = 0.3                // a MOOS variable has no airtime: a packet in a 2 s slot
  tdma.slots = ["topside", "vehicle"]
  modalities.survey.stream = ${{STREAM}}
  modalities.survey.options.geofence.radius = 500
  modalities.timeseries.options = {{ channels = [{{ name = "temperature", lo = -2.0, hi = 40.0, resolution = 0.01 }}] }}
  modalities.bathymetry.stream = 3
  inputs[0].type = moos
  inputs[0].feeds = ["status", "timeseries"]
  inputs[0].channels = {{ CTD_TEMP = "temperature" }}
  inputs[0].nav."x" = USM_X
  inputs[0].channels."Salinity" = salinity
  inputs[1].type = points
  inputs[1].path = "pts"
  autonomy.type = moos
  autonomy.depth_var = COEX_DEPTH_UPDATE
}}
"""
BASE = """
[node]
role = "vehicle"
id = 9
log_level = "debug"
[tdma]
slot_seconds = 2.0
guard = 0.5
[modalities.timeseries]
stream = 5
[modalities.survey]
stream = 6
priority = 80
"""


def _mission(tmp_path: Path, text: str = MISSION, port: int = 9000) -> Path:
    (tmp_path / "k.key").write_text(KEY)
    (tmp_path / "base.toml").write_text(BASE)
    (tmp_path / "pts").mkdir(exist_ok=True)
    p = tmp_path / "m.moos"
    p.write_text(text.format(port=port))
    return p


def test_a_pcoex_block_is_the_configuration_a_toml_file_gives(tmp_path: Path) -> None:
    raw, problems = read_mission(_mission(tmp_path), "pCoex")
    assert problems == []
    assert raw == {
        "node": {"role": "vehicle", "id": 2, "log_level": "debug", "command_key_file": "k.key", "store": False,
                 "origin": {"lat": 42.358436, "lon": -71.087448}},
        "tdma": {"slot_seconds": 2.0, "guard": 0.5, "slots": ["topside", "vehicle"]},
        "modems": [{"uri": "moos://127.0.0.1:9000?name=pCoex_modem", "rate": 3, "packet_seconds": 0.3}],
        "modalities": {"timeseries": {"stream": 5, "options": {"channels": [
                           {"name": "temperature", "lo": -2.0, "hi": 40.0, "resolution": 0.01}]}},
                       "survey": {"stream": 7, "priority": 80, "options": {"geofence": {"radius": 500}}},
                       "bathymetry": {"stream": 3}},
        "inputs": [{"type": "moos", "feeds": ["status", "timeseries"], "channels": {"CTD_TEMP": "temperature", "Salinity": "salinity"},
                    "nav": {"x": "USM_X"}, "server": "127.0.0.1:9000", "name": "pCoex_in"},
                   {"type": "points", "path": "pts"}],
        "autonomy": {"type": "moos", "depth_var": "COEX_DEPTH_UPDATE", "server": "127.0.0.1:9000",
                     "name": "pCoex_helm"},
    }
    # --moos-host / --moos-port and the environment
    os.environ["COEX_TEST_MOOS_HOST"] = "10.0.0.5"
    try:
        raw, _ = read_mission(tmp_path / "m.moos", "PCOEX", port=9123)  # block names: case-insensitive
    finally:
        del os.environ["COEX_TEST_MOOS_HOST"]
    assert raw is not None and raw["modems"][0]["uri"] == "moos://10.0.0.5:9123?name=pCoex_modem"
    assert raw["autonomy"]["server"] == raw["inputs"][0]["server"] == "10.0.0.5:9123"
    assert "time_warp" not in raw["autonomy"] and "time_warp" not in raw["inputs"][0]  # no MOOSTimeWarp: 1
    # MOOSTimeWarp: every MOOS client of pCoex stamps and reads warped MOOS times
    warped = MISSION.replace("Community  = alpha\n", "Community  = alpha\nMOOSTimeWarp = 12.5\n")
    raw, problems = read_mission(_mission(tmp_path, warped), "pCoex")
    assert problems == [] and raw is not None
    assert raw["autonomy"]["time_warp"] == raw["inputs"][0]["time_warp"] == 12.5
    assert raw["modems"][0]["uri"] == "moos://127.0.0.1:9000?name=pCoex_modem&warp=12.5"
    assert "time_warp" not in raw["inputs"][1]  # not a moos input
    _, problems = read_mission(_mission(tmp_path, MISSION.replace("Community  = alpha\n", "Community  = alpha\n"
                                                                  "MOOSTimeWarp = 0\n")), "pCoex")
    assert problems == ["MOOSTimeWarp: a number above 0 and at most 400, got '0'"], problems
    _mission(tmp_path)
    cfg, problems = check_mission(tmp_path / "m.moos")
    assert problems == [], problems
    assert cfg is not None and cfg.node_id == 2 and cfg.origin_lat == 42.358436 and cfg.slots == ("topside", "vehicle")
    assert cfg.inputs[0]["channels"] == {"CTD_TEMP": "temperature", "Salinity": "salinity"}


def test_bad_keys_are_named(tmp_path: Path) -> None:
    bad = MISSION.replace("  node.store = false\n", "  node.store = false\n  node.idd = 3\n  modems[2].uri = x\n"
                          "  inputs[0].nav = {{ z = \"NAV_Z\" }}\n  what ever = 1\n")
    _, problems = read_mission(_mission(tmp_path, bad), "pCoex")
    assert any("'what ever' is not a configuration key" in p for p in problems), problems
    assert "modems[1]: missing (a later modems[...] is given)" in problems, problems
    bad = MISSION.replace("  node.store = false\n", "  node.store = false\n  node.idd = 3\n"
                          "  inputs[0].server = nohost\n  autonomy.updates = X\n")
    cfg, problems = check_mission(_mission(tmp_path, bad))
    assert cfg is not None
    assert any(p.startswith("node.idd: unknown key") for p in problems), problems
    assert any(p.startswith("inputs[0]:") and "'server'" in p for p in problems), problems
    assert any(p.startswith("autonomy:") and "unknown option 'updates'" in p for p in problems), problems
    twice = MISSION.replace("  node.store = false\n", "  node.store = false\n  NODE.store = true\n")
    _, problems = read_mission(_mission(tmp_path, twice), "pCoex")
    assert any(p.startswith("node.store: given twice") for p in problems), problems
    _, problems = read_mission(_mission(tmp_path), "pOther")
    assert problems == ["no ProcessConfig = pOther block (blocks: ANTLER, pCoex)"]
    unset = MISSION.replace("${{STREAM}}", "${{COEX_TEST_UNSET_VARIABLE}}")
    _, problems = read_mission(_mission(tmp_path, unset), "pCoex")
    assert any("COEX_TEST_UNSET_VARIABLE" in p for p in problems), problems


# ------------------------------------------------------------------ against MOOSDB
@pytest.fixture
def pymoos_client(moosdb: MoosDB) -> Iterator[Callable[..., Any]]:
    """pymoos clients (the helm, the navigation) registered for the given variables."""
    pymoos = pytest.importorskip("pymoos", reason="pymoos not installed (`make moos` installs it into .venv)")
    made: list[Any] = []

    def make(*variables: str) -> Any:
        comms = pymoos.comms()
        comms.set_quiet(True)
        comms.set_on_connect_callback(lambda: all(comms.register(v, 0) for v in variables) or True)
        comms.run("127.0.0.1", moosdb.port, unique("pymoos"))
        assert comms.wait_until_connected(5000)
        made.append(comms)
        return comms

    yield make
    for c in made:
        c.close(True)


def _collect(comms: Any, into: list[tuple[str, Any]]) -> list[tuple[str, Any]]:
    for m in comms.fetch():
        into.append((m.key(), m.double() if m.is_double() else m.string()))
    return into


def test_nav_and_channels_become_items(moosdb: MoosDB, pymoos_client: Callable[..., Any]) -> None:
    temp = unique("CTD_TEMP")
    inp = MoosInput({"server": f"127.0.0.1:{moosdb.port}", "name": unique("pCoex_in"),
                     "nav": {"x": unique("USM_X"), "lat": ""}, "channels": {temp: "temperature"}}, InputContext())
    nav = pymoos_client()
    inp.open()
    try:
        _wait(lambda: inp.client.connected, what="the input's connection")
        time.sleep(0.3)
        x_var = inp.config["nav"]["x"]
        for var, value in [(x_var, 12.5), ("NAV_Y", -4.0), ("NAV_DEPTH", 30.2), ("NAV_HEADING", 271.0),
                           (temp, 4.25), (temp, 4.5), ("NAV_X", 999.0)]:
            assert nav.notify(var, value, -1)
        items: list[Any] = []
        _wait(lambda: items.extend(inp.poll(time.time())) or (
            sum(len(i.times) for i in items if isinstance(i, Samples)) >= 2
            and {k for i in items if isinstance(i, Nav) for k in ("x", "y", "depth", "heading")
                 if getattr(i, k) is not None} == {"x", "y", "depth", "heading"}), what="nav and samples")
        navs = [i for i in items if isinstance(i, Nav)]
        merged = {k: getattr(n, k) for n in navs for k in ("x", "y", "depth", "heading") if getattr(n, k) is not None}
        assert merged == {"x": 12.5, "y": -4.0, "depth": 30.2, "heading": 271.0}  # NAV_X is not read: x is USM_X
        samples = [i for i in items if isinstance(i, Samples)]
        assert [s.channel for s in samples] == ["temperature"] * len(samples)
        assert np.concatenate([s.values for s in samples]).tolist() == [4.25, 4.5]
        assert all(abs(t - time.time()) < 30 for s in samples for t in s.times)  # the writer's MOOS time
        assert inp.poll(time.time()) == []  # never blocks, nothing twice
    finally:
        inp.close()


def test_nav_times_are_real_seconds_under_time_warp(moosdb: MoosDB) -> None:
    """Under MOOSTimeWarp a MOOS clock reads the Unix time times the warp: the input's items
    are timed in real seconds again (the vehicle status topside must not be years ahead)."""
    from coex_transports.moos import MoosClient

    x_var, temp = unique("NAV_X"), unique("CTD_T")
    inp = MoosInput({"server": f"127.0.0.1:{moosdb.port}", "name": unique("pCoex_in"), "time_warp": 25.0,
                     "nav": {"x": x_var, "y": "", "depth": "", "altitude": "", "heading": "", "speed": "",
                             "lat": "", "lon": ""}, "channels": {temp: "temperature"}}, InputContext())
    nav = MoosClient("127.0.0.1", moosdb.port, unique("uSimMarine"), time_warp=25.0)
    inp.open()
    try:
        assert nav.connect(5)
        _wait(lambda: inp.client.connected, what="the input's connection")
        time.sleep(0.3)
        before = time.time()
        nav.notify(x_var, 3.0)
        nav.notify(temp, 4.5)
        assert nav.flush(5)
        items: list[Any] = []
        _wait(lambda: items.extend(inp.poll(time.time())) or (
            any(isinstance(i, Nav) for i in items) and any(isinstance(i, Samples) for i in items)), what="items")
        times = [i.time for i in items if isinstance(i, Nav)] + [t for i in items if isinstance(i, Samples)
                                                                   for t in i.times]
        assert all(before - 1 <= t <= time.time() + 1 for t in times), (before, times)
    finally:
        inp.close()
        nav.close()
    with pytest.raises(ConfigError, match="time_warp"):
        MoosInput({"time_warp": 0}, InputContext())
    with pytest.raises(ConfigError, match="time_warp"):
        MoosAutonomy({"time_warp": "fast"}, InputContext())


def _autonomy(moosdb: MoosDB, **options: Any) -> MoosAutonomy:
    a = MoosAutonomy({"server": f"127.0.0.1:{moosdb.port}", "name": unique("pCoex_helm"), **options},
                     InputContext())
    a.open()
    _wait(lambda: a.client.connected, what="the autonomy's connection")
    time.sleep(0.3)
    return a


def _reports(a: MoosAutonomy, n: int) -> list[Any]:
    got: list[Any] = []
    _wait(lambda: got.extend(a.poll(time.time())) or len(got) >= n, what=f"{n} reports")
    return got


class _Helm:
    """pymoos playing the IvP helm's side of the hand-over: it answers each update of the
    output as pHelmIvP does (IVPHELM_UPDATE_RESULT, BHV_WARNING) and records what it was sent."""

    def __init__(self, comms: Any, *variables: str) -> None:
        self.comms, self.seen = comms, []  # type: ignore[var-annotated]
        self.variables = variables
        self.answered = 0  # updates answered so far
        self.stop = threading.Event()
        # the helm's heartbeat: IVPHELM_STATE every iteration (the output watches for silence)
        self.beat = threading.Thread(target=self._beat, daemon=True)
        self.beat.start()

    def _beat(self) -> None:
        while not self.stop.wait(0.25):
            self.comms.notify("IVPHELM_STATE", "DRIVE", -1)

    def answer(self, bhv: str, var: str, result: str = "success") -> str:
        """Answer the next update of ``var`` (not the output's ``name=`` separator)."""
        def nxt() -> Any:
            updates = [v for k, v in _collect(self.comms, self.seen) if k == var and "#" in str(v)]
            return updates[self.answered] if len(updates) > self.answered else None

        update = _wait(nxt, what=f"an update of {var}")
        self.answered += 1
        self.comms.notify("IVPHELM_UPDATE_RESULT", f"bhv={bhv},var={var},time=1.0,result={result},val={update}", -1)
        return str(update)

    def values(self, var: str) -> list[Any]:
        _collect(self.comms, self.seen)
        return [v for k, v in self.seen if k == var]


def test_the_helm_hand_over_through_moosdb(moosdb: MoosDB, pymoos_client: Callable[..., Any]) -> None:
    """What the output posts and reads, as MOOS values through a real MOOSDB: refused by the
    helm (its words come back), flown, taken over, ended by the endflag."""
    upd, act, bhv = unique("UPD"), unique("SURVEY"), unique("bhv")
    done = unique("SURVEY_DONE")
    a = _autonomy(moosdb, updates_var=upd, activate=f"{act} = true", behavior=bhv,
                  wpt_index_var=unique("IDX"), wpt_status_var=unique("STAT"), endflag=f"{done} = true")
    helm = _Helm(pymoos_client(upd, act), upd, act)
    try:
        plan = SurveyPlan(3, SurveyKind.LINE, ((0.0, 0.0), (50.0, 0.0)), depth=12.0)
        a.submit(plan, time.time())
        assert helm.answer(bhv, upd, "param_error") == f"name={bhv}#points=0,0:50,0"
        helm.comms.notify("BHV_WARNING", f"Faulty update for behavior: {bhv}. Bad parameter(s): points", -1)
        [r] = _reports(a, 1)
        assert (r.survey_id, r.state, r.reason, r.detail) == (3, SurveyState.REJECTED, SurveyReason.AUTONOMY_REFUSED,
                                                              f"{bhv}: Bad parameter(s): points")
        assert _wait(lambda: helm.values(act)[-1:] == ["false"], what="deactivated") and "true" not in helm.values(act)
        # taken by the helm: activated; a manual override aborts it and deactivates it
        a.submit(SurveyPlan(4, SurveyKind.GOTO, ((5.0, 5.0),)), time.time())
        assert helm.answer(bhv, upd) == f"name={bhv}#point=5,5"
        _wait(lambda: a.poll(time.time()) == [] and helm.values(act)[-1:] == ["true"], what="the activation")
        helm.comms.notify("MOOS_MANUAL_OVERRIDE", "true", -1)
        [r] = _reports(a, 1)
        assert (r.survey_id, r.state, r.reason) == (4, SurveyState.ABORTED, SurveyReason.MANUAL_OVERRIDE)
        assert _wait(lambda: helm.values(act)[-1:] == ["false"], what="deactivation")
        helm.comms.notify("MOOS_MANUAL_OVERRIDE", "false", -1)
        # the endflag ends a survey (a STARTED first: it did set off)
        a.submit(SurveyPlan(5, SurveyKind.GOTO, ((6.0, 5.0),)), time.time())
        helm.answer(bhv, upd)
        _wait(lambda: a.poll(time.time()) == [] and helm.values(act)[-1:] == ["true"], what="the activation")
        helm.comms.notify(done, "true", -1)
        got = _reports(a, 2)
        assert [(r.survey_id, r.state, r.index) for r in got] == [(5, SurveyState.STARTED, 0),
                                                                   (5, SurveyState.COMPLETED, None)]
        time.sleep(0.3)
        assert a.poll(time.time()) == []  # nothing after the end
    finally:
        helm.stop.set()
        a.close()


# ------------------------------------------------------------------ two nodes over simulated modems
COMMON = """
[tdma]
slots = ["topside", "vehicle"]
slot_seconds = 5.0
guard = 0.5
"""
VEHICLE = """
[node]
role = "vehicle"
id = 2
command_key_file = "k.key"
store = false
[modalities.survey]
stream = 7
priority = 90
options = {{ geofence = {{ radius = 400.0 }} }}
[status]
interval = 1
[[modems]]
uri = "{modem}?src=2&dest=1&rate=5"
[[inputs]]
type = "moos"
feeds = ["status"]
server = "127.0.0.1:{moos}"
name = "{name}_in"
[autonomy]
type = "moos"
server = "127.0.0.1:{moos}"
name = "{name}_helm"
updates_var = "{upd}"
activate = "{act} = true"
""" + COMMON
TOPSIDE = """
[node]
role = "topside"
id = 1
command_key_file = "k.key"
store = false
[modalities.survey]
stream = 7
[console]
http = "127.0.0.1:0"
[[modems]]
uri = "{modem}?src=1&dest=2&rate=5"
""" + COMMON


def test_a_survey_command_reaches_the_helm_and_its_progress_comes_back(
        tmp_path: Path, moosdb: MoosDB, pymoos_client: Callable[..., Any]) -> None:
    pytest.importorskip("serial")
    from coex_apps.console.cli import topside_from_config
    from coex_apps.vehicle.config import load
    from coex_apps.vehicle.daemon import VehicleApp

    from ._modemsim import modem_sim

    upd, act = unique("COEX_WPT_UPDATE"), unique("COEX_SURVEY")
    with contextlib.ExitStack() as stack:
        modems = stack.enter_context(modem_sim((1, 2)))  # two simulated Micromodems, real time
        (tmp_path / "k.key").write_text(KEY)
        (tmp_path / "v.toml").write_text(VEHICLE.format(modem=modems[2], moos=moosdb.port, name=unique("pCoex"),
                                                        upd=upd, act=act))
        (tmp_path / "t.toml").write_text(TOPSIDE.format(modem=modems[1]))
        helm = _Helm(pymoos_client(upd, act), upd, act)
        stack.callback(helm.stop.set)
        vehicle = VehicleApp(load(tmp_path / "v.toml", "vehicle")).start()
        stack.callback(vehicle.close)
        topside = topside_from_config(str(tmp_path / "t.toml")).start()
        stack.callback(topside.close)
        _survey_to_helm(vehicle, topside, helm, upd, act)


def _survey_to_helm(vehicle: Any, topside: Any, helm: _Helm, upd: str, act: str) -> None:
    # the navigation, as pNodeReporter reads it, reaches topside as the vehicle status
    def nav() -> Any:
        for var, value in [("NAV_X", 31.5), ("NAV_Y", -12.0), ("NAV_DEPTH", 22.4), ("NAV_ALTITUDE", 6.5),
                           ("NAV_HEADING", 135.0), ("NAV_SPEED", 1.2)]:
            helm.comms.notify(var, value, -1)
        st = topside.hub.state.status
        return st is not None and abs(st.x - 31.5) < 0.1 and st

    st = _wait(nav, 120, "the vehicle status topside")
    assert (st.x, st.y, st.depth, st.altitude, st.heading) == (31.5, -12.0, 22.4, 6.5, 135.0)
    # a lawnmower survey goes up and becomes a helm update; the helm takes it; the activation
    rx = topside.node.receiver("survey")
    with topside.hub.lock:
        req = rx.request("lawnmower", 20.0, 10.0, time.time(), heading=30.0, length=100.0, width=40.0,
                         spacing=20.0, depth=15.0, speed=1.5)
    update = _wait(lambda: helm.answer("coex_survey", upd), 120, "the helm update")
    plan = vehicle.autonomy.plan
    assert plan is not None and plan.survey_id == req.survey_id and len(plan.waypoints) == 6
    assert update == "name=coex_survey#points=" + ":".join(f"{x:g},{y:g}" for x, y in plan.waypoints) + "#speed=1.5"
    _wait(lambda: helm.values(act)[-1:] == ["true"], 30, "the activation")
    keys = [k for k, _ in helm.seen]
    assert keys.index(act) < keys.index(upd) < len(keys) - 1 - keys[::-1].index(act)  # off, update, on
    # the helm flies it: WPT_INDEX, then WPT_STAT completed, as BHV_Waypoint posts them
    for k in (0, 1, 3):
        helm.comms.notify("WPT_INDEX", float(k), -1)
        time.sleep(0.1)
    s = rx.surveys[req.survey_id]
    _wait(lambda: s.state == "started" and s.index == 3, 120, "started, heading for waypoint 3")
    helm.comms.notify("WPT_STAT", "vname=alpha,behavior-name=some_other_bhv,completed", -1)
    time.sleep(0.5)
    assert s.state == "started"  # another behaviour's completion is not ours
    helm.comms.notify("WPT_STAT", "vname=alpha,behavior-name=coex_survey,index=5,hits=1/1,cycles=0,dist=40,eta=27", -1)
    helm.comms.notify("WPT_STAT", "behavior-name=coex_survey,completed", -1)
    _wait(lambda: s.state == "completed", 120, "completed topside")
    states = {h[1] for h in s.history}
    assert {"requested", "accepted", "started", "completed"} <= states, s.history
    assert vehicle.counts["plans"] == 1


# ------------------------------------------------------------------ pCoex as a process
def test_pcoex_runs_from_the_example_mission_and_stops_on_sigterm(
        tmp_path: Path, moosdb: MoosDB, pymoos_client: Callable[..., Any]) -> None:
    for sub in ("moos", "deploy"):
        shutil.copytree(EXAMPLES / sub, tmp_path / sub)
    mission = tmp_path / "moos" / "coex_alpha.moos"
    watcher = pymoos_client("COEX_WPT_UPDATE")
    env = dict(os.environ)
    extra = [str(ROOT / p) for p in ("", "transports", "runtime", "conformance_tests", "plugins", "apps")]
    if SHIM is not None:
        extra.append(SHIM)
    env["PYTHONPATH"] = os.pathsep.join(extra + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    check = subprocess.run([sys.executable, "-m", "coex_core.cli", "config", "check", str(mission)],
                           env=env, capture_output=True, text=True, timeout=120)
    assert check.returncode == 0 and ": ok: vehicle node 2" in check.stdout, check.stdout + check.stderr
    proc = subprocess.Popen([sys.executable, "-m", "coex_core.cli", "vehicle", "--moos", str(mission),
                             "--moos-port", str(moosdb.port)], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, cwd=tmp_path)
    try:
        assert proc.stdout is not None
        killer = threading.Timer(90.0, proc.kill)  # never hang the suite on a silent process
        killer.start()
        lines: list[str] = []
        want = ("coex vehicle: node 2 on moos://localhost:" + str(moosdb.port), "MOOS client pCoex_in connected",
                "MOOS client pCoex_helm connected", "MOOS client pCoex_modem connected")
        while not all(any(w in line for line in lines) for w in want):
            line = proc.stdout.readline()
            assert line, "".join(lines)
            lines.append(line)
        killer.cancel()
        text = "".join(lines)
        assert "autonomy moos" in text and "1 input(s)" in text, text
        assert proc.poll() is None
        watcher.notify("NAV_X", 1.0, -1)
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=30)
        assert proc.returncode == 0, text + out
        assert "coex vehicle: stopped" in out, out
        assert (tmp_path / "moos" / "coex-vehicle.sqlite").exists()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
