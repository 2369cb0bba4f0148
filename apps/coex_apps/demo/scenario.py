"""Demo scenarios: the site, the survey, the modem and the link of one simulated dive.

A scenario is a TOML file (``coex demo --scenario FILE.toml``) or a built-in preset
(``coex demo --preset NAME``, see :data:`PRESETS`). Every key is optional; an unknown key is a
:class:`~coex_core.errors.ConfigError` naming it. The keys (defaults are today's dive, preset
``default``)::

    name = "my-site"              # shown in the report and metrics.json
    area = 256.0                  # side of the square survey area (m); the site spans [0, area]
    water_depth = 500.0           # m
    duration = 7200.0             # length of the dive (s), descent to the end of the camera pass

    [survey]                      # the multibeam lawnmower survey
    altitude = 30.0               # m above the seafloor
    line_spacing = 0.0            # m between lines; 0 = 70 % of the swath width
    speed = 1.0                   # m/s

    [camera]
    altitude = 5.0                # m above the seafloor on the camera transects

    [seafloor]
    relief = 2.0                  # amplitude of the smooth relief (m)
    ripple_amplitude = 0.15       # sand ripples (m)
    random_targets = 2            # cars placed at random (when no [[targets]] are listed)
    random_decoys = 0             # car-sized rocks placed at random (when no [[decoys]] are listed)

    [[targets]]                   # true targets: cars (any number of these tables)
    x = 102.0                     # centre (m)
    y = 145.0
    length = 4.5                  # m (defaults: a car)
    width = 1.8
    height = 1.5
    heading = 30.0                # degrees clockwise from north

    [[decoys]]                    # objects that are not targets, e.g. car-sized rocks (same keys)
    x = 170.0
    y = 60.0

    [modem]
    rate = 5                      # Micromodem packet rate (0-6)
    slots = ["topside", "vehicle", "vehicle", "topside", "vehicle", "vehicle"]
                                  # "camera" slots make a fleet dive: a second vehicle (node 3)
                                  # with the camera; "vehicle" is then the mapping AUV (node 2)
    slot_seconds = 20.0
    guard_seconds = 2.0

    [loss]                        # frame loss on the acoustic link
    model = "independent"         # "independent", "gilbert-elliott" (bursts) or "range"
    rate = 0.3                    # independent / mean burst loss; floor of the range model
    mean_burst = 4.0              # gilbert-elliott: mean burst length in frames
    range_50 = 1000.0             # range: slant range (m) at which the range loss is half of range_max
    range_width = 200.0           # range: how fast the loss grows with range (m)
    range_max = 0.9               # range: loss at very long range

    [ship]                        # the topside modem, relative to the site's south-west corner (m)
    x = 128.0
    y = -200.0

    [navigation]                  # the vehicle's dead reckoning (issue 56, docs/navigation.md)
    drift = 0.005                 # 1-sigma bias, fraction of the distance travelled (0: perfect navigation)
    heading_bias = 0.5            # degrees: the vehicle's heading reads this much clockwise of the truth
    seed_offset = 2.0             # metres of error at the bottom (the descent has no bottom lock)
    aiding = false                # the vehicle takes topside's estimate as position fixes during its survey

    [usbl]                        # the ship's USBL fixes of the vehicle
    interval = 10.0               # seconds between fixes
    sigma = 0.01                  # 1-sigma horizontal error, fraction of the slant range
    outliers = 0.02               # fraction of fixes that are wild

``--seed`` places random targets and decoys and draws the losses; ``--loss`` and ``--burst``
override the loss model of the scenario.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from coex import ConfigError, Option, Problem, Problems
from coex_core.acoustic import RATES, GilbertElliott
from coex_plugins.bathymetry.sim import Target

__all__ = ["LossSpec", "ObjectSpec", "PRESETS", "Scenario", "load_scenario", "preset"]

LOSS_MODELS = ("independent", "gilbert-elliott", "range")
#: who a TDMA slot belongs to: topside, the vehicle (in a fleet: the mapping AUV) or, in a fleet
#: dive, the camera vehicle
SLOT_OWNERS = ("topside", "vehicle", "camera")


#: An object of the scenario: a car (``shape="box"``, the targets) or a boulder (``"dome"``, the
#: decoys), as the seafloor simulator takes it.
ObjectSpec = Target


#: a car-sized rock: about the footprint and height of a car, rounder, and the colour of the sand
ROCK: dict[str, Any] = {"length": 3.6, "width": 2.6, "height": 1.6, "shape": "dome"}


@dataclass(frozen=True)
class LossSpec:
    model: str = "independent"
    rate: float = 0.3
    mean_burst: float = 4.0
    range_50: float = 1000.0
    range_width: float = 200.0
    range_max: float = 0.9

    def describe(self) -> str:
        if self.model == "independent":
            return f"{self.rate:.0%} independent frame loss"
        if self.model == "gilbert-elliott":
            return f"{self.rate:.0%} bursty frame loss (Gilbert-Elliott, mean burst {self.mean_burst:g} frames)"
        return (f"range-dependent frame loss ({self.range_max:.0%} at long range, half of it at "
                f"{self.range_50:.0f} m; at least {self.rate:.0%})")

    def burst(self) -> GilbertElliott | None:
        """The burst model of ``gilbert-elliott``: a bad state losing every frame, a good state
        losing none, with the given mean loss and mean burst length."""
        if self.model != "gilbert-elliott":
            return None
        p_bg = 1.0 / self.mean_burst
        p_gb = self.rate * p_bg / max(1.0 - self.rate, 1e-6)
        return GilbertElliott(p_good_bad=min(p_gb, 1.0), p_bad_good=p_bg, loss_good=0.0, loss_bad=1.0)

    def independent(self) -> float:
        return self.rate if self.model in ("independent", "range") else 0.0

    def range_loss(self) -> Callable[[float], float] | None:
        if self.model != "range":
            return None
        mid, width, top = self.range_50, self.range_width, self.range_max

        def loss(distance: float) -> float:
            return top / (1.0 + math.exp(-(distance - mid) / width))
        return loss

    def mean_at(self, distance: float) -> float:
        """Mean frame loss at a slant range (for the report)."""
        rl = self.range_loss()
        if rl is None:
            return self.rate
        return 1.0 - (1.0 - self.independent()) * (1.0 - rl(distance))


@dataclass(frozen=True)
class Scenario:
    """One simulated dive (see the module docstring for the TOML keys)."""

    name: str = "default"
    area: float = 256.0
    water_depth: float = 500.0
    duration: float = 7200.0
    survey_altitude: float = 30.0
    line_spacing: float = 0.0
    survey_speed: float = 1.0
    camera_altitude: float = 5.0
    relief: float = 2.0
    ripple_amplitude: float = 0.15
    random_targets: int = 2
    random_decoys: int = 0
    targets: tuple[ObjectSpec, ...] = ()
    decoys: tuple[ObjectSpec, ...] = ()
    modem_rate: int = 5
    slots: tuple[str, ...] = ("topside", "vehicle", "vehicle", "topside", "vehicle", "vehicle")
    slot_seconds: float = 20.0
    guard_seconds: float = 2.0
    #: share of each vehicle packet spare traffic may fill (0: off; docs/channel.md)
    spare: float = 1.0
    loss: LossSpec = field(default_factory=LossSpec)
    ship: tuple[float, float] = (128.0, -200.0)
    #: issue 56: the vehicle's dead reckoning ([navigation]; drift 0: perfect navigation) and the
    #: ship's USBL ([usbl]); apps/coex_apps/demo/navigation.py, docs/navigation.md
    drift: float = 0.005
    heading_bias: float = 0.5
    seed_offset: float = 2.0
    #: the vehicle's navigation takes topside's estimate as position fixes during its survey
    #: (issue 56 follow-up; coex_apps.demo.navigation, docs/navigation.md "Aiding the vehicle")
    aiding: bool = False
    usbl_interval: float = 10.0
    usbl_sigma: float = 0.01
    usbl_outliers: float = 0.02

    def __post_init__(self) -> None:
        p = Problems()
        self.check(p)
        p.check()

    def check(self, p: Problems) -> None:
        """Every problem of the scenario's values, each with its key, into ``p``."""
        if not 16.0 <= self.area <= 4096.0:
            p.said("area", f"area must be 16-4096 m, got {self.area}")
        if not 10.0 <= self.water_depth <= 11000.0:
            p.said("water_depth", f"water_depth must be 10-11000 m, got {self.water_depth}")
        if not 600.0 <= self.duration <= 86400.0:
            p.said("duration", f"duration must be 600-86400 s, got {self.duration}")
        if not 2.0 <= self.survey_altitude <= 200.0:
            p.said("survey.altitude", f"survey.altitude must be 2-200 m, got {self.survey_altitude}")
        if self.line_spacing < 0:
            p.said("survey.line_spacing", "survey.line_spacing must be >= 0 (0: 70 % of the swath)")
        if not 0.2 <= self.survey_speed <= 5.0:
            p.said("survey.speed", f"survey.speed must be 0.2-5 m/s, got {self.survey_speed}")
        if not 1.0 <= self.camera_altitude <= 10.0:
            p.said("camera.altitude", f"camera.altitude must be 1-10 m, got {self.camera_altitude}")
        if not 0 <= self.random_targets <= 20 or not 0 <= self.random_decoys <= 20:
            p.said("seafloor.random_targets" if not 0 <= self.random_targets <= 20 else "seafloor.random_decoys",
                   "seafloor.random_targets and random_decoys must be 0-20")
        if self.modem_rate not in RATES:
            p.said("modem.rate", f"modem.rate must be one of {sorted(RATES)}, got {self.modem_rate}")
        if not self.slots or any(s not in SLOT_OWNERS for s in self.slots):
            p.said("modem.slots", f"modem.slots must list 'topside', 'vehicle' or 'camera' per slot, got {list(self.slots)}")
        elif "topside" not in self.slots or "vehicle" not in self.slots:
            p.said("modem.slots", "modem.slots needs at least one topside and one vehicle slot")
        if not 0.0 <= self.spare <= 1.0:
            p.said("modem.spare", f"modem.spare must be in [0, 1] (a share of each packet), got {self.spare}")
        if not 0.0 <= self.guard_seconds < self.slot_seconds:
            p.said("modem.guard_seconds", "modem.guard_seconds must be >= 0 and below modem.slot_seconds")
        elif self.modem_rate in RATES:
            packet = RATES[self.modem_rate].packet_airtime()
            if packet > self.slot_seconds - self.guard_seconds:
                p.said("modem.slot_seconds", f"a rate-{self.modem_rate} packet lasts {packet:.1f} s: "
                                             "modem.slot_seconds minus guard_seconds must be at least that")
        for key, v, lo, hi in (("navigation.drift", self.drift, 0.0, 0.1),
                               ("navigation.heading_bias", self.heading_bias, -10.0, 10.0),
                               ("navigation.seed_offset", self.seed_offset, 0.0, 100.0),
                               ("usbl.interval", self.usbl_interval, 1.0, 600.0),
                               ("usbl.sigma", self.usbl_sigma, 0.0, 0.1), ("usbl.outliers", self.usbl_outliers, 0.0, 0.5)):
            if not lo <= v <= hi:
                p.said(key, f"{key} must be {lo:g}-{hi:g}, got {v}")
        if self.loss.model not in LOSS_MODELS:
            p.said("loss.model", f"loss.model must be one of {', '.join(LOSS_MODELS)}, got {self.loss.model!r}")
        if not 0.0 <= self.loss.rate < 1.0:
            p.said("loss.rate", f"loss.rate must be in [0, 1), got {self.loss.rate}")
        if self.loss.mean_burst < 1.0:
            p.said("loss.mean_burst", "loss.mean_burst must be at least 1 frame")
        if self.loss.range_width <= 0 or not 0.0 <= self.loss.range_max <= 1.0:
            p.said("loss.range_width" if self.loss.range_width <= 0 else "loss.range_max",
                   "loss.range_width must be positive and loss.range_max in [0, 1]")
        for kind, objs in (("targets", self.targets), ("decoys", self.decoys)):
            for i, o in enumerate(objs):
                if not (0.0 <= o.x <= self.area and 0.0 <= o.y <= self.area):
                    p.said(f"{kind}[{i}]", f"{kind}: ({o.x}, {o.y}) is outside the area [0, {self.area}]")
                if not (0.5 <= o.length <= 30 and 0.5 <= o.width <= 30 and 0.2 <= o.height <= 10):
                    p.said(f"{kind}[{i}]", f"{kind}: size {o.length} x {o.width} x {o.height} m is not a "
                                           "plausible object")

    # ------------------------------------------------------------------ derived
    @property
    def fleet(self) -> bool:
        """A fleet dive (issue 43): the schedule gives slots to a camera vehicle too."""
        return "camera" in self.slots

    @property
    def cycle(self) -> float:
        """Length of one TDMA cycle (s)."""
        return self.slot_seconds * len(self.slots)

    def place(self, seed: int) -> tuple[tuple[ObjectSpec, ...], tuple[ObjectSpec, ...]]:
        """Targets and decoys: the listed ones, or random ones (the seed places them) well inside
        the area and apart from each other."""
        rng = np.random.default_rng([seed, 1])
        targets = [replace(o, shape="box") for o in self.targets]
        decoys = [replace(o, shape="dome") for o in self.decoys]  # boulders, whatever was given
        margin = 0.2 * self.area
        min_gap = 0.25 * self.area if self.random_targets + self.random_decoys <= 3 else 0.12 * self.area

        def free(x: float, y: float) -> bool:
            return all(math.hypot(x - o.x, y - o.y) > min_gap for o in targets + decoys)

        def draw() -> tuple[float, float]:
            for _ in range(1000):
                x, y = rng.uniform(margin, self.area - margin, 2)
                if free(x, y):
                    return float(round(x, 1)), float(round(y, 1))
            raise ConfigError("cannot place the random targets and decoys apart from each other; "
                              "use fewer or a larger area")
        if not self.targets:
            for _ in range(self.random_targets):
                x, y = draw()
                targets.append(ObjectSpec(x, y, heading=float(round(rng.uniform(-90, 90), 1))))
        if not self.decoys:
            for _ in range(self.random_decoys):
                x, y = draw()
                decoys.append(ObjectSpec(x, y, **ROCK, heading=float(round(rng.uniform(-90, 90), 1))))
        return tuple(targets), tuple(decoys)

    def quick(self) -> Scenario:
        """The short scenario of ``--quick`` (tests): the same site scaled to 96 m, a 50-minute dive."""
        f = 96.0 / self.area

        def scale(objs: tuple[ObjectSpec, ...]) -> tuple[ObjectSpec, ...]:
            return tuple(replace(o, x=round(o.x * f, 1), y=round(o.y * f, 1)) for o in objs)
        return replace(self, area=96.0, duration=min(self.duration, 3000.0), targets=scale(self.targets),
                       decoys=scale(self.decoys), ship=(self.ship[0] * f, self.ship[1] * f)
                       if self.loss.model != "range" else self.ship)

    def with_loss(self, loss: float | None, burst: bool) -> Scenario:
        """The scenario with ``--loss``/``--burst`` applied (``None``/``False``: as it is)."""
        if loss is None and not burst:
            return self
        rate = self.loss.rate if loss is None else float(loss)
        model = "gilbert-elliott" if burst else "independent"
        return replace(self, loss=replace(self.loss, model=model, rate=rate))

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["slots"] = list(self.slots)
        d["ship"] = {"x": self.ship[0], "y": self.ship[1]}
        d["targets"] = [asdict(o) for o in self.targets]
        d["decoys"] = [asdict(o) for o in self.decoys]
        d["loss_description"] = self.loss.describe()
        return d


