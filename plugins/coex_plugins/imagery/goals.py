"""Transfer goals: how much of an image's body the sender delivers."""

from __future__ import annotations

import math
from dataclasses import dataclass

from coex import ConfigError, persistent
from coex.messages import RegionGoal

from .codec import Encoded

__all__ = ["Goal", "parse_goal", "region_fields"]


@persistent("imagery.Goal")
@dataclass(frozen=True)
class Goal:
    """``kind`` is ``"none"``, ``"bytes"``, ``"fraction"`` (value in percent), ``"layer"`` or ``"full"``."""

    kind: str
    value: int = 0

    def bytes_for(self, enc: Encoded) -> int:
        """Body bytes this goal asks for, rounded up to a whole packet."""
        total = len(enc.body)
        if self.kind == "none":
            return 0
        if self.kind == "full":
            return total
        if self.kind == "layer":
            return enc.layer_end(self.value)
        want = self.value if self.kind == "bytes" else math.ceil(total * self.value / 100)
        want = min(max(want, 0), total)
        if want <= 0:
            return 0
        # round up to the end of the packet holding byte want - 1
        import numpy as np

        idx = int(np.searchsorted(enc.packet_starts, want - 1, side="right")) - 1
        return int(enc.packet_starts[idx + 1]) if idx + 1 < len(enc.packet_starts) else total


def parse_goal(text: str | Goal) -> Goal:
    """Parse ``"none"``, ``"full"``, ``"layer:N"``, ``"fraction:P"`` or ``"bytes:N"``."""
    if isinstance(text, Goal):
        return text
    t = str(text).strip().lower()
    if t in ("none", "full"):
        return Goal(t)
    kind, _, value = t.partition(":")
    if kind not in ("layer", "fraction", "bytes") or not value:
        raise ConfigError(f"goal must be none, full, layer:N, fraction:P or bytes:N; got {text!r}")
    try:
        v = int(value)
    except ValueError:
        raise ConfigError(f"goal value must be an integer: {text!r}") from None
    if v < 0 or (kind == "fraction" and v > 100) or (kind == "layer" and not 1 <= v <= 32):
        raise ConfigError(f"goal value out of range: {text!r}")
    return Goal(kind, v)


def region_fields(corners: tuple[float, float, float, float], kind: RegionGoal | str, value: float,
                  width: int, height: int, layers: int, precincts: int) -> tuple[tuple[int, int, int, int],
                                                                                   RegionGoal, int]:
    """The fields of an ``ImageRegionRequest`` for a rectangle and a goal on an image of
    ``width x height`` with ``layers`` quality layers: the box (x0, y0, x1, y1), x1 and y1
    exclusive, from corners in any order, rounded to pixels), the goal kind and its wire value
    (quality in 0.1 dB). Raises :class:`ConfigError`, in words an operator reads, for an image
    coded without precincts, corners that are not finite, an empty box or one outside the
    image, an unknown goal or a value outside its range (quality 10..60 dB, layers 1..``layers``,
    bytes 1..65535)."""
    if not precincts:
        raise ConfigError("coded without precincts: a region cannot be sent on its own; "
                          "ask for more of the whole image")
    vals = [float(v) for v in corners]
    if not all(math.isfinite(v) for v in vals):
        raise ConfigError("region corners must be finite numbers")
    (x0, x1), (y0, y1) = sorted(vals[0::2]), sorted(vals[1::2])
    bx0, by0, bx1, by1 = (round(v) for v in (x0, y0, x1, y1))
    if bx1 <= bx0 or by1 <= by0:
        raise ConfigError("the region is empty: drag a rectangle over the image")
    if bx0 < 0 or by0 < 0 or bx1 > width or by1 > height:
        raise ConfigError(f"region {bx0}..{bx1} x {by0}..{by1} is outside the {width} x {height} image")
    if isinstance(kind, RegionGoal):
        goal = kind
    else:
        name = {"layers": "layer"}.get(str(kind).lower(), str(kind).lower())
        if name not in ("quality", "layer", "bytes"):
            raise ConfigError(f"unknown region goal {kind!r} (quality, layer or bytes)")
        goal = RegionGoal[name.upper()]
    v = float(value)
    if not math.isfinite(v):
        raise ConfigError("the region's goal must be a finite number")
    if goal == RegionGoal.QUALITY:
        if not 10.0 <= v <= 60.0:
            raise ConfigError(f"a region quality of {v:g} dB is outside 10..60 dB")
        return (bx0, by0, bx1, by1), goal, round(v * 10)
    if goal == RegionGoal.LAYER:
        if v != int(v) or not 1 <= v <= layers:
            raise ConfigError(f"a region goal of {v:g} layers is outside 1..{layers}")
    elif v != int(v) or not 1 <= v <= 65535:
        raise ConfigError(f"a region budget of {v:g} bytes is outside 1..65535")
    return (bx0, by0, bx1, by1), goal, int(v)
