"""Subgrids predicted from what topside holds: :class:`~coex_core.messages.PredictedSubgrid`
(type 20) to cells and back. Part of the wire format (``spec/payloads.md`` sections 1.6 to 1.10).

A subgrid at level ``L`` is predicted from the cells of its *parent*, the subgrid at level
``L + 1`` that covers it (``(ix >> 1, iy >> 1)``, of which it is the quarter ``(ix & 1, iy &
1)``), as the receiver holds them (``context`` PARENT), or from a base value of its own
(``NONE``: it decodes on its own). Only the residuals (cell minus prediction) travel,
arithmetic-coded (:mod:`coex_core._wire._subgrid_code`). The prediction is

* a *surface* ``u(i, j)``: the parent cell over the cell (``NEAREST``), its bilinear or cubic
  interpolation from the parent's cell centres (taps outside the parent or on absent parent
  cells replaced by the centre's mirror image, else the centre), or ``z_base`` (NONE);
* plus, for some predictors, a correction ``g`` from the cell's west, south and south-west
  neighbours' deviations ``d = z - u`` (already decoded: row-major order): planar ``W + S -
  SW``, the median edge detector of JPEG-LS, or half a plane ``(2W + 2S - SW) / 4``.

``check`` (PARENT) is a CRC-8 of the parent cells within two cells of the quarter: a receiver
that holds other cells there (the parent never arrived, or arrived in another version than the
sender assumed) knows the prediction would be wrong: :class:`ContextMismatch`, and the subgrid
waits (or is asked for again). The sender predicts from a parent only when frame acks have told
it that topside holds exactly those cells (``coex_plugins.bathymetry.sender``); otherwise it
codes the subgrid on its own (``NONE``, or a :class:`~coex_core.messages.Subgrid`).

The encoder is numpy-vectorised (every candidate predictor at once, then the arithmetic coder
for the best); the decoder visits the cells once in row-major order.
"""

from __future__ import annotations

import functools
import math
import zlib
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from ._wire._subgrid_code import MAX_RESIDUAL, CodedCells, encode_cells, table_for
from .messages import PredictedSubgrid, SubgridCells, SubgridContext, SubgridMessage
from .subgrid import decode_subgrid_units

__all__ = [
    "ABSENT",
    "ContextMismatch",
    "HEADER_BITS",
    "PREDICTORS",
    "SubgridParent",
    "context_check",
    "decode_predicted",
    "decode_predicted_units",
    "encode_predicted",
    "parent_key",
    "parent_from_rows",
    "parent_from_values",
    "predicted_table",
    "region_digest",
    "subgrid_units",
    "units_rows",
]

IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]
#: the value of an absent cell in the integer arrays
ABSENT = np.iinfo(np.int64).min
#: elevations are below this in magnitude (vertical units; the wire's range)
Z_LIMIT = 1 << 19
#: the coded cells take at most this many bits
MAX_CELL_BITS = 1536
#: bits before the coded cells (type id included): type 8, level 4, ix 14, iy 14, stamp 18, side
#: 2, context 1, then the check (PARENT, 8) or the geometry and base (NONE, 3 + 3 + 20), then
#: predictor 2, shift 2, partial 1
HEADER_BITS = {SubgridContext.PARENT: 8 + 4 + 14 + 14 + 18 + 2 + 1 + 8 + 2 + 2 + 1,
               SubgridContext.NONE: 8 + 4 + 14 + 14 + 18 + 2 + 1 + 3 + 3 + 20 + 2 + 2 + 1}

# surfaces and corrections
NEAREST, BILINEAR, CUBIC, BASE = "nearest", "bilinear", "cubic", "base"
NO_G, PLANAR, MED, HALF = "none", "planar", "med", "half"
#: (surface, correction) of each ``predictor`` code, by context
PREDICTORS: dict[SubgridContext, tuple[tuple[str, str], ...]] = {
    SubgridContext.PARENT: ((NEAREST, NO_G), (BILINEAR, NO_G), (CUBIC, NO_G), (CUBIC, HALF)),
    SubgridContext.NONE: ((BASE, NO_G), (BASE, MED), (BASE, PLANAR), (BASE, HALF)),
}
#: 1-D interpolation taps (offset, weight) for an even and an odd child row or column
_TAPS: dict[str, tuple[dict[int, tuple[tuple[int, int], ...]], int]] = {
    BILINEAR: ({0: ((-1, 1), (0, 3)), 1: ((0, 3), (1, 1))}, 2),
    CUBIC: ({0: ((-2, -3), (-1, 29), (0, 111), (1, -9)), 1: ((-1, -9), (0, 111), (1, 29), (2, -3))}, 7),
}


