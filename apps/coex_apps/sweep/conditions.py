"""A sweep's conditions and seeds.

A :class:`Condition` is one dive set-up: a scenario (a preset or a scenario file, with the
grid's overrides applied), the operator, and whether the dive is the short ``--quick`` one.
:func:`grid` expands presets and scenario files by a grid of overrides (Micromodem rate, loss
model and level, TDMA slots, number of vehicles, operator) into conditions, each named by what
it is. :func:`fresh_seeds` draws seeds from the operating system's randomness, never from the
development seeds (:data:`DEVELOPMENT_SEEDS`)."""

from __future__ import annotations

import hashlib
import itertools
import json
import secrets
from collections.abc import Container, Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from coex import ConfigError
from coex_apps.demo.config import OPERATORS
from coex_apps.demo.scenario import LOSS_MODELS, SLOT_OWNERS, Scenario, load_scenario, preset

__all__ = ["DEVELOPMENT_SEEDS", "SEED_LIMIT", "Condition", "Overrides", "fresh_seeds", "grid",
           "is_development_seed", "with_vehicles"]

#: Seeds used while developing the demo (its scenes, its operator, its eye and its referee):
#: never reported, so never drawn by a sweep. Every seed the project has developed on is below
#: 1000 (the reported sweeps' 1-8 among them, which later changes were also tried on, and the
#: development runs' 101 and up). The demo may declare its own set (``DEVELOPMENT_SEEDS`` in
#: :mod:`coex_apps.demo`); a seed in either is a development seed. 2000-2099: the navigation
#: work's (issue 56: drift, USBL fusion and map placement were measured and chosen on 2000-2015).
DEVELOPMENT_SEEDS: Container[int] = frozenset(range(0, 1000)) | frozenset(range(2000, 2100))
#: fresh seeds are drawn below this (31 bits: any seed the demo takes)
SEED_LIMIT = 2**31


def _demo_development_seeds() -> Container[int]:
    import coex_apps.demo as demo

    found: Container[int] = vars(demo).get("DEVELOPMENT_SEEDS", ())
    return found


def is_development_seed(seed: int) -> bool:
    """Whether ``seed`` is one the demo was developed on (this module's
    :data:`DEVELOPMENT_SEEDS`, or the demo's own declaration)."""
    return seed in DEVELOPMENT_SEEDS or seed in _demo_development_seeds()


def fresh_seeds(n: int, avoid: Iterable[int] = ()) -> list[int]:
    """``n`` distinct seeds drawn from the operating system's randomness (:mod:`secrets`),
    none a development seed nor in ``avoid``."""
    if n < 0:
        raise ConfigError(f"cannot draw {n} seeds")
    taken = set(avoid)
    out: list[int] = []
    while len(out) < n:
        s = secrets.randbelow(SEED_LIMIT)
        if s in taken or is_development_seed(s):
            continue
        taken.add(s)
        out.append(s)
    return out


@dataclass(frozen=True)
class Condition:
    """One condition of a sweep: every dive of it runs this scenario at its own seed."""

    #: the condition's name (a row's ``condition`` in dives.csv, a key of summary.json)
    name: str
    scenario: Scenario
    #: ``"script"`` (the scripted operator) or ``"none"``
    operator: str = "script"
    #: the demo's short dive (``coex demo --quick``: the site scaled to 96 m, 50 minutes)
    quick: bool = False

    def __post_init__(self) -> None:
        if not self.name or any(c in self.name for c in "\n\r"):
            raise ConfigError(f"a condition needs a one-line name, got {self.name!r}")
        if self.operator not in OPERATORS:
            raise ConfigError(f"operator must be one of {', '.join(OPERATORS)}, got {self.operator!r}")

    def describe(self) -> dict[str, Any]:
        """What the condition is, as JSON (summary.json, sweep.json)."""
        return {"scenario": self.scenario.to_dict(), "operator": self.operator, "quick": self.quick}

    def fingerprint(self) -> str:
        """A digest of :meth:`describe`: a resumed sweep checks that a condition of that name is
        still the same dive set-up."""
        text = json.dumps(self.describe(), sort_keys=True, default=str)
        return hashlib.blake2b(text.encode(), digest_size=8).hexdigest()


