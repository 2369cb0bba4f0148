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
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from coex import DecodeError

from .codec import StreamParams, packet_order, parse_params

__all__ = ["PacketParser", "packet_lengths", "precinct_codeblocks"]

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


def _read_header(bands: list[_Band], layer: int, rd: _Bits) -> int:
    """Read one packet header (state updated in place); return the sum of contribution lengths."""
    if not rd.bit():
        return 0  # empty packet (B.10.3)
    total = 0
    for band in bands:
        included, lblock, passes, paths = band.included, band.lblock, band.passes, band.paths
        for k in range(band.n):
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
            n = _num_passes(rd)
            passes[k] += n
            if passes[k] > _MAX_PASSES:
                raise DecodeError(f"packet header: more than {_MAX_PASSES} coding passes in a code-block")
            while rd.bit():
                lblock[k] += 1
                if lblock[k] > _MAX_LBLOCK:
                    raise DecodeError(f"packet header: Lblock above {_MAX_LBLOCK}")
            total += rd.bits(lblock[k] + n.bit_length() - 1)
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
