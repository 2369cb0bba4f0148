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
    assert p.items == ["boat.colour: unknown key (known: size, speed)", "boat.speed: a number, got 'x'",
                       "boat.size: 99 is outside 1..10", "a boat needs a crew", "engine: no fuel", "engine: no oil"]
    assert p.warnings == [f"log: {tmp_path / 'nothere'} does not exist now (written at the end)"]
    with pytest.raises(ConfigError) as err:
        p.check("boat.toml")
    assert str(err.value).startswith("boat.toml: 6 problems:\n  boat.colour: unknown key")
    assert [x.key for x in err.value.problems] == p.keys()
    one = Problems()
    one.add("crew", "missing")
    assert str(one.error("boat.toml")) == "boat.toml: crew: missing"


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
