"""What version 1 of the topside receiver saved (one object per subgrid, one dense mosaic per
level), read only: a store written by CoEx 0.1 still opens (``bathymetry.Receiver`` version 1
is upgraded on load; the receiver moves these into tiles)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from coex import persistent

__all__ = ["Held", "Mosaic", "import_v1"]

FloatArray = npt.NDArray[np.float64]


@persistent("bathymetry.Held")
@dataclass
class Held:
    stamp: float
    values: FloatArray
    received: float


@persistent("bathymetry.Mosaic")
@dataclass
class Mosaic:
    side: int
    ix0: int = 0
    iy0: int = 0
    nx: int = 0
    ny: int = 0
    array: FloatArray = field(default_factory=lambda: np.full((0, 0), np.nan))


def import_v1(receiver: Any, held: dict[int, dict[tuple[int, int], Held]], mosaics: dict[int, Mosaic],
              off: set[tuple[int, int, int]]) -> None:
    """Move what a version 1 ``receiver`` saved into its tiles and overviews (its mosaics become
    the overviews at full resolution; a subgrid already drawn in one is not drawn again)."""
    from .overview import Overview

    for level, mos in mosaics.items():
        receiver._overviews[level] = Overview(1, mos.ix0 * mos.side, mos.iy0 * mos.side,
                                              mos.nx * mos.side, mos.ny * mos.side, mos.array)
    for level, cells in held.items():
        if level not in receiver._geometry:
            continue
        for (ix, iy), h in cells.items():
            drawn = level in mosaics and mosaics[level].side == receiver._geometry[level][1] \
                and (level, ix, iy) not in off
            receiver._hold(level, ix, iy, float(h.stamp), np.asarray(h.values, np.float64),
                           float(h.received), draw=not drawn)