# ---------------------------------------------------------------------------- loading

_TOP = {"name", "area", "water_depth", "duration", "survey", "camera", "seafloor", "targets", "decoys",
        "modem", "loss", "ship", "navigation", "usbl"}
_SECTIONS: dict[str, dict[str, str]] = {
    "survey": {"altitude": "survey_altitude", "line_spacing": "line_spacing", "speed": "survey_speed"},
    "camera": {"altitude": "camera_altitude"},
    "seafloor": {"relief": "relief", "ripple_amplitude": "ripple_amplitude", "random_targets": "random_targets",
                 "random_decoys": "random_decoys"},
    "modem": {"rate": "modem_rate", "slots": "slots", "slot_seconds": "slot_seconds",
              "guard_seconds": "guard_seconds", "spare": "spare"},
    "navigation": {"drift": "drift", "heading_bias": "heading_bias", "seed_offset": "seed_offset",
                   "aiding": "aiding"},
    "usbl": {"interval": "usbl_interval", "sigma": "usbl_sigma", "outliers": "usbl_outliers"},
}
_OBJECT_KEYS = {"x", "y", "length", "width", "height", "heading"}
_LOSS_KEYS = {"model", "rate", "mean_burst", "range_50", "range_width", "range_max"}


_NOT_GIVEN = object()


