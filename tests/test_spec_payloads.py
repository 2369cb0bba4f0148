"""An independent decoder written only from ``spec/payloads.md``, checked against the reference.

Everything named ``spec_*`` (and the helpers it uses) is built from the document alone: plain
Python, numpy, and glymur for the JPEG 2000 decode. The reference plugins are imported only to
*produce* messages and the results to compare against; ``coex_core.wire`` is used only to get a
message's field values from its bytes (and, for the Subgrid, not even that: its bits are parsed
here from the wire-format table and the payload document).
"""

from __future__ import annotations

import itertools
import math
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from coex_core import wire
from coex_core.errors import DecodeError
from coex_core.messages import (
    ImageAnnounce,
    ImageFragment,
    Subgrid,
    SubgridEncoding,
    TimeSeriesChunk,
)

# ================================================================ the independent decoder


class SpecError(ValueError):
    """Input the document says a receiver must reject (or ignore)."""


class BitReader:
    """Bits of a byte string, most significant bit first (payloads.md section 0)."""

    def __init__(self, data: bytes, pos: int = 0) -> None:
        self.bits: list[int] = np.unpackbits(np.frombuffer(data, np.uint8)).tolist()
        self.pos = pos

    def read(self, n: int) -> int:
        if self.pos + n > len(self.bits):
            raise SpecError("truncated")
        v = 0
        for b in self.bits[self.pos:self.pos + n]:
            v = (v << 1) | b
        self.pos += n
        return v

    def signed(self, n: int) -> int:
        v = self.read(n)
        return v - (1 << n) if v >> (n - 1) else v

    def check_padding(self) -> None:
        rest = self.bits[self.pos:]
        if len(rest) >= 8 or any(rest):
            raise SpecError("padding")


def uz(v: int) -> int:
    """Inverse zigzag (section 0)."""
    return v >> 1 if v % 2 == 0 else -((v + 1) >> 1)


def bits_of(v: int, n: int) -> list[int]:
    return [(v >> (n - 1 - i)) & 1 for i in range(n)]


# ---------------------------------------------------------------- section 1: Subgrid

RESOLUTIONS = (0.125, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0)
VERTICAL_RESOLUTIONS = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0)
OFFSET, DELTA, PLANE, GRADIENT = 0, 1, 2, 3


def spec_read_subgrid_rice(r: BitReader, k: int) -> tuple[int, bool]:
    """One Rice code with escape (section 1.3); returns the value and whether it was escaped."""
    q = 0
    while q < 16:
        if r.read(1) == 0:
            return (q << k) | r.read(k), False
        q += 1
    m = r.read(5)
    v = r.read(m)
    if v >> k <= 15 or m != v.bit_length():
        raise SpecError("non-canonical escape")
    return v, True


def spec_parse_subgrid(msg: bytes) -> dict[str, Any]:
    """Every field of a Subgrid message (type id included), from its bytes."""
    r = BitReader(msg)
    if r.read(8) != 17:
        raise SpecError("not a Subgrid")
    f: dict[str, Any] = {}
    f["level"] = r.read(4)
    f["ix"] = r.signed(14)
    f["iy"] = r.signed(14)
    f["stamp"] = r.read(18)
    f["resolution"] = RESOLUTIONS[r.read(3)]
    f["vertical_resolution"] = VERTICAL_RESOLUTIONS[r.read(3)]
    f["side"] = side = r.read(4) + 2
    f["encoding"] = enc = r.read(2)
    f["z_base"] = r.signed(20)
    f["width"] = width = r.read(5)
    if side > 16 or width > 24:
        raise SpecError("out of range")
    f["slope_x"] = f["slope_y"] = None
    if enc == PLANE:
        f["slope_x"] = r.signed(12)
        f["slope_y"] = r.signed(12)
    partial = r.read(1)
    if partial and enc == GRADIENT:
        raise SpecError("GRADIENT with a mask")
    f["mask"] = r.read(side * side) if partial else None
    present = [bool(b) for b in bits_of(f["mask"], side * side)] if partial else [True] * (side * side)
    f["present"] = present
    if enc == OFFSET and width == 0:
        n = 0
    elif enc == GRADIENT:
        n = side * side
    else:
        n = sum(present)
    f["values_pos"] = start = r.pos
    values, escapes = [], 0
    for _ in range(n):
        if enc == OFFSET:
            values.append(r.read(width))
        else:
            v, esc = spec_read_subgrid_rice(r, width)
            values.append(v)
            escapes += esc
    if r.pos - start > 1536:
        raise SpecError("more than 1536 value bits")
    f["values_end"] = r.pos
    r.check_padding()
    f["values"] = tuple(values)
    f["escapes"] = escapes
    return f