class ContextMismatch(ValueError):
    """A PARENT subgrid cannot be decoded with the parent cells given (none, or other cells than
    it was predicted from)."""


class SubgridParent:
    """A parent subgrid's cells as the receiver holds them: ``z`` (side x side integers,
    vertical units, row 0 south) and ``present``."""

    __slots__ = ("present", "z")

    def __init__(self, z: npt.ArrayLike, present: npt.ArrayLike) -> None:
        self.present: BoolArray = np.asarray(present, bool)
        zz = np.asarray(z, np.int64)
        self.z: IntArray = np.where(self.present, zz, 0)


def parent_key(level: int, ix: int, iy: int) -> tuple[int, int, int]:
    """The parent of subgrid ``(level, ix, iy)``."""
    return level + 1, ix >> 1, iy >> 1


def predicted_table(context: SubgridContext, level: int) -> int:
    """The initial probability table of a subgrid (spec/payloads.md 1.7)."""
    return table_for(context == SubgridContext.PARENT, level)


def _region(side: int, qx: int, qy: int) -> tuple[int, int, int, int]:
    h = side // 2
    return max(0, qy * h - 2), min(side, qy * h + h + 2), max(0, qx * h - 2), min(side, qx * h + h + 2)


def _crc8_table() -> tuple[int, ...]:
    out = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        out.append(crc)
    return tuple(out)


_CRC8 = _crc8_table()


def _crc8(data: bytes) -> int:
    """CRC-8, polynomial x^8 + x^2 + x + 1 (0x07), initial value 0, no reflection, no final XOR."""
    crc = 0
    table = _CRC8
    for byte in data:
        crc = table[crc ^ byte]
    return crc


def _region_bytes(parent: SubgridParent, qx: int, qy: int) -> bytes:
    side = parent.z.shape[0]
    r0, r1, c0, c1 = _region(side, qx, qy)
    zz = parent.z[r0:r1, c0:c1]
    pp = parent.present[r0:r1, c0:c1]
    codes = np.where(pp, zz & 0xFFFFFF, 0x800000).astype(">u4").ravel()
    return codes.view(np.uint8).reshape(-1, 4)[:, 1:].tobytes()


def context_check(parent: SubgridParent, qx: int, qy: int) -> int:
    """The ``check`` of a PARENT subgrid, quarter ``(qx, qy)`` of ``parent``: the CRC-8 of its
    cells within two cells of the quarter, row-major, three bytes each (the elevation in 24-bit
    two's complement, big-endian; ``80 00 00`` for an absent cell)."""
    return _crc8(_region_bytes(parent, qx, qy))


def region_digest(parent: SubgridParent, qx: int, qy: int) -> int:
    """A 32-bit digest (never 0) of the cells :func:`context_check` covers: what a sender
    remembers of the parent cells topside holds, to know it may predict from them."""
    return zlib.crc32(_region_bytes(parent, qx, qy)) or 1


@functools.lru_cache(maxsize=64)
def _taps(side: int, qx: int, qy: int, kind: str) -> tuple[IntArray, IntArray, BoolArray, IntArray, BoolArray, IntArray]:
    """Flat indices of each child cell's parent centre, of its taps (clipped) and whether they
    are inside the parent, of their mirror images about the centre and whether those are
    inside, and the taps' weights: (cells,), then (cells, taps) each."""
    h = side // 2
    ii, jj = np.divmod(np.arange(side * side), side)
    pa, pb = qy * h + ii // 2, qx * h + jj // 2
    taps, _ = _TAPS[kind]
    offs = [[(da, db, wa * wb) for da, wa in taps[int(i % 2)] for db, wb in taps[int(j % 2)]]
            for i, j in zip(ii.tolist(), jj.tolist(), strict=True)]
    da = np.array([[o[0] for o in row] for row in offs])
    db = np.array([[o[1] for o in row] for row in offs])
    w = np.array([[o[2] for o in row] for row in offs], np.int64)
    a, b = pa[:, None] + da, pb[:, None] + db
    ma, mb = pa[:, None] - da, pb[:, None] - db
    inside = (a >= 0) & (a < side) & (b >= 0) & (b < side)
    m_in = (ma >= 0) & (ma < side) & (mb >= 0) & (mb < side)
    tap = np.clip(a, 0, side - 1) * side + np.clip(b, 0, side - 1)
    mir = np.clip(ma, 0, side - 1) * side + np.clip(mb, 0, side - 1)
    return pa * side + pb, tap, inside, mir, m_in, w


