"""The bathymetry receiver's product: a level of the map as topside holds it."""

from __future__ import annotations

from dataclasses import dataclass

from coex import TypedProduct

__all__ = ["MapLevel"]


@dataclass(frozen=True, kw_only=True)
class MapLevel(TypedProduct):
    """A level of the map (kind ``map-level``, key ``level-<n>``). ``data``: the drawn grid of
    depths (row 0 = south, NaN where empty), a decimated overview of a big level (``step``
    level cells per pixel); ``x0``, ``y0`` (metres) its south-west corner, ``cell_size`` its
    pixel side (``level_cell * step``)."""

    level: int
    cell_size: float
    step: int
    level_cell: float
    x0: float
    y0: float
    #: subgrids and cells held
    subgrids: int
    cells: int
    #: the newest data's time (0 while nothing is held)
    newest: float
    origin_lat: float
    origin_lon: float
    #: the depth range held (None while nothing is)
    zmin: float | None = None
    zmax: float | None = None
    #: the oldest data's age at the time asked (None when no time was given)
    oldest_age: float | None = None
    #: placed by topside's navigation (its drift correction applied; ``coex_plugins.navigation``)
    corrected: bool = False
