"""Find JPEG 2000 packet boundaries in an image body by parsing the packet headers.

Every packet of the body (spec/payloads.md section 3.2) starts with a *packet header* that says,
for every code-block of the packet's precinct, whether it contributes to this layer and with how
many bytes. The header alone therefore gives the packet's total length (header bytes plus the sum
of the code-block contributions), hence the start of the next packet. A receiver can find every
packet start itself, in codestream order, as long as it holds the header bytes of each packet:
the bodies of the packets (the code-block data) need not be held.

:class:`PacketParser` is fed the receiver's buffer and which bytes it holds, any number of
times; it keeps the header state of every precinct (tag trees, code-block inclusion, ``Lblock``)
and resumes at the first packet not yet parsed. :func:`packet_lengths` parses a whole body.

Rules implemented (ITU-T T.800 | ISO/IEC 15444-1, with the choices OpenJPEG 2.5 makes):

* B.5, B.6: tile = image (origin 0, one tile, no subsampling); resolution ``r`` of ``R`` spans
  ``ceil(W / 2^(R-1-r))`` samples; subbands LL (``r = 0``) or HL, LH, HH (``r > 0``, in that
  order) with the band bounds of equation B-15.
* B.6, B.7: precincts of ``2^PP`` samples at every resolution (``PP = 15``, one precinct, when
  the ``params`` precinct size is 0), mapped to ``2^(PP-1)`` band samples for ``r > 0``;
  code-blocks of ``2^min(6, PP')`` (COD exponents 4, 4 give 64 x 64; ``PP' = PP`` at ``r = 0``,
  ``PP - 1`` above), anchored at 0 and clipped to the precinct; code-blocks in raster order
  within each band of a precinct. Empty bands and precincts contribute nothing.
* B.10.1: header bits are read MSB first; after a byte ``FF`` the next byte carries only 7 bits
  (its MSB is a stuffed 0). The header ends at the next byte boundary, plus one byte when the
  last byte was ``FF``.
* B.10.3: the first bit is 0 for an empty packet (then nothing else is coded).
* B.10.2, B.10.4: code-block inclusion: a tag tree per band and precinct (value = first layer)
  for a code-block not yet included, decoded against ``layer + 1``; one bit for a code-block
  included before.
* B.10.5: zero bit-planes: a second tag tree, decoded on first inclusion.
* B.10.6: number of coding passes (codewords 0, 10, 11xx, 1111 xxxxx, 1111 11111 xxxxxxx: 1 to
  164 passes).
* B.10.7.1: ``Lblock`` starts at 3 and grows by the number of 1 bits before a 0; the
  contribution length has ``Lblock + floor(log2(passes))`` bits. Code-block style 0 (no
  bypass, no termination on every pass) makes each contribution a single codeword segment.
* Packet order: :func:`codec.packet_order` for every progression (LRCP, RLCP with any precinct
  size; RPCL, PCRL, CPRL with one precinct per resolution, which is all
  :class:`codec.CodingParams` allows). The header state is per (resolution, component, precinct)
  so the order does not matter to the parser.

Limits: no SOP/EPH markers, no PPM/PPT (packed headers), one tile, code-block style 0, at most
164 passes per code-block and ``Lblock`` up to 40 (anything beyond is not a body CoEx makes and
raises :class:`DecodeError`). A contribution of more than 109 passes, which OpenJPEG would split
into two segments, cannot arise from 8-bit samples and is read as one. The parser checks the
syntax and that lengths stay inside the body, not the entropy-coded data: random bytes may parse
as packets that are nonsense, but the parser never reads or reports past the body, and every
error is a :class:`DecodeError`.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from coex import DecodeError

from ._stream import StreamParams, packet_order, parse_params

__all__ = ["CodeBlock", "CodeBlocks", "LayerWriter", "PacketParser", "code_blocks", "packet_lengths",
           "precinct_codeblocks", "write_packets"]

#: Code-block size exponent (COD: exponents 4, 4 -> 2^6 = 64 samples).
_CBLK_EXP = 6
#: Precinct exponent when the ``params`` precinct size is 0 (OpenJPEG's default, 2^15).
_NO_PRECINCT_EXP = 15
_MAX_PASSES = 164
_MAX_ZERO_PLANES = 74
_MAX_LBLOCK = 40
_INF = 1 << 30


class _NeedMore(Exception):
    """A header byte is not held yet (internal)."""


def _ceil_shift(a: int, s: int) -> int:
    return -((-a) >> s)


def precinct_codeblocks(sp: StreamParams, width: int, height: int, r: int, p: int) -> list[tuple[int, int]]:
    """Code-blocks (across, down) of each band (LL, or HL, LH, HH) of precinct ``p`` (raster
    order) at resolution ``r``; (0, 0) for a band the precinct does not meet."""
    return list(_precinct_codeblocks(sp, int(width), int(height), int(r), int(p)))


@functools.lru_cache(maxsize=4096)
def _precinct_codeblocks(sp: StreamParams, width: int, height: int, r: int, p: int) -> tuple[tuple[int, int], ...]:
    levelno = sp.resolutions - 1 - r
    pp = (sp.precincts.bit_length() - 1) if sp.precincts else _NO_PRECINCT_EXP
    rx1, ry1 = _ceil_shift(width, levelno), _ceil_shift(height, levelno)
    pw = _ceil_shift(rx1, pp) if rx1 > 0 else 0
    if pw == 0 or ry1 <= 0:
        return ()
    px, py = p % pw, p // pw
    if r == 0:
        cbg = pp
        bands = [(_ceil_shift(width, levelno), _ceil_shift(height, levelno))]
    else:
        cbg = pp - 1
        bands = []
        for b in (1, 2, 3):  # HL, LH, HH
            xo, yo = b & 1, b >> 1
            bands.append((_ceil_shift(width - (xo << levelno), levelno + 1),
                          _ceil_shift(height - (yo << levelno), levelno + 1)))
    cb = min(_CBLK_EXP, cbg)
    out = []
    for bx1, by1 in bands:
        x0, x1 = max(px << cbg, 0), min((px + 1) << cbg, bx1)
        y0, y1 = max(py << cbg, 0), min((py + 1) << cbg, by1)
        if x1 <= x0 or y1 <= y0:
            out.append((0, 0))
            continue
        cw = _ceil_shift(x1, cb) - (x0 >> cb)
        ch = _ceil_shift(y1, cb) - (y0 >> cb)
        out.append((cw, ch))
    return tuple(out)


@functools.lru_cache(maxsize=1024)
def _tree_paths(w: int, h: int) -> tuple[int, tuple[tuple[int, ...], ...]]:
    """Tag tree of ``w x h`` leaves (B.10.2): node count and, per leaf, its path root -> leaf."""
    dims = [(w, h)]
    while dims[-1][0] * dims[-1][1] > 1:
        cw, ch = dims[-1]
        dims.append(((cw + 1) // 2, (ch + 1) // 2))
    offsets = [0]
    for cw, ch in dims:
        offsets.append(offsets[-1] + cw * ch)
    paths = []
    for j in range(h):
        for i in range(w):
            path = []
            x, y = i, j
            for k, (cw, _ch) in enumerate(dims):
                path.append(offsets[k] + y * cw + x)
                x, y = x // 2, y // 2
            paths.append(tuple(reversed(path)))
    return offsets[-1], tuple(paths)


class _Band:
    """Header state of one band of one precinct: two tag trees and per code-block state."""

    __slots__ = ("incl_lo", "incl_v", "included", "lblock", "msb_lo", "msb_v", "n", "passes", "paths")

    def __init__(self, w: int, h: int) -> None:
        nodes, self.paths = _tree_paths(w, h)
        self.n = w * h
        self.incl_v = [_INF] * nodes
        self.incl_lo = [0] * nodes
        self.msb_v = [_INF] * nodes
        self.msb_lo = [0] * nodes
        self.included = [False] * self.n
        self.lblock = [3] * self.n
        self.passes = [0] * self.n

    def snapshot(self) -> tuple[list[int], list[int], list[int], list[int], list[bool], list[int], list[int]]:
        return (self.incl_v[:], self.incl_lo[:], self.msb_v[:], self.msb_lo[:], self.included[:],
                self.lblock[:], self.passes[:])

    def restore(self, s: tuple[list[int], list[int], list[int], list[int], list[bool], list[int], list[int]]) -> None:
        self.incl_v, self.incl_lo, self.msb_v, self.msb_lo, self.included, self.lblock, self.passes = s


class _Bits:
    """Packet header bit reader (B.10.1) over ``buf[pos:limit]``; ``total`` is the body size."""

    __slots__ = ("buf", "byte", "ct", "limit", "pos", "total")

    def __init__(self, buf: bytes | bytearray | memoryview, pos: int, limit: int, total: int) -> None:
        self.buf, self.pos, self.limit, self.total = buf, pos, limit, total
        self.byte = 0  # the last byte read
        self.ct = 0  # bits of it not yet read

    def _next(self) -> None:
        if self.pos >= self.limit:
            if self.pos >= self.total:
                raise DecodeError(f"packet header runs past the end of the body ({self.total} B)")
            raise _NeedMore
        stuffed = self.byte == 0xFF
        self.byte = self.buf[self.pos]
        self.pos += 1
        self.ct = 7 if stuffed else 8

    def bit(self) -> int:
        if self.ct == 0:
            self._next()
        self.ct -= 1
        return (self.byte >> self.ct) & 1

    def bits(self, n: int) -> int:
        v = 0
        for _ in range(n):
            if self.ct == 0:
                self._next()
            self.ct -= 1
            v = (v << 1) | ((self.byte >> self.ct) & 1)
        return v

    def align(self) -> int:
        """End of the header (B.10.1): skip to the byte boundary, and a byte after an ``FF``."""
        self.ct = 0
        if self.byte == 0xFF:
            self._next()
            self.ct = 0
        return self.pos


def _tag_decode(path: Sequence[int], values: list[int], lows: list[int], threshold: int, rd: _Bits) -> bool:
    """Tag tree decoding (B.10.2) of the leaf at the end of ``path`` against ``threshold``."""
    low = 0
    node = 0
    for node in path:
        if low > lows[node]:
            lows[node] = low
        else:
            low = lows[node]
        while low < threshold and low < values[node]:
            if rd.bit():
                values[node] = low
            else:
                low += 1
        lows[node] = low
    return values[node] < threshold


def _num_passes(rd: _Bits) -> int:
    """Number of coding passes (B.10.6, Table B.4)."""
    if not rd.bit():
        return 1
    if not rd.bit():
        return 2
    n = rd.bits(2)
    if n != 3:
        return 3 + n
    n = rd.bits(5)
    if n != 31:
        return 6 + n
    return 37 + rd.bits(7)


def _read_header(bands: list[_Band], layer: int, rd: _Bits,
                 record: list[tuple[int, int, int, int, int]] | None = None) -> int:
    """Read one packet header (state updated in place); return the sum of contribution lengths.
    With ``record``, append each contribution: (band, code-block, zero bit-planes or -1 when
    included before, passes, bytes), in the order their bytes follow the header."""
    if not rd.bit():
        return 0  # empty packet (B.10.3)
    total = 0
    for b, band in enumerate(bands):
        included, lblock, passes, paths = band.included, band.lblock, band.passes, band.paths
        for k in range(band.n):
            zero = -1
            if included[k]:
                if not rd.bit():
                    continue
            else:
                if not _tag_decode(paths[k], band.incl_v, band.incl_lo, layer + 1, rd):
                    continue
                i = 0
                while not _tag_decode(paths[k], band.msb_v, band.msb_lo, i, rd):
                    i += 1
                    if i > _MAX_ZERO_PLANES:
                        raise DecodeError(f"packet header: more than {_MAX_ZERO_PLANES} zero bit-planes")
                included[k] = True
                zero = i - 1
            n = _num_passes(rd)
            passes[k] += n
            if passes[k] > _MAX_PASSES:
                raise DecodeError(f"packet header: more than {_MAX_PASSES} coding passes in a code-block")
            while rd.bit():
                lblock[k] += 1
                if lblock[k] > _MAX_LBLOCK:
                    raise DecodeError(f"packet header: Lblock above {_MAX_LBLOCK}")
            length = rd.bits(lblock[k] + n.bit_length() - 1)
            total += length
            if record is not None:
                record.append((b, k, zero, n, length))
    return total


class PacketParser:
    """Packet starts of one image body, found by parsing packet headers as the bytes arrive.

    ``params`` is the ``ImageAnnounce.params`` code (or its :class:`StreamParams`), ``width`` x
    ``height`` the image size and ``total_bytes`` the body size (taken from the first buffer
    when not given). Call :meth:`parse` with the receiver's buffer (``total_bytes`` long, bytes
    not held may hold anything) and which bytes it holds, as often as bytes arrive. Raises
    :class:`DecodeError` for a body that is not one of these parameters (and again on every
    later call)."""

    def __init__(self, params: int | StreamParams, width: int, height: int, total_bytes: int | None = None) -> None:
        self.sp = params if isinstance(params, StreamParams) else parse_params(int(params))
        self.width, self.height = int(width), int(height)
        if not (1 <= self.width <= 1 << 16 and 1 <= self.height <= 1 << 16):
            raise DecodeError(f"image size {width}x{height} out of range")
        if self.sp.resolutions > 1 and min(self.width, self.height) < 1 << self.sp.resolutions:
            raise DecodeError(f"{self.sp.resolutions} resolutions impossible for {width}x{height}")
        self.order = packet_order(self.sp, self.width, self.height)
        self.n_packets = len(self.order)
        self.total = None if total_bytes is None else int(total_bytes)
        self._starts = np.full(self.n_packets, -1, np.int64)
        self._header = np.full(self.n_packets, -1, np.int64)
        if self.n_packets:
            self._starts[0] = 0
        #: packets whose header has been parsed (their starts and ends are known)
        self.parsed = 0
        self._state: dict[tuple[int, int, int], list[_Band]] = {}
        self._error: DecodeError | None = None

    @property
    def starts(self) -> npt.NDArray[np.int64]:
        """Start of every packet in the body (-1: not known yet)."""
        return self._starts.copy()

    @property
    def header_bytes(self) -> npt.NDArray[np.int64]:
        """Bytes of every parsed packet's header (-1: not parsed yet)."""
        return self._header.copy()

    @property
    def done(self) -> bool:
        """Every packet start is known (and the packets fill the body exactly)."""
        return self.parsed == self.n_packets

    def _bands(self, key: tuple[int, int, int]) -> list[_Band]:
        bands = self._state.get(key)
        if bands is None:
            r, _c, p = key
            geo = _precinct_codeblocks(self.sp, self.width, self.height, r, p)
            bands = [_Band(w, h) for w, h in geo if w * h]
            self._state[key] = bands
        return bands

    def parse(self, buf: bytes | bytearray | memoryview, have: npt.NDArray[np.bool_] | None = None) -> npt.NDArray[np.int64]:
        """Parse every further packet whose header bytes are all held; return :attr:`starts`.

        ``have`` (bool, one per body byte; ``None`` = all held) says which bytes of ``buf`` are
        real. Stops at the first packet whose header needs a byte not held."""
        if self._error is not None:
            raise self._error
        try:
            self._parse(buf, have)
        except DecodeError as exc:
            self._error = exc
            raise
        return self.starts

    def _parse(self, buf: bytes | bytearray | memoryview, have: npt.NDArray[np.bool_] | None) -> None:
        total = len(buf)
        if self.total is None:
            self.total = total
        elif total != self.total:
            raise DecodeError(f"buffer of {total} B for a body of {self.total} B")
        if have is not None:
            have = np.asarray(have, bool)
            if have.shape != (total,):
                raise DecodeError(f"have has shape {have.shape}, expected ({total},)")
            missing = np.flatnonzero(~have)
        else:
            missing = np.zeros(0, np.int64)
        if self.n_packets == 0:
            if total:
                raise DecodeError("a body with no packets must be empty")
            return
        while self.parsed < self.n_packets:
            i = self.parsed
            start = int(self._starts[i])
            if start >= total:
                raise DecodeError(f"packet {i} starts at {start}, at or past the end of the body ({total} B)")
            m = int(np.searchsorted(missing, start))
            limit = int(missing[m]) if m < len(missing) else total
            if limit <= start:
                return
            layer, r, c, p = (int(v) for v in self.order[i])
            bands = self._bands((r, c, p))
            saved = [b.snapshot() for b in bands]
            rd = _Bits(buf, start, limit, total)
            try:
                body = _read_header(bands, layer, rd)
                end_hdr = rd.align()
            except _NeedMore:
                for b, s in zip(bands, saved, strict=True):
                    b.restore(s)
                return
            end = end_hdr + body
            if end > total:
                raise DecodeError(f"packet {i} ends at {end}, past the end of the body ({total} B)")
            self._header[i] = end_hdr - start
            self.parsed = i + 1
            if i + 1 < self.n_packets:
                self._starts[i + 1] = end
            elif end != total:
                raise DecodeError(f"the last packet ends at {end}, the body has {total} B")


