"""One option schema (issue 53): every numeric option every registered plugin declares (a
modality's sender and receiver, a detector, an input, an autonomy output, a transport's URI
query), the deployment file's numbers and the demo scenario's refuse NaN, infinities,
booleans and words, each problem naming its full key; the constructor, ``coex config check``
and the daemons say it with the same checker (``coex_core.config.Option``)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest

from coex import ConfigError, Option, Options, check_transport_uri, merged_config
from coex.registry import entry_points
from coex_apps.vehicle.config import check_problems
from coex_core.adapters import Adapter, adapter_check
from coex_core.config import Problems, integer, number
from coex_core.transport import parse_query

#: what a numeric option must refuse: (id, the value in a mapping, the text in a URI query)
BAD: list[tuple[str, Any, str]] = [
    ("nan", math.nan, "nan"), ("inf", math.inf, "inf"), ("-inf", -math.inf, "-inf"),
    ("true", True, "true"), ("soon", "soon", "soon"),
]
BAD_IDS = [b[0] for b in BAD]


def _loaded(group: str) -> dict[str, Any]:
    out = {}
    for name, ep in sorted(entry_points(group).items()):
        try:
            out[name] = ep.load()
        except ImportError:  # an extra not installed here: its plugin is not registered usable
            continue
    return out


MODALITIES = _loaded("coex.modalities")
DETECTORS = _loaded("coex.detectors")
ADAPTERS = {**{("input", k): v for k, v in _loaded("coex.inputs").items()},
            **{("autonomy", k): v for k, v in _loaded("coex.autonomy").items()}}
TRANSPORTS = _loaded("coex.transports")


def _side_options(name: str, side: str) -> Options:
    return type(getattr(MODALITIES[name](), side)()).options


SIDE_OPTIONS = [(name, side, key) for name in MODALITIES for side in ("sender", "receiver")
                for key in _side_options(name, side).numeric()]
DETECTOR_OPTIONS = [(name, key) for name, cls in DETECTORS.items() for key in cls.options.numeric()]
ADAPTER_OPTIONS = [(kind, name, key) for (kind, name), cls in ADAPTERS.items()
                   for key in Options.of(cls.options).numeric()]
TRANSPORT_OPTIONS = [(scheme, key) for scheme, cls in TRANSPORTS.items() for key, t in cls.options.items()
                     if (t.numeric if isinstance(t, Option) else t in (int, float))]


def test_the_declarations_cover_every_built_in_kind() -> None:
    """The parametrised tests below run over something: each kind of plugin declares numbers."""
    assert {"bathymetry", "imagery", "timeseries", "survey", "detections"} <= {n for n, _, _ in SIDE_OPTIONS}
    assert ("bathymetry", "sender", "send_delay") in SIDE_OPTIONS
    assert ("relief", "threshold") in DETECTOR_OPTIONS
    assert {k for k, _, _ in ADAPTER_OPTIONS} == {"input", "autonomy"}
    assert {"loopback", "micromodem"} <= {s for s, _ in TRANSPORT_OPTIONS}


# ------------------------------------------------------------------ a plugin built directly
@pytest.mark.parametrize("bad", BAD, ids=BAD_IDS)
@pytest.mark.parametrize(("name", "side", "key"), SIDE_OPTIONS, ids=["-".join(x) for x in SIDE_OPTIONS])
def test_every_numeric_modality_option_refuses_a_non_number(name: str, side: str, key: str,
                                                           bad: tuple[str, Any, str]) -> None:
    with pytest.raises(ConfigError) as err:
        getattr(MODALITIES[name](), side)({key: bad[1]})
    assert [p.key for p in err.value.problems] == [key], str(err.value)
    assert str(err.value.problems[0]).startswith(f"{key}: ")


@pytest.mark.parametrize("bad", BAD, ids=BAD_IDS)
@pytest.mark.parametrize(("name", "key"), DETECTOR_OPTIONS, ids=["-".join(x) for x in DETECTOR_OPTIONS])
def test_every_numeric_detector_option_refuses_a_non_number(name: str, key: str, bad: tuple[str, Any, str]) -> None:
    with pytest.raises(ConfigError) as err:
        DETECTORS[name]({key: bad[1]})
    assert [p.key for p in err.value.problems] == [key], str(err.value)


@pytest.mark.parametrize("bad", BAD, ids=BAD_IDS)
@pytest.mark.parametrize(("kind", "name", "key"), ADAPTER_OPTIONS, ids=["-".join(x) for x in ADAPTER_OPTIONS])
def test_every_numeric_adapter_option_refuses_a_non_number(kind: str, name: str, key: str,
                                                          bad: tuple[str, Any, str]) -> None:
    cls: type[Adapter] = ADAPTERS[(kind, name)]
    required = {k: "x" for k, o in Options.of(cls.options).items() if o.required}
    p = adapter_check(cls, {**required, key: bad[1]})
    mine = [q.text for q in p if q.key == key]
    assert mine and mine[0].startswith(f"{key}: "), p.items


#: a URI each transport's check takes, its query options added after it
URIS = {"loopback": "loopback://x", "micromodem": "micromodem:socket://127.0.0.1:4001?src=2&dest=1",
        "mavlink": "mavlink:udpout:127.0.0.1:14550", "lcm": "lcm:udpm://239.255.76.67:7667",
        "moos": "moos://localhost:9000"}


@pytest.mark.parametrize("bad", BAD, ids=BAD_IDS)
@pytest.mark.parametrize(("scheme", "key"), TRANSPORT_OPTIONS, ids=["-".join(x) for x in TRANSPORT_OPTIONS])
def test_every_numeric_transport_uri_option_refuses_a_non_number(scheme: str, key: str,
                                                                bad: tuple[str, Any, str]) -> None:
    if scheme not in URIS:
        pytest.skip(f"no sample URI for a third-party transport {scheme!r}")
    base = URIS[scheme]
    uri = f"{base}{'&' if '?' in base else '?'}{key}={bad[2]}"
    check_transport_uri(base)  # the sample URI itself passes: the option alone is refused below
    with pytest.raises(ConfigError, match=f"option {key}: "):
        check_transport_uri(uri)


# ------------------------------------------------------------------ the full key, from a file
def _node(role: str, modalities: dict[str, Any], **more: Any) -> dict[str, Any]:
    return {"node": {"role": role, "id": 2 if role == "vehicle" else 1, "peer": 1 if role == "vehicle" else 2,
                     "store": False},
            "modems": [{"uri": "loopback://x"}], "modalities": modalities, **more}


def _problems(raw: dict[str, Any]) -> Problems:
    return check_problems(raw, Path("/nonexistent/node.toml"), None)[1]


#: every (modality, role) whose side declares a numeric option (a side with none has nothing to
#: check here: pings' topside side)
NUMERIC_SIDES = [(name, role) for name in sorted(MODALITIES) for role in ("vehicle", "topside")
                 if _side_options(name, "sender" if role == "vehicle" else "receiver").numeric()]


def test_most_modality_sides_declare_numeric_options() -> None:
    """The test below runs on every side that has numeric options: most of them do."""
    assert len(NUMERIC_SIDES) >= 2 * len(MODALITIES) - 2, NUMERIC_SIDES


@pytest.mark.parametrize("bad", BAD, ids=BAD_IDS)
@pytest.mark.parametrize(("name", "role"), NUMERIC_SIDES, ids=[f"{n}-{r}" for n, r in NUMERIC_SIDES])
def test_config_check_names_every_bad_modality_option_by_its_full_key(name: str, role: str,
                                                                     bad: tuple[str, Any, str]) -> None:
    """Every numeric option of a modality's side given a non-number at once: ``coex config
    check``'s checker names each one ``modalities.NAME.options.KEY``."""
    keys = _side_options(name, "sender" if role == "vehicle" else "receiver").numeric()
    p = _problems(_node(role, {name: {"stream": 9, "options": dict.fromkeys(keys, bad[1])}}))
    for key in keys:
        full = f"modalities.{name}.options.{key}"
        texts = [q.text for q in p if q.key == full]
        assert texts and texts[0].startswith(f"{full}: "), (full, p.items)


