"""`coex config check`: a deployment file is checked whole before anything opens, and every
problem names its key."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from coex_apps.vehicle.config import check, expand, load
from coex_core.errors import ConfigError

EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "deploy"

BAD = """
[node]
role = "vehicle"
id = 22
peer = 1
colour = "red"
store = 3
[[modems]]
uri = "micromodm:///dev/ttyUSB0"
rate = 9
[tdma]
slots = ["topside", "vehicle", "ship"]
guard = 30
[modalities.bathymetry]
stream = 3
options = { send_dleay = 2 }
[modalities.survey]
stream = 3
options = { geofence = { polygon = [[0, 0], [1, 1]] } }
[console]
http = "x"
"""


def test_every_problem_is_reported_with_its_key(tmp_path: Path) -> None:
    f = tmp_path / "v.toml"
    f.write_text(BAD)
    _, problems = check(f)
    keys = [p.split(":", 1)[0] for p in problems]
    for key in ("node.colour", "node.id", "node.store", "modems[0].uri", "modems[0].rate", "tdma.slots",
                "tdma.guard", "modalities.bathymetry.options", "modalities.survey.stream",
                "modalities.survey.options.geofence.polygon", "console"):
        assert key in keys, (key, problems)
    text = "\n".join(problems)
    assert "send_dleay" in text and "micromodm" in text and "polygon" in text
    with pytest.raises(ConfigError, match="problems"):
        load(f)
    out = subprocess.run([sys.executable, "-m", "coex_core.cli", "config", "check", str(f)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 1
    assert "modems[0].uri: no transport 'micromodm'" in out.stdout


def test_the_role_must_match_and_toml_errors_are_clear(tmp_path: Path) -> None:
    f = tmp_path / "t.toml"
    f.write_text('[node]\nrole = "topside"\nid = 1\n[[modems]]\nuri = "loopback://a"\n')
    cfg = load(f, "topside")
    assert cfg.owners() == [1, 2, 2, 1, 2, 2] and cfg.store == tmp_path / "topside.sqlite"
    with pytest.raises(ConfigError, match="configures the topside"):
        load(f, "vehicle")
    f.write_text("[node\n")
    assert "not valid TOML" in check(f)[1][0]
    assert "cannot read" in check(tmp_path / "missing.toml")[1][0]


def test_environment_variables_fill_the_file(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("COEX_X", "7")
    assert expand("a = ${COEX_X:-3}\nb = ${COEX_UNSET_Y:-4}") == "a = 7\nb = 4"
    with pytest.raises(ConfigError, match="COEX_UNSET_Y"):
        expand("${COEX_UNSET_Y}")


def test_the_topside_example_checks_clean() -> None:
    cfg, problems = check(EXAMPLES / "topside.toml")
    assert problems == [] and cfg is not None
    assert [m.name for m in cfg.modalities] == ["bathymetry", "imagery", "timeseries", "survey"]
    assert cfg.command_key is not None


# --------------------------------------------------------------- what the daemon will do
GOOD = """
[node]
role = "vehicle"
id = 2
peer = 1
store = false
[[modems]]
uri = "{uri}"
{modem}
[modalities.survey]
stream = 7
{rest}
"""


@pytest.mark.parametrize(("uri", "words"), [
    ("micromodem:///dev/ttyUSB0?dst=1", "unknown option 'dst'"),
    ("micromodem:///dev/ttyUSB0?rate=9", "rate 9 is not valid for mode cycle"),
    ("micromodem:socket://127.0.0.1?src=2", "expected HOST:PORT"),
    ("mavlink:udpot:127.0.0.1:14550", "connection kind must be one of"),
    ("lcm:udpm://239.255.76.67:7667?ttl=0&chanel=COEX", "unknown option 'chanel'"),
    ("moos://localhost:9000?nmae=pCoex", "unknown option 'nmae'"),
])
def test_config_check_refuses_what_the_transport_would_refuse_by_key(tmp_path: Path, uri: str, words: str) -> None:
    f = tmp_path / "v.toml"
    f.write_text(GOOD.format(uri=uri, modem="", rest=""))
    _, problems = check(f)
    assert [p for p in problems if p.startswith("modems[0].uri: ") and words in p], problems
    out = subprocess.run([sys.executable, "-m", "coex_core.cli", "config", "check", str(f)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 1 and words in out.stdout


def test_a_rate_the_uri_contradicts_is_a_problem_and_one_it_gives_is_used(tmp_path: Path) -> None:
    f = tmp_path / "v.toml"
    f.write_text(GOOD.format(uri="micromodem:socket://127.0.0.1:4001?src=2&rate=1", modem="rate = 5", rest=""))
    _, problems = check(f)
    assert any(p.startswith("modems[0].rate: 5, but the modem's URI says rate=1") for p in problems), problems
    f.write_text(GOOD.format(uri="micromodem:socket://127.0.0.1:4001?src=2&rate=1", modem="", rest=""))
    cfg, problems = check(f)
    assert not problems and cfg is not None and cfg.modems[0].rate == 1


def test_missing_devices_files_and_folders_are_warnings_with_their_keys(tmp_path: Path) -> None:
    rest = f"""