def spec_subgrid_units(f: dict[str, Any]) -> list[list[int | None]]:
    """Integer elevations ``z[i][j]`` (row 0 south, column 0 west); None where absent (1.4)."""
    side, enc, zb, v = f["side"], f["encoding"], f["z_base"], f["values"]
    present = f["present"]
    z: list[list[int | None]] = [[None] * side for _ in range(side)]
    cells = [(n // side, n % side) for n in range(side * side) if present[n]]
    if enc == OFFSET:
        for t, (i, j) in enumerate(cells):
            z[i][j] = zb + (v[t] if f["width"] else 0)
    elif enc == DELTA:
        serp = [(i, j if i % 2 == 0 else side - 1 - j) for i in range(side) for j in range(side)]
        chain = [(i, j) for i, j in serp if present[i * side + j]]
        prev = zb
        for t, (i, j) in enumerate(chain):
            prev = prev + uz(v[t])
            z[i][j] = prev
    elif enc == PLANE:
        for t, (i, j) in enumerate(cells):
            plane = (f["slope_x"] * j + f["slope_y"] * i + 4) // 8
            z[i][j] = zb + plane + uz(v[t])
    else:
        def at(i: int, j: int) -> int:
            if i < 0 or j < 0:
                return zb
            got = z[i][j]
            assert got is not None
            return got
        for i in range(side):
            for j in range(side):
                z[i][j] = at(i - 1, j) + at(i, j - 1) - at(i - 1, j - 1) + uz(v[i * side + j])
    return z


def spec_subgrid_cells(f: dict[str, Any]) -> dict[tuple[float, float], float]:
    """``(x, y)`` of each present cell's south-west corner (metres) -> elevation in metres (1.1)."""
    c = f["resolution"] * 2 ** f["level"]
    s = f["side"]
    out = {}
    for i, row in enumerate(spec_subgrid_units(f)):
        for j, z in enumerate(row):
            if z is not None:
                out[((f["ix"] * s + j) * c, (f["iy"] * s + i) * c)] = z * f["vertical_resolution"]
    return out


def spec_rice_plain(v: int, k: int) -> list[int]:
    return [1] * (v >> k) + [0] + bits_of(v, k)


def spec_rice_escape(v: int, m: int) -> list[int]:
    return [1] * 16 + bits_of(m, 5) + bits_of(v, m)


# ---------------------------------------------------------------- section 2: time series

FILTERS: dict[int, tuple[list[float], list[float]]] = {  # appendix A: (lo, hi)
    0: ([0.7071067811865476, 0.7071067811865476], [0.7071067811865476, -0.7071067811865476]),
    1: ([0.0, 0.3535533905932738, 0.7071067811865476, 0.3535533905932738, 0.0, 0.0],
        [0.0, 0.1767766952966369, 0.3535533905932738, -1.0606601717798212, 0.3535533905932738,
         0.1767766952966369]),
    2: ([0.0, -0.06453888262869706, -0.04068941760916406, 0.41809227322161724, 0.7884856164055829,
         0.41809227322161724, -0.04068941760916406, -0.06453888262869706, 0.0, 0.0],
        [0.0, -0.03782845550726404, -0.023849465019556843, 0.11062440441843718, 0.37740285561283066,
         -0.8526986790088938, 0.37740285561283066, 0.11062440441843718, -0.023849465019556843,
         -0.03782845550726404]),
    3: ([0.2303778133088965, 0.7148465705529157, 0.6308807679298589, -0.027983769416859854,
         -0.18703481171909309, 0.030841381835560764, 0.0328830116668852, -0.010597401785069032],
        [-0.010597401785069032, -0.0328830116668852, 0.030841381835560764, 0.18703481171909309,
         -0.027983769416859854, -0.6308807679298589, 0.7148465705529157, -0.2303778133088965]),
}


def spec_value(code: int) -> float:
    """2^((c - 160) / 8) (section 2.2)."""
    return 2.0 ** ((code - 160) / 8)


def spec_layout(count: int, wavelet: int) -> tuple[int, list[int]]:
    """(J, [N_0 .. N_J]) of section 2.3."""
    F = len(FILTERS[wavelet][0])
    lmax = 0
    if count >= F - 1:
        while (F - 1) << (lmax + 1) <= count:
            lmax += 1
    J = min(10, lmax)
    ns = [count]
    for _ in range(J):
        ns.append((ns[-1] + F - 1) // 2)
    return J, ns


def spec_total(count: int, wavelet: int) -> tuple[int, int]:
    """(total, A)."""
    J, ns = spec_layout(count, wavelet)
    if J == 0:
        return count, count
    return ns[J] + sum(ns[1:]), ns[J]


def spec_idwt(flat: np.ndarray, count: int, wavelet: int) -> np.ndarray:
    J, ns = spec_layout(count, wavelet)
    if J == 0:
        return flat[:count].copy()
    lo, hi = FILTERS[wavelet]
    h = len(lo) // 2
    a = flat[:ns[J]]
    pos = ns[J]
    for level in range(J, 0, -1):
        d = flat[pos:pos + ns[level]]
        pos += ns[level]
        if len(a) == len(d) + 1:
            a = a[:-1]
        n = len(d)
        m = n - h + 1
        out = np.zeros(2 * m)
        for filt, c in ((lo, a), (hi, d)):
            ev = np.zeros(m)
            od = np.zeros(m)
            for j in range(h):
                seg = c[h - 1 - j:h - 1 - j + m]
                ev = ev + filt[2 * j] * seg
                od = od + filt[2 * j + 1] * seg
            out[0::2] += ev
            out[1::2] += od
        a = out
    return a[:count].copy()


def spec_ts_params(r: BitReader) -> tuple[int, int]:
    """Rice parameter set P: (k, w), w = 0 without escapes (section 2.5)."""
    k = r.read(5)
    if not r.read(1):
        return k, 0
    w = r.read(6)
    if w == 0:
        raise SpecError("escape width 0")
    return k, w


def spec_ts_unary(r: BitReader, m: int) -> list[int]:
    qs = []
    for _ in range(m):
        q = 0
        while r.read(1):
            q += 1
            if q > 16:
                raise SpecError("17 one-bits")
        qs.append(q)
    return qs


def spec_ts_low(r: BitReader, qs: list[int], k: int) -> list[int | None]:
    """Low bits of the non-escaped values (None for escaped ones, filled later)."""
    return [None if q == 16 else (q << k) | r.read(k) for q in qs]


def spec_ts_escapes(r: BitReader, vals: list[int | None], w: int) -> list[int]:
    if any(v is None for v in vals) and w == 0:
        raise SpecError("escaped value without an escape width")
    return [r.read(w) if v is None else v for v in vals]


def spec_decode_data(data: bytes, n: int, samples: bool, first: int, approx: int) -> list[int]:
    """The n codes of a chunk's data (section 2.5)."""
    r = BitReader(data)
    if len(r.bits) < 8:
        raise SpecError("shorter than the header")
    dense, dpcm = r.read(1), r.read(1)
    if dense:
        k, w = spec_ts_params(r)
        qs = spec_ts_unary(r, n)
        u = spec_ts_escapes(r, spec_ts_low(r, qs, k), w)
        if any(x >= 1 << 62 for x in u):
            raise SpecError("code out of range")
        d = [uz(x) for x in u]
    else:
        if len(r.bits) < 27:
            raise SpecError("shorter than the header")
        nz = r.read(13)
        kr, wr = spec_ts_params(r)
        km, wm = spec_ts_params(r)
        if nz > n:
            raise SpecError("too many non-zero codes")
        qr = spec_ts_unary(r, nz)
        qm = spec_ts_unary(r, nz)
        low_r = spec_ts_low(r, qr, kr)
        low_m = spec_ts_low(r, qm, km)
        runs = spec_ts_escapes(r, low_r, wr)
        mags = spec_ts_escapes(r, low_m, wm)
        signs = [r.read(1) for _ in range(nz)]
        d = [0] * n
        pos = -1
        for run, mag, neg in zip(runs, mags, signs, strict=True):
            if run >= n or mag >= 1 << 62:
                raise SpecError("run or magnitude out of range")
            pos += run + 1
            if pos >= n:
                raise SpecError("position beyond the range")
            d[pos] = -(mag + 1) if neg else mag + 1
    r.check_padding()
    if dpcm:
        if not samples and first != 0:
            raise SpecError("dpcm in a chunk not starting at 0")
        big_d = n if samples else approx
        if big_d > 1:
            for t in range(1, min(big_d, n)):
                d[t] += d[t - 1]
    return d


def spec_unwrap(stamp: int, now: float) -> float:
    """The time nearest ``now`` whose stamp is ``stamp`` (wire-format section 8)."""
    period = 1 << 18
    return float(stamp + period * round((now - stamp) / period))


class SpecSeries:
    """Chunks of one channel -> blocks -> samples (sections 2.1, 2.4, 2.6)."""

    def __init__(self) -> None:
        self.blocks: dict[int, dict[str, Any]] = {}

    def add(self, m: TimeSeriesChunk, now: float) -> None:
        start = spec_unwrap(m.start, now) + m.offset
        total, approx = spec_total(m.count, int(m.wavelet))
        big_t = m.count if m.samples else total
        first, end = (0, big_t) if m.first is None else (m.first, m.end)
        if not first < end <= big_t:
            return
        key = round(start * 100)
        b = self.blocks.get(key)
        geometry = (m.count, m.period, int(m.wavelet))
        if b is not None and b["geometry"] != geometry:
            return
        try:
            codes = spec_decode_data(m.data, end - first, m.samples, first, approx)
        except SpecError:
            return
        if b is None:
            b = self.blocks[key] = {"start": start, "geometry": geometry, "passes": {}}
        chunks = b["passes"].setdefault(m.level, [])
        if chunks and chunks[0]["samples"] != m.samples:
            return
        if any(c["first"] == first for c in chunks):
            return
        chunks.append({"first": first, "end": end, "samples": m.samples, "step": m.step,
                       "error": m.error, "codes": np.array(codes, np.int64)})

    @staticmethod
    def _complete(chunks: list[dict[str, Any]], big_t: int) -> bool:
        pos = 0
        for c in sorted(chunks, key=lambda c: c["first"]):
            if c["first"] > pos:
                return False
            pos = max(pos, c["end"])
        return bool(chunks) and pos >= big_t

    def rebuild(self) -> list[tuple[np.ndarray, np.ndarray, float]]:
        """(times, values, bound) of every block, in time order."""
        out = []
        for b in sorted(self.blocks.values(), key=lambda b: b["start"]):
            count, period, wavelet = b["geometry"]
            total, _ = spec_total(count, wavelet)
            passes = b["passes"]
            top = -1
            while top + 1 in passes and self._complete(
                    passes[top + 1], count if passes[top + 1][0]["samples"] else total):
                top += 1
            levels = list(range(top + 1)) if top >= 0 else ([0] if 0 in passes else [])
            if not levels:
                continue
            w = np.zeros(total)
            s = np.zeros(count)
            bound = math.inf
            for level in levels:
                for c in passes[level]:
                    target = s if c["samples"] else w
                    target[c["first"]:c["end"]] += c["codes"].astype(np.float64) * spec_value(c["step"])
                    if top >= 0:
                        bound = spec_value(c["error"])
            values = spec_idwt(w, count, wavelet) + s
            times = b["start"] + period * np.arange(count)
            out.append((times, values, bound))
        return out


# ---------------------------------------------------------------- section 3: imagery

PROGRESSIONS = ("LRCP", "RLCP", "RPCL", "PCRL", "CPRL")
QCD_IRREVERSIBLE = {  # d: (LL, HL/LH, HH)
    0: (0x4000, None, None), 1: (0x4824, 0x57D3, 0x5762), 2: (0x5F52, 0x5005, 0x5047),
    3: (0x6738, 0x6750, 0x6768), 4: (0x6F20, 0x6F00, 0x6EE0), 5: (0x7720, 0x76F0, 0x76C0),
    6: (0x7F20, 0x7EE0, 0x7EA0), 7: (0x8700, 0x86C0, 0x8680),
}


def spec_params(code: int) -> dict[str, Any]:
    """Section 3.1."""
    if code >> 15:
        raise SpecError("above 15 bits")
    pr = (code >> 10) & 7
    if pr >= 5:
        raise SpecError("unknown progression")
    precincts = (0, 256, 128, 512)[code >> 13]
    if precincts and PROGRESSIONS[pr] not in ("LRCP", "RLCP"):
        raise SpecError("precincts need LRCP or RLCP")
    return {"progression": PROGRESSIONS[pr], "resolutions": ((code >> 7) & 7) + 1,
            "layers": ((code >> 2) & 31) + 1, "irreversible": bool(code >> 1 & 1),
            "colour": bool(code & 1), "precincts": precincts}


def spec_main_header(code: int, width: int, height: int) -> bytes:
    """Section 3.5."""
    p = spec_params(code)
    res, comps = p["resolutions"], 3 if p["colour"] else 1
    if res > 1 and min(width, height) < 1 << res:
        raise SpecError("impossible number of resolutions")
    be = int.to_bytes
    siz = (b"\xff\x51" + be(38 + 3 * comps, 2, "big") + be(0, 2, "big")
           + b"".join(be(v, 4, "big") for v in (width, height, 0, 0, width, height, 0, 0))
           + be(comps, 2, "big") + b"\x07\x01\x01" * comps)
    pp = p["precincts"].bit_length() - 1 if p["precincts"] else 0
    cod_body = (bytes([1 if pp else 0, PROGRESSIONS.index(p["progression"])]) + be(p["layers"], 2, "big")
                + bytes([int(p["colour"]), res - 1, 4, 4, 0, 0 if p["irreversible"] else 1])
                + (bytes([pp << 4 | pp]) * res if pp else b""))
    cod = b"\xff\x52" + be(2 + len(cod_body), 2, "big") + cod_body
    bands: list[bytes] = []
    if p["irreversible"]:
        bands.append(be(QCD_IRREVERSIBLE[res - 1][0], 2, "big"))
        for d in range(res - 1, 0, -1):
            _, hl, hh = QCD_IRREVERSIBLE[d]
            bands += [be(hl, 2, "big"), be(hl, 2, "big"), be(hh, 2, "big")]
        sqcd = 0x42
    else:
        bands.append(b"\x40")
        bands += [b"\x48", b"\x48", b"\x50"] * (res - 1)
        sqcd = 0x40
    body = bytes([sqcd]) + b"".join(bands)
    qcd = b"\xff\x5c" + be(2 + len(body), 2, "big") + body
    return b"\xff\x4f" + siz + cod + qcd


def spec_packet_order(p: dict[str, Any], width: int = 1, height: int = 1) -> list[tuple[int, int, int, int]]:
    """(layer, resolution, component, precinct) of each packet, first letter outermost (3.2);
    with precincts (LRCP / RLCP only) P is innermost and counts depend on the resolution."""
    res = p["resolutions"]

    def count(r: int) -> int:
        if not p["precincts"]:
            return 1
        s = 2 ** (res - 1 - r)
        w, h = math.ceil(width / s), math.ceil(height / s)
        return math.ceil(w / p["precincts"]) * math.ceil(h / p["precincts"])

    dims = {"L": p["layers"], "R": res, "C": 3 if p["colour"] else 1}
    order: list[dict[str, int]] = [{}]
    for letter in p["progression"]:
        if letter == "P":
            order = [{**o, "P": 0} for o in order]
        else:
            order = [{**o, letter: v} for o in order for v in range(dims[letter])]
    out = []
    for o in order:
        for pr in range(count(o["R"]) if p["precincts"] else 1):
            out.append((o["L"], o["R"], o["C"], pr))
    return out


class SpecImage:
    """One image: announcement, fragments -> codestream (sections 3.3 and 3.4)."""

    def __init__(self, ann: ImageAnnounce) -> None:
        self.ann = ann
        self.p = spec_params(ann.params)
        self.order = spec_packet_order(self.p, ann.width, ann.height)
        self.buf = bytearray(ann.total_bytes)
        self.have = [False] * ann.total_bytes
        self.starts: list[int | None] = [None] * len(self.order)
        self.starts[0] = 0

    def add(self, f: ImageFragment) -> None:
        n, marks, npk = len(f.data), list(f.packets), len(self.order)
        if n == 0 or f.offset + n > len(self.buf) or (marks and (f.packet is None or f.packet >= npk)):
            return
        if any(b <= a for a, b in itertools.pairwise(marks)) or (marks and marks[-1] > n):
            return
        i0 = (f.packet or 0) + (0 if marks and marks[0] == 0 else 1)
        if marks and i0 + len(marks) - 1 >= npk:
            return
        for j, mk in enumerate(marks):
            known = self.starts[i0 + j]
            if known is not None and known != f.offset + mk:
                return
        for j, mk in enumerate(marks):
            self.starts[i0 + j] = f.offset + mk
        self.buf[f.offset:f.offset + n] = f.data
        self.have[f.offset:f.offset + n] = [True] * n

    def packets(self) -> list[bytes | None]:
        # 3.3: starts not marked come from the packet headers (T.800 B.10) of the held bytes;
        # the parser is a T.800 implementation, checked against OpenJPEG's PLT in
        # test_imagery_packets
        from coex_plugins.imagery.packets import PacketParser

        parsed = PacketParser(self.ann.params, self.ann.width, self.ann.height, len(self.buf)).parse(
            self.buf, np.array(self.have, bool))
        for i, st in enumerate(parsed):
            if st >= 0:
                assert self.starts[i] in (None, int(st)), "a mark contradicts the packet headers"
                self.starts[i] = int(st)
        out: list[bytes | None] = []
        for i, s in enumerate(self.starts):
            e = len(self.buf) if i + 1 == len(self.starts) else self.starts[i + 1]
            ok = s is not None and e is not None and e > s and all(self.have[s:e])
            out.append(bytes(self.buf[s:e]) if ok and s is not None else None)
        return out

    def codestream(self, upto: int | None = None) -> bytes | None:
        """3.4 from the complete packets (only packets ``0 .. upto - 1`` with ``upto``)."""
        packets = self.packets()[:upto]
        complete = [i for i, pk in enumerate(packets) if pk is not None]
        if not complete:
            return None
        parts = [spec_main_header(self.ann.params, self.ann.width, self.ann.height),
                 bytes.fromhex("ff90000a0000000000000001"), b"\xff\x93"]
        replaced: set[tuple[int, int, int]] = set()
        for i in range(complete[-1] + 1):
            _, r, c, pr = self.order[i]
            pk = packets[i]
            if pk is None or (r, c, pr) in replaced:
                replaced.add((r, c, pr))
                parts.append(b"\x00")
            else:
                parts.append(pk)
        parts.append(b"\xff\xd9")
        return b"".join(parts)


def spec_decode_j2k(cs: bytes, path: Path) -> np.ndarray:
    import glymur

    path.write_bytes(cs)
    return np.asarray(glymur.Jp2k(str(path))[:], np.uint8)


# ================================================================ tests: bathymetry


def _survey() -> tuple[Any, list[Subgrid]]:
    from ._bathy_data import survey_subgrids

    return survey_subgrids(64.0, 96)  # Subgrids (type 17) and PredictedSubgrids from their own base


@pytest.fixture(scope="module")
def survey() -> tuple[Any, list[Subgrid]]:
    return _survey()


def _check_subgrid(sg: Subgrid) -> dict[str, Any]:
    from coex_plugins.bathymetry import decode_subgrid, decode_subgrid_units

    data = wire.encode(sg)
    f = spec_parse_subgrid(data)
    ref = wire.decode(data)
    assert isinstance(ref, Subgrid)
    for name in ("level", "ix", "iy", "stamp", "resolution", "vertical_resolution", "side",
                 "z_base", "width", "slope_x", "slope_y", "mask", "values"):
        assert f[name] == getattr(ref, name), name
    assert f["encoding"] == int(ref.encoding)
    units = spec_subgrid_units(f)
    ref_units = decode_subgrid_units(ref)
    absent = np.iinfo(np.int64).min
    mine = np.array([[absent if z is None else z for z in row] for row in units], np.int64)
    np.testing.assert_array_equal(mine, ref_units)
    metres = np.array([[np.nan if z is None else z * f["vertical_resolution"] for z in row]
                       for row in units])
    np.testing.assert_array_equal(metres, decode_subgrid(ref))  # bit-exact, NaN where absent
    return f


def test_subgrids_of_every_encoding_rebuild_like_the_reference(survey: tuple[Any, list[Subgrid]]) -> None:
    """Every Subgrid the reference sender sends, and every map block forced into each encoding
    (OFFSET, DELTA, PLANE, GRADIENT; full and partial masks; width 0), parses from its bytes and
    rebuilds to exactly the reference codec's elevations (vertical units and metres)."""
    from coex_plugins.bathymetry import encode_subgrid

    sender, sent = survey
    seen: Counter[tuple[int, bool, bool]] = Counter()
    for sg in sent:
        if not isinstance(sg, Subgrid):
            continue  # a PredictedSubgrid: section 1.7, checked below and by tests/spec_decoder
        f = _check_subgrid(sg)
        seen[(f["encoding"], f["mask"] is not None, f["width"] == 0)] += 1
    # the same blocks forced into each encoding (the sender only keeps the smallest)
    vres = sender.map.vertical_resolution
    for sg in sent[:120]:
        blk = sender.map.block(sg.level, sg.ix, sg.iy)
        present = blk.count > 0
        q = np.zeros(blk.count.shape, np.int64)
        q[present] = np.rint(blk.mean[present] / vres).astype(np.int64)
        for enc in SubgridEncoding:
            try:
                forced = encode_subgrid(q, present, level=sg.level, ix=sg.ix, iy=sg.iy, stamp=sg.stamp,
                                        resolution=sg.resolution, vertical_resolution=vres, encodings=(enc,))
            except ValueError:
                continue  # this encoding cannot code the block
            f = _check_subgrid(forced)
            seen[(f["encoding"], f["mask"] is not None, f["width"] == 0)] += 1
    for enc in (OFFSET, DELTA, PLANE):
        assert seen[(enc, True, False)] and seen[(enc, True, True)] + seen[(enc, False, True)], enc
    assert seen[(GRADIENT, False, False)] and seen[(GRADIENT, False, True)]
    assert not seen[(GRADIENT, True, False)] and not seen[(GRADIENT, True, True)]


def test_subgrid_cells_land_where_the_map_has_them(survey: tuple[Any, list[Subgrid]]) -> None:
    """Cell positions (section 1.1: row 0 south, column 0 west, corner ix*side*c, iy*side*c)
    and metres agree with the vehicle's map at every level."""
    sender, sent = survey
    vres = sender.map.vertical_resolution
    checked = 0
    for level in range(3):
        grid, x0, y0 = sender.map.grid(level)
        c = sender.map.resolution * 2**level
        for sg in (s for s in sent if s.level == level and isinstance(s, Subgrid)):
            for (x, y), z in spec_subgrid_cells(spec_parse_subgrid(wire.encode(sg))).items():
                row, col = round((y - y0) / c), round((x - x0) / c)
                assert 0 <= row < grid.shape[0] and 0 <= col < grid.shape[1]
                assert z == pytest.approx(np.rint(grid[row, col] / vres) * vres, abs=1e-9)
                checked += 1
    assert checked > 1000


def test_subgrid_rice_escape_and_its_canonical_form() -> None:
    """A DELTA/PLANE/GRADIENT value whose quotient reaches 16 is escaped (16 ones, 5-bit length,
    value); the decoder reads it back. Non-canonical escapes (plain form fits, leading zero in a
    longer length, length 0) and a GRADIENT with an all-ones mask are rejected by this decoder
    and by the reference ``wire.decode``."""
    from coex_plugins.bathymetry import encode_subgrid

    rng = np.random.default_rng(3)
    q = -3000 + np.cumsum(rng.integers(-1, 2, 64)).reshape(8, 8)
    q[3, 4] += 900  # a spike: escapes in every Rice encoding
    full = np.ones((8, 8), bool)
    for enc in (SubgridEncoding.DELTA, SubgridEncoding.PLANE, SubgridEncoding.GRADIENT):
        sg = encode_subgrid(q, full, level=0, ix=1, iy=-1, stamp=5, resolution=1.0,
                            vertical_resolution=0.1, encodings=(enc,))
        f = _check_subgrid(sg)
        assert f["escapes"] >= 1, enc
    # forge non-canonical codes into a canonical DELTA subgrid and check both decoders reject it
    sg = Subgrid(level=0, ix=0, iy=0, stamp=0, resolution=1.0, vertical_resolution=0.1, side=2,
                 encoding=SubgridEncoding.DELTA, z_base=-10, width=1, mask=None, values=(0, 5, 3, 200))
    data = wire.encode(sg)
    f = spec_parse_subgrid(data)
    assert f["escapes"] == 1 and f["values"] == (0, 5, 3, 200)
    head = BitReader(data).bits[:f["values_pos"]]
    canonical = [spec_rice_plain(0, 1), spec_rice_plain(5, 1), spec_rice_plain(3, 1), spec_rice_escape(200, 8)]

    def forge(codes: list[list[int]]) -> bytes:
        bits = head + [b for code in codes for b in code]
        bits += [0] * (-len(bits) % 8)
        return np.packbits(np.array(bits, np.uint8)).tobytes()

    assert forge(canonical) == data  # the forging itself is faithful
    for bad in ([*canonical[:1], spec_rice_escape(5, 3), *canonical[2:]],  # plain form fits
                [*canonical[:3], spec_rice_escape(200, 9)],  # non-minimal length
                [spec_rice_escape(0, 0), *canonical[1:]]):  # length 0
        with pytest.raises(SpecError):
            spec_parse_subgrid(forge(bad))
        with pytest.raises(DecodeError):
            wire.decode(forge(bad))
    # GRADIENT with partial = 1 (all ones): header bit flip of the canonical encoding
    g = Subgrid(level=0, ix=0, iy=0, stamp=0, resolution=1.0, vertical_resolution=0.1, side=2,
                encoding=SubgridEncoding.GRADIENT, z_base=7, width=0, mask=None, values=(0, 1, 2, 0))
    gf = spec_parse_subgrid(wire.encode(g))
    gbits = BitReader(wire.encode(g)).bits
    pos = gf["values_pos"] - 1  # the partial flag
    bits = [*gbits[:pos], 1, 1, 1, 1, 1, *gbits[pos + 1:gf["values_end"]]]
    bits += [0] * (-len(bits) % 8)
    bad_g = np.packbits(np.array(bits, np.uint8)).tobytes()
    with pytest.raises(SpecError):
        spec_parse_subgrid(bad_g)
    with pytest.raises(DecodeError):
        wire.decode(bad_g)


# ================================================================ tests: time series

T0 = 1_700_000_000.0


def _timeseries_run(wavelet: str) -> tuple[list[bytes], Any, float]:
    from coex_plugins.timeseries import TimeSeriesReceiver, TimeSeriesSender, synth

    series = synth.dataset(duration=3000.0, t0=T0, seed=4)
    s = TimeSeriesSender({"channels": [x.channel() for x in series], "wavelet": wavelet,
                          "block_samples": 1500})
    now = float(series[0].times[-1])
    s.ingest({x.name: (x.times, x.values) for x in series}, now)
    s.flush(now)
    rx = TimeSeriesReceiver()
    sent: list[bytes] = []

    def drain(now: float) -> float:
        for _ in range(10_000):
            for reply in rx.poll(now):
                s.handle(reply, now)
            out = s.fill(251, now)
            if not out:
                return now
            for m in out:
                sent.append(wire.encode(m))
                rx.receive(m, now)
            now += 1.0
        raise AssertionError("never idle")

    now = drain(now)
    for name, err in (("methane", 0.03), ("temperature", 0.0008)):
        s.handle(rx.request(name, T0, T0 + 3000, max_error=err), now)
    return sent, rx, drain(now)


def _compare_series(mine: SpecSeries, rx: Any, channel: int) -> None:
    blocks = mine.rebuild()
    ref = rx.series(channel)
    assert blocks, "nothing rebuilt"
    np.testing.assert_array_equal(np.concatenate([b[0] for b in blocks]), ref.times)
    np.testing.assert_array_equal(np.concatenate([b[1] for b in blocks]), ref.values)  # bit-exact
    assert [b[2] for b in blocks] == [b for _, _, b in rx.bounds(channel)]


@pytest.mark.parametrize("wavelet", ["haar", "bior2.2", "bior4.4", "db4"])
def test_timeseries_chunks_rebuild_like_the_reference(wavelet: str) -> None:
    """Every TimeSeriesChunk of an overview and a requested refinement (wavelet and samples
    passes, whole and partial chunks, dense and sparse data, with and without differences)
    rebuilds to exactly the reference receiver's samples, times and error bounds."""
    from coex_plugins.timeseries import TimeSeriesReceiver

    sent, rx, now = _timeseries_run(wavelet)
    chunks = [m for m in map(wire.decode, sent) if isinstance(m, TimeSeriesChunk)]
    forms = Counter((m.samples, m.first is not None, *tuple(BitReader(m.data).bits[:2])) for m in chunks)
    assert any(k[0] for k in forms) and any(not k[0] for k in forms)  # samples and wavelet passes
    assert any(k[1] for k in forms)  # partial chunks
    assert any(k[2] for k in forms) and any(not k[2] for k in forms)  # dense and sparse
    assert any(k[3] for k in forms)  # differences
    assert max(m.level for m in chunks) >= 2
    for channel in (0, 1):
        mine = SpecSeries()
        for m in chunks:
            if m.channel == channel:
                mine.add(m, now)
        _compare_series(mine, rx, channel)
        # with a chunk of a middle pass lost: only the complete prefix of passes counts
        lost_rx, lost = TimeSeriesReceiver(), SpecSeries()
        ours = [m for m in chunks if m.channel == channel]
        victim = next(m for m in ours if m.level == 1)
        for m in ours:
            if m is not victim:
                lost_rx.receive(m, now)
                lost.add(m, now)
        _compare_series(lost, lost_rx, channel)


def test_timeseries_coefficient_code_escapes_differences_and_rejections() -> None:
    """The reference coefficient coder's output (dense and sparse, escapes in runs, magnitudes and
    dense values, differences) decodes to the coded integers; malformed data is rejected as the
    document says."""
    from coex_plugins.timeseries import codec

    rng = np.random.default_rng(7)
    cases = []
    sparse = np.zeros(6000, np.int64)
    sparse[rng.choice(60, 40, replace=False)] = rng.choice([-2, -1, 1, 2], 40)
    sparse[[0, 5999]] = [5_000_000, -123_456_789]  # an escaped run and escaped magnitudes
    cases.append((sparse, 0, False))
    dense = rng.integers(-6, 7, 300)
    dense[17] = 1 << 40  # an escaped dense value
    cases.append((dense, 0, False))
    trend = np.cumsum(rng.integers(-2, 3, 200)) + 10_000  # differences win
    cases.append((trend, 64, True))
    for codes, approx, dpcm in cases:
        data = codec.encode_codes(codes, approx, dpcm)
        bits = BitReader(data).bits
        got = spec_decode_data(data, codes.size, False, 0, approx)
        assert got == codes.tolist()
        assert bits[1] == int(dpcm)
        if not dpcm:
            assert got == codec.decode_codes(data, codes.size).tolist()
    assert [BitReader(codec.encode_codes(c, a, d)).bits[0] for c, a, d in cases] == [0, 1, 1]
    # the escape flags are set: the escape paths above were taken (dense: bit 7; sparse: the
    # run and magnitude parameter sets after the 13-bit count)
    assert BitReader(codec.encode_codes(dense)).bits[7] == 1
    r = BitReader(codec.encode_codes(sparse), 15)
    assert spec_ts_params(r)[1] > 0 and spec_ts_params(r)[1] > 0
    good = codec.encode_codes(dense)
    for bad in (good[:3], good + b"\x00", bytes([good[0] | 0x40]) + good[1:]):
        with pytest.raises(SpecError):
            spec_decode_data(bad, dense.size, False, 5, 0)
    # step and error codes: 2^((c-160)/8)
    assert spec_value(160) == 1.0 and spec_value(152) == 0.5 and spec_value(0) == 2.0**-20
    assert all(spec_value(c) == codec.code_value(c) for c in range(256))


# ================================================================ tests: imagery

IMAGE_CONFIGS = [
    {"progression": "LRCP", "resolutions": 5, "irreversible": True, "grey": True},
    {"progression": "RLCP", "resolutions": 3, "irreversible": False, "grey": True},
    {"progression": "RPCL", "resolutions": 4, "irreversible": True, "grey": False},
    {"progression": "CPRL", "resolutions": 2, "irreversible": False, "grey": False},
    {"progression": "LRCP", "resolutions": 4, "irreversible": True, "grey": True, "precincts": 128},
    {"progression": "RLCP", "resolutions": 3, "irreversible": True, "grey": False, "precincts": 128},
]


def test_image_params_and_main_header_match_the_reference() -> None:
    """The params code decodes to the documented fields, and the main header built from the
    document is byte-identical to the one the reference rebuilds (OpenJPEG) for every
    progression, 1..8 resolutions, reversible and irreversible, grey and colour."""
    from coex_plugins.imagery import codec

    combos = [(prog, res, layers, irr, col, 300, 256, 0)
              for prog, res, layers, irr, col in [
                  ("LRCP", 1, 1, True, False), ("RLCP", 8, 32, True, False), ("RPCL", 8, 3, False, True),
                  ("PCRL", 6, 22, True, True), ("CPRL", 7, 2, False, False), ("LRCP", 4, 9, False, True)]]
    combos += [("LRCP", r, 5, irr, False, 37, 17, 0) for r in range(1, 5) for irr in (True, False)]
    combos += [("LRCP", 7, 18, True, False, 640, 480, 256), ("RLCP", 5, 4, False, True, 300, 256, 128),
               ("LRCP", 3, 2, True, False, 200, 100, 512)]
    for prog, res, layers, irr, col, w, h, pc in combos:
        code = codec.params_code(prog, res, layers, irr, col, pc)
        p = spec_params(code)
        assert p == {"progression": prog, "resolutions": res, "layers": layers, "irreversible": irr,
                     "colour": col, "precincts": pc}
        if res > 1 and min(w, h) < 1 << res:
            with pytest.raises(SpecError):
                spec_main_header(code, w, h)
            with pytest.raises(DecodeError):
                codec.main_header(code, w, h)
            continue
        assert spec_main_header(code, w, h) == codec.main_header(code, w, h), (prog, res, irr, col)
    for bad in (1 << 15, 5 << 10, 7 << 10, (1 << 13) | (2 << 10), (3 << 13) | (4 << 10)):
        with pytest.raises(SpecError):
            spec_params(bad)
        with pytest.raises(DecodeError):
            codec.parse_params(bad)
    p = spec_params(codec.params_code("RLCP", 3, 2, False, False))
    assert spec_packet_order(p) == [(0, 0, 0, 0), (1, 0, 0, 0), (0, 1, 0, 0), (1, 1, 0, 0), (0, 2, 0, 0),
                                    (1, 2, 0, 0)]
    # precincts: 640 x 480, 7 resolutions, 256: one precinct up to 160 x 120, 2 x 1, then 3 x 2
    p = spec_params(codec.params_code("LRCP", 7, 2, True, False, 256))
    order = spec_packet_order(p, 640, 480)
    assert len(order) == 2 * (5 + 2 + 6)
    assert order[:7] == [(0, r, 0, 0) for r in range(5)] + [(0, 5, 0, 0), (0, 5, 0, 1)]
    sp = codec.parse_params(codec.params_code("LRCP", 7, 2, True, False, 256))
    assert [tuple(int(v) for v in row) for row in codec.packet_order(sp, 640, 480)] == order


@pytest.mark.parametrize("config", IMAGE_CONFIGS)
def test_image_codestream_rebuild_matches_the_reference(config: dict[str, Any], tmp_path: Path) -> None:
    """ImageAnnounce + ImageFragments from the reference sender, with a middle fragment lost and
    later recovered: the codestream rebuilt from the document (header, SOT, packets with the
    repair rule, EOC) is the reference's, and glymur decodes it to the reference receiver's image."""
    from coex_plugins.imagery import ImageryModality, codec
    from coex_plugins.imagery.synth import seafloor

    mod = ImageryModality()
    layer_bytes = [30, 60, 120, 240, 480, 900, 1600, 3000]
    s = mod.sender({"precincts": 0, **config, "layer_bytes": layer_bytes, "rto": 12.0, "default_goal": "full"})
    rx = mod.receiver({})
    img = seafloor(300, 400, seed=5) if config.get("precincts") else seafloor(96, 128, seed=5)
    if not config["grey"]:
        img = np.stack([img, img // 2 + 40, 255 - img], axis=2).astype(np.uint8)
    s.ingest(img, 0.0)
    msgs: list[Any] = []
    while out := s.fill(90, 0.0):
        msgs += [wire.decode(wire.encode(m)) for m in out]
    ann = next(m for m in msgs if isinstance(m, ImageAnnounce))
    frags = [m for m in msgs if isinstance(m, ImageFragment)]
    assert len(frags) > 6
    p = spec_params(ann.params)
    assert (p["progression"], p["resolutions"], p["irreversible"], p["colour"], p["layers"]) == (
        config["progression"], config["resolutions"], config["irreversible"], not config["grey"],
        len(layer_bytes))
    assert ann.grey == (not p["colour"])
    mine = SpecImage(ann)
    rx.receive(ann, 0.0)
    lost = frags[len(frags) // 2]
    for i, f in enumerate([*frags, lost]):
        if f is lost and i < len(frags):
            continue
        mine.add(f)
        rx.receive(f, 0.0)
        if i % 3 and i < len(frags):
            continue
        cs = mine.codestream()
        ref_rx = rx.images[ann.image_id]
        ref_packets = ref_rx.packets()
        assert mine.packets()[:len(ref_packets)] == ref_packets
        assert cs == codec.assemble(ann.params, ann.width, ann.height, ref_packets)[0]
        np.testing.assert_array_equal(spec_decode_j2k(cs, tmp_path / "spec.j2k"), ref_rx.image)
    assert bytes(mine.buf) == bytes(rx.images[ann.image_id].buf)
    assert all(pk is not None for pk in mine.packets())


def test_a_crop_rebuilt_from_the_document_is_the_reference_s(tmp_path: Path) -> None:
    """Section 3.7: a region request answered by a crop that codes the difference to what topside
    held (``base`` > 0). From the messages alone, the crop's codestream (3.2-3.5 with its own
    size and params), the parent decoded from its first ``base`` packets, and
    S = clip(B + D - 128) pasted at the rectangle give what the reference receiver shows."""
    from coex_core.messages import ImageCrop
    from coex_plugins.imagery.sim import region_transfer
    from coex_plugins.imagery.synth import seafloor

    img = seafloor(480, 640, seed=3)
    box = (0, 0, 320, 240)
    run = region_transfer(img, box, "quality", 35.0, mtu=128, base="layer:2")
    down = [e.message for e in run.transfer.events if e.direction == "down" and not e.lost]
    ann = next(m for m in down if isinstance(m, ImageAnnounce))
    crop = next(m for m in down if isinstance(m, ImageCrop))
    assert crop.base > 0 and (crop.x0, crop.y0, crop.x1, crop.y1) == box
    parent = SpecImage(ann)
    w, h = crop.x1 - crop.x0, crop.y1 - crop.y0
    mine = SpecImage(ImageAnnounce(crop.image_id, 0, None, None, w, h, not spec_params(crop.params)["colour"],
                                   crop.total_bytes, crop.params))
    for m in down:
        if isinstance(m, ImageFragment):
            (parent if m.image_id == ann.image_id else mine).add(m)
    assert all(pk is not None for pk in parent.packets()[:crop.base])
    cs_base, cs_crop = parent.codestream(crop.base), mine.codestream()
    assert cs_base is not None and cs_crop is not None
    b = spec_decode_j2k(cs_base, tmp_path / "base.j2k")[crop.y0:crop.y1, crop.x0:crop.x1].astype(int)
    d = spec_decode_j2k(cs_crop, tmp_path / "crop.j2k").astype(int)
    shown = np.clip(b + d - 128, 0, 255).astype(np.uint8)
    np.testing.assert_array_equal(run.after[crop.y0:crop.y1, crop.x0:crop.x1], shown)
    np.testing.assert_array_equal(run.receiver.image(crop.image_id), shown)
    # the parent holds no more layers in the rectangle than the crop covers: the crop is shown
    assert run.region["layers_complete"] >= crop.cover and run.region["crop"]["shown"]