def packet_lengths(params: int | StreamParams, width: int, height: int, body: bytes | bytearray) -> npt.NDArray[np.int64]:
    """Length of every packet of a complete body (raises :class:`DecodeError` if it is not one)."""
    pp = PacketParser(params, width, height, len(body))
    starts = pp.parse(body)
    if not pp.done:  # cannot happen with every byte held, but be explicit
        raise DecodeError("body ends before its last packet")
    return np.diff(np.append(starts, len(body))).astype(np.int64)


# ------------------------------------------------------------------ code-blocks and the writer

#: A code-block of a body: (resolution, component, precinct, band in the precinct, index in the
#: band's raster order).
CodeBlock = tuple[int, int, int, int, int]


@dataclass(frozen=True)
class CodeBlocks:
    """What the packets of a body say about each code-block that contributes to it: its
    codeword (the bytes of all its contributions, in order), its zero bit-planes, and after each
    layer ``l`` the passes and codeword bytes included so far (``cum[cb][l]``)."""

    layers: int
    data: dict[CodeBlock, bytes]
    zero: dict[CodeBlock, int]
    cum: dict[CodeBlock, list[tuple[int, int]]]

    def allocation(self, layer: int) -> dict[CodeBlock, tuple[int, int]]:
        """``{code-block: (passes, bytes)}`` included up to and with ``layer`` (0 = the first)."""
        return {cb: c[layer] for cb, c in self.cum.items() if c[layer][0] > 0}