[[inputs]]
type = "rosbag"
path = "no-such.bag"
nav_topic = "/nav"
feeds = ["status"]
[[inputs]]
type = "directory"
path = "{tmp_path / 'no-such-dir'}"
feeds = []
[[inputs]]
type = "nmea"
serial = "/dev/ttyNOPE3"
feeds = ["status"]
[autonomy]
type = "mavlink"
connection = "/dev/ttyNOPE4"
"""
    f = tmp_path / "v.toml"
    f.write_text(GOOD.format(uri="micromodem:///dev/ttyNOPE0?src=2&rate=5", modem="required = false", rest=rest))
    cfg, problems = check(f)
    assert not problems, problems
    assert cfg is not None
    keys = {w.split(":", 1)[0] for w in cfg.warnings}
    assert keys == {"modems[0].uri", "inputs[0].path", "inputs[1].path", "inputs[2].serial", "autonomy.connection"}
    assert any(str(tmp_path / "no-such.bag") in w for w in cfg.warnings)  # relative to the file
    out = subprocess.run([sys.executable, "-m", "coex_core.cli", "config", "check", str(f)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "warning: modems[0].uri: /dev/ttyNOPE0 does not exist now" in out.stdout
    assert ": ok: vehicle node 2" in out.stdout


def test_the_console_s_host_and_idle_keys_are_checked(tmp_path: Path) -> None:
    text = (EXAMPLES / "topside.toml").read_text()
    assert "\n[console]\n" in text
    f = tmp_path / "t.toml"
    f.write_text(text.replace("\n[console]\n", '\n[console]\nallowed_hosts = "ship.example"\nidle_minutes = -1\n'
                              'trusted_proxies = ["127.0.0.1"]\n'))
    _, problems = check(f)
    keys = [p.split(":", 1)[0] for p in problems]
    assert "console.allowed_hosts" in keys and "console.idle_minutes" in keys, problems
    assert "console.trusted_proxies" not in keys and "console" not in keys


def test_detections_run_when_named_with_their_stream_and_a_low_link_priority(tmp_path: Path) -> None:
    """Not run unless named (what a vehicle looks for is the mission's); named, detections take
    stream 8 at priority 100; ``low_priority`` reaches the stream (docs/channel.md)."""
    from coex_apps.vehicle.daemon import build_vehicle_node

    f = tmp_path / "v.toml"
    head = '[node]\nrole = "vehicle"\nid = 2\npeer = 1\nstore = false\n[[modems]]\nuri = "loopback://d"\n'
    f.write_text(head)
    assert "detections" not in [m.name for m in load(f, "vehicle").modalities]
    f.write_text(head + '[modalities.bathymetry]\nlow_priority = 40\n'
                 '[modalities.detections]\noptions = { detectors = [{ type = "relief", threshold = 0.9 }] }\n')
    cfg = load(f, "vehicle")
    det = next(m for m in cfg.modalities if m.name == "detections")
    assert (det.stream, det.priority, det.low_priority) == (8, 100, None)
    node = build_vehicle_node(cfg, {0: type("T", (), {"mtu": 256})()})
    assert node.manager.stream(3).config.low_priority == 40
    assert node.sender("detections").detectors[0].threshold == 0.9
    f.write_text(head + '[modalities.detections]\nlow_priority = 300\n')
    assert any("low_priority" in p for p in check(f)[1])


def test_the_map_metadata_names_node_origin(tmp_path: Path) -> None:
    """Issue 51: the vehicle's map metadata (and so the console's map) gives ``node.origin``, not
    0, 0; an origin the bathymetry options give themselves still wins."""
    from coex_apps.vehicle.daemon import build_vehicle_node
    from coex_core.messages import MapMetadata

    f = tmp_path / "v.toml"
    head = ('[node]\nrole = "vehicle"\nid = 2\npeer = 1\nstore = false\norigin = { lat = 41.5245, lon = -70.6712 }\n'
            '[[modems]]\nuri = "loopback://d"\n[modalities.bathymetry]\n')
    f.write_text(head)
    node = build_vehicle_node(load(f, "vehicle"), {0: type("T", (), {"mtu": 256})()})
    sender = node.sender("bathymetry")
    assert sender.origin == (41.5245, -70.6712)
    meta = sender.metadata(0.0)
    assert isinstance(meta, MapMetadata)
    assert (meta.origin_lat, meta.origin_lon) == pytest.approx((41.5245, -70.6712), abs=1e-6)
    f.write_text(head + "options = { origin_lat = 10.0, origin_lon = 20.0 }\n")
    node = build_vehicle_node(load(f, "vehicle"), {0: type("T", (), {"mtu": 256})()})
    assert node.sender("bathymetry").origin == (10.0, 20.0)


def test_one_build_node_for_the_vehicle_and_the_topside_from_a_file_or_the_options(tmp_path: Path) -> None:
    """``build_node(config, role, transports)`` builds both nodes; the topside's command-line
    options make the same checked configuration as a file saying the same (``topside_config``)."""
    from coex_apps.console.cli import topside_config
    from coex_apps.vehicle.build import build_node, link_configs

    link = type("T", (), {"mtu": 128})()
    f = tmp_path / "t.toml"
    f.write_text('[node]\nrole = "topside"\nid = 1\npeer = 2\nstore = false\n[tdma]\nslot_seconds = 10.0\n'
                 'guard = 1.0\n[[modems]]\nuri = "loopback://b1"\nrate = 3\n'
                 '[modalities.bathymetry]\n[modalities.pings]\nstream = 9\nids = { 100 = 4100 }\n')
    from_file = load(f, "topside")
    from_options = topside_config("loopback://b1", rate=3, slot=10.0, guard=1.0,
                                  modalities=("bathymetry", "pings"), remap_ids={"pings": {100: 4100}})
    for cfg in (from_file, from_options):
        (lc,) = link_configs(cfg, {0: link})
        assert (lc.link, lc.rate, lc.frame_bytes, lc.dst) == (0, 3, 128, 2)
        assert lc.schedule.to_dict() == from_file.schedule().to_dict()
        node = build_node(cfg, "topside", {0: link})
        assert sorted(dict(node.receivers())) == ["bathymetry", "pings"]
        assert [m.ids for m in cfg.modalities] == [{}, {100: 4100}]
    with pytest.raises(ConfigError, match="the topside's, not the vehicle's"):
        build_node(from_file, "vehicle", {0: link})
    missing: list[str] = []
    cfg = topside_config(["loopback://b2", "loopback://b3"], link=4, modalities=("nosuch", "survey"),
                         missing=missing)  # a modality not installed stays a warning, as it was
    assert cfg.link_ids() == [4, 5] and [m.name for m in cfg.modalities] == ["survey"]
    assert len(missing) == 1 and missing[0].startswith("modality nosuch not available: no modality 'nosuch'")
    node = build_node(cfg, "topside", {4: link, 5: link})
    assert node.manager.links == [4, 5]


def test_the_topside_options_are_checked_by_the_files_checker_naming_each_option() -> None:
    from coex_apps.console.cli import topside_config

    with pytest.raises(ConfigError) as err:
        topside_config("loopback://c1", node_id=20, slot=1.0, guard=3.0, rate=9)
    text = str(err.value)
    assert text.startswith("3 problems:"), text
    assert "--node-id: 20 is outside 1..15" in text and "--rate: 9 is outside 0..6" in text
    assert "--guard: the guard (3 s) must be shorter than a slot (1 s)" in text
    assert {p.key for p in err.value.problems} == {"node.id", "modems[0].rate", "tdma.guard"}
    out = subprocess.run([str(Path(sys.executable).with_name("coex")), "topside", "--transport", "loopback://c2",
                          "--vehicle-id", "1"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "coex topside: --vehicle-id: the other node's id must differ" in out.stderr


def _fleet_topside(tmp_path: Path, vehicles: str) -> Path:
    (tmp_path / "t.toml").write_text(f"""