@dataclass(frozen=True)
class Overrides:
    """The grid: every combination of the values given is a condition (an empty axis keeps the
    scenario's own value)."""

    #: Micromodem packet rates (``modem.rate``)
    rate: Sequence[int] = ()
    #: loss models (``loss.model``: independent, gilbert-elliott, range)
    loss_model: Sequence[str] = ()
    #: loss levels (``loss.rate``: independent or mean burst loss, the floor of the range model)
    loss: Sequence[float] = ()
    #: TDMA cycles (``modem.slots``), each a sequence of slot owners
    slots: Sequence[Sequence[str]] = ()
    #: vehicles on the network: 1, or 2 (a mapping AUV and a camera vehicle, :func:`with_vehicles`)
    vehicles: Sequence[int] = ()
    #: who operates topside (``script`` or ``none``)
    operator: Sequence[str] = ()

    def check(self) -> None:
        for m in self.loss_model:
            if m not in LOSS_MODELS:
                raise ConfigError(f"loss model must be one of {', '.join(LOSS_MODELS)}, got {m!r}")
        for p in self.loss:
            if not 0.0 <= p < 1.0:
                raise ConfigError(f"loss must be in [0, 1), got {p}")
        for s in self.slots:
            bad = [o for o in s if o not in SLOT_OWNERS]
            if bad or not s:
                raise ConfigError(f"slots must list {', '.join(SLOT_OWNERS)} per slot, got {','.join(s)!r}")
        for v in self.vehicles:
            if v not in (1, 2):
                raise ConfigError(f"vehicles must be 1 or 2, got {v}")
        for o in self.operator:
            if o not in OPERATORS:
                raise ConfigError(f"operator must be one of {', '.join(OPERATORS)}, got {o!r}")


def with_vehicles(scenario: Scenario, vehicles: int) -> Scenario:
    """The scenario with one vehicle (every ``camera`` slot becomes the vehicle's) or two (a
    fleet dive: when the cycle has no ``camera`` slot, its second vehicle slot becomes the
    camera vehicle's; on the NUI cycle that is preset ``fleet``'s)."""
    slots = list(scenario.slots)
    if vehicles == 1:
        slots = ["vehicle" if s == "camera" else s for s in slots]
    elif vehicles == 2:
        if "camera" not in slots:
            mine = [i for i, s in enumerate(slots) if s == "vehicle"]
            if len(mine) < 2:
                raise ConfigError(f"two vehicles need two vehicle slots to share, got {','.join(slots)}")
            slots[mine[1]] = "camera"
    else:
        raise ConfigError(f"vehicles must be 1 or 2, got {vehicles}")
    return replace(scenario, slots=tuple(slots))


def _base(spec: str) -> tuple[str, Scenario]:
    """A preset name or a scenario file (a path ending in ``.toml``): its name and scenario."""
    if spec.endswith(".toml") or "/" in spec:
        path = Path(spec)
        return path.stem, load_scenario(path)
    return spec, preset(spec)


def grid(bases: Sequence[str], overrides: Overrides | None = None, *, quick: bool = False) -> list[Condition]:
    """Conditions: each base (a preset name, or a scenario file ``*.toml``) under every
    combination of the overrides. A condition's name is its base's, then each override axis
    that was given, ``key=value``, e.g. ``lowrate rate=1 loss=0.6 vehicles=2``."""
    ov = overrides or Overrides()
    ov.check()
    axes: list[tuple[str, Sequence[Any]]] = [
        (k, v) for k, v in (("rate", ov.rate), ("loss_model", ov.loss_model), ("loss", ov.loss),
                            ("slots", ov.slots), ("vehicles", ov.vehicles), ("operator", ov.operator)) if v]
    names = {"loss_model": "model"}
    out: list[Condition] = []
    for spec in bases:
        base_name, base = _base(spec)
        for combo in itertools.product(*(v for _, v in axes)):
            scn, operator, parts = base, "script", [base_name]
            for (key, _), value in zip(axes, combo, strict=True):
                if key == "rate":
                    scn = replace(scn, modem_rate=int(value))
                elif key == "loss_model":
                    scn = replace(scn, loss=replace(scn.loss, model=str(value)))
                elif key == "loss":
                    scn = replace(scn, loss=replace(scn.loss, rate=float(value)))
                elif key == "slots":
                    scn = replace(scn, slots=tuple(value))
                elif key == "vehicles":
                    scn = with_vehicles(scn, int(value))
                else:
                    operator = str(value)
                shown = ",".join(value) if key == "slots" else f"{value:g}" if isinstance(value, float) else str(value)
                parts.append(f"{names.get(key, key)}={shown}")
            out.append(Condition(" ".join(parts), scn, operator, quick))
    seen: set[str] = set()
    for c in out:
        if c.name in seen:
            raise ConfigError(f"condition {c.name!r} is given twice")
        seen.add(c.name)
    return out