def _number(p: Problems, where: str, v: Any, kind: type = float) -> Any:
    """``v`` as a number (``kind`` int: an integer), checked by the core's option schema (NaN,
    infinities, booleans and words refused); a problem of ``where`` and ``_NOT_GIVEN`` when it
    is not one."""
    return Option("integer" if kind is int else "number", None).checked(p, where, v, _NOT_GIVEN)


def _unknown(p: Problems, where: str, got: Mapping[str, Any], known: set[str] | Mapping[str, Any]) -> None:
    p.unknown(got, tuple(known), where)


def _table(p: Problems, data: Mapping[str, Any], section: str) -> Mapping[str, Any] | None:
    return p.table(data[section], section) if section in data else None


def scenario_from_dict(data: Mapping[str, Any], base: Scenario | None = None) -> Scenario:
    """A :class:`Scenario` from the TOML structure, on top of ``base`` (default: preset
    ``default``). :class:`ConfigError` lists every problem, each with its key."""
    p = Problems()
    _unknown(p, "", data, _TOP)
    kw: dict[str, Any] = {}
    ints = {"random_targets", "random_decoys", "modem_rate"}

    def put(attr: str, value: Any) -> None:
        if value is not _NOT_GIVEN:
            kw[attr] = value
    for key in ("area", "water_depth", "duration"):
        if key in data:
            put(key, _number(p, key, data[key]))
    if "name" in data:
        if not isinstance(data["name"], str) or not data["name"]:
            p.said("name", "name must be a non-empty string")
        else:
            kw["name"] = data["name"]
    for section, keys in _SECTIONS.items():
        sec = _table(p, data, section)
        if sec is None:
            continue
        _unknown(p, section, sec, keys)
        for k, attr in keys.items():
            if k not in sec:
                continue
            if attr == "slots":
                if not isinstance(sec[k], list) or not all(isinstance(s, str) for s in sec[k]):
                    p.said("modem.slots", "modem.slots must be a list of 'topside' / 'vehicle' / 'camera'")
                else:
                    kw[attr] = tuple(sec[k])
            elif attr == "aiding":
                if not isinstance(sec[k], bool):
                    p.said("navigation.aiding", "navigation.aiding must be true or false")
                else:
                    kw[attr] = sec[k]
            else:
                put(attr, _number(p, f"{section}.{k}", sec[k], int if attr in ints else float))
    for kind in ("targets", "decoys"):
        if kind not in data:
            continue
        items = data[kind]
        if not isinstance(items, list):
            p.said(kind, f"[[{kind}]] must be an array of tables")
            continue
        objs = []
        for i, item in enumerate(items):
            if not isinstance(item, Mapping):
                p.said(f"{kind}[{i}]", f"{kind}[{i}] must be a table")
                continue
            before = len(p)
            _unknown(p, f"{kind}[{i}]", item, _OBJECT_KEYS)
            if "x" not in item or "y" not in item:
                p.said(f"{kind}[{i}]", f"{kind}[{i}] needs x and y")
            values = {k: _number(p, f"{kind}[{i}].{k}", v) for k, v in item.items() if k in _OBJECT_KEYS}
            if len(p) == before:
                defaults = ROCK if kind == "decoys" else {}
                objs.append(ObjectSpec(**{**defaults, **values}))
        kw[kind] = tuple(objs)
    base = base or Scenario()
    sec = _table(p, data, "loss")
    if sec is not None:
        _unknown(p, "loss", sec, _LOSS_KEYS)
        lk = {k: (v if k == "model" else _number(p, f"loss.{k}", v)) for k, v in sec.items() if k in _LOSS_KEYS}
        kw["loss"] = replace(base.loss, **{k: v for k, v in lk.items() if v is not _NOT_GIVEN})
    sec = _table(p, data, "ship")
    if sec is not None:
        _unknown(p, "ship", sec, {"x", "y"})
        x, y = (_number(p, f"ship.{k}", sec.get(k, d)) for k, d in zip("xy", base.ship, strict=True))
        if x is not _NOT_GIVEN and y is not _NOT_GIVEN:
            kw["ship"] = (x, y)
    try:
        scenario = replace(base, **kw)
    except ConfigError as exc:  # the values' ranges: every one, with the problems above
        p.merge(exc.problems or [Problem("", str(exc))])
        raise p.error() from None
    p.check()
    return scenario


