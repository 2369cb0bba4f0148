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
    random_targets = 2            # targets placed at random (when no [[targets]] are listed)
    random_decoys = 0             # decoys placed at random (when no [[decoys]] are listed)
    target_kinds = ["car", "container", "hull", "debris"]   # what a random target can be
    target_length = [2.0, 8.0]    # m: a random target's length is drawn in its kind's range and this one
    decoy_kinds = ["rock", "dark rock", "biology"]          # what a random decoy can be

    [[targets]]                   # true targets (any number of these tables)
    kind = "car"                  # car, container, hull or debris (default car)
    x = 102.0                     # centre (m)
    y = 145.0
    length = 4.5                  # m (defaults: the kind's nominal size, KINDS)
    width = 1.8
    height = 1.5
    heading = 30.0                # degrees clockwise from north
    albedo = 0.07                 # reflectance of its top (default: the kind's)

    [[decoys]]                    # objects that are not targets (same keys; kind rock, dark rock
    x = 170.0                     # or biology, default rock)
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

__all__ = ["DECOY_KINDS", "KINDS", "TARGET_KINDS", "Kind", "LossSpec", "ObjectSpec", "PRESETS", "Scenario",
           "draw_object", "load_scenario", "preset"]

LOSS_MODELS = ("independent", "gilbert-elliott", "range")
#: who a TDMA slot belongs to: topside, the vehicle (in a fleet: the mapping AUV) or, in a fleet
#: dive, the camera vehicle
SLOT_OWNERS = ("topside", "vehicle", "camera")


#: An object of the scenario (a target or a decoy), as the seafloor simulator takes it: its
#: ``kind`` and ``shape`` (:data:`KINDS`), size, heading and ``albedo``.
ObjectSpec = Target


@dataclass(frozen=True)
class Kind:
    """What an object of one kind is like in the simulated world: its shape on the seafloor,
    its nominal size (a listed object's defaults), and the ranges a random one is drawn from
    (length in m; width and height in m, or as shares of the length with ``*_of_length``; the
    albedo of its top, ``None``: the sand's own colour). A target kind is man-made."""

    shape: str
    target: bool
    nominal: tuple[float, float, float]
    length: tuple[float, float]
    width: tuple[float, float]
    height: tuple[float, float]
    albedo: tuple[float, float] | None
    width_of_length: bool = False


#: The kinds of objects a scenario can hold. Targets: cars (from a small city car to a large
#: saloon, dark to pale paint), a 20-ft container (6.06 x 2.44 x 2.59 m), a small boat's hull
#: (4-8 m) and a patch of debris (2-5 m); decoys: a boulder of the sand's colour, a dark boulder
#: (basalt, as dark as a car) and a dark mound of living things.
KINDS: dict[str, Kind] = {
    "car": Kind("box", True, (4.5, 1.8, 1.5), (2.6, 5.2), (1.5, 1.95), (1.2, 1.8), (0.05, 0.45)),
    "container": Kind("box", True, (6.06, 2.44, 2.59), (6.06, 6.06), (2.44, 2.44), (2.59, 2.59), (0.12, 0.30)),
    "hull": Kind("hull", True, (6.0, 2.1, 1.3), (4.0, 8.0), (0.28, 0.38), (1.0, 1.6), (0.20, 0.45), True),
    "debris": Kind("debris", True, (3.5, 2.6, 1.1), (2.0, 5.0), (0.6, 0.9), (0.9, 1.3), (0.05, 0.35), True),
    "rock": Kind("dome", False, (3.6, 2.6, 1.6), (2.0, 5.0), (0.55, 0.9), (1.0, 2.0), None, True),
    "dark rock": Kind("dome", False, (3.6, 2.6, 1.6), (2.0, 5.0), (0.55, 0.9), (1.0, 2.0), (0.06, 0.15), True),
    "biology": Kind("mound", False, (3.2, 2.4, 1.1), (2.0, 4.5), (0.6, 0.9), (0.8, 1.4), (0.06, 0.14), True),
}
TARGET_KINDS = tuple(k for k, v in KINDS.items() if v.target)
DECOY_KINDS = tuple(k for k, v in KINDS.items() if not v.target)

#: a car-sized rock: about the footprint and height of a car, rounder, and the colour of the sand
ROCK: dict[str, Any] = {"length": 3.6, "width": 2.6, "height": 1.6, "shape": "dome", "kind": "rock"}


