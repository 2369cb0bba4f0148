"""Compact timestamps ("stamps") and their rollover rule.

A stamp is whole seconds modulo 2^18 (262,144 s, about 72.8 h). The receiver unwraps a stamp to
the absolute time nearest its own ``now``; this is unambiguous while clocks agree to within
half the period (36.4 h). Absolute times are float seconds on the system's clock (POSIX time, or a
simulated clock in replays).
"""

from __future__ import annotations

from ._wire._primitives import STAMP_BITS, STAMP_MODULUS

__all__ = ["STAMP_BITS", "STAMP_MODULUS", "to_stamp", "unwrap"]


def to_stamp(t: float) -> int:
    """The stamp of absolute time ``t`` (floor to whole seconds, modulo 2^18)."""
    return int(t // 1) % STAMP_MODULUS


def unwrap(stamp: int, now: float) -> float:
    """The absolute time nearest ``now`` whose stamp is ``stamp``."""
    base = now - (now % STAMP_MODULUS)
    candidates = (base - STAMP_MODULUS + stamp, base + stamp, base + STAMP_MODULUS + stamp)
    return float(min(candidates, key=lambda c: abs(c - now)))