[node]
role = "topside"
id = 1
store = false
{vehicles}
[[modems]]
uri = "loopback://fleet"
packet_seconds = 1.0
[tdma]
slots = ["topside", "mapper", "camera"]
[modalities.bathymetry]
[modalities.imagery]
options = {{ out_dir = "images" }}
[modalities.survey]
""")
    return tmp_path / "t.toml"


def test_a_fleet_vehicle_carries_the_modalities_it_lists(tmp_path: Path) -> None:
    """``[[vehicles]] modalities``: topside has receivers for those alone; a vehicle without the
    list has every modality; one vehicle's imagery writes into ``out_dir`` itself (a folder per
    vehicle only when several carry it); a name that is not one of the modalities is refused."""
    from coex_apps.vehicle.build import build_node
    from coex_core.loopback import LoopbackLink, LoopbackTransport

    path = _fleet_topside(tmp_path, """
[[vehicles]]
id = 2
name = "mapper"
modalities = ["bathymetry", "survey"]
[[vehicles]]
id = 3
name = "camera"
""")
    cfg = load(path, "topside")
    assert [v.modalities for v in cfg.vehicles] == [("bathymetry", "survey"), None]
    node = build_node(cfg, "topside", {0: LoopbackTransport(LoopbackLink(), 0)})
    held = {(r.name, r.peer) for r in node._receivers}
    assert held == {("bathymetry", 2), ("survey", 2), ("bathymetry", 3), ("imagery", 3), ("survey", 3)}
    imagery: Any = node.receiver("imagery", 3)
    assert imagery.out_dir == str(tmp_path.resolve() / "images")  # the camera alone carries it
    path = _fleet_topside(tmp_path, """
