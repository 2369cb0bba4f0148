"""What the vehicle knows of the cells topside holds: the context a subgrid may be predicted from.

A :class:`~coex.messages.PredictedSubgrid` with ``context`` PARENT is coded against its parent
subgrid's cells *as topside holds them*. The sender may do so only when it knows those cells,
and it learns them from the channel's frame acks (``BathymetrySender.acked``):

* every subgrid message built is remembered by its wire bytes (:func:`message_id`) with its
  *version* (the subgrid's key and a digest of its stamp and cells: two encodings of the same
  cells are one version) and, at a parent level, the digests of the cells a child of each of its
  four quarters would be predicted from (:func:`coex.region_digest`);
* when a parent version is sent, each quarter whose cells differ from what topside was known to
  hold becomes unknown (the new version may land first);
* when a frame ack confirms a parent version, each quarter whose cells are those of the newest
  version sent becomes known;
* when topside says it lacks a subgrid (a region or gap request), what was known of it is
  forgotten.

A child is predicted from its parent when the parent's current cells around its quarter have
the digest topside is known to hold there; otherwise it is coded on its own. The wire's
``check`` still guards the rare case this misjudges (another copy, a restart): topside keeps
such a subgrid aside until it holds the parent cells, or asks for it again.

The knowledge is kept per map tile in numpy arrays (4 uint32 per parent-level subgrid), like
the sender's other per-subgrid bookkeeping, and saved with it.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict

import numpy as np
import numpy.typing as npt

from coex import persistent
from coex.messages import Message

__all__ = ["ContextBook", "Key", "content_id", "message_id"]

Key = tuple[int, int, int]  # (level, ix, iy)
#: messages remembered by their bytes (those in flight and a margin for late acks: the channel
#: remembers 4096 lost ones)
MAX_VERSIONS = 8192
Digests = tuple[int, int, int, int]


def message_id(message: Message) -> int:
    """A 64-bit digest of a message's fields (the same in every process: a message's ``repr``
    holds its type, field values and enum members, never an address; cheaper than its bytes,
    which a message built but not sent never needs)."""
    return int.from_bytes(hashlib.blake2b(repr(message).encode(), digest_size=8).digest(), "big")


def content_id(stamp: int, q: npt.NDArray[np.int64], present: npt.NDArray[np.bool_]) -> int:
    """A 64-bit digest of a subgrid version: its stamp and cells (not how they are coded)."""
    h = hashlib.blake2b(digest_size=8)
    h.update(int(stamp).to_bytes(4, "big"))
    h.update(np.packbits(present).tobytes())
    h.update(np.where(present, q, 0).astype("<i4").tobytes())
    return int.from_bytes(h.digest(), "big")


def quarter(ix: int, iy: int) -> int:
    """The quarter of its parent a subgrid is: 0 south-west, 1 south-east, 2 north-west, 3 north-east."""
    return (iy & 1) * 2 + (ix & 1)


@persistent("bathymetry.ContextBook", transient=("versions",))
class ContextBook:
    """Per parent-level subgrid (levels 1 and up) and quarter: the digest of the cells topside
    is known to hold (``top``, 0: unknown) and of the newest version sent (``last_sent``); and the
    versions of the messages built, by :func:`message_id` (not saved: after a restart the fate
    of a message built before it is judged from the message, ``SubgridCoding._is_current``: an
    ack counts when the message is the current build, a loss when it carries the current
    version's stamp; and such an ack teaches nothing of the parent's cells)."""

    def __init__(self, per_tile: list[int], cap: int = 4) -> None:
        #: subgrids per tile side, by level
        self.per_tile = list(per_tile)
        self.top: dict[int, npt.NDArray[np.uint32]] = {
            lv: np.zeros((cap, p, p, 4), np.uint32) for lv, p in enumerate(self.per_tile) if lv >= 1}
        self.last_sent: dict[int, npt.NDArray[np.uint32]] = {lv: a.copy() for lv, a in self.top.items()}
        self._after_restore()

    def _after_restore(self) -> None:
        #: message id -> (key, version, quarter digests at a parent level)
        self.versions: OrderedDict[int, tuple[Key, int, Digests | None]] = OrderedDict()

    def grow(self, cap: int) -> None:
        """Room for tile numbers below ``cap``."""
        for arrays in (self.top, self.last_sent):
            for lv, a in arrays.items():
                if a.shape[0] < cap:
                    b = np.zeros((cap, *a.shape[1:]), np.uint32)
                    b[:a.shape[0]] = a
                    arrays[lv] = b

    def _cell(self, n: int, key: Key) -> tuple[int, int, int]:
        level, ix, iy = key
        p = self.per_tile[level]
        return n, iy % p, ix % p

    def known(self, n: int, child: Key) -> int:
        """The digest of the parent cells topside is known to hold around ``child`` (0: unknown,
        or ``child`` is at the coarsest level)."""
        level, ix, iy = child
        if level + 1 not in self.top:
            return 0
        parent = (level + 1, ix >> 1, iy >> 1)
        i, b, a = self._cell(n, parent)
        return int(self.top[level + 1][i, b, a, quarter(ix, iy)])

    def record(self, message: Message, key: Key, version: int, digests: Digests | None) -> None:
        """A message built for ``key``: its version and, at a parent level, its quarters' digests."""
        mid = message_id(message)
        self.versions[mid] = (key, version, digests)
        self.versions.move_to_end(mid)
        while len(self.versions) > MAX_VERSIONS:
            self.versions.popitem(last=False)

    def version(self, message: Message) -> tuple[Key, int, Digests | None] | None:
        """What :meth:`record` remembers of ``message`` (None: not built here, or long ago)."""
        return self.versions.get(message_id(message))

    def on_sent(self, n: int, key: Key, digests: Digests | None) -> None:
        """A version of ``key`` went to the link: a quarter whose cells differ from what topside
        was known to hold is unknown until a frame ack says which version topside holds."""
        if digests is None or key[0] not in self.top:
            return
        i, b, a = self._cell(n, key)
        new = np.array(digests, np.uint32)
        top = self.top[key[0]]
        top[i, b, a] = np.where(top[i, b, a] == new, new, 0)
        self.last_sent[key[0]][i, b, a] = new

    def on_acked(self, n: int, key: Key, digests: Digests | None) -> None:
        """A frame ack confirmed a version of ``key``: each quarter whose cells are those of the
        newest version sent is known."""
        if digests is None or key[0] not in self.top:
            return
        i, b, a = self._cell(n, key)
        got = np.array(digests, np.uint32)
        top = self.top[key[0]]
        top[i, b, a] = np.where(self.last_sent[key[0]][i, b, a] == got, got, top[i, b, a])

    def forget(self, n: int, key: Key) -> None:
        """Topside lacks ``key``: nothing is known of its cells."""
        if key[0] in self.top:
            i, b, a = self._cell(n, key)
            self.top[key[0]][i, b, a] = 0
