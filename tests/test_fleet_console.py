"""A topside of a fleet (issue 43): ``[[vehicles]]`` in the topside's configuration, checked by
the one checker and built by the one ``build_node``; the console of two vehicles on one
simulated network shows both and sends a survey command only to the vehicle it names."""

from __future__ import annotations

import json
import subprocess
import sys
import urllib.error
import urllib.request
import uuid
from pathlib import Path
from typing import Any

import pytest

from coex import SimNetwork
from coex_apps.console.fleet import fleet_hub
from coex_apps.console.server import serve
from coex_apps.vehicle.build import build_node
from coex_apps.vehicle.config import check_mapping, from_mapping
from coex_core.acoustic import AcousticChannel
from coex_core.errors import ConfigError
from coex_core.messages import VehicleMode, VehicleStatus
from coex_core.registry import open_transport
from tests.test_console_browser import browser  # noqa: F401 (headless Chromium, a fixture)

ROOT = Path(__file__).resolve().parents[1]
COEX = str(Path(sys.executable).with_name("coex"))
MODALITIES = {"bathymetry": {"stream": 3}, "imagery": {"stream": 4}, "survey": {"stream": 7}}


def topside_raw(**extra: Any) -> dict[str, Any]:
    raw: dict[str, Any] = {
        "node": {"role": "topside", "id": 1, "store": False},
        "vehicles": [{"id": 2, "name": "mapper"}, {"id": 3, "name": "camera"}],
        "modems": [{"uri": "loopback://fleet-top?rate=5"}],
        "tdma": {"slots": ["topside", "mapper", "camera"], "slot_seconds": 7.0, "guard": 3.0},
        "modalities": MODALITIES}
    raw.update(extra)
    return raw


def vehicle_raw(vid: int) -> dict[str, Any]:
    return {"node": {"role": "vehicle", "id": vid, "peer": 1, "store": False},
            "modems": [{"uri": "loopback://fleet-veh?rate=5"}],
            "tdma": {"slots": [1, 2, 3], "slot_seconds": 7.0, "guard": 3.0},
            "modalities": MODALITIES, "autonomy": {"type": "log"}}