[[vehicles]]
id = 2
name = "mapper"
modalities = ["bathymetry", "sonar"]
[[vehicles]]
id = 3
name = "camera"
modalities = "imagery"
""")
    _, problems = check(path)
    assert problems == ["vehicles[1].modalities: a list of the modalities this vehicle carries, got 'imagery'",
                        "vehicles[0].modalities: 'sonar' is not one of this topside's modalities "
                        "(bathymetry, imagery, survey)"]


# --------------------------------------------------------------- [tdma] queue_status
def _queue_status_interval(text: str, tmp_path: Path) -> float | None:
    import tomllib

    from coex_apps.vehicle.build import build_node
    from coex_apps.vehicle.config import from_mapping
    from coex_core.loopback import LoopbackLink, LoopbackTransport

    cfg = from_mapping(tomllib.loads(text), tmp_path / "n.toml")
    node = build_node(cfg, cfg.role, {0: LoopbackTransport(LoopbackLink(), 0)})
    return node.manager.queue_status_interval  # type: ignore[no-any-return]


QS = """
[node]
role = "{role}"
id = {id}
peer = {peer}
store = false
[[modems]]
uri = "loopback://qs"
[tdma]
slots = ["topside", "vehicle", "vehicle"]
slot_seconds = 10
{qs}
"""


@pytest.mark.parametrize(("role", "qs", "want"), [
    ("vehicle", "", 30.0), ("topside", "", None),
    ("topside", "queue_status = true", 30.0), ("vehicle", "queue_status = false", None)])
def test_tdma_queue_status_says_which_node_reports_its_queues(tmp_path: Path, role: str, qs: str,
                                                                want: float | None) -> None:
    ids = {"vehicle": (2, 1), "topside": (1, 2)}[role]
    text = QS.format(role=role, id=ids[0], peer=ids[1], qs=qs)
    assert _queue_status_interval(text, tmp_path) == want


@pytest.mark.parametrize("bad", ["1", "\"yes\"", "nan"])
def test_tdma_queue_status_takes_only_true_or_false(tmp_path: Path, bad: str) -> None:
    f = tmp_path / "v.toml"
    f.write_text(QS.format(role="vehicle", id=2, peer=1, qs=f"queue_status = {bad}"))
    _, problems = check(f)
    assert any(p.startswith("tdma.queue_status: true or false") for p in problems), problems
