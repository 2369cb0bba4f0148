"""An independent decoder of bathymetry subgrids, written from ``spec/wire-format.md`` (the field
tables of `Subgrid` and `PredictedSubgrid`, sections 2, 5, 6, 13.1 and 13.3) and
``spec/payloads.md`` (sections 0 and 1.1 to 1.10) alone. It imports nothing of CoEx: the
initial probability tables are read from the text of payloads.md section 1.10.

It speaks the vector-checking protocol of wire-format.md section 13.3 on standard input and
output (``message HEX`` for a Subgrid or PredictedSubgrid, ``cells JSON``), so it is checked with
``coex spec vectors --check-command "python tests/spec_decoder/subgrids.py" --only ...``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
PAYLOADS = (ROOT / "spec" / "payloads.md").read_text()

RESOLUTIONS = [0.125, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0]            # wire-format.md, table index
VERTICAL = [0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0]
ENCODINGS = ["OFFSET", "DELTA", "PLANE", "GRADIENT"]
CONTEXTS = ["NONE", "PARENT"]
SIDES = [2, 4, 8, 16]


class Invalid(Exception):
    """The input breaks a rule; ``args[0]`` is its error word (section 13.2)."""


# ------------------------------------------------------------------------------- bits

class Bits:
    """Most significant bit first (section 2); reading past the end is `truncated`, peeking
    past it gives 0."""

    def __init__(self, data: bytes) -> None:
        self.bits = [(b >> (7 - k)) & 1 for b in data for k in range(8)]
        self.pos = 0

    def read(self, n: int) -> int:
        if self.pos + n > len(self.bits):
            raise Invalid("truncated")
        v = 0
        for b in self.bits[self.pos:self.pos + n]:
            v = 2 * v + b
        self.pos += n
        return v

    def signed(self, n: int) -> int:
        v = self.read(n)
        return v - 2 ** n if v >= 2 ** (n - 1) else v

    def peek(self, k: int) -> int:
        return self.bits[k] if k < len(self.bits) else 0

    def padding(self) -> None:
        while self.pos % 8:
            if self.read(1):
                raise Invalid("padding")


# ------------------------------------------------------------------- the tables, 1.10

def _tables() -> list[dict[str, Any]]:
    section = PAYLOADS.split("### 1.10", 1)[1].split("\n## ", 1)[0]
    out = []
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 9 and cells[0].isdigit():
            nums = [[int(x) for x in c.split(",")] for c in cells[2:]]
            out.append({"Z": nums[0], "U": nums[1:5], "S": nums[5][0], "P": nums[6]})
    assert len(out) == 4, "payloads.md 1.10 has four tables"
    return out


TABLES = _tables()


# ---------------------------------------------------------------- the coder, 1.7

class Coder:
    """Both directions of the arithmetic coder of payloads.md 1.7 (an encoder when ``bits`` is
    None, otherwise a decoder reading them from ``start``)."""

    HALF, QTR = 2 ** 31, 2 ** 30

    def __init__(self, bits: Bits | None = None, start: int = 0) -> None:
        self.low, self.high, self.pending = 0, 2 ** 32 - 1, 0
        self.src, self.start, self.shifts = bits, start, 0
        self.out: list[int] = []
        self.read_upto = start + 32  # bits taken into `value` so far
        self.value = 0
        if bits is not None:
            for k in range(32):
                self.value = 2 * self.value + bits.peek(start + k)

    def _write(self, b: int) -> None:
        self.out += [b] + [1 - b] * self.pending
        self.pending = 0

    def decision(self, b: int | None, p0: int) -> int:
        split = self.low + (self.high - self.low + 1) * p0 // 4096 - 1
        if self.src is not None:
            b = 0 if self.value <= split else 1
        if b == 0:
            self.high = split
        else:
            self.low = split + 1
        while True:
            if self.high < self.HALF:
                self._write(0)
            elif self.low >= self.HALF:
                self._write(1)
                self.low -= self.HALF
                self.high -= self.HALF
                self.value -= self.HALF
            elif self.low >= self.QTR and self.high < 3 * self.QTR:
                self.pending += 1
                self.low -= self.QTR
                self.high -= self.QTR
                self.value -= self.QTR
            else:
                break
            self.low, self.high = 2 * self.low, 2 * self.high + 1
            self.shifts += 1
            if self.src is not None and self.shifts + 2 > 1536:
                raise Invalid("too large")
            if self.src is not None:
                self.value = 2 * self.value + self.src.peek(self.read_upto)
                self.read_upto += 1
        assert b is not None
        return b

    def finish(self) -> list[int]:
        self.pending += 1
        self._write(0 if self.low < self.QTR else 1)
        return self.out


class Adaptive:
    def __init__(self, coder: Coder) -> None:
        self.c = coder

    def __call__(self, probs: list[int], k: int, b: int | None = None) -> int:
        p0 = probs[k]
        b = self.c.decision(b, p0)
        probs[k] = p0 + (4096 - p0) // 16 if b == 0 else p0 - p0 // 16
        return b


def cells_code(side: int, partial: bool, shift: int, table: int, coder: Coder,
               mask: int | None = None, residuals: list[int] | None = None) -> tuple[int | None, list[int]]:
    """Presence and residuals through ``coder`` (decoding when ``residuals`` is None)."""
    t = TABLES[table]
    Z, S, P = list(t["Z"]), [t["S"]], list(t["P"])
    U = [list(r) for r in t["U"]]
    adapt = Adaptive(coder)
    raw = coder.decision
    enc = residuals is not None
    n_cells = side * side
    present = [True] * n_cells
    if partial:
        for n in range(n_cells):
            i, j = divmod(n, side)
            ctx = (1 if j > 0 and present[n - 1] else 0) + (2 if i > 0 and present[n - side] else 0)
            want = ((mask or 0) >> (n_cells - 1 - n)) & 1 if enc else None
            present[n] = bool(adapt(P, ctx, want))
    mags: dict[int, int] = {}
    res: list[int] = []
    k = 0
    for n in range(n_cells):
        if not present[n]:
            continue
        i, j = divmod(n, side)
        mw = mags.get(n - 1) if j > 0 else None
        ms = mags.get(n - side) if i > 0 else None
        if mw is not None and ms is not None:
            a = (mw + ms) // 2 ** shift
        elif mw is not None:
            a = 2 * mw // 2 ** shift
        elif ms is not None:
            a = 2 * ms // 2 ** shift
        else:
            a = None
        c = 1 if a is None else 0 if a == 0 else 1 if a <= 2 else 2 if a <= 5 else 3
        e = residuals[k] if residuals is not None else 0
        k += 1
        u = abs(e) // 2 ** shift
        if adapt(Z, c, (1 if u > 0 else 0) if enc else None):
            t_ = 1
            while True:
                if not adapt(U[c], min(t_ - 1, 3), (1 if u > t_ else 0) if enc else None):
                    u = t_
                    break
                if t_ == 15:  # an escape: order-0 Exp-Golomb of x = u - 16
                    x1 = u - 16 + 1 if enc else 0
                    kk = x1.bit_length() - 1 if enc else 0
                    ones = 0
                    while raw(1 if enc and ones < kk else 0 if enc else None, 2048):
                        ones += 1
                        if ones > 21:
                            raise Invalid("above maximum")
                    v = 1
                    for bit in range(ones - 1, -1, -1):
                        v = 2 * v + raw(((x1 >> bit) & 1) if enc else None, 2048)
                    u = 16 + v - 1
                    break
                t_ += 1
        elif not enc:
            u = 0
        m = u
        for bit in range(shift - 1, -1, -1):
            m = 2 * m + raw(((abs(e) >> bit) & 1) if enc else None, 2048)
        if m >= 2 ** 21:
            raise Invalid("above maximum")
        if m:
            neg = adapt(S, 0, (1 if e < 0 else 0) if enc else None)
            e = -m if neg else m
        else:
            e = 0
        mags[n] = m
        res.append(e)
    out_mask = None
    if partial:
        out_mask = 0
        for p in present:
            out_mask = 2 * out_mask + int(p)
    return out_mask, res


# ------------------------------------------------------------------ the messages

def predicted(b: Bits) -> dict[str, Any]:
    """PredictedSubgrid (type 20) after its type id: wire-format.md's table."""
    f: dict[str, Any] = {"level": b.read(4), "ix": b.signed(14), "iy": b.signed(14), "stamp": b.read(18),
                         "side": SIDES[b.read(2)], "context": CONTEXTS[b.read(1)]}
    parent = f["context"] == "PARENT"
    f["check"] = b.read(8) if parent else None
    f["resolution"] = None if parent else RESOLUTIONS[b.read(3)]
    f["vertical_resolution"] = None if parent else VERTICAL[b.read(3)]
    f["z_base"] = None if parent else b.signed(20)
    f["predictor"], f["shift"] = b.read(2), b.read(2)
    partial = bool(b.read(1))
    table = (min(f["level"], 2) if parent else 3)
    mask, res = coded_cells(b, f["side"], partial, f["shift"], table)
    b.padding()
    f["cells"] = {"mask": mask, "residuals": res}
    return f