def code_blocks(params: int | StreamParams, width: int, height: int, body: bytes | bytearray) -> CodeBlocks:
    """Every contribution of a complete body, by code-block (raises :class:`DecodeError` if it
    is not a body of these parameters)."""
    sp = params if isinstance(params, StreamParams) else parse_params(int(params))
    order = packet_order(sp, width, height)
    state: dict[tuple[int, int, int], list[_Band]] = {}
    data: dict[CodeBlock, bytearray] = {}
    zero: dict[CodeBlock, int] = {}
    cum: dict[CodeBlock, list[tuple[int, int]]] = {}
    pos, total = 0, len(body)
    for layer, r, c, p in order.tolist():
        key = (r, c, p)
        bands = state.get(key)
        if bands is None:
            bands = [_Band(w, h) for w, h in _precinct_codeblocks(sp, width, height, r, p) if w * h]
            state[key] = bands
        rd = _Bits(body, pos, total, total)
        record: list[tuple[int, int, int, int, int]] = []
        try:
            length = _read_header(bands, layer, rd, record)
        except _NeedMore:  # cannot happen with every byte held; said plainly
            raise DecodeError("the body ends inside a packet header") from None
        pos = rd.align()
        if pos + length > total:
            raise DecodeError(f"a packet runs past the end of the body ({total} B)")
        for b, k, z, n, ln in record:
            cb = (r, c, p, b, k)
            if cb not in data:
                data[cb], zero[cb], cum[cb] = bytearray(), z, [(0, 0)] * sp.layers
            data[cb] += body[pos:pos + ln]
            pos += ln
            passes = (cum[cb][layer - 1][0] if layer else 0) + n
            for later in range(layer, sp.layers):
                cum[cb][later] = (passes, len(data[cb]))
    if pos != total:
        raise DecodeError(f"the packets end at {pos}, the body has {total} B")
    return CodeBlocks(sp.layers, {cb: bytes(d) for cb, d in data.items()}, zero, cum)


