"""The receiver's intake of subgrids, either form: a ``Subgrid`` decodes on its own; a
:class:`~coex.messages.PredictedSubgrid` is rebuilt from its own base or from its parent.

A subgrid predicted from its parent (``context`` PARENT) is decoded with the parent's cells as
the receiver holds them (:func:`coex.decode_predicted`), at the parent level's geometry. When the
receiver does not hold the parent, or holds other cells there than the sender predicted from
(the message's ``check`` says so: the parent was lost, or a newer version of it overtook the
subgrid), the subgrid is *set aside*: not held, so a region or gap request asks for it again,
and decoded as soon as the parent cells it needs arrive (each time a subgrid is stored, the
subgrids set aside under it are tried again). At most :data:`MAX_WAITING` wait (the oldest
goes); they are not saved with the receiver's state (after a restart the requests bring them
again).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

from coex import (
    ContextMismatch,
    Product,
    decode_predicted,
    decode_subgrid,
    parent_from_values,
    unwrap,
)
from coex.messages import PredictedSubgrid, Subgrid, SubgridContext, SubgridMessage

from .tiles import LevelStats

__all__ = ["MAX_WAITING", "PredictedInput"]

FloatArray = npt.NDArray[np.float64]
Key = tuple[int, int, int]
#: subgrids set aside at most (the oldest goes first)
MAX_WAITING = 4096


class PredictedInput:
    """Mixed into :class:`~.receiver.BathymetryReceiver`: geometry, decoding and the subgrids set
    aside. Uses the receiver's ``_geometry``, ``_vres``, ``metadata`` and ``_held_block``."""

    _geometry: dict[int, tuple[float, int]]
    _vres: dict[int, float]
    metadata: Any
    #: PARENT subgrids waiting for the parent cells they were predicted from: key -> (message, arrival)
    _waiting: dict[Key, tuple[PredictedSubgrid, float]]
    #: subgrids set aside so far (decoded later or not), and of them decoded once the parent came
    set_aside: int
    resolved: int

    mismatched: int
    duplicates: int
    tile_subgrids: int
    _stats: dict[int, LevelStats]
    _versions: dict[int, int]

    #: defined by the bathymetry receiver, which mixes this class in (declared for the type checker)
    _tile: Callable[..., Any]
    _put: Callable[..., None]
    level_product: Callable[..., Product]

    def _subgrid(self, sg: SubgridMessage, now: float) -> list[Product]:
        level = sg.level
        geo = self._geometry_of(sg)
        if geo is None:  # predicted from a level of which nothing came yet
            assert isinstance(sg, PredictedSubgrid)
            self._set_aside(sg, now)
            return []
        cell, side, vres = geo
        geometry = self._geometry.get(level)
        if geometry is not None and (geometry[1] != side or geometry[0] != cell):
            self.mismatched += 1  # the level's cells would not line up: ignored
            return []
        stamp = unwrap(sg.stamp, now)
        n = self.tile_subgrids
        tx, lx = divmod(sg.ix, n)
        ty, ly = divmod(sg.iy, n)
        known = self._tile(level, tx, ty)
        if known is not None and known.held[ly, lx] and known.stamp[ly, lx] >= stamp:
            self.duplicates += 1
            return []
        values = self._cells_of(sg, vres)
        if values is None:  # predicted from parent cells not held (yet)
            assert isinstance(sg, PredictedSubgrid)
            self._set_aside(sg, now)
            return []
        waiting = self._waiting.get((level, sg.ix, sg.iy))
        if waiting is not None and unwrap(waiting[0].stamp, now) <= stamp:
            del self._waiting[(level, sg.ix, sg.iy)]  # a newer version came whole
        if geometry is None:
            self._geometry[level] = (cell, side)
            self._stats[level] = LevelStats()
        self._vres[level] = vres
        tile = self._tile(level, tx, ty, create=True)
        assert tile is not None
        self._put(level, tile, sg.ix, sg.iy, lx, ly, stamp, values, now, draw=True)
        self._versions[level] = self._versions.get(level, 0) + 1
        return [self.level_product(level), *self._resolve_children(level, sg.ix, sg.iy, now)]

    def _held_block(self, level: int, ix: int, iy: int) -> FloatArray | None:
        """The cells (m, NaN where none) of a held subgrid, None when it is not held."""
        geometry = self._geometry.get(level)
        if geometry is None:
            return None
        n = self.tile_subgrids
        tx, lx = divmod(ix, n)
        ty, ly = divmod(iy, n)
        tile = self._tile(level, tx, ty)
        if tile is None or not tile.held[ly, lx]:
            return None
        side = geometry[1]
        block: FloatArray = tile.values[ly * side:(ly + 1) * side, lx * side:(lx + 1) * side].copy()
        return block

    def _init_waiting(self) -> None:
        self._waiting = {}

    def _geometry_of(self, sg: SubgridMessage) -> tuple[float, int, float] | None:
        """``(cell size, side, vertical resolution)`` of a subgrid; a PARENT one has its parent
        level's (None while that level is unknown)."""
        if isinstance(sg, Subgrid):
            return sg.resolution * (1 << sg.level), sg.side, sg.vertical_resolution
        if sg.context == SubgridContext.NONE:
            assert sg.resolution is not None and sg.vertical_resolution is not None
            return sg.resolution * (1 << sg.level), sg.side, sg.vertical_resolution
        up = self._geometry.get(sg.level + 1)
        vres = self._vres.get(sg.level + 1)
        if vres is None and self.metadata is not None:
            vres = self.metadata.vertical_resolution  # a level held before the receiver kept it
        if up is None or vres is None:
            return None
        return up[0] / 2, sg.side, vres

    def _cells_of(self, sg: SubgridMessage, vres: float) -> FloatArray | None:
        """Elevations (m) of a subgrid; None when it is predicted from parent cells not held."""
        if isinstance(sg, Subgrid):
            return decode_subgrid(sg)
        if sg.context == SubgridContext.NONE:
            return decode_predicted(sg)
        held = self._held_block(sg.level + 1, sg.ix >> 1, sg.iy >> 1)
        if held is None:
            return None
        try:
            return decode_predicted(sg, parent_from_values(held, vres), vres)
        except ContextMismatch:
            return None

    def _set_aside(self, sg: PredictedSubgrid, now: float) -> None:
        key = (sg.level, sg.ix, sg.iy)
        old = self._waiting.get(key)
        if old is not None and old[0].stamp == sg.stamp and old[0] == sg:
            return  # a copy of one already waiting
        self._waiting.pop(key, None)
        self._waiting[key] = (sg, now)
        self.set_aside += 1
        while len(self._waiting) > MAX_WAITING:
            del self._waiting[next(iter(self._waiting))]

    def _resolve_children(self, level: int, ix: int, iy: int, now: float) -> list[Product]:
        """Try again the subgrids set aside under ``(level, ix, iy)``, which just changed."""
        if level == 0 or not self._waiting:
            return []
        out: list[Product] = []
        for b in (0, 1):
            for a in (0, 1):
                key = (level - 1, 2 * ix + a, 2 * iy + b)
                got = self._waiting.get(key)
                if got is None:
                    continue
                del self._waiting[key]
                out.extend(self._subgrid(got[0], now))
                if key not in self._waiting:  # not set aside again
                    self.resolved += 1
        return out

    def waiting(self) -> list[tuple[int, int, int]]:
        """Subgrids set aside for want of the parent cells they were predicted from."""
        return sorted(self._waiting)