def _surface(parent: SubgridParent, qx: int, qy: int, kind: str) -> IntArray | None:
    """The parent surface over the quarter (side x side), or None when no parent cell within
    two cells of the quarter is present."""
    side = parent.z.shape[0]
    r0, r1, c0, c1 = _region(side, qx, qy)
    reg = parent.present[r0:r1, c0:c1]
    n = int(reg.sum())
    if n == 0:
        return None
    fallback = int(parent.z[r0:r1, c0:c1][reg].sum()) // n
    z = parent.z.ravel()
    pres = parent.present.ravel()
    if kind == NEAREST:
        h = side // 2
        ii, jj = np.indices((side, side))
        pa, pb = qy * h + ii // 2, qx * h + jj // 2
        return np.where(parent.present[pa, pb], parent.z[pa, pb], fallback)
    centre_idx, tap, inside, mir, m_in, w = _taps(side, qx, qy, kind)
    centre = np.where(pres[centre_idx], z[centre_idx], fallback)[:, None]
    here = inside & pres[tap]
    mirror = ~here & m_in & pres[mir]
    v = np.where(here, z[tap], np.where(mirror, 2 * centre - z[mir], centre))
    shift = 2 * _TAPS[kind][1]
    out: IntArray = ((v * w).sum(axis=1) + (1 << (shift - 1))) >> shift
    return out.reshape(side, side)


def _correction_all(d: IntArray, present: BoolArray, kind: str) -> IntArray:
    """The correction of every cell from its neighbours' ``d`` (the encoder knows them all)."""
    if kind == NO_G:
        return np.zeros_like(d)
    w = np.zeros_like(d)
    s = np.zeros_like(d)
    sw = np.zeros_like(d)
    hw = np.zeros_like(present)
    hs = np.zeros_like(present)
    hsw = np.zeros_like(present)
    w[:, 1:], hw[:, 1:] = d[:, :-1], present[:, :-1]
    s[1:, :], hs[1:, :] = d[:-1, :], present[:-1, :]
    sw[1:, 1:], hsw[1:, 1:] = d[:-1, :-1], present[:-1, :-1]
    three = hw & hs & hsw
    if kind == PLANAR:
        full = w + s - sw
        one_w, one_s = w, s
    elif kind == MED:
        mx, mn = np.maximum(w, s), np.minimum(w, s)
        full = np.where(sw >= mx, mn, np.where(sw <= mn, mx, w + s - sw))
        one_w, one_s = w, s
    else:  # HALF
        full = (2 * w + 2 * s - sw + 2) >> 2
        one_w, one_s = (w + 1) >> 1, (s + 1) >> 1
    g = np.where(three, full, np.where(hw, one_w, np.where(hs, one_s, 0)))
    return np.asarray(g, np.int64)


def _correction(d: list[int], have: list[bool], n: int, side: int, kind: str) -> int:
    """The correction of cell ``n`` (row-major) from the ``d`` of its decoded neighbours."""
    if kind == NO_G:
        return 0
    i, j = divmod(n, side)
    hw = j > 0 and have[n - 1]
    hs = i > 0 and have[n - side]
    hsw = i > 0 and j > 0 and have[n - side - 1]
    w = d[n - 1] if hw else 0
    s = d[n - side] if hs else 0
    if hw and hs and hsw:
        sw = d[n - side - 1]
        if kind == PLANAR:
            return w + s - sw
        if kind == MED:
            mx, mn = max(w, s), min(w, s)
            return mn if sw >= mx else mx if sw <= mn else w + s - sw
        return (2 * w + 2 * s - sw + 2) >> 2
    if hw:
        return (w + 1) >> 1 if kind == HALF else w
    if hs:
        return (s + 1) >> 1 if kind == HALF else s
    return 0


def _mask_int(present: BoolArray) -> int | None:
    if present.all():
        return None
    return int("".join("1" if p else "0" for p in present.ravel().tolist()), 2)


def _mask_bits(mask: int | None, side: int) -> list[bool]:
    n = side * side
    if mask is None:
        return [True] * n
    return [bool((mask >> (n - 1 - k)) & 1) for k in range(n)]


