"""How the vehicle answers a region request (:meth:`.sender.ImagerySender.handle` of an
``ImageRegionRequest``): which of an image's packets reach a quality target inside the box, what
sending them costs on the wire, and the packet runs worth bridging. Pure functions of a
transfer; the sender decides between these packets and a crop."""

from __future__ import annotations

import itertools

import numpy as np
import numpy.typing as npt

from ._transfer import _Tx, fragment_size
from .codec import decode_packets, packet_end, psnr


def wire_estimate(tx: _Tx, mask: npt.NDArray[np.bool_]) -> int:
    """Wire bytes of sending the bytes of ``mask`` (at least): the bytes, a fragment header
    per run and the packet marks of runs after a gap (see :meth:`.sender.ImagerySender._marked`)."""
    if not mask.any():
        return 0
    edges = np.diff(mask.astype(np.int8), prepend=0, append=0)
    runs = zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True)
    starts = tx.enc.packet_starts
    total = int(mask.sum())
    before = tx.acked | mask
    for run_start, run_end in runs:
        s, e = int(run_start), int(run_end)
        total += fragment_size(0, 0, s)
        if not bool(before[:s].all()):
            lo, hi = np.searchsorted(starts, [s, e])
            total += fragment_size(int(hi - lo) + 1, 0, s) - fragment_size(0, 0, s)
    return total

def decoded(tx: _Tx, sel: npt.NDArray[np.bool_]) -> npt.NDArray[np.uint8]:
    """The image decoded from the packets ``sel`` (the receiver's rule, spec/payloads.md 3.4)."""
    enc = tx.enc
    starts = enc.packet_starts
    pk: list[bytes | None] = [enc.body[int(s):packet_end(starts, tx.total, i)] if sel[i] else None
                              for i, s in enumerate(starts)]
    return decode_packets(enc.params, enc.width, enc.height, pk)

def box_psnr(tx: _Tx, sel: npt.NDArray[np.bool_], box: tuple[int, int, int, int]) -> float:
    """PSNR inside ``box`` of the image decoded from the packets ``sel``, against the original."""
    x0, y0, x1, y1 = box
    return psnr(decoded(tx, sel)[y0:y1, x0:x1], tx.enc.image[y0:y1, x0:x1])

def held_packets(tx: _Tx) -> npt.NDArray[np.bool_]:
    """Packets whose every byte topside acknowledged."""
    starts = tx.enc.packet_starts
    cum = np.concatenate([[0], np.cumsum(tx.acked, dtype=np.int64)])
    ends = np.append(starts[1:], tx.total)
    out: npt.NDArray[np.bool_] = (cum[ends] - cum[starts]) == (ends - starts)
    return out

def fewest(tx: _Tx, candidates: npt.NDArray[np.bool_], held: npt.NDArray[np.bool_],
            box: tuple[int, int, int, int], target: float) -> npt.NDArray[np.bool_]:
    """What topside holds and the fewest of the ``candidates`` packets not held, in codestream
    order (whole packets, so a layer may be taken in part, lowest resolutions first), whose
    decode reaches ``target`` dB PSNR inside the box, measured against the original (all of
    them when none does). Bisection on the count: a few decodes."""
    todo = np.flatnonzero(candidates & ~held)

    def chosen(k: int) -> npt.NDArray[np.bool_]:
        out = held.copy()
        out[todo[:k]] = True
        return out

    def quality(k: int) -> float:
        return box_psnr(tx, chosen(k), box)

    lo, hi = 0, len(todo)
    if quality(hi) < target:
        return chosen(hi)
    if quality(lo) >= target:
        return chosen(lo)
    while hi - lo > 1:  # quality(lo) < target <= quality(hi)
        mid = (lo + hi) // 2
        if quality(mid) >= target:
            hi = mid
        else:
            lo = mid
    return chosen(hi)

def way(tx: _Tx, chosen: npt.NDArray[np.bool_], held: npt.NDArray[np.bool_],
         box: tuple[int, int, int, int]) -> tuple[npt.NDArray[np.bool_], float, int]:
    """Sending the packets ``chosen`` not held: the bytes (mask), the PSNR the box then has,
    the wire bytes (estimated)."""
    starts = tx.enc.packet_starts
    mask = np.zeros(tx.total, bool)
    for i in np.flatnonzero(chosen & ~held):
        mask[int(starts[i]):packet_end(starts, tx.total, int(i))] = True
    return mask, box_psnr(tx, chosen | held, box), wire_estimate(tx, mask)


#: a run of packets outside a region this small (bytes) between two region packets is sent too:
#: cheaper than breaking the fragment (a new message header, fragment header and packet marks)
BRIDGE_BYTES = 8


def _bridge(chosen: npt.NDArray[np.bool_], held: npt.NDArray[np.bool_],
            sizes: npt.NDArray[np.int64]) -> npt.NDArray[np.bool_]:
    """``chosen`` plus every gap of unheld packets between two chosen unheld packets whose bytes
    are at most :data:`BRIDGE_BYTES` (a gap with a held packet stays: it breaks the fragment
    anyway)."""
    out = chosen.copy()
    idx = np.flatnonzero(chosen & ~held)
    for a, b in itertools.pairwise(idx):
        if b - a > 1 and not held[a + 1:b].any() and int(sizes[a + 1:b].sum()) <= BRIDGE_BYTES:
            out[a + 1:b] = True
    return out


def _within(candidates: npt.NDArray[np.bool_], held: npt.NDArray[np.bool_], sizes: npt.NDArray[np.int64],
            budget: int) -> npt.NDArray[np.bool_]:
    """What topside holds and the ``candidates`` packets not held, in codestream order, while
    their bytes total at most ``budget``."""
    cost = np.where(candidates & ~held, sizes, 0)
    out: npt.NDArray[np.bool_] = held | (candidates & (np.cumsum(cost) <= budget))
    return out
