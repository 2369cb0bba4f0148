"""One configuration convention: every built-in sender and receiver rejects an unknown
(misspelt) option with a ConfigError naming it, and takes its documented options."""

from __future__ import annotations

from pathlib import Path

import pytest

from coex import ConfigError, load_modality
from coex_core.config import Problems, merged_config

MODALITIES = ["bathymetry", "imagery", "timeseries"]


@pytest.mark.parametrize("name", MODALITIES)
@pytest.mark.parametrize("side", ["sender", "receiver"])
def test_a_misspelt_option_is_refused_with_its_name(name: str, side: str) -> None:
    modality = load_modality(name)()
    with pytest.raises(ConfigError, match=r"unknown .*option 'max_imgaes' \(known: "):
        getattr(modality, side)({"max_imgaes": 3})


@pytest.mark.parametrize("name, side, config", [
    ("bathymetry", "sender", {"levels": 3}),
    ("bathymetry", "receiver", {"levels": 3}),
    ("imagery", "sender", {"max_images": 3, "resolutions": 4, "rto": 90.0}),
    ("imagery", "receiver", {"max_images": 3, "retry": 30.0}),
    ("timeseries", "sender", {"block_samples": 256}),
    ("timeseries", "receiver", {"request_retry": 30.0}),
])
def test_documented_options_are_taken(name: str, side: str, config: dict[str, object]) -> None:
    part = getattr(load_modality(name)(), side)(config)
    for key, value in config.items():
        held = getattr(part, key, None)
        if held is None or callable(held):  # kept in the part's config mapping or a settings object
            held = None
            for v in vars(part).values():
                if isinstance(v, dict) and key in v:
                    held = v[key]
                elif hasattr(v, key) and not isinstance(v, dict):
                    held = getattr(v, key)
        assert held == value, key


def test_merged_config() -> None:
    assert merged_config({"a": 2}, {"a": 1, "b": 3}) == {"a": 2, "b": 3}
    assert merged_config(None, {"a": 1}) == {"a": 1}
    with pytest.raises(ConfigError, match="unknown imagery sender option 'c' \\(known: a, b\\)"):
        merged_config({"c": 1}, {"a": 1, "b": 2}, "imagery sender")
    with pytest.raises(ConfigError, match="mapping"):
        merged_config([("a", 1)], {"a": 1})  # type: ignore[arg-type]


def test_merged_config_names_every_unknown_option_at_once() -> None:
    with pytest.raises(ConfigError) as err:
        merged_config({"c": 1, "a": 2, "d": 3}, {"a": 1, "b": 2}, "imagery sender")
    assert [p.key for p in err.value.problems] == ["c", "d"]
    assert str(err.value) == ("2 problems:\n  unknown imagery sender option 'c' (known: a, b)\n"
                              "  unknown imagery sender option 'd' (known: a, b)")


def test_problems_collects_every_problem_with_its_key(tmp_path: Path) -> None:
    """The one collector: ``add`` words "key: text", ``said`` keeps a sentence, the common checks
    add theirs, and ``error`` lists them all (one alone on its line) with each key."""
    p = Problems()
    assert not p and p.error.__doc__
    p.check()  # nothing found: nothing raised
    t = p.table({"speed": "x", "size": 99, "colour": 1}, "boat")
    p.unknown(t, {"speed", "size"}, "boat")
    assert p.number(t, "speed", "boat", 1.0) == 1.0
    assert p.number(t, "size", "boat", 5, lo=1, hi=10, integer=True) == 5
    p.said("crew", "a boat needs a crew")
    p.extend("engine", ["no fuel", "no oil"])
    p.path("log", tmp_path / "nothere", "written at the end")
    assert p.keys() == ["boat.colour", "boat.speed", "boat.size", "crew", "engine", "engine"]
    assert p.items == ["boat.colour: unknown key (known: size, speed)", "boat.speed: not a finite number, got 'x'",
                       "boat.size: 99 is outside 1..10", "a boat needs a crew", "engine: no fuel", "engine: no oil"]
    assert p.warnings == [f"log: {tmp_path / 'nothere'} does not exist now (written at the end)"]
    with pytest.raises(ConfigError) as err:
        p.check("boat.toml")
    assert str(err.value).startswith("boat.toml: 6 problems:\n  boat.colour: unknown key")
    assert [x.key for x in err.value.problems] == p.keys()
    one = Problems()
    one.add("crew", "missing")
    assert str(one.error("boat.toml")) == "boat.toml: crew: missing"