def _cost_estimate(e: IntArray) -> float:
    """Rough bits of residuals ``e`` (to rank candidates before coding the best exactly)."""
    a = np.abs(e)
    return float(np.where(a == 0, 0.6, 2.2 + 1.6 * np.log2(a + 1.0)).sum())


def _shifts(e: IntArray) -> range:
    if e.size == 0:
        return range(0, 1)
    mean = float(np.abs(e).mean())
    if mean < 4.0:
        return range(0, 1)
    k = min(3, max(0, int(math.log2(mean)) - 1))
    return range(max(0, k - 1), min(3, k + 1) + 1)


def encode_predicted(
    q: npt.ArrayLike,
    present: npt.ArrayLike,
    *,
    level: int,
    ix: int,
    iy: int,
    stamp: int,
    resolution: float,
    vertical_resolution: float,
    parent: SubgridParent | None = None,
    standalone: bool = True,
    exact: int = 2,
    only: tuple[SubgridContext, int, int] | None = None,
) -> tuple[PredictedSubgrid, int] | None:
    """The smallest PredictedSubgrid for integer elevations ``q`` (side x side, vertical units,
    row 0 south) where ``present``, and its size in bits (type id included, before the padding
    to a byte): predicted from ``parent`` (the parent subgrid's cells as topside holds them)
    when given, on its own (``NONE``) when ``standalone``, whichever is smaller. ``exact``: how
    many of the best-looking candidates are coded exactly; ``only``: that one ``(context,
    predictor, shift)`` (tests, vectors). None when nothing fits (no present cell, no parent
    cell near the subgrid, or too many bits)."""
    qa = np.asarray(q, np.int64)
    pa = np.asarray(present, bool)
    side = qa.shape[0]
    if not pa.any():
        return None
    vals = qa[pa]
    if np.abs(vals).max() >= Z_LIMIT:
        raise ValueError("elevation outside the wire range (|z| < 2**19 vertical units)")
    mask = _mask_int(pa)
    qx, qy = ix & 1, iy & 1
    cands: list[tuple[float, SubgridContext, int, IntArray, int | None, int | None]] = []
    want_parent = only is None or only[0] == SubgridContext.PARENT
    if parent is not None and parent.z.shape == (side, side) and want_parent:
        chk = context_check(parent, qx, qy)
        surfaces: dict[str, IntArray | None] = {}
        for code, (surf, corr) in enumerate(PREDICTORS[SubgridContext.PARENT]):
            if only is not None and only[1] != code:
                continue
            if surf not in surfaces:
                surfaces[surf] = _surface(parent, qx, qy, surf)
            u = surfaces[surf]
            if u is None:
                break
            d = qa - u
            e = (d - _correction_all(d, pa, corr))[pa]
            cost = _cost_estimate(e) + HEADER_BITS[SubgridContext.PARENT]
            cands.append((cost, SubgridContext.PARENT, code, e, chk, None))
    if (standalone and only is None) or (only is not None and only[0] == SubgridContext.NONE):
        z_base = int(vals[0])
        d = qa - z_base
        # beside a usable parent, the median edge detector alone stands for NONE: the others
        # (and NONE itself) almost never win there, and each candidate costs time
        beside = only is None and any(c[1] == SubgridContext.PARENT for c in cands)
        for code, (_, corr) in enumerate(PREDICTORS[SubgridContext.NONE]):
            if (only is not None and only[1] != code) or (beside and code != 1):
                continue
            e = (d - _correction_all(d, pa, corr))[pa]
            cost = _cost_estimate(e) + HEADER_BITS[SubgridContext.NONE]
            cands.append((cost, SubgridContext.NONE, code, e, None, z_base))
    if not cands:
        return None
    cands.sort(key=lambda c: c[0])
    best: tuple[int, PredictedSubgrid] | None = None
    for _, context, code, e, check, zb in cands[:max(1, exact)]:
        if np.abs(e).max(initial=0) >= MAX_RESIDUAL:
            continue
        residuals = tuple(int(v) for v in e.tolist())
        cells = CodedCells(None if mask is None else pa.ravel().tolist(), residuals)
        table = predicted_table(context, level)
        for shift in (range(only[2], only[2] + 1) if only is not None else _shifts(e)):
            nbits = len(encode_cells(side, cells, shift, table))
            if nbits > MAX_CELL_BITS:
                continue
            total = nbits + HEADER_BITS[context]
            if best is None or total < best[0]:
                geo = context == SubgridContext.NONE
                sg = PredictedSubgrid(
                    level=level, ix=ix, iy=iy, stamp=stamp, side=side, context=context, predictor=code,
                    shift=shift, cells=SubgridCells(mask, residuals), check=check,
                    resolution=resolution if geo else None,
                    vertical_resolution=vertical_resolution if geo else None, z_base=zb)
                best = (total, sg)
    if best is None:
        return None
    return best[1], best[0]