def coded_cells(b: Bits, side: int, partial: bool, shift: int, table: int) -> tuple[int | None, list[int]]:
    """`cells` (payloads.md 1.7) from ``b.pos``, with every check of that section; ``b.pos`` ends
    after the last bit of `cells`."""
    start = b.pos
    coder = Coder(b, start)
    try:
        mask, res = cells_code(side, partial, shift, table, coder)
    except Invalid as exc:
        if coder.read_upto > len(b.bits):  # decided on bits past the end: they were not there
            raise Invalid("truncated") from exc
        raise
    length = coder.shifts + 2
    if start + length > len(b.bits):
        raise Invalid("truncated")
    again = Coder()
    cells_code(side, partial, shift, table, again, mask, res)
    if again.finish() != b.bits[start:start + length]:
        raise Invalid("canonical")
    b.pos = start + length
    return mask, res


def _rice(b: Bits, k: int) -> int:
    q = 0
    while b.read(1):
        q += 1
        if q == 16:
            m = b.read(5)
            v = b.read(m)
            if v >> k <= 15 or m != v.bit_length():
                raise Invalid("canonical")
            return v
    return int(q * 2 ** k + b.read(k))


def subgrid(b: Bits) -> dict[str, Any]:
    """Subgrid (type 17) after its type id: wire-format.md's table, payloads.md 1.2 and 1.3."""
    f: dict[str, Any] = {"level": b.read(4), "ix": b.signed(14), "iy": b.signed(14), "stamp": b.read(18),
                         "resolution": RESOLUTIONS[b.read(3)], "vertical_resolution": VERTICAL[b.read(3)]}
    side_code = b.read(4)
    if side_code > 14:
        raise Invalid("above maximum")
    f["side"] = side_code + 2
    f["encoding"] = ENCODINGS[b.read(2)]
    f["z_base"] = b.signed(20)
    f["width"] = b.read(5)
    if f["width"] > 24:
        raise Invalid("above maximum")
    plane = f["encoding"] == "PLANE"
    f["slope_x"] = b.signed(12) if plane else None
    f["slope_y"] = b.signed(12) if plane else None
    partial = b.read(1)
    n = f["side"] ** 2
    f["mask"] = b.read(n) if partial else None
    count = 0 if f["encoding"] == "OFFSET" and f["width"] == 0 else (n if f["mask"] is None else bin(f["mask"]).count("1"))
    start = b.pos
    if f["encoding"] == "OFFSET":
        f["values"] = [b.read(f["width"]) for _ in range(count)]
    else:
        f["values"] = [_rice(b, f["width"]) for _ in range(count)]
    if b.pos - start > 1536:
        raise Invalid("too large")
    if f["encoding"] == "GRADIENT" and partial:
        raise Invalid("GRADIENT")
    b.padding()
    return f