class _Writer:
    """Packet header bit writer (B.10.1): MSB first, a 0 bit stuffed after every ``FF`` byte."""

    __slots__ = ("byte", "ct", "out")

    def __init__(self) -> None:
        self.out = bytearray()
        self.byte = 0
        self.ct = 8  # bits still free in ``byte``

    def bit(self, v: int) -> None:
        if self.ct == 0:
            self.out.append(self.byte)
            self.ct = 7 if self.byte == 0xFF else 8
            self.byte = 0
        self.ct -= 1
        self.byte |= (v & 1) << self.ct

    def bits(self, v: int, n: int) -> None:
        for i in range(n - 1, -1, -1):
            self.bit((v >> i) & 1)

    def end(self) -> bytes:
        """The header's bytes: the last one padded with 0 bits, and a 0 byte after a last ``FF``."""
        self.out.append(self.byte)
        if self.byte == 0xFF:
            self.out.append(0)
        return bytes(self.out)


def _tag_encode(path: Sequence[int], values: list[int], lows: list[int], known: list[bool], threshold: int,
                wr: _Writer) -> None:
    """Tag tree coding (B.10.2) of the leaf at the end of ``path`` against ``threshold``."""
    low = 0
    for node in path:
        if low > lows[node]:
            lows[node] = low
        else:
            low = lows[node]
        while low < threshold:
            if low >= values[node]:
                if not known[node]:
                    wr.bit(1)
                    known[node] = True
                break
            wr.bit(0)
            low += 1
        lows[node] = low


