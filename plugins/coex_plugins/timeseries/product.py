"""The time-series receiver's product: a channel as topside holds it."""

from __future__ import annotations

from dataclasses import dataclass

from coex import TypedProduct

__all__ = ["SeriesProduct"]


@dataclass(frozen=True, kw_only=True)
class SeriesProduct(TypedProduct):
    """A channel (kind ``series``, key its name). ``data``: its :class:`~.receiver.Series`
    (times, values, error bounds)."""

    channel: int
    name: str
    unit: str
    samples: int
    blocks: int
    #: the largest error bound held (None while nothing is held or a bound is unknown)
    max_bound: float | None
    #: the channel's registration (None before it is known)
    lo: float | None = None
    hi: float | None = None
    resolution: float | None = None