@pytest.mark.parametrize("bad", BAD, ids=BAD_IDS)
def test_nested_option_tables_are_named_by_their_full_key(bad: tuple[str, Any, str]) -> None:
    """Tables inside a modality's options (the survey's geofence, a time-series channel, a
    detector) are declared the same way and named down to the value."""
    from coex_plugins.survey.plan import GEOFENCE_OPTIONS
    from coex_plugins.timeseries.sender import CHANNEL_OPTIONS

    fence = dict.fromkeys(GEOFENCE_OPTIONS.numeric(), bad[1])
    channel = {"name": "t", **dict.fromkeys(CHANNEL_OPTIONS.numeric(), bad[1])}
    detectors = [{"type": name, **dict.fromkeys(cls.options.numeric(), bad[1])} for name, cls in DETECTORS.items()]
    p = _problems(_node("vehicle", {"survey": {"options": {"geofence": fence}},
                                    "timeseries": {"options": {"channels": [channel]}},
                                    "detections": {"options": {"detectors": detectors}}}))
    want = ([f"modalities.survey.options.geofence.{k}" for k in fence]
            + [f"modalities.timeseries.options.channels[0].{k}" for k in CHANNEL_OPTIONS.numeric()]
            + [f"modalities.detections.options.detectors[{i}].{k}" for i, d in enumerate(detectors)
               for k in d if k != "type"])
    assert len(want) >= 12
    for full in want:
        assert any(q.key == full and q.text.startswith(f"{full}: ") for q in p), (full, p.items)