def _write_passes(n: int, wr: _Writer) -> None:
    """Number of coding passes (B.10.6, Table B.4)."""
    if n == 1:
        wr.bit(0)
    elif n == 2:
        wr.bits(0b10, 2)
    elif n <= 5:
        wr.bits(0b11, 2)
        wr.bits(n - 3, 2)
    elif n <= 36:
        wr.bits(0b1111, 4)
        wr.bits(n - 6, 5)
    else:
        wr.bits(0b1111_11111, 9)
        wr.bits(n - 37, 7)


class _BandWriter:
    """The header state of one band of one precinct while writing: its two tag trees (values,
    lower bounds sent, nodes known) and per code-block whether it was included and its ``Lblock``."""

    __slots__ = ("incl", "incl_known", "incl_lo", "included", "lblock", "msb", "msb_known", "msb_lo", "paths")

    def __init__(self, w: int, h: int, first: Mapping[int, int], zero: Mapping[int, int]) -> None:
        nodes, self.paths = _tree_paths(w, h)
        self.incl, self.msb = [_INF] * nodes, [_INF] * nodes
        for k, path in enumerate(self.paths):
            f = first.get(k)
            if f is None:
                continue
            for node in path:  # a node's value is the least of its leaves' (those included)
                self.incl[node] = min(self.incl[node], f)
                self.msb[node] = min(self.msb[node], zero[k])
        self.incl_lo, self.incl_known = [0] * nodes, [False] * nodes
        self.msb_lo, self.msb_known = [0] * nodes, [False] * nodes
        self.included, self.lblock = [False] * (w * h), [3] * (w * h)

    def snapshot(self) -> tuple[list[int], list[bool], list[int], list[bool], list[bool], list[int]]:
        return (self.incl_lo[:], self.incl_known[:], self.msb_lo[:], self.msb_known[:], self.included[:],
                self.lblock[:])

    def restore(self, s: tuple[list[int], list[bool], list[int], list[bool], list[bool], list[int]]) -> None:
        self.incl_lo, self.incl_known, self.msb_lo, self.msb_known, self.included, self.lblock = s


