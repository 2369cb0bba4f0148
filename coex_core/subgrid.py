"""Subgrid coding: cell arrays to :class:`~coex_core.messages.Subgrid` messages and back.

Part of the wire format (spec/payloads.md, Subgrid: the encodings are defined there and by
:class:`~coex_core.messages.SubgridEncoding`), so every layer decodes a subgrid with this module:
the bathymetry modality, the LCM decoded products, a third-party tool.

The encoder tries every :class:`~coex_core.messages.SubgridEncoding` (OFFSET: fixed-width offsets
above the block minimum; DELTA: serpentine differences; PLANE: residuals from a fitted plane;
GRADIENT: second differences, complete blocks only; the last three Rice-coded with the best
parameter) and keeps the smallest. All of them use
only the subgrid's own bits, so a lost subgrid never makes another one useless. Both directions
are numpy-vectorised (a DELTA decode is a cumulative sum).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .messages import Subgrid, SubgridEncoding

__all__ = [
    "HEADER_BITS",
    "RICE_ESCAPE",
    "decode_subgrid",
    "decode_subgrid_units",
    "encode_subgrid",
    "subgrid_bits",
]

#: Bits before the values: type id (8) + level 4 + ix 14 + iy 14 + stamp 18 + resolution 3 +
#: vertical resolution 3 + side 4 + encoding 2 + z_base 20 + width 5 + partial flag 1.
HEADER_BITS = 8 + 4 + 14 + 14 + 18 + 3 + 3 + 4 + 2 + 20 + 5 + 1
PLANE_BITS = 24
RICE_ESCAPE = 16
RICE_ESCAPE_LEN_BITS = 5
MAX_K = 16
Z_LIMIT = 1 << 19

IntArray = npt.NDArray[np.int64]


def _zigzag(r: IntArray) -> IntArray:
    return np.where(r >= 0, 2 * r, -2 * r - 1)


def _unzigzag(v: IntArray) -> IntArray:
    return np.where(v & 1, -((v + 1) >> 1), v >> 1)


def _rice_cost(v: IntArray) -> tuple[int, int]:
    """Best Rice parameter for ``v`` and its cost in bits (escapes included)."""
    if v.size == 0:
        return 0, 0
    ks = np.arange(MAX_K)[:, None]
    q = v[None, :] >> ks
    nbits = np.floor(np.log2(np.maximum(v, 1))).astype(np.int64) + 1
    esc = RICE_ESCAPE + RICE_ESCAPE_LEN_BITS + nbits[None, :]
    cost = np.where(q < RICE_ESCAPE, q + 1 + ks, esc).sum(axis=1)
    k = int(np.argmin(cost))
    return k, int(cost[k])


def _serpentine(side: int) -> IntArray:
    """Flat row-major cell indices in serpentine order (even rows west to east, odd rows back)."""
    idx = np.arange(side * side).reshape(side, side)
    idx[1::2] = idx[1::2, ::-1]
    return idx.ravel()


def _mask_int(present: npt.NDArray[np.bool_]) -> int | None:
    if present.all():
        return None
    return int.from_bytes(np.packbits(present.ravel()).tobytes(), "big") >> (-present.size % 8)


def _mask_bits(mask: int | None, side: int) -> npt.NDArray[np.bool_]:
    n = side * side
    if mask is None:
        return np.ones(n, bool)
    nbytes = (n + 7) // 8
    raw = np.frombuffer((mask << (-n % 8)).to_bytes(nbytes, "big"), np.uint8)
    return np.unpackbits(raw)[:n].astype(bool)


def subgrid_bits(sg: Subgrid) -> int:
    """Encoded size in bits (type id included, before padding), computed without construct."""
    bits = HEADER_BITS + (PLANE_BITS if sg.encoding == SubgridEncoding.PLANE else 0)
    if sg.mask is not None:
        bits += sg.side * sg.side
    v = np.asarray(sg.values, np.int64)
    if sg.encoding == SubgridEncoding.OFFSET:
        return bits + v.size * sg.width
    k = sg.width
    q = v >> k
    nb = np.floor(np.log2(np.maximum(v, 1))).astype(np.int64) + 1
    return bits + int(np.where(q < RICE_ESCAPE, q + 1 + k, RICE_ESCAPE + RICE_ESCAPE_LEN_BITS + nb).sum())


def encode_subgrid(
    q: npt.ArrayLike,
    present: npt.ArrayLike,
    *,
    level: int,
    ix: int,
    iy: int,
    stamp: int,
    resolution: float,
    vertical_resolution: float,
    encodings: tuple[SubgridEncoding, ...] = tuple(SubgridEncoding),
) -> Subgrid:
    """The smallest Subgrid for integer elevations ``q`` (side x side, in vertical-resolution
    units, row 0 = south) where ``present`` is true."""
    qa = np.asarray(q, np.int64)
    pa = np.asarray(present, bool)
    side = qa.shape[0]
    mask = _mask_int(pa)
    base = dict(level=level, ix=ix, iy=iy, stamp=stamp, resolution=resolution,
                vertical_resolution=vertical_resolution, side=side, mask=mask)
    flat = qa.ravel()
    pf = pa.ravel()
    vals = flat[pf]
    if vals.size == 0:
        return Subgrid(encoding=SubgridEncoding.OFFSET, z_base=0, width=0, values=(), **base)
    if np.abs(vals).max() >= Z_LIMIT:
        raise ValueError("elevation outside the wire range (|z| < 2**19 vertical units)")
    candidates: list[tuple[int, Subgrid]] = []
    header = HEADER_BITS + (0 if mask is None else side * side)
    if SubgridEncoding.OFFSET in encodings:
        lo = int(vals.min())
        width = int(vals.max() - lo).bit_length()
        codes = vals - lo if width else vals[:0]
        if vals.size * width <= 1536:
            sg = Subgrid(encoding=SubgridEncoding.OFFSET, z_base=lo, width=width,
                         values=tuple(int(c) for c in codes), **base)
            candidates.append((header + vals.size * width, sg))
    if SubgridEncoding.DELTA in encodings:
        order = _serpentine(side)
        ser = flat[order][pf[order]]
        r = np.diff(ser, prepend=ser[0])
        v = _zigzag(r)
        k, cost = _rice_cost(v)
        if cost <= 1536:
            sg = Subgrid(encoding=SubgridEncoding.DELTA, z_base=int(ser[0]), width=k,
                         values=tuple(int(c) for c in v), **base)
            candidates.append((header + cost, sg))
    if SubgridEncoding.PLANE in encodings and vals.size >= 3:
        ii, jj = np.divmod(np.arange(side * side), side)
        ii, jj = ii[pf], jj[pf]
        a = np.stack([np.ones(vals.size), jj, ii], axis=1)
        coef, *_ = np.linalg.lstsq(a, vals.astype(np.float64), rcond=None)
        sx = int(np.clip(round(coef[1] * 8), -2048, 2047))
        sy = int(np.clip(round(coef[2] * 8), -2048, 2047))
        plane = (sx * jj + sy * ii + 4) >> 3
        zb = int(np.median(vals - plane))
        if abs(zb) < Z_LIMIT:
            v = _zigzag(vals - zb - plane)
            k, cost = _rice_cost(v)
            if cost <= 1536:
                sg = Subgrid(encoding=SubgridEncoding.PLANE, z_base=zb, width=k, values=tuple(int(c) for c in v),
                             slope_x=sx, slope_y=sy, **base)
                candidates.append((header + PLANE_BITS + cost, sg))
    if SubgridEncoding.GRADIENT in encodings and mask is None:
        d = qa - qa[0, 0]
        r = np.diff(np.diff(np.pad(d, ((1, 0), (1, 0))), axis=0), axis=1)
        v = _zigzag(r.ravel())
        k, cost = _rice_cost(v)
        if cost <= 1536:
            sg = Subgrid(encoding=SubgridEncoding.GRADIENT, z_base=int(qa[0, 0]), width=k,
                         values=tuple(int(c) for c in v), **base)
            candidates.append((header + cost, sg))
    if not candidates:
        raise ValueError("no encoding fits this subgrid")
    return min(candidates, key=lambda c: (c[0], int(c[1].encoding)))[1]


def decode_subgrid(sg: Subgrid) -> npt.NDArray[np.float64]:
    """Elevations in metres (side x side, row 0 = south), NaN where the subgrid has no cell."""
    q = decode_subgrid_units(sg)
    out = np.full(q.shape, np.nan)
    ok = q != np.iinfo(np.int64).min
    out[ok] = q[ok] * sg.vertical_resolution
    return out


def decode_subgrid_units(sg: Subgrid) -> IntArray:
    """Integer elevations (vertical-resolution units); ``iinfo(int64).min`` where absent."""
    side = sg.side
    present = _mask_bits(sg.mask, side)
    v = np.asarray(sg.values, np.int64)
    out = np.full(side * side, np.iinfo(np.int64).min, np.int64)
    n = int(present.sum())
    if sg.encoding == SubgridEncoding.OFFSET:
        out[present] = sg.z_base + (v if sg.width else np.zeros(n, np.int64))
    elif sg.encoding == SubgridEncoding.DELTA:
        order = _serpentine(side)
        sel = order[present[order]]
        out[sel] = sg.z_base + np.cumsum(_unzigzag(v))
    elif sg.encoding == SubgridEncoding.GRADIENT:
        if sg.mask is not None:
            raise ValueError("a GRADIENT subgrid has no mask")
        r = _unzigzag(v).reshape(side, side)
        out[:] = (sg.z_base + np.cumsum(np.cumsum(r, axis=0), axis=1)).ravel()
    else:
        ii, jj = np.divmod(np.arange(side * side), side)
        if sg.slope_x is None or sg.slope_y is None:
            raise ValueError("a PLANE subgrid needs slopes")
        plane = (sg.slope_x * jj[present] + sg.slope_y * ii[present] + 4) >> 3
        out[present] = sg.z_base + plane + _unzigzag(v)
    return out.reshape(side, side)
