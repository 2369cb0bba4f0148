"""The coded cells of a ``PredictedSubgrid``: presence and residuals through the binary
arithmetic coder (:mod:`._arith`), with adaptive contexts (spec/payloads.md section 1.7).

The stream codes, in order:

1. when the subgrid is partial, one presence decision per cell in row-major order (1 = present),
   context ``P[n]``, ``n = w + 2 s`` where ``w`` (``s``) is 1 when the cell west (south) of it
   is inside the block and present;
2. for each present cell in row-major order, its residual ``e`` (an integer): with ``u = |e| >>
   shift``, the decision ``u > 0`` (context ``Z[c]``); if so, ``u > t`` for ``t = 1, 2, ...``
   (context ``U[c][min(t - 1, 3)]``) until a 0 or ``t = 15``; past 15, ``u - 16`` in an
   order-0 Exp-Golomb code of fixed-probability decisions; then the ``shift`` low bits of ``|e|``
   (fixed probability, most significant first); then, when ``e != 0``, its sign (context ``S``,
   1 = negative). The class ``c`` comes from the residuals of the cell's west and south
   neighbours already coded: ``a = (|e_w| + |e_s|) >> shift`` when both are present, ``2 |e_x| >>
   shift`` when one is, and ``c = 1`` when neither; otherwise ``c = 0`` for ``a = 0``, 1 for ``a
   <= 2``, 2 for ``a <= 5``, 3 above.

Every context starts from the initial table the message's ``table`` selects
(:data:`INITIAL`) and adapts as :func:`._arith.adapt` says.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

from ._arith import HALF_P, ArithDecoder, ArithEncoder, CodeError

__all__ = [
    "CodeError",
    "CodedCells",
    "INITIAL",
    "MAX_ESCAPE_BITS",
    "MAX_RESIDUAL",
    "Table",
    "UNARY_LIMIT",
    "decode_cells",
    "encode_cells",
    "table_for",
]

#: unary decisions ``u > t`` up to this ``t``; larger ``u`` take the escape
UNARY_LIMIT = 15
#: residuals are below this in magnitude (elevations and predictions are within +-2^19 units)
MAX_RESIDUAL = 1 << 21
#: an escape's Exp-Golomb prefix is at most this many one-decisions
MAX_ESCAPE_BITS = 21


class Table:
    """One set of initial probabilities (of a 0, in 1/4096): ``z[c]``, ``u[c][k]``, ``s``,
    ``p[n]``."""

    __slots__ = ("p", "s", "u", "z")

    def __init__(self, z: Sequence[int], u: Sequence[Sequence[int]], s: int, p: Sequence[int]) -> None:
        self.z, self.u, self.s, self.p = tuple(z), tuple(tuple(r) for r in u), int(s), tuple(p)


#: Initial probability tables, by :func:`table_for` (spec/payloads.md 1.10; fitted on the
#: benchmark's development scenes by ``scripts/subgrid_tables.py``, two rounds from flat tables).
INITIAL: tuple[Table, ...] = (
    Table([2328, 2171, 1761, 1157], [[3885, 3997, 3430, 463], [3795, 3971, 3642, 894], [3472, 3821, 3189, 656], [1598, 1239, 1059, 489]], 1931, [3915, 2436, 623, 16]),
    Table([2900, 2469, 1175, 804], [[3922, 3259, 3099, 2168], [3546, 3281, 3300, 2581], [2464, 2866, 3010, 2904], [1753, 1944, 1940, 1509]], 1764, [3964, 1465, 1452, 16]),
    Table([3177, 2512, 713, 467], [[3878, 2090, 1942, 1874], [3226, 2035, 1928, 1949], [1437, 1665, 1800, 2111], [964, 1152, 1582, 1780]], 1811, [4002, 1851, 1477, 16]),
    Table([3096, 2405, 1540, 876], [[3229, 1685, 1465, 868], [3450, 2883, 2319, 1542], [2048, 2530, 2658, 1624], [843, 671, 890, 924]], 2123, [3964, 1475, 1493, 16]),
)


def table_for(parent_context: bool, level: int) -> int:
    """The initial table of a subgrid: predicted from its parent, by level (0, 1, 2 and up: 0,
    1, 2); from its own base: 3."""
    return min(int(level), 2) if parent_context else 3


class CodedCells:
    """What the stream holds: the presence of each cell (row-major; None: every cell present)
    and the residuals of the present cells in row-major order."""

    __slots__ = ("present", "residuals")

    def __init__(self, present: Sequence[bool] | None, residuals: Sequence[int]) -> None:
        self.present = None if present is None else tuple(bool(p) for p in present)
        self.residuals = tuple(int(e) for e in residuals)


def _cls(a: int) -> int:
    return 0 if a == 0 else 1 if a <= 2 else 2 if a <= 5 else 3


def _class(mags: list[int], n: int, i: int, j: int, side: int, shift: int) -> int:
    w = mags[n - 1] if j > 0 else -1
    s = mags[n - side] if i > 0 else -1
    if w >= 0 and s >= 0:
        return _cls((w + s) >> shift)
    if w >= 0:
        return _cls((2 * w) >> shift)
    if s >= 0:
        return _cls((2 * s) >> shift)
    return 1


def encode_cells(side: int, cells: CodedCells, shift: int, table: int,
                 counts: dict[tuple[str, int, int], list[int]] | None = None) -> list[int]:
    """The coded bits of ``cells`` (presence when partial, then the residuals). ``counts``, when
    given, counts each adaptive decision by context (``("z", c, 0)``, ``("u", c, k)``, ``("s",
    0, 0)``, ``("p", n, 0)`` -> [zeros, ones]): what the initial tables are fitted to."""
    if counts is None:
        return list(_encode_cached(side, cells.present, cells.residuals, shift, table))
    return _encode(side, cells.present, cells.residuals, shift, table, counts)


@functools.lru_cache(maxsize=4096)
def _encode_cached(side: int, present: tuple[bool, ...] | None, residuals: tuple[int, ...], shift: int,
                   table: int) -> tuple[int, ...]:
    # the sender sizes candidates, then construct builds the one chosen: coded once
    return tuple(_encode(side, present, residuals, shift, table, None))


def _encode(side: int, present_in: tuple[bool, ...] | None, residuals: tuple[int, ...], shift: int, table: int,
            counts: dict[tuple[str, int, int], list[int]] | None) -> list[int]:
    t = INITIAL[table]
    z, u, p = list(t.z), [list(r) for r in t.u], list(t.p)
    sgn = [t.s]
    enc = ArithEncoder()
    adaptive = enc.adaptive
    n_cells = side * side
    present = present_in if present_in is not None else (True,) * n_cells
    if len(present) != n_cells:
        raise ValueError(f"{len(present)} presence flags for {n_cells} cells")
    if present_in is not None:
        for n in range(n_cells):
            i, j = divmod(n, side)
            ctx = (1 if j > 0 and present[n - 1] else 0) + (2 if i > 0 and present[n - side] else 0)
            b = 1 if present[n] else 0
            if counts is not None:
                counts.setdefault(("p", ctx, 0), [0, 0])[b] += 1
            adaptive(b, p, ctx)
    if sum(present) != len(residuals):
        raise ValueError(f"{len(residuals)} residuals for {sum(present)} present cells")
    mags = [-1] * n_cells
    k = 0
    for n in range(n_cells):
        if not present[n]:
            continue
        e = residuals[k]
        k += 1
        m = -e if e < 0 else e
        if m >= MAX_RESIDUAL:
            raise ValueError(f"residual {e} too large")
        c = _class(mags, n, n // side, n % side, side, shift)
        mags[n] = m
        q = m >> shift
        if counts is not None:
            counts.setdefault(("z", c, 0), [0, 0])[1 if q else 0] += 1
        adaptive(1 if q else 0, z, c)
        if q:
            row = u[c]
            tt = 1
            while tt <= UNARY_LIMIT:
                b = 1 if q > tt else 0
                ix = tt - 1 if tt < 4 else 3
                if counts is not None:
                    counts.setdefault(("u", c, ix), [0, 0])[b] += 1
                adaptive(b, row, ix)
                if not b:
                    break
                tt += 1
            else:
                v = q - UNARY_LIMIT
                nb = v.bit_length() - 1
                for _ in range(nb):
                    enc.encode(1, HALF_P)
                enc.encode(0, HALF_P)
                for bit in range(nb - 1, -1, -1):
                    enc.encode((v >> bit) & 1, HALF_P)
        for bit in range(shift - 1, -1, -1):
            enc.encode((m >> bit) & 1, HALF_P)
        if m:
            b = 1 if e < 0 else 0
            if counts is not None:
                counts.setdefault(("s", 0, 0), [0, 0])[b] += 1
            adaptive(b, sgn, 0)
    return enc.finish()


def decode_cells(read: Callable[[], int], side: int, partial: bool, shift: int,
                 table: int, max_bits: int | None = None) -> tuple[CodedCells, int]:
    """The cells coded at the reader's position and the length of their code in bits;
    :class:`CodeError` (``too large``) as soon as the code passes ``max_bits``."""
    t = INITIAL[table]
    z, u, p = list(t.z), [list(r) for r in t.u], list(t.p)
    sgn = [t.s]
    dec = ArithDecoder(read, max_bits)
    n_cells = side * side
    present: list[bool]
    if partial:
        present = []
        for n in range(n_cells):
            i, j = divmod(n, side)
            ctx = (1 if j > 0 and present[n - 1] else 0) + (2 if i > 0 and present[n - side] else 0)
            present.append(bool(dec.adaptive(p, ctx)))
    else:
        present = [True] * n_cells
    mags = [-1] * n_cells
    res: list[int] = []
    for n in range(n_cells):
        if not present[n]:
            continue
        i, j = divmod(n, side)
        c = _class(mags, n, i, j, side, shift)
        b = dec.adaptive(z, c)
        q = 0
        if b:
            row = u[c]
            q = 1
            while True:
                b = dec.adaptive(row, min(q - 1, 3))
                if not b:
                    break
                q += 1
                if q > UNARY_LIMIT:
                    nb = 0
                    while dec.decode(HALF_P):
                        nb += 1
                        if nb > MAX_ESCAPE_BITS:
                            raise CodeError("an escape's prefix is too long", "above maximum")
                    v = 1
                    for _ in range(nb):
                        v = (v << 1) | dec.decode(HALF_P)
                    q = v - 1 + UNARY_LIMIT + 1
                    break
        m = q
        for _ in range(shift):
            m = (m << 1) | dec.decode(HALF_P)
        if m >= MAX_RESIDUAL:
            raise CodeError(f"residual {m} too large", "above maximum")
        e = m
        if m:
            e = -m if dec.adaptive(sgn, 0) else m
        mags[n] = m
        res.append(e)
    return CodedCells(present if partial else None, res), dec.length