class _PrecinctWriter:
    """The header state of one precinct while writing (a :class:`_BandWriter` per band)."""

    def __init__(self, geometry: Sequence[tuple[int, int]], first: Mapping[int, Mapping[int, int]],
                 zero: Mapping[int, Mapping[int, int]]) -> None:
        self.bands = [_BandWriter(w, h, first.get(b, {}), zero.get(b, {})) for b, (w, h) in enumerate(geometry)]

    def header(self, layer: int, contributions: Mapping[tuple[int, int], tuple[int, int]]) -> bytes:
        """The header of this precinct's packet of ``layer``: ``contributions`` maps (band,
        code-block) to (passes, bytes) for the code-blocks in it. A packet without any is written
        as one saying so code-block by code-block when that fits in its one byte (the inclusion
        trees then say some of what later packets would; OpenJPEG does so), else as an empty
        packet."""
        saved = [band.snapshot() for band in self.bands] if not contributions else []
        wr = _Writer()
        self._codeblocks(layer, contributions, wr)
        out = wr.end()
        if contributions or len(out) == 1:
            return out
        for band, old in zip(self.bands, saved, strict=True):  # as it was: an empty packet
            band.restore(old)
        empty = _Writer()
        empty.bit(0)  # an empty packet (B.10.3)
        return empty.end()

    def _codeblocks(self, layer: int, contributions: Mapping[tuple[int, int], tuple[int, int]], wr: _Writer) -> None:
        wr.bit(1)
        for b, band in enumerate(self.bands):
            for k in range(len(band.included)):
                got = contributions.get((b, k))
                if band.included[k]:
                    wr.bit(1 if got else 0)
                else:
                    _tag_encode(band.paths[k], band.incl, band.incl_lo, band.incl_known, layer + 1, wr)
                if got is None:
                    continue
                if not band.included[k]:
                    _tag_encode(band.paths[k], band.msb, band.msb_lo, band.msb_known, _INF, wr)
                    band.included[k] = True
                n, length = got
                _write_passes(n, wr)
                extra = max(0, length.bit_length() - (band.lblock[k] + n.bit_length() - 1))
                for _ in range(extra):  # Lblock grows (B.10.7.1)
                    wr.bit(1)
                wr.bit(0)
                band.lblock[k] += extra
                wr.bits(length, band.lblock[k] + n.bit_length() - 1)