@pytest.mark.parametrize("bad", BAD, ids=BAD_IDS)
@pytest.mark.parametrize(("role", "table", "key"), [
    ("vehicle", "node", "snapshot_interval"), ("vehicle", "tdma", "slot_seconds"), ("vehicle", "tdma", "guard"),
    ("vehicle", "tdma", "epoch"), ("vehicle", "status", "interval"), ("vehicle", "node.origin", "lat"),
    ("topside", "console", "session_hours"), ("topside", "console", "idle_minutes"),
])
def test_the_deployment_files_numbers_refuse_a_non_number(role: str, table: str, key: str,
                                                          bad: tuple[str, Any, str]) -> None:
    raw = _node(role, {})
    where = raw
    for part in table.split("."):
        where = where.setdefault(part, {})
    where[key] = bad[1]
    p = _problems(raw)
    full = f"{table}.{key}"
    assert any(q.key == full and q.text.startswith(f"{full}: ") for q in p), (full, p.items)


@pytest.mark.parametrize("bad", BAD, ids=BAD_IDS)
@pytest.mark.parametrize("key", ["rate", "frame_bytes", "spare", "packet_seconds"])
def test_a_modems_numbers_refuse_a_non_number(key: str, bad: tuple[str, Any, str]) -> None:
    raw = _node("vehicle", {})
    raw["modems"][0][key] = bad[1]
    assert any(q.key == f"modems[0].{key}" for q in _problems(raw)), _problems(raw).items


@pytest.mark.parametrize("bad", BAD, ids=BAD_IDS)
def test_an_inputs_bad_number_is_named_by_its_full_key(bad: tuple[str, Any, str]) -> None:
    raw = _node("vehicle", {"timeseries": {}}, inputs=[{"type": "nmea", "udp": "0.0.0.0:10110", "variation": bad[1]}])
    p = _problems(raw)
    assert any(q.key == "inputs[0].variation" and q.text.startswith("inputs[0].variation: not a finite number")
               for q in p), p.items


# ------------------------------------------------------------------ the demo scenario
def _scenario_keys() -> list[str]:
    from coex_apps.demo.scenario import _SECTIONS

    keys = ["area", "water_depth", "duration", "ship.x", "ship.y", "loss.rate", "loss.mean_burst",
            "targets[0].x", "decoys[0].height"]
    return keys + [f"{s}.{k}" for s, ks in _SECTIONS.items() for k, attr in ks.items()
                   if attr not in ("slots", "aiding", "target_kinds", "decoy_kinds", "target_length")]