def draw_object(kind: str, rng: np.random.Generator, x: float, y: float,
                length: tuple[float, float] = (0.0, math.inf)) -> ObjectSpec:
    """A random object of ``kind`` at (x, y): its length drawn in the kind's range and
    ``length``, its width, height, albedo and heading in theirs."""
    k = KINDS[kind]
    lo, hi = max(k.length[0], length[0]), min(k.length[1], length[1])
    ln = float(rng.uniform(lo, hi)) if hi > lo else lo
    wd = float(rng.uniform(*k.width)) * (ln if k.width_of_length else 1.0)
    ht = float(rng.uniform(*k.height))
    alb = None if k.albedo is None else round(float(rng.uniform(*k.albedo)), 3)
    heading = float(round(rng.uniform(-90, 90), 1))
    return ObjectSpec(x, y, round(ln, 2), round(min(wd, ln), 2), round(ht, 2), heading, k.shape, kind, alb)


def listed_object(values: Mapping[str, Any], decoy: bool) -> ObjectSpec:
    """A listed ``[[targets]]`` or ``[[decoys]]`` table as an object: its kind's shape and
    nominal size unless it gives its own."""
    kind = str(values.get("kind", "rock" if decoy else "car"))
    k = KINDS[kind]
    length, width, height = k.nominal
    return ObjectSpec(**{"length": length, "width": width, "height": height, "shape": k.shape,
                         **{key: v for key, v in values.items()}, "kind": kind})


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
    #: what random targets and decoys are drawn from (:data:`KINDS`), and the random targets'
    #: length range (m)
    target_kinds: tuple[str, ...] = TARGET_KINDS
    target_length: tuple[float, float] = (2.0, 8.0)
    decoy_kinds: tuple[str, ...] = DECOY_KINDS
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
        if not self.target_kinds or any(k not in TARGET_KINDS for k in self.target_kinds):
            p.said("seafloor.target_kinds", f"seafloor.target_kinds must list kinds of {', '.join(TARGET_KINDS)}, "
                                            f"got {list(self.target_kinds)}")
        elif not (len(self.target_length) == 2 and 0.5 <= self.target_length[0] <= self.target_length[1] <= 30.0):
            p.said("seafloor.target_length", f"seafloor.target_length must be [min, max] in 0.5-30 m, got "
                                             f"{list(self.target_length)}")
        else:
            lo, hi = self.target_length
            empty = [k for k in self.target_kinds if KINDS[k].length[0] > hi or KINDS[k].length[1] < lo]
            if empty:
                p.said("seafloor.target_length", f"no {', '.join(empty)} is {lo:g}-{hi:g} m long "
                                                 f"(their lengths: {', '.join(f'{k} {KINDS[k].length[0]:g}-{KINDS[k].length[1]:g} m' for k in empty)})")
        if not self.decoy_kinds or any(k not in DECOY_KINDS for k in self.decoy_kinds):
            p.said("seafloor.decoy_kinds", f"seafloor.decoy_kinds must list kinds of {', '.join(DECOY_KINDS)}, "
                                           f"got {list(self.decoy_kinds)}")
        for kind, objs in (("targets", self.targets), ("decoys", self.decoys)):
            for i, o in enumerate(objs):
                if o.kind not in (TARGET_KINDS if kind == "targets" else DECOY_KINDS):
                    p.said(f"{kind}[{i}]", f"{kind}[{i}].kind must be one of "
                                           f"{', '.join(TARGET_KINDS if kind == 'targets' else DECOY_KINDS)}, got {o.kind!r}")
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
        # each listed object takes its kind's shape
        targets = [replace(o, shape=KINDS[o.kind].shape) for o in self.targets]
        decoys = [replace(o, shape=KINDS[o.kind].shape) for o in self.decoys]
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
                kind = str(rng.choice(list(self.target_kinds)))
                targets.append(draw_object(kind, rng, x, y, self.target_length))
        if not self.decoys:
            for _ in range(self.random_decoys):
                x, y = draw()
                decoys.append(draw_object(str(rng.choice(list(self.decoy_kinds))), rng, x, y))
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
        d["target_kinds"], d["decoy_kinds"] = list(self.target_kinds), list(self.decoy_kinds)
        d["target_length"] = list(self.target_length)
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
                 "random_decoys": "random_decoys", "target_kinds": "target_kinds", "target_length": "target_length",
                 "decoy_kinds": "decoy_kinds"},
    "modem": {"rate": "modem_rate", "slots": "slots", "slot_seconds": "slot_seconds",
              "guard_seconds": "guard_seconds", "spare": "spare"},
    "navigation": {"drift": "drift", "heading_bias": "heading_bias", "seed_offset": "seed_offset",
                   "aiding": "aiding"},
    "usbl": {"interval": "usbl_interval", "sigma": "usbl_sigma", "outliers": "usbl_outliers"},
}
_OBJECT_KEYS = {"kind", "x", "y", "length", "width", "height", "heading", "albedo"}
#: scenario keys that are lists of kinds
_KIND_LISTS = {"target_kinds", "decoy_kinds"}
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
    for key in ("area", "water_depth", "duration"):
        if key in data:
            _put(kw, key, _number(p, key, data[key]))
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
            if k in sec:
                _section_value(p, f"{section}.{k}", attr, sec[k], kw)
    for kind in ("targets", "decoys"):
        if kind in data:
            objs = _objects(p, kind, data[kind])
            if objs is not None:
                kw[kind] = objs
    base = base or Scenario()
    _loss_and_ship(p, data, base, kw)
    try:
        scenario = replace(base, **kw)
    except ConfigError as exc:  # the values' ranges: every one, with the problems above
        p.merge(exc.problems or [Problem("", str(exc))])
        raise p.error() from None
    p.check()
    return scenario