def write_packets(sp: StreamParams, width: int, height: int, allocations: Sequence[Mapping[CodeBlock, tuple[int, int]]],
                  blocks: CodeBlocks) -> tuple[bytes, list[int]]:
    """A body of ``len(allocations)`` layers whose layer ``l`` includes, of each code-block, the
    passes and codeword bytes ``allocations[l][cb]`` (cumulative: each layer at least the
    previous; a code-block a layer leaves out has nothing yet), taken from ``blocks``; returns the
    body and the length of every packet. A layer may end inside a coding pass (fewer bytes than
    its passes have): a decoder reads the rest of the codeword as 1 bits (T.800 C.3.4), and the
    next layer that includes the code-block brings the rest of that pass with at least one more
    pass. ``sp.layers`` is ignored: the layers are the allocations'."""
    layers = len(allocations)
    spl = StreamParams(sp.progression, sp.resolutions, layers, sp.irreversible, sp.colour, sp.precincts)
    first: dict[tuple[int, int, int], dict[int, dict[int, int]]] = {}
    zero: dict[tuple[int, int, int], dict[int, dict[int, int]]] = {}
    for layer, alloc in enumerate(allocations):
        for (r, c, p, b, k), (n, _nb) in alloc.items():
            if n > 0 and k not in first.setdefault((r, c, p), {}).setdefault(b, {}):
                first[(r, c, p)][b][k] = layer
                zero.setdefault((r, c, p), {}).setdefault(b, {})[k] = blocks.zero[(r, c, p, b, k)]
    writers: dict[tuple[int, int, int], _PrecinctWriter] = {}
    done: dict[CodeBlock, tuple[int, int]] = {}
    # per layer, per precinct, per (band, code-block): (passes added, first byte, end byte)
    by_precinct: list[dict[tuple[int, int, int], dict[tuple[int, int], tuple[int, int, int]]]] = []
    for alloc in allocations:
        now: dict[tuple[int, int, int], dict[tuple[int, int], tuple[int, int, int]]] = {}
        for cb, (n, nb) in alloc.items():
            r, c, p, b, k = cb
            n0, b0 = done.get(cb, (0, 0))
            if n > n0:
                if nb < b0 or nb > len(blocks.data[cb]):
                    raise ValueError(f"code-block {cb}: bytes {nb} outside {b0}..{len(blocks.data[cb])}")
                now.setdefault((r, c, p), {})[(b, k)] = (n - n0, b0, nb)
                done[cb] = (n, nb)
            elif (n, nb) != (n0, b0):
                raise ValueError(f"code-block {cb}: a layer adds bytes {b0}..{nb} but no pass")
        by_precinct.append(now)
    out = bytearray()
    lengths: list[int] = []
    for layer, r, c, p in packet_order(spl, width, height).tolist():
        key = (r, c, p)
        wr_state = writers.get(key)
        if wr_state is None:
            geometry = [g for g in _precinct_codeblocks(spl, width, height, r, p) if g[0] * g[1]]
            wr_state = writers[key] = _PrecinctWriter(geometry, first.get(key, {}), zero.get(key, {}))
        packet = _packet(wr_state, layer, key, by_precinct[layer].get(key, {}), blocks)
        out += packet
        lengths.append(len(packet))
    return bytes(out), lengths


