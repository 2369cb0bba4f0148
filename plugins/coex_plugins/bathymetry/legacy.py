"""What version 1 of the topside receiver saved (one object per subgrid, one dense mosaic per
level), read only: a store written by CoEx 0.1 still opens (``bathymetry.Receiver`` version 1
is upgraded on load; the receiver moves these into tiles)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from coex import persistent

__all__ = ["Held", "Mosaic"]

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
