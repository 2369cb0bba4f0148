"""How the bathymetry sender codes a subgrid: the smallest of the self-contained ``Subgrid`` and
the ``PredictedSubgrid`` candidates, predicted from the parent when :mod:`.context` says topside
holds its cells; cached until the tile or that knowledge changes. Mixed into
:class:`~.sender.BathymetrySender`."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TypeAlias

import numpy as np
import numpy.typing as npt

from coex import (
    SubgridParent,
    encode_predicted,
    encode_subgrid,
    region_digest,
    subgrid_bits,
    to_stamp,
)
from coex.messages import Message, PredictedSubgrid, SubgridContext, SubgridMessage

from .context import ContextBook, Digests, Key, content_id
from .quadtree import QuadtreeMap

__all__ = ["Built", "SubgridCoding"]

log = logging.getLogger("coex_plugins.bathymetry.sender")

#: a built subgrid: tile version, message, size, the parent digest it was built knowing (0:
#: none), its version (content digest), its quarters' digests (a parent level)
Built: TypeAlias = tuple[int, SubgridMessage, int, int, int, Digests | None]


class SubgridCoding:
    """The sender's coding of subgrids (uses its ``map``, ``_cache``, ``_book``, ``unsendable``,
    ``_sent_row``, ``_mark_sent`` and ``subgrid_time``)."""

    map: QuadtreeMap
    _cache: dict[Key, Built]
    _book: ContextBook | None
    unsendable: set[Key]

    #: defined by the bathymetry sender, which mixes this class in (declared for the type checker)
    _sent_row: Callable[[tuple[int, int]], int]
    _mark_sent: Callable[..., None]
    subgrid_time: Callable[[Key], float]

    @property
    def book(self) -> ContextBook:
        """What topside is known to hold of the parent levels (:mod:`.context`)."""
        assert self._book is not None  # made by __init__ or _after_restore
        return self._book

    def build(self, key: Key) -> SubgridMessage | None:
        """The current subgrid message for ``key`` (None when the map has nothing there)."""
        built = self._built(key)
        return None if built is None else built[0]

    def _built(self, key: Key) -> tuple[SubgridMessage, int] | None:
        """The current subgrid message for ``key`` and its encoded size, cached until its tile
        changes or what topside is known to hold of its parent does (a subgrid that did not fit
        one packet is not coded again for the next)."""
        hit = self._entry(key)
        return None if hit is None else (hit[1], hit[2])

    def _entry(self, key: Key) -> Built | None:
        level, ix, iy = key
        tile, _, _ = self.map.tile_of_subgrid(level, ix, iy)
        version = self.map.tile_version(tile)
        known = self.book.known(self._sent_row(tile), key) if self.map.has_tile(tile) else 0
        hit = self._cache.get(key)
        if hit is not None and hit[0] == version and hit[3] == known:
            return hit
        try:
            built = self._build(key, known)
        except ValueError as exc:  # elevations outside the wire's range: skip, never crash
            self.unsendable.add(key)
            log.warning("subgrid %s cannot be sent: %s", key, exc)
            self._mark_sent(key, self.subgrid_time(key))
            return None
        if built is None:
            return None
        sg, size, content, digests = built
        entry: Built = (version, sg, size, known, content, digests)
        self._cache[key] = entry
        self.book.record(sg, key, content, digests)
        return entry

    def _cells(self, key: Key) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.bool_], float] | None:
        """A subgrid's cells in vertical units, their presence and its last update (None: empty)."""
        blk = self.map.block(*key)
        if blk is None or not (blk.count > 0).any():
            return None
        present = blk.count > 0
        q = np.zeros(blk.mean.shape, np.int64)
        q[present] = np.rint(blk.mean[present] / self.map.vertical_resolution).astype(np.int64)
        return q, present, blk.updated

    def _build(self, key: Key, known: int) -> tuple[SubgridMessage, int, int, Digests | None] | None:
        """The smallest message for ``key``: coded on its own (a Subgrid or a PredictedSubgrid
        from its own base) or, when topside is known to hold its parent's cells around it
        (``known``, their digest), predicted from them. Returns it, its size, its version and,
        at a parent level, the digests of its quarters' surroundings."""
        level, ix, iy = key
        cells = self._cells(key)
        if cells is None:
            return None
        q, present, updated = cells
        stamp = to_stamp(updated)
        res, vres = float(self.map.resolution), float(self.map.vertical_resolution)
        parent = None
        if known:
            pc = self._cells((level + 1, ix >> 1, iy >> 1))
            if pc is not None:
                parent = SubgridParent(pc[0], pc[1])
                if region_digest(parent, ix & 1, iy & 1) != known:
                    parent = None  # the parent changed there since: topside holds other cells
        got = encode_predicted(q, present, level=level, ix=ix, iy=iy, stamp=stamp, resolution=res,
                               vertical_resolution=vres, parent=parent)
        best: tuple[SubgridMessage, int] | None = None if got is None else (got[0], (got[1] + 7) // 8)
        if best is None or not (isinstance(best[0], PredictedSubgrid) and best[0].context == SubgridContext.PARENT):
            # coded on its own: the Subgrid encodings may be smaller (against a parent they
            # almost never are, and are not tried: the time goes to the candidates that win)
            alone = encode_subgrid(q, present, level=level, ix=ix, iy=iy, stamp=stamp, resolution=res,
                                   vertical_resolution=vres)
            size = (subgrid_bits(alone) + 7) // 8
            if best is None or size < best[1]:
                best = (alone, size)
        digests: Digests | None = None
        if level >= 1:
            me = SubgridParent(q, present)
            d = [region_digest(me, qx, qy) for qy in (0, 1) for qx in (0, 1)]
            digests = (d[0], d[1], d[2], d[3])
        return best[0], best[1], content_id(stamp, q, present), digests

    def _version(self, message: Message) -> tuple[Key, int | None] | None:
        """The subgrid key of a subgrid message and its version (None: not built here lately)."""
        if not isinstance(message, SubgridMessage):
            return None
        key = (message.level, message.ix, message.iy)
        rec = self.book.version(message)
        return key, (rec[1] if rec is not None and rec[0] == key else None)

    def _is_current(self, key: Key, message: SubgridMessage, version: int | None, *, lost: bool = False) -> bool:
        """Whether ``message`` carries the current version of ``key`` (however it is coded).

        ``version`` None: the message was built before the sender was restored from a saved
        state (:class:`.context.ContextBook` does not save the versions of the messages it
        built), or so long ago that the book forgot it. Its version is then judged from the
        message: the current build itself is the current version; otherwise, for a loss
        (``lost``), a message with the current version's stamp is taken as the current
        version. The current build may be coded otherwise than the lost message (what topside
        is known to hold of the parent changed since: an ack taught the book, so the child is
        now predicted from its parent), and a loss taken for an old version's is never sent
        again (the background sends a subgrid only when it changes), so topside would keep
        the old version for good. A same-stamp misjudgement only sends the current version
        once more. For an ack the message must be the current build itself: a misjudgement
        there would drop a re-send topside still needs."""
        entry = self._entry(key)
        if entry is None:
            return False
        if version is not None:
            return entry[4] == version
        return entry[1] == message or (lost and entry[1].stamp == message.stamp)