def _packet(writer: _PrecinctWriter, layer: int, key: tuple[int, int, int],
            got: Mapping[tuple[int, int], tuple[int, int, int]], blocks: CodeBlocks) -> bytes:
    """The packet of precinct ``key`` for ``layer``: its header (``writer``'s state moves on)
    and the codeword bytes of ``got`` ((band, code-block) -> (passes added, first byte, end
    byte)), band by band in raster order."""
    r, c, p = key
    packet = bytearray(writer.header(layer, {bk: (v[0], v[2] - v[1]) for bk, v in got.items()}))
    for b, band in enumerate(writer.bands):
        for k in range(len(band.included)):
            v = got.get((b, k))
            if v is not None:
                packet += blocks.data[(r, c, p, b, k)][v[1]:v[2]]
    return bytes(packet)


class LayerWriter:
    """:func:`write_packets` of one layer (``[allocation]``) for one body's ``blocks``, called
    many times with allocations that differ in a few code-blocks (:mod:`.tighten`'s trials):
    a one-layer packet depends only on its own precinct's contributions, so each precinct's
    packet is written once for each set of contributions it is given and remembered. The
    same bytes as :func:`write_packets` (tested), without writing again the packets a trial
    leaves as they were."""

    def __init__(self, sp: StreamParams, width: int, height: int, blocks: CodeBlocks) -> None:
        self.sp = StreamParams(sp.progression, sp.resolutions, 1, sp.irreversible, sp.colour, sp.precincts)
        self.width, self.height = int(width), int(height)
        self.blocks = blocks
        self._keys = [(r, c, p) for _layer, r, c, p in packet_order(self.sp, self.width, self.height).tolist()]
        self._geometry = {key: [g for g in _precinct_codeblocks(self.sp, self.width, self.height, key[0], key[2])
                                if g[0] * g[1]] for key in self._keys}
        self._memo: dict[tuple[tuple[int, int, int], tuple[tuple[int, int, int, int], ...]], bytes] = {}

    def packets(self, allocation: Mapping[CodeBlock, tuple[int, int]]) -> list[bytes]:
        """The packets (codestream order) of the one-layer body of ``allocation``."""
        blocks = self.blocks
        now: dict[tuple[int, int, int], list[tuple[int, int, int, int]]] = {}
        for cb, (n, nb) in allocation.items():
            if n > 0:
                if nb < 0 or nb > len(blocks.data[cb]):
                    raise ValueError(f"code-block {cb}: bytes {nb} outside 0..{len(blocks.data[cb])}")
                r, c, p, b, k = cb
                now.setdefault((r, c, p), []).append((b, k, n, nb))
            elif nb != 0:
                raise ValueError(f"code-block {cb}: a layer adds bytes 0..{nb} but no pass")
        out: list[bytes] = []
        for key in self._keys:
            got = tuple(sorted(now.get(key, ())))
            packet = self._memo.get((key, got))
            if packet is None:
                first: dict[int, dict[int, int]] = {}
                zero: dict[int, dict[int, int]] = {}
                for b, k, _n, _nb in got:
                    first.setdefault(b, {})[k] = 0
                    zero.setdefault(b, {})[k] = blocks.zero[(*key, b, k)]
                writer = _PrecinctWriter(self._geometry[key], first, zero)
                packet = _packet(writer, 0, key, {(b, k): (n, 0, nb) for b, k, n, nb in got}, blocks)
                self._memo[(key, got)] = packet
            out.append(packet)
        return out