#: scenario attributes that are integers
_INTS = {"random_targets", "random_decoys", "modem_rate"}


def _put(kw: dict[str, Any], attr: str, value: Any) -> None:
    if value is not _NOT_GIVEN:
        kw[attr] = value


def _section_value(p: Problems, key: str, attr: str, value: Any, kw: dict[str, Any]) -> None:
    """One key of a section (``modem.slots``, ``site.area`` ...) into the attribute ``attr``."""
    if attr == "slots":
        if not isinstance(value, list) or not all(isinstance(s, str) for s in value):
            p.said("modem.slots", "modem.slots must be a list of 'topside' / 'vehicle' / 'camera'")
        else:
            kw[attr] = tuple(value)
    elif attr == "aiding":
        if not isinstance(value, bool):
            p.said("navigation.aiding", "navigation.aiding must be true or false")
        else:
            kw[attr] = value
    elif attr in _KIND_LISTS:
        if not isinstance(value, list) or not all(isinstance(s, str) for s in value):
            p.said(key, f"{key} must be a list of kinds (strings)")
        else:
            kw[attr] = tuple(value)
    elif attr == "target_length":
        if not isinstance(value, list) or len(value) != 2:
            p.said(key, f"{key} must be [min, max] (m)")
        else:
            pair = [_number(p, key, v) for v in value]
            if _NOT_GIVEN not in pair:
                kw[attr] = (pair[0], pair[1])
    else:
        _put(kw, attr, _number(p, key, value, int if attr in _INTS else float))


def _objects(p: Problems, kind: str, items: Any) -> tuple[ObjectSpec, ...] | None:
    """``[[targets]]`` or ``[[decoys]]`` placed by hand (None: not a list)."""
    if not isinstance(items, list):
        p.said(kind, f"[[{kind}]] must be an array of tables")
        return None
    objs = []
    for i, item in enumerate(items):
        if not isinstance(item, Mapping):
            p.said(f"{kind}[{i}]", f"{kind}[{i}] must be a table")
            continue
        before = len(p)
        _unknown(p, f"{kind}[{i}]", item, _OBJECT_KEYS)
        if "x" not in item or "y" not in item:
            p.said(f"{kind}[{i}]", f"{kind}[{i}] needs x and y")
        values = {k: _number(p, f"{kind}[{i}].{k}", v) for k, v in item.items()
                  if k in _OBJECT_KEYS and k != "kind"}
        if "kind" in item:
            allowed = TARGET_KINDS if kind == "targets" else DECOY_KINDS
            if item["kind"] not in allowed:
                p.said(f"{kind}[{i}].kind", f"{kind}[{i}].kind must be one of {', '.join(allowed)}, "
                                            f"got {item['kind']!r}")
            else:
                values["kind"] = item["kind"]
        if len(p) == before:
            objs.append(listed_object(values, kind == "decoys"))
    return tuple(objs)


def _loss_and_ship(p: Problems, data: Mapping[str, Any], base: Scenario, kw: dict[str, Any]) -> None:
    """The ``[loss]`` table (on top of ``base``'s loss model) and the ship's position."""
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
    # issue 50: a site with a 20-ft container, a 7 m boat hull and a small car (the kinds and sizes
    # the car-only demo could not see), on the default dive's link
    "container-hull-car": {
        "name": "container-hull-car",
        "targets": [{"kind": "container", "x": 90.0, "y": 170.0, "heading": 35.0},
                    {"kind": "hull", "x": 172.0, "y": 92.0, "length": 7.0, "width": 2.3, "height": 1.4, "heading": -60.0},
                    {"kind": "car", "x": 70.0, "y": 68.0, "length": 3.0, "width": 1.6, "height": 1.4, "heading": 10.0,
                     "albedo": 0.3}]},
}


def preset(name: str) -> Scenario:
    try:
        data = PRESETS[name]
    except KeyError:
        raise ConfigError(f"unknown preset {name!r}; known: {', '.join(PRESETS)}") from None
    return scenario_from_dict(data)