def message(data: bytes) -> dict[str, Any]:
    if not data:
        raise Invalid("empty")
    b = Bits(data)
    tid = b.read(8)
    if tid == 17:
        fields, name = subgrid(b), "Subgrid"
    elif tid == 20:
        fields, name = predicted(b), "PredictedSubgrid"
    else:
        raise Invalid(f"not a subgrid: type {tid}")
    if b.pos != len(b.bits):
        raise Invalid("after the message")
    return {"type": name, "fields": fields}


# ---------------------------------------------------------------- elevations, 1.4 and 1.8

def _uz(v: int) -> int:
    return v // 2 if v % 2 == 0 else -(v + 1) // 2


def subgrid_cells(f: dict[str, Any]) -> list[list[int | None]]:
    side = f["side"]
    n = side * side
    present = [True] * n if f["mask"] is None else [bool((f["mask"] >> (n - 1 - k)) & 1) for k in range(n)]
    z: list[int | None] = [None] * n
    vals = f["values"]
    order = [i * side + (j if i % 2 == 0 else side - 1 - j) for i in range(side) for j in range(side)]
    if f["encoding"] == "OFFSET":
        k = 0
        for c in range(n):
            if present[c]:
                z[c] = f["z_base"] + (vals[k] if f["width"] else 0)
                k += 1
    elif f["encoding"] == "DELTA":
        last = f["z_base"]
        k = 0
        for c in order:
            if present[c]:
                last = last + _uz(vals[k])
                z[c] = last
                k += 1
    elif f["encoding"] == "PLANE":
        k = 0
        for c in range(n):
            if present[c]:
                i, j = divmod(c, side)
                z[c] = f["z_base"] + (f["slope_x"] * j + f["slope_y"] * i + 4) // 8 + _uz(vals[k])
                k += 1
    else:
        for c in range(n):
            i, j = divmod(c, side)
            def at(a: int, b: int) -> int:
                v = f["z_base"] if a < 0 or b < 0 else z[a * side + b]
                assert v is not None
                return int(v)
            z[c] = at(i - 1, j) + at(i, j - 1) - at(i - 1, j - 1) + _uz(vals[c])
    return [z[i * side:(i + 1) * side] for i in range(side)]


class Context(Exception):
    """The subgrid cannot be rebuilt with the parent cells given (payloads.md 1.9)."""