def test_the_example_fleet_configurations_check() -> None:
    for name in ("topside", "mapper", "camera"):
        r = subprocess.run([COEX, "config", "check", str(ROOT / "examples/fleet" / f"{name}.toml")],
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stdout + r.stderr
    assert "vehicles mapper (2), camera (3)" in subprocess.run(
        [COEX, "config", "check", str(ROOT / "examples/fleet/topside.toml")],
        capture_output=True, text=True, timeout=120).stdout


def test_a_three_node_topside_is_checked_and_built(tmp_path: Path) -> None:
    cfg = from_mapping(topside_raw(), tmp_path / "t.toml", "topside")
    assert [(v.id, v.name) for v in cfg.vehicles] == [(2, "mapper"), (3, "camera")]
    assert cfg.owners() == [1, 2, 3] and cfg.vehicle_ids() == [2, 3]
    tr = open_transport(f"loopback://fleet-{uuid.uuid4().hex[:6]}")
    try:
        node = build_node(cfg, "topside", {0: tr})
    finally:
        tr.close()
    # one receiver per modality and vehicle, links to every node (each message names its vehicle)
    for name in MODALITIES:
        assert node.receiver(name, 2) is not node.receiver(name, 3)
    assert node.manager._links[0].cfg.dst == 0
    assert [s.owner for s in node.manager.schedule(0).slots] == [1, 2, 3]
    # a vehicle of the fleet names the slots by node id
    vcfg = from_mapping(vehicle_raw(3), tmp_path / "v.toml", "vehicle")
    assert vcfg.owners() == [1, 2, 3]


def test_the_one_checker_says_every_fleet_problem(tmp_path: Path) -> None:
    raw = topside_raw(vehicles=[{"id": 2, "name": "mapper"}, {"id": 2, "name": "mapper", "color": 1},
                                {"id": 1, "name": "topside"}, {"name": "x"}],
                      tdma={"slots": ["topside", "vehicle", "nobody", 9]})
    raw["node"]["peer"] = 2
    _cfg, problems = check_mapping(raw, tmp_path / "t.toml", "topside")
    text = "\n".join(problems)
    for needle in ("node.peer: give the vehicles in [[vehicles]] or the one vehicle in node.peer",
                   "vehicles[1].id: 2 is already mapper's id", "vehicles[1].name: 'mapper' names another",
                   "vehicles[1].color: unknown key", "vehicles[2].id: 1 is this topside's own id",
                   "vehicles[2].name: a name of 1 to 32", "vehicles[3].id: missing", "tdma.slots:"):
        assert needle in text, (needle, text)
    # a vehicle without a slot, 'vehicle' where several are listed
    _cfg, problems = check_mapping(topside_raw(tdma={"slots": ["topside", "mapper"]}), tmp_path / "t.toml", "topside")
    assert any("camera has none" in p for p in problems), problems
    _cfg, problems = check_mapping(topside_raw(tdma={"slots": ["topside", "vehicle"]}), tmp_path / "t.toml", "topside")
    assert any("not 'vehicle'" in p for p in problems), problems
    # only a topside lists vehicles; a per-vehicle key needs the network key
    _cfg, problems = check_mapping({**vehicle_raw(2), "vehicles": [{"id": 3}]}, tmp_path / "v.toml", "vehicle")
    assert any(p.startswith("vehicles: only a topside") for p in problems), problems
    (tmp_path / "k").write_text("00" * 16)
    raw = topside_raw(vehicles=[{"id": 2, "name": "mapper", "command_key_file": "k"}, {"id": 3, "name": "camera"}])
    _cfg, problems = check_mapping(raw, tmp_path / "t.toml", "topside")
    assert any("needs the network key" in p for p in problems), problems
    raw["node"]["command_key_file"] = "k"
    cfg = from_mapping(raw, tmp_path / "t.toml", "topside")
    assert cfg.vehicles[0].command_key == bytes(16) and cfg.vehicles[1].command_key is None
    # a one-vehicle topside gives slots to its vehicle alone
    _cfg, problems = check_mapping({"node": {"role": "topside", "id": 1, "peer": 2, "store": False},
                                    "modems": [{"uri": "loopback://x"}], "tdma": {"slots": [1, 2, 3]}},
                                   tmp_path / "t.toml", "topside")
    assert any("node 3 is neither this topside nor its vehicle" in p for p in problems), problems
    # a one-vehicle file is as it was
    with pytest.raises(ConfigError, match="both the topside and the vehicle"):
        from_mapping({"node": {"role": "topside", "id": 1, "peer": 2, "store": False},
                      "modems": [{"uri": "loopback://x"}], "tdma": {"slots": ["topside", "topside"]}},
                     tmp_path / "t.toml", "topside")


class FleetConsole:
    """Topside (from a ``[[vehicles]]`` configuration) and the mapper and camera vehicles on one
    simulated acoustic network; the topside's fleet console served over HTTP."""

    def __init__(self, tmp_path: Path, move: bool = False, *, top: dict[str, Any] | None = None,
                 vehicles: dict[int, dict[str, Any]] | None = None) -> None:
        tr = open_transport(f"loopback://fleet-{uuid.uuid4().hex[:6]}")
        try:
            cfg = from_mapping(top or topside_raw(), tmp_path / "t.toml", "topside")
            self.top = build_node(cfg, "topside", {0: tr})
            self.veh = {v: build_node(from_mapping((vehicles or {}).get(v) or vehicle_raw(v), tmp_path / "v.toml",
                                                   "vehicle"), "vehicle", {0: tr})
                        for v in (2, 3)}
        finally:
            tr.close()
        self.net = SimNetwork({0: AcousticChannel(loss=0.0, seed=4)})
        self.net.add_node(self.top, (0.0, 0.0, 0.0))
        self.net.add_node(self.veh[2], (300.0, 400.0, 900.0))
        self.net.add_node(self.veh[3], (-400.0, 300.0, 900.0))
        for v, x in ((2, 100.0), (3, -250.0)):
            self.net.every(10.0, lambda now, v=v, x=x: self.veh[v].push_status(VehicleStatus(
                int(now), x + (0.3 * now if move else 0.0), 50.0 * v - (0.2 * now if move else 0.0), 900.0, 12.0,
                90.0, 1.2, 80, VehicleMode.SURVEY, 0), now))
        self.hub = fleet_hub(self.top, {2: "mapper", 3: "camera"}, lambda: self.net.now)
        self.server = serve(self.hub, "127.0.0.1", 0)

    def run(self, until: float) -> None:
        while self.net.now < until:
            with self.hub.lock:
                self.net.run(min(until, self.net.now + 5.0))
                self.hub.pump(self.top, self.net.now)
            for v in self.veh.values():
                v.events()

    def get(self, path: str) -> Any:
        with urllib.request.urlopen(self.server.url + path, timeout=10) as r:
            return json.loads(r.read())

    def act(self, action: str, args: dict[str, Any]) -> tuple[int, dict[str, Any]]:
        req = urllib.request.Request(self.server.url + "api/action", method="POST",
                                     data=json.dumps({"action": action, "args": args}).encode(),
                                     headers={"Content-Type": "application/json"})
        try:
            with urllib.request.urlopen(req, timeout=10) as r:
                return r.status, json.loads(r.read())
        except urllib.error.HTTPError as exc:
            return exc.code, json.loads(exc.read())


def surveys(node: Any) -> dict[int, Any]:
    return dict(node.sender("survey").surveys)


def test_the_fleet_console_shows_both_vehicles_and_sends_a_survey_to_one(tmp_path: Path) -> None:
    f = FleetConsole(tmp_path)
    try:
        f.run(120.0)
        for name, vid, x in (("mapper", 2, 100.0), ("camera", 3, -250.0)):
            st = f.get(f"api/state?vehicle={name}")
            assert st["fleet"]["vehicle"] == vid and st["fleet"]["name"] == name
            assert st["vehicle"]["status"]["x"] == x  # each page: its vehicle's own track
            assert st["vehicle"]["status"]["y"] == 50.0 * vid
            rows = {r["name"]: r for r in st["fleet"]["vehicles"]}
            assert rows.keys() == {"mapper", "camera"}
            assert rows["mapper"]["x"] == 100.0 and rows["camera"]["x"] == -250.0
            assert all(r["links"]["0"]["last_heard"] is not None for r in rows.values())
        assert f.get("api/state?vehicle=3")["fleet"]["name"] == "camera"
        # the operator sends the camera to a candidate: only the camera flies it
        code, body = f.act("survey", {"vehicle": "camera", "kind": "goto", "x": 40.0, "y": -20.0})
        assert code == 200, body
        f.run(400.0)
        cam, mapper = surveys(f.veh[3]), surveys(f.veh[2])
        assert [(s.command.x, s.command.y) for s in cam.values()] == [(40.0, -20.0)]
        assert mapper == {}  # a command meant for the camera never acts on the mapper
        cmds = {n: f.get(f"api/state?vehicle={n}")["commands"] for n in ("mapper", "camera")}
        assert cmds["mapper"] == []  # nor shows on the mapper's page
        assert [c["status"] for c in cmds["camera"]] == ["accepted"]
        assert "survey" in json.dumps(f.get("api/state?vehicle=camera")["surveys"]).lower()
        # then the mapper gets its own, by id; the camera's survey stays the only one it has
        code, body = f.act("survey", {"vehicle": 2, "kind": "goto", "x": 5.0, "y": 6.0})
        assert code == 200, body
        f.run(700.0)
        assert [(s.command.x, s.command.y) for s in surveys(f.veh[2]).values()] == [(5.0, 6.0)]
        assert [(s.command.x, s.command.y) for s in surveys(f.veh[3]).values()] == [(40.0, -20.0)]
    finally:
        f.server.close()


def test_the_fleet_console_refuses_a_vehicle_it_does_not_have(tmp_path: Path) -> None:
    f = FleetConsole(tmp_path)
    try:
        survey = {"kind": "goto", "x": 1.0, "y": 2.0}
        for args, reason in (({**survey}, "needs vehicle"), ({**survey, "vehicle": "nosuch"}, "no vehicle 'nosuch'"),
                             ({**survey, "vehicle": 9}, "no vehicle '9'"),
                             ({**survey, "vehicle": [3]}, "vehicle is a vehicle's name or id"),
                             ({**survey, "vehicle": True}, "vehicle is a vehicle's name or id")):
            code, body = f.act("survey", args)
            assert code == 400 and reason in body["error"], (args, body)
        for path in ("api/state?vehicle=nosuch", "api/events?vehicle=7", "map/0.png?vehicle=x",
                     "image/1.png?vehicle=x"):
            with pytest.raises(urllib.error.HTTPError) as exc:
                urllib.request.urlopen(f.server.url + path, timeout=10)
            assert exc.value.code == 400 and "no vehicle" in exc.value.read().decode()
        assert all(surveys(v) == {} for v in f.veh.values())
    finally:
        f.server.close()


def test_the_store_keeps_each_vehicles_console(tmp_path: Path) -> None:
    from coex_apps.console.cli import topside_app
    from coex_apps.console.fleet import FleetHub

    raw = topside_raw()
    raw["node"]["store"] = "top.sqlite"
    cfg = from_mapping(raw, tmp_path / "t.toml", "topside")
    now = [1000.0]

    def start() -> Any:
        tr = open_transport(f"loopback://store-{uuid.uuid4().hex[:6]}")
        return topside_app(cfg, "127.0.0.1", 0, clock=lambda: now[0], transports={0: tr})

    app = start()
    try:
        assert isinstance(app.hub, FleetHub)
        app.hub.act("survey", {"vehicle": "camera", "kind": "goto", "x": 3.0, "y": 4.0})
        app.step()
        assert {v: len(s.commands) for v, s in app.hub.states().items()} == {2: 0, 3: 1}
    finally:
        app.close()
    app = start()  # the topside restarts: each vehicle's page as it was
    try:
        states = app.hub.states()
        assert {v: len(s.commands) for v, s in states.items()} == {2: 0, 3: 1}
        assert states[3].receivers["survey"] is app.node.receiver("survey", 3)
        assert states[2].receivers["survey"] is app.node.receiver("survey", 2)
    finally:
        app.close()


def test_the_fleet_page_shows_every_vehicle_and_commands_the_one_shown(
        tmp_path: Path, browser: Any) -> None:  # noqa: F811 (the fixture of test_console_browser)
    """In headless Chromium: the fleet strip lists both vehicles, the camera's page shows the
    camera, and an action from that page reaches the camera alone."""
    f = FleetConsole(tmp_path, move=True)
    try:
        f.run(120.0)
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(f.server.url + "?vehicle=camera")
        page.wait_for_selector("#fleet a.current[data-vehicle=camera]")
        strip = page.inner_text("#fleet")
        assert "mapper (2)" in strip and "camera (3)" in strip, strip
        assert page.get_attribute("#fleet a[data-vehicle=mapper]", "href") == "/?vehicle=mapper"
        page.wait_for_function("document.querySelector('#vehicle-status').textContent.includes('pos')")
        # the TDMA bar names each slot's vehicle, not "veh"
        page.wait_for_function("S.link && S.link.schedules.length > 0")
        assert page.evaluate("[1, 2, 3].map((o) => slotOwner(o, S.link))") == ["top", "mapper", "camera"]
        # the page's own action carries its vehicle (the operator never types it)
        page.evaluate("act('survey', {kind: 'goto', x: 40, y: -20})")
        page.wait_for_function("act.lastError === ''")
        page.click("#fleet a[data-vehicle=mapper]")
        page.wait_for_selector("#fleet a.current[data-vehicle=mapper]")
        assert errors == []
        f.run(400.0)
        assert [(s.command.x, s.command.y) for s in surveys(f.veh[3]).values()] == [(40.0, -20.0)]
        assert surveys(f.veh[2]) == {}
    finally:
        f.server.close()


def test_a_vehicle_that_restarts_does_not_disturb_the_other(tmp_path: Path) -> None:
    """The camera's node is replaced by a fresh one (a restart without its store) while the
    mapper keeps delivering: the mapper's page keeps moving, the camera's comes back, and a
    survey for the restarted camera reaches it alone."""
    f = FleetConsole(tmp_path, move=True)
    try:
        f.run(200.0)
        mapper_t = f.get("api/state?vehicle=mapper")["vehicle"]["status"]["t"]
        del f.net.nodes[3]  # the camera goes silent ...
        f.run(400.0)
        silent_t = f.get("api/state?vehicle=camera")["vehicle"]["status"]["t"]
        assert f.get("api/state?vehicle=mapper")["vehicle"]["status"]["t"] > mapper_t + 100  # the mapper did not
        tr = open_transport(f"loopback://re-{uuid.uuid4().hex[:6]}")
        try:
            f.veh[3] = build_node(from_mapping(vehicle_raw(3), tmp_path / "v.toml", "vehicle"), "vehicle", {0: tr})
        finally:
            tr.close()
        f.net.add_node(f.veh[3], (-400.0, 300.0, 900.0))  # ... and comes back, fresh
        f.run(700.0)
        assert f.get("api/state?vehicle=camera")["vehicle"]["status"]["t"] > silent_t + 100
        code, body = f.act("survey", {"vehicle": "camera", "kind": "goto", "x": 7.0, "y": 8.0})
        assert code == 200, body
        f.run(1000.0)
        assert [(s.command.x, s.command.y) for s in surveys(f.veh[3]).values()] == [(7.0, 8.0)]
        assert surveys(f.veh[2]) == {}
        rows = {r["name"]: r for r in f.get("api/state?vehicle=mapper")["fleet"]["vehicles"]}
        assert rows["mapper"]["status_t"] > 900 and rows["camera"]["status_t"] > 900
    finally:
        f.server.close()


def test_coex_topside_config_lists_the_vehicles(tmp_path: Path) -> None:
    lines = ['[node]', 'role = "topside"', 'id = 1', 'store = false',
             '[[vehicles]]', 'id = 2', 'name = "mapper"', '[[vehicles]]', 'id = 3', 'name = "camera"',
             '[[modems]]', f'uri = "loopback://fleet-cli-{uuid.uuid4().hex[:6]}"',
             '[tdma]', 'slots = ["topside", "mapper", 3]', 'slot_seconds = 5', 'guard = 1',
             '[modalities.survey]', '[console]', 'http = "127.0.0.1:0"']
    (tmp_path / "topside.toml").write_text("\n".join(lines) + "\n")
    proc = subprocess.Popen([COEX, "topside", "--config", str(tmp_path / "topside.toml")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert "vehicles mapper (2), camera (3)" in line, line + proc.stderr.read()
        url = line.split()[3]
        with urllib.request.urlopen(url + "api/state?vehicle=camera", timeout=10) as r:
            state = json.loads(r.read())
        assert state["fleet"]["name"] == "camera"
        assert [v["name"] for v in state["fleet"]["vehicles"]] == ["mapper", "camera"]
        (sched,) = state["link"]["schedules"]
        assert [s["owner"] for s in sched["slots"]] == [1, 2, 3]
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_a_vehicle_with_its_own_key(tmp_path: Path) -> None:
    """The camera shares a key with the topside alone (``[[vehicles]] command_key_file`` and the
    camera's ``node.peer_key_file``); the mapper holds only the network key. Each accepts the
    surveys signed for it; the topside signs each vehicle's commands with that vehicle's key."""
    (tmp_path / "network.key").write_text("11" * 16)
    (tmp_path / "camera.key").write_text("22" * 16)
    top = topside_raw(vehicles=[{"id": 2, "name": "mapper"},
                                {"id": 3, "name": "camera", "command_key_file": "camera.key"}])
    top["node"]["command_key_file"] = "network.key"
    mapper, camera = vehicle_raw(2), vehicle_raw(3)
    mapper["node"]["command_key_file"] = camera["node"]["command_key_file"] = "network.key"
    camera["node"]["peer_key_file"] = "camera.key"
    f = FleetConsole(tmp_path, top=top, vehicles={2: mapper, 3: camera})
    try:
        assert set(f.top.manager.peer_signers) == {3} and set(f.veh[3].manager.peer_signers) == {1}
        assert f.veh[2].manager.peer_signers == {}
        f.run(120.0)
        for vehicle, x in (("camera", 40.0), ("mapper", 5.0)):
            code, body = f.act("survey", {"vehicle": vehicle, "kind": "goto", "x": x, "y": 1.0})
            assert code == 200, body
        f.run(600.0)
        assert [s.command.x for s in surveys(f.veh[3]).values()] == [40.0]
        assert [s.command.x for s in surveys(f.veh[2]).values()] == [5.0]
        assert f.top.manager.peer_signers[3].counter > 0  # the camera's commands: under its own key
        assert f.veh[3].manager.peer_verifiers[1].counter > 0
    finally:
        f.server.close()
    # the checker: a vehicle's own key needs the network key; a topside has none of its own
    del camera["node"]["command_key_file"]
    _cfg, problems = check_mapping(camera, tmp_path / "v.toml", "vehicle")
    assert any(p.startswith("node.peer_key_file: a key shared with the topside alone needs") for p in problems)
    top["node"]["peer_key_file"] = "camera.key"
    _cfg, problems = check_mapping(top, tmp_path / "t.toml", "topside")
    assert any(p.startswith("node.peer_key_file: a topside gives each vehicle's own key") for p in problems)


def test_checking_the_example_leaves_nothing_behind(tmp_path: Path) -> None:
    """`coex config check` builds the receivers to check their options; it must not make their
    output folders (the imagery receiver's ``out_dir``) or anything else beside the file."""
    import shutil

    for f in (ROOT / "examples/fleet").iterdir():
        if f.is_file():
            shutil.copy(f, tmp_path / f.name)
    before = sorted(p.name for p in tmp_path.iterdir())
    r = subprocess.run([COEX, "config", "check", str(tmp_path / "topside.toml")], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == before