@pytest.mark.parametrize("bad", BAD, ids=BAD_IDS)
@pytest.mark.parametrize("key", _scenario_keys())
def test_every_scenario_number_refuses_a_non_number(key: str, bad: tuple[str, Any, str]) -> None:
    from coex_apps.demo.scenario import scenario_from_dict

    data: dict[str, Any] = {}
    if key.startswith(("targets[", "decoys[")):
        kind, _, field = key.partition("[0].")
        data[kind] = [{"x": 10.0, "y": 10.0, field: bad[1]}]
    elif "." in key:
        section, field = key.split(".")
        data[section] = {field: bad[1]}
    else:
        data[key] = bad[1]
    with pytest.raises(ConfigError) as err:
        scenario_from_dict(data)
    assert any(p.key == key and str(p).startswith(f"{key}: ") for p in err.value.problems), str(err.value)


@pytest.mark.parametrize("bad", BAD, ids=BAD_IDS)
def test_a_scenario_size_range_refuses_a_non_number(bad: tuple[str, Any, str]) -> None:
    from coex_apps.demo.scenario import scenario_from_dict

    with pytest.raises(ConfigError) as err:
        scenario_from_dict({"seafloor": {"target_length": [2.0, bad[1]]}})
    assert any(p.key == "seafloor.target_length" for p in err.value.problems), str(err.value)


def test_a_scenario_file_with_nan_is_refused_by_key(tmp_path: Path) -> None:
    from coex_apps.demo.scenario import load_scenario

    f = tmp_path / "s.toml"
    f.write_text("area = nan\n[survey]\nspeed = inf\n[modem]\nrate = true\n[ship]\nx = \"soon\"\n")
    with pytest.raises(ConfigError) as err:
        load_scenario(f)
    assert sorted(p.key for p in err.value.problems) == ["area", "modem.rate", "ship.x", "survey.speed"]


# ------------------------------------------------------------------ the schema itself
def test_detections_sender_refuses_the_word_nan() -> None:
    """The issue's own case: ``DetectionsSender({"interval": "nan"})`` ran no detector, ever."""
    from coex_plugins.detections import DetectionsSender

    with pytest.raises(ConfigError, match=r"^interval: not a finite number, got 'nan'$"):
        DetectionsSender({"interval": "nan"})


def test_an_option_checks_type_range_and_unit() -> None:
    delay = number(20.0, "quiet time", unit="s", lo=0)
    assert delay.problem(5) is None and delay.value(5) == 5.0 and isinstance(delay.value(5), float)
    assert delay.problem(-1) == "-1 is below 0 s"
    assert delay.problem(math.nan) == "not a finite number, got nan"
    assert delay.problem(False) == "not a finite number, got false"
    assert delay.describe() == "number, at least 0 s"
    levels = integer(5, lo=1, hi=8)
    assert levels.problem(2.0) == "not an integer, got 2.0" and levels.problem(9) == "9 is outside 1..8"
    share = number(0.4, above=0, below=1)
    assert share.problem(0) == "0 is not above 0" and share.problem(1) == "1 is not below 1"
    assert number(None, none=True).problem(None) is None


def test_merged_config_coerces_and_keeps_plain_defaults_working() -> None:
    """A plain ``{name: default}`` mapping (a third party's older plugin) still works, its
    number defaults declaring numbers; an :class:`Options` coerces ints to floats."""
    assert merged_config({"a": 2}, {"a": 1.5, "b": "x"}) == {"a": 2, "b": "x"}
    with pytest.raises(ConfigError, match=r"^a: not a finite number, got inf$"):
        merged_config({"a": math.inf}, {"a": 1.5})
    opts = Options(a=number(1.0), b=integer(2))
    got = merged_config({"a": 3}, opts)
    assert got == {"a": 3.0, "b": 2} and isinstance(got["a"], float)
    with pytest.raises(ConfigError) as err:
        merged_config({"a": "x", "b": True, "c": 1}, opts, "thing")
    assert [p.key for p in err.value.problems] == ["a", "b", "c"]