def _crc8(data: list[int]) -> int:
    crc = 0
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


BILINEAR = ({-1: 1, 0: 3}, {0: 3, 1: 1}, 16)
CUBIC = ({-2: -3, -1: 29, 0: 111, 1: -9}, {-1: -9, 0: 111, 1: 29, 2: -3}, 16384)
PARENT_TABLE = [("nearest", "none"), ("bilinear", "none"), ("cubic", "none"), ("cubic", "half")]
NONE_TABLE = [("base", "none"), ("base", "median"), ("base", "planar"), ("base", "half")]


def predicted_cells(f: dict[str, Any], parent: list[list[int | None]] | None) -> list[list[int | None]]:
    side = f["side"]
    n = side * side
    mask = f["cells"]["mask"]
    present = [True] * n if mask is None else [bool((mask >> (n - 1 - k)) & 1) for k in range(n)]
    surface_kind, correction = (PARENT_TABLE if f["context"] == "PARENT" else NONE_TABLE)[f["predictor"]]
    if f["context"] == "PARENT":
        if parent is None or len(parent) != side or any(len(r) != side for r in parent):
            raise Context("no parent of this side")
        h = side // 2
        qx, qy = f["ix"] % 2, f["iy"] % 2  # Python's % is the floor one of 1.6
        rows = range(max(0, qy * h - 2), min(side, qy * h + h + 2))
        cols = range(max(0, qx * h - 2), min(side, qx * h + h + 2))
        data: list[int] = []
        held = []
        for a in rows:
            for b in cols:
                v = parent[a][b]
                data += [0x80, 0, 0] if v is None else list((v % 2 ** 24).to_bytes(3, "big"))
                if v is not None:
                    held.append(v)
        if not held or _crc8(data) != f["check"]:
            raise Context("the check fails")
        M = sum(held) // len(held)

        held_rows = parent

        def P(a: int, b: int) -> int | None:
            return held_rows[a][b] if 0 <= a < side and 0 <= b < side else None

        def surface(i: int, j: int) -> int:
            pa, pb = qy * h + i // 2, qx * h + j // 2
            centre = P(pa, pb)
            C = centre if centre is not None else M
            if surface_kind == "nearest":
                return C
            even, odd, D = BILINEAR if surface_kind == "bilinear" else CUBIC
            total = 0
            for da, wa in (even if i % 2 == 0 else odd).items():
                for db, wb in (even if j % 2 == 0 else odd).items():
                    tap, mirror = P(pa + da, pb + db), P(pa - da, pb - db)
                    if tap is not None:
                        V = tap
                    elif mirror is not None:
                        V = 2 * C - mirror
                    else:
                        V = C
                    total += wa * wb * V
            return (total + D // 2) // D
    else:
        def surface(i: int, j: int) -> int:
            return int(f["z_base"])
    z: list[int | None] = [None] * n
    d: dict[tuple[int, int], int] = {}
    res = iter(f["cells"]["residuals"])
    for c in range(n):
        if not present[c]:
            continue
        i, j = divmod(c, side)
        W, S, SW = d.get((i, j - 1)), d.get((i - 1, j)), d.get((i - 1, j - 1))
        if correction == "none":
            g = 0
        elif W is not None and S is not None and SW is not None:
            if correction == "planar":
                g = W + S - SW
            elif correction == "median":
                g = min(W, S) if SW >= max(W, S) else max(W, S) if SW <= min(W, S) else W + S - SW
            else:
                g = (2 * W + 2 * S - SW + 2) // 4
        elif W is not None or S is not None:
            x = W if W is not None else S
            assert x is not None
            g = (x + 1) // 2 if correction == "half" else x
        else:
            g = 0
        u = surface(i, j)
        value = u + g + next(res)
        z[c] = value
        d[(i, j)] = value - u
    return [z[i * side:(i + 1) * side] for i in range(side)]


# ------------------------------------------------------------------ the protocol, 13.3

def answer(line: str) -> dict[str, Any]:
    scope, _, rest = line.strip().partition(" ")
    try:
        if scope == "message":
            return message(bytes.fromhex(rest))
        if scope == "cells":
            q = json.loads(rest)
            m = message(bytes.fromhex(q["hex"]))
            try:
                if m["type"] == "Subgrid":
                    return {"cells": subgrid_cells(m["fields"])}
                return {"cells": predicted_cells(m["fields"], q["parent"])}
            except Context:
                return {"error": "context"}
        return {"error": f"unsupported scope {scope}"}
    except Invalid as exc:
        return {"error": str(exc.args[0])}


def main() -> int:
    for line in sys.stdin:
        if line.strip():
            sys.stdout.write(json.dumps(answer(line)) + "\n")
            sys.stdout.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