def load_scenario(path: str | Path) -> Scenario:
    """Read a scenario TOML file (unknown keys and bad values: :class:`ConfigError`)."""
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text())
    except OSError as exc:
        raise ConfigError(f"cannot read scenario {p}: {exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"scenario {p} is not valid TOML: {exc}") from exc
    if "name" not in data:
        data["name"] = p.stem
    return scenario_from_dict(data)


#: The built-in presets (``coex demo --preset NAME``).
PRESETS: dict[str, dict[str, Any]] = {
    # today's dive: the ship 200 m south of the site, 30 % independent frame loss
    "default": {"name": "default"},
    # NUI dive 040: the ship about 1.5 water depths (750 m) from the site, where the acoustics were
    # poor; the loss grows with slant range (about 35 % over the near edge of the site, 50 % over
    # the far edge)
    "dive040": {"name": "dive040", "ship": {"x": 128.0, "y": -750.0},
                "loss": {"model": "range", "rate": 0.05, "range_50": 1000.0, "range_width": 220.0,
                         "range_max": 0.85}},
    # a lower Micromodem rate (rate 3: two 256-byte frames a packet) and bursty loss
    "harsh": {"name": "harsh", "modem": {"rate": 3},
              "loss": {"model": "gilbert-elliott", "rate": 0.4, "mean_burst": 6.0}},
    # deep water and long range: Micromodem rate 1 (three 64-byte frames a packet, about 32 B/s
    # of vehicle slots) with the ship far from the site; range-dependent loss of about 40 % over
    # the near edge of the site, 50 % over its centre and 57 % over the far edge (about 14 B/s
    # delivered when the vehicle's packets are full)
    "lowrate": {"name": "lowrate", "water_depth": 1000.0, "modem": {"rate": 1},
                "ship": {"x": 128.0, "y": -1200.0},
                "loss": {"model": "range", "rate": 0.05, "range_50": 1620.0, "range_width": 250.0,
                         "range_max": 0.9}},
    # issue 43: a mapping AUV (node 2) and a camera vehicle (node 3) in one dive over the default
    # seafloor, three nodes on one acoustic network: the mapper keeps three slots of the NUI cycle,
    # the camera vehicle takes the fourth; the operator sends the camera to the candidates of the
    # mapper's received 1 m map while the survey runs
    "fleet": {"name": "fleet", "modem": {"slots": ["topside", "vehicle", "camera", "topside", "vehicle", "vehicle"]}},
}


def preset(name: str) -> Scenario:
    try:
        data = PRESETS[name]
    except KeyError:
        raise ConfigError(f"unknown preset {name!r}; known: {', '.join(PRESETS)}") from None
    return scenario_from_dict(data)
