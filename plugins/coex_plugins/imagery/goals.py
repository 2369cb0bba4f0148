"""Transfer goals: how much of an image's body the sender delivers."""

from __future__ import annotations

import math
from dataclasses import dataclass

from coex_core.errors import ConfigError
from coex_core.state import persistent

from .codec import Encoded

__all__ = ["Goal", "parse_goal"]


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