def test_an_adapters_option_checks_collect_every_problem_with_its_option() -> None:
    """An adapter's problems, each keyed by its option: its own checks in its words (an NMEA
    input's ``udp``), its declared options' types and ranges in the schema's (``baud``)."""
    from coex_core.adapters import adapter_check, adapter_problems
    from coex_plugins.inputs.nmea import NmeaInput

    options = {"udp": "nowhere", "baud": 0, "require_checksum": "yes", "variation": float("nan")}
    p = adapter_check(NmeaInput, options)
    assert p.keys() == ["udp", "baud", "require_checksum", "variation"]
    assert p.items == [
        "input 'nmea': option 'udp' must be 'host:port' (e.g. '0.0.0.0:10110'), not 'nowhere'",
        "baud: 0 is outside 1..10000000 baud",
        "require_checksum: true or false, got 'yes'",
        "variation: not a finite number, got nan",
    ]
    assert adapter_problems(NmeaInput, options) == p.items
    from coex_plugins.autonomy.mavlink import MavlinkAutonomy

    out = adapter_check(MavlinkAutonomy, {"connection": "udpout:127.0.0.1:14550", "baud": 0, "hold": -1,
                                          "start": "soon"})
    assert out.keys() == ["baud", "hold", "start"]
    assert out.items == ["baud: 0 is outside 1..10000000 baud", "hold: -1 is below 0 s",
                         "start: one of 'mission_start', 'auto_mode', 'none', got 'soon'"]
    q = Problems()
    q.option_str("input 'x'", {"path": " "}, "path", nonempty=True)
    q.option_number("input 'x'", {"settle": -1}, "settle", minimum=0)
    q.option_number("input 'x'", {"speed": 0}, "speed", positive=True)
    q.option_choice("input 'x'", {"start": "later"}, "start", ("now", "original"))
    q.option_bool("input 'x'", {}, "nav")  # not given: its default applies
    assert q.items == ["input 'x': option 'path' must not be empty",
                       "input 'x': option 'settle' must be at least 0, not -1",
                       "input 'x': option 'speed' must be greater than 0, not 0",
                       "input 'x': option 'start' must be one of 'now', 'original', not 'later'"]


def test_a_nodes_file_names_every_bad_input_option_and_ros_key_in_one_error(tmp_path: Path) -> None:
    """A deployment file with two inputs, each with bad options, and a bad ``[ros]`` table: one
    ConfigError lists them all, each under its full key (``inputs[0].baud``, ``ros.interval``)."""
    from coex_apps.vehicle.config import load

    (tmp_path / "t.toml").write_text("""
[node]
role = "topside"
id = 1
[[modems]]
uri = "loopback://t"
[ros]
prefix = "coex"
interval = 0
track = -1
""")
    with pytest.raises(ConfigError) as err:
        load(tmp_path / "t.toml")
    assert [x.key for x in err.value.problems] == ["ros.prefix", "ros.interval", "ros.track"]
    assert str(err.value) == (f"{tmp_path / 't.toml'}: 3 problems:\n"
                              "  ros.prefix: a global namespace starting with '/', got 'coex'\n"
                              "  ros.interval: seconds from 0.05 to 3600, got 0\n"
                              "  ros.track: an integer from 0 to 100000, got -1")
    (tmp_path / "v.toml").write_text("""
[node]
role = "vehicle"
id = 2
[[modems]]
uri = "loopback://v"
[modalities.timeseries]
[modalities.imagery]
[[inputs]]
type = "nmea"
feeds = ["timeseries"]
udp = "nowhere"
baud = 0
[[inputs]]
type = "directory"
feeds = ["imagery"]
path = ""
settle = -1
existing = "yes"
""")
    with pytest.raises(ConfigError) as err:
        load(tmp_path / "v.toml")
    assert [x.key for x in err.value.problems] == [
        "inputs[0].udp", "inputs[0].baud", "inputs[1].path", "inputs[1].settle", "inputs[1].existing"]
    assert str(err.value).splitlines()[1:] == [
        "  inputs[0]: input 'nmea': option 'udp' must be 'host:port' (e.g. '0.0.0.0:10110'), not 'nowhere'",
        "  inputs[0].baud: 0 is outside 1..10000000 baud",  # the declared range: the full key
        "  inputs[1]: input 'directory': option 'path' must not be empty",
        "  inputs[1].settle: -1 is below 0 s",
        "  inputs[1].existing: true or false, got 'yes'",
    ]


