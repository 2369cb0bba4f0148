"""The receiver's side of predicted subgrids (:class:`~coex.messages.PredictedSubgrid`).

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

from typing import Any

import numpy as np
import numpy.typing as npt

from coex import ContextMismatch, decode_predicted, decode_subgrid, parent_from_values
from coex.messages import PredictedSubgrid, Subgrid, SubgridContext, SubgridMessage

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

    def _held_block(self, level: int, ix: int, iy: int) -> FloatArray | None:
        raise NotImplementedError

    def _subgrid(self, sg: SubgridMessage, now: float) -> list[Any]:
        raise NotImplementedError

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

    def _resolve_children(self, level: int, ix: int, iy: int, now: float) -> list[Any]:
        """Try again the subgrids set aside under ``(level, ix, iy)``, which just changed."""
        if level == 0 or not self._waiting:
            return []
        out: list[Any] = []
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