def test_a_uri_query_is_read_by_the_declared_options() -> None:
    assert parse_query("rate=2.5&n=3&on=yes", {"rate": float, "n": int, "on": bool}) == {
        "rate": 2.5, "n": 3, "on": True}
    for q in ("rate=nan", "rate=-inf", "rate=soon", "rate=true"):
        with pytest.raises(ConfigError, match="option rate: not a finite number"):
            parse_query(q, {"rate": float})
    with pytest.raises(ConfigError, match="option n: 0 is below 1"):
        parse_query("n=0", {"n": integer(1, lo=1)})


# ------------------------------------------------------------------ an adapter's declared ranges
def _outside(option: Option) -> Any:
    """A number of the option's kind that its declaration refuses for its range or choices."""
    if option.choices:
        return max(option.choices) + 1
    if option.hi is not None:
        return option.hi + 1 if option.kind == "integer" else option.hi + 0.5
    assert option.lo is not None
    return option.lo - 1 if option.kind == "integer" else option.lo - 0.5


ADAPTER_RANGES = [(kind, name, key) for (kind, name), cls in ADAPTERS.items()
                  for key, o in Options.of(cls.options).items()
                  if o.numeric and (o.lo is not None or o.hi is not None or o.choices)]


def test_the_built_in_adapters_declare_their_ranges() -> None:
    """Issue 53: the built-in inputs' and autonomy outputs' ranges are declared, not checked in
    their own ``check()`` (a sample of what must be there)."""
    for kind, name, key in [("input", "nmea", "baud"), ("input", "nmea", "variation"),
                            ("input", "mavlink", "source_system"), ("input", "directory", "settle"),
                            ("input", "ros", "queue"), ("input", "rosbag", "speed"),
                            ("input", "moos", "time_warp"), ("autonomy", "mavlink", "timeout"),
                            ("autonomy", "mavlink", "frame"), ("autonomy", "lcm", "retries"),
                            ("autonomy", "ros", "silence"), ("autonomy", "moos", "timeout"),
                            ("autonomy", "sim", "speed")]:
        if (kind, name) in ADAPTERS:
            assert (kind, name, key) in ADAPTER_RANGES, (kind, name, key)


@pytest.mark.parametrize(("kind", "name", "key"), ADAPTER_RANGES, ids=["-".join(x) for x in ADAPTER_RANGES])
def test_an_adapter_value_out_of_its_declared_range_is_refused_once_by_the_declaration(
        kind: str, name: str, key: str) -> None:
    """Out of range: one problem, the declaration's (``baud: 0 is outside 1..10000000 baud``);
    the adapter's own ``check()`` says nothing of it (no second copy of the range)."""
    cls: type[Adapter] = ADAPTERS[(kind, name)]
    declared = Options.of(cls.options)
    required = {k: "x" for k, o in declared.items() if o.required}
    value = _outside(declared[key])
    p = adapter_check(cls, {**required, key: value})
    assert [q.text for q in p if q.key == key] == [f"{key}: {declared[key].problem(value)}"], p.items
    own = cls.check({**required, key: value})
    own_keys = own.keys() if isinstance(own, Problems) else []
    assert key not in own_keys, own


def test_config_check_names_an_adapters_range_problem_by_its_full_key() -> None:
    raw = _node("vehicle", {"timeseries": {}, "survey": {}},
                inputs=[{"type": "nmea", "feeds": ["timeseries"], "udp": "0.0.0.0:10110", "baud": 0,
                         "variation": math.inf}],
                autonomy={"type": "sim", "speed": 0})
    p = _problems(raw)
    assert p.items == ["inputs[0].baud: 0 is outside 1..10000000 baud",
                       "inputs[0].variation: not a finite number, got inf",
                       "autonomy.speed: 0 is not above 0 m/s"], p.items