def test_ros_products_refuse_every_bad_key_at_once() -> None:
    from coex_apps.console.ros import RosProducts

    with pytest.raises(ConfigError) as err:
        RosProducts({"master": "ship:11311", "interval": 0, "topics": 1})
    assert [x.key for x in err.value.problems] == ["ros.topics", "ros.master", "ros.interval"]
    assert str(err.value).startswith("3 problems:\n  ros.topics: unknown key (known: ")


def test_request_tracker_sends_retries_and_gives_up() -> None:
    from coex_core.requests import RequestTracker

    t: RequestTracker[str] = RequestTracker(retry=10.0, max_tries=3)
    t.add(1, "a")
    t.add(2, "b")
    assert t.due(0.0) == ["a", "b"] and t.due(5.0) == []
    assert t.answered(1) is not None and t.answered(1) is None
    assert t.due(10.0) == ["b"]  # unanswered: again after the retry interval
    assert t.due(19.0) == []
    assert t.due(3.0) == ["b"]  # a clock that went back resends
    t2: RequestTracker[str] = RequestTracker(retry=10.0, max_tries=2)
    t2.add("k", "x")
    assert t2.due(0.0) == ["x"] and t2.due(10.0) == ["x"]
    assert t2.due(20.0) == [] and len(t2) == 0 and t2.given_up == 1  # two sends, then given up
    t3: RequestTracker[str] = RequestTracker(retry=10.0, max_tries=5)
    t3.add("k", "x")
    assert t3.due(0.0, done=lambda m: False) == ["x"]
    assert t3.pending(done=lambda m: True) == [] and t3.due(30.0, done=lambda m: True) == []
    assert "k" not in t3  # done: dropped as answered, not given up
    assert t3.given_up == 0


def test_a_scale_table_is_checked_the_same_for_lcm_and_ros_inputs() -> None:
    """The LCM input's ``own`` and the ROS input's ``series`` check their ``scale`` tables with
    one function: a name not in the entry's table scales nothing, a factor must be a finite
    number (NaN included, for both)."""
    from coex_plugins.inputs.lcm import LcmInput
    from coex_plugins.inputs.ros import RosInput

    ros = RosInput.check({"series": [{"topic": "/ctd", "channels": {"t": "temperature"},
                                      "scale": {"t": float("nan"), "s": 2.0}}]})
    lcm = LcmInput.check({"own": [{"channel": "CTD", "type": "ctd.ctd_t", "feeds": "timeseries",
                                   "channels": {"t": "temperature"}, "scale": {"t": float("nan"), "s": 2.0}}]})
    for p, option, table in ((ros, "series", "channels"), (lcm, "own", "channels")):
        texts = [q.text for q in p.found if q.key == option]
        assert f"option '{option}[0].scale.t' must be a number" in " ".join(texts), texts
        assert f"option '{option}[0].scale.s' scales nothing (not in '{option}[0].{table}')" in " ".join(texts), texts