def decode_predicted_units(sg: PredictedSubgrid, parent: SubgridParent | None = None) -> IntArray:
    """Integer elevations (vertical units, side x side, row 0 south; :data:`ABSENT` where no
    cell). A PARENT subgrid needs ``parent``, the parent subgrid's cells as the receiver holds
    them: :class:`ContextMismatch` when it is missing or its cells do not pass ``check``."""
    side = sg.side
    present = _mask_bits(sg.cells.mask, side)
    if sum(present) != len(sg.cells.residuals):
        raise ValueError("the residuals do not match the mask")
    surf, corr = PREDICTORS[sg.context][sg.predictor]
    if sg.context == SubgridContext.PARENT:
        if parent is None:
            raise ContextMismatch("the parent subgrid is not held")
        if parent.z.shape != (side, side):
            raise ContextMismatch("the parent subgrid has another side")
        qx, qy = sg.ix & 1, sg.iy & 1
        if context_check(parent, qx, qy) != sg.check:
            raise ContextMismatch("the parent's cells are not those the subgrid was predicted from")
        if not any(present):
            return np.full((side, side), ABSENT, np.int64)
        u = _surface(parent, qx, qy, surf)
        if u is None:
            raise ContextMismatch("no parent cell near the subgrid")
        base = u.ravel().tolist()
    else:
        if sg.z_base is None:
            raise ValueError("a NONE subgrid has a z_base")
        base = [sg.z_base] * (side * side)
    out = [int(ABSENT)] * (side * side)
    d = [0] * (side * side)
    k = 0
    for n in range(side * side):
        if not present[n]:
            continue
        g = _correction(d, present, n, side, corr)
        z = base[n] + g + sg.cells.residuals[k]
        k += 1
        d[n] = z - base[n]
        out[n] = z
    return np.array(out, np.int64).reshape(side, side)


def decode_predicted(sg: PredictedSubgrid, parent: SubgridParent | None = None,
                     vertical_resolution: float | None = None) -> npt.NDArray[np.float64]:
    """Elevations in metres (NaN where no cell); ``vertical_resolution`` is the parent's for a
    PARENT subgrid (its own for NONE)."""
    vres = sg.vertical_resolution if sg.context == SubgridContext.NONE else vertical_resolution
    if vres is None:
        raise ValueError("the vertical resolution of a PARENT subgrid is its parent's: give it")
    units = decode_predicted_units(sg, parent)
    out = np.full(units.shape, np.nan)
    ok = units != ABSENT
    out[ok] = units[ok] * vres
    return out


def subgrid_units(sg: SubgridMessage, parent: SubgridParent | None = None) -> IntArray:
    """The integer elevations (:data:`ABSENT` where no cell) a receiver holding ``parent`` rebuilds
    from either form of a subgrid; :class:`ContextMismatch` for a PARENT one it cannot rebuild."""
    if isinstance(sg, PredictedSubgrid):
        return decode_predicted_units(sg, parent)
    return decode_subgrid_units(sg)


def parent_from_rows(rows: Sequence[Sequence[int | None]]) -> SubgridParent:
    """A :class:`SubgridParent` from rows of integer elevations (row 0 south, None where absent):
    the form of the vectors' ``parent`` (wire-format.md 13)."""
    present = np.array([[v is not None for v in row] for row in rows], bool)
    z = np.array([[0 if v is None else int(v) for v in row] for row in rows], np.int64)
    return SubgridParent(z, present)


def units_rows(units: IntArray) -> list[list[int | None]]:
    """Integer elevations as rows (row 0 south), None where :data:`ABSENT` (the vectors' form)."""
    return [[None if int(v) == ABSENT else int(v) for v in row] for row in units.tolist()]


def parent_from_values(values: Sequence[Sequence[float]] | npt.ArrayLike, vertical_resolution: float) -> SubgridParent:
    """A :class:`SubgridParent` from elevations in metres (NaN where absent), as a receiver holds them."""
    v = np.asarray(values, np.float64)
    ok = np.isfinite(v)
    z = np.zeros(v.shape, np.int64)
    z[ok] = np.rint(v[ok] / vertical_resolution).astype(np.int64)
    return SubgridParent(z, ok)
