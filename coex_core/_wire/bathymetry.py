"""Bathymetry messages: map metadata, subgrids, region-of-interest requests."""

from __future__ import annotations

from typing import Any

import construct as cs

from ..messages import (
    MapMetadata,
    MapRoiReply,
    MapRoiRequest,
    PredictedSubgrid,
    Subgrid,
    SubgridCells,
    SubgridContext,
    SubgridEncoding,
)
from ._primitives import (
    Bits,
    Body,
    Bool,
    Bounded,
    Choice,
    Entries,
    Enum,
    FieldSpec,
    OutOfRange,
    Rule,
    SInt,
    Stamp,
    UInt,
    When,
)
from ._registry import MessageSpec, register
from ._subgrid_code import CodedCells, CodeError, decode_cells, encode_cells, table_for

#: Horizontal cell size at level 0 (metres): a 3-bit code.
RESOLUTIONS = (0.125, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0)
#: Vertical resolution (metres): a 3-bit code.
VERTICAL_RESOLUTIONS = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0)
#: At most this many value bits in one subgrid (keeps every subgrid inside one sub-frame).
MAX_SUBGRID_VALUE_BITS = 1536
#: A region request with stamps covers at most this many subgrids.
MAX_ROI_HELD = 64

MAP_METADATA = Body(
    "stamp" / Stamp() * "Time of the newest sounding",
    "resolution" / Choice(RESOLUTIONS, unit="m") * "Cell size at level 0",
    "vertical_resolution" / Choice(VERTICAL_RESOLUTIONS, unit="m") * "Elevation quantum",
    "subgrid_side" / Bounded(2, 16, unit="cells") * "Subgrid side",
    "levels" / Bounded(1, 16) * "Number of levels sent",
    "origin_lat" / Bounded(-90, 90, 1e-6, unit="deg") * "Latitude of the local origin (WGS 84)",
    "origin_lon" / Bounded(-180, 180, 1e-6, unit="deg") * "Longitude of the local origin (WGS 84)",
    "x_min" / Bounded(-65536, 65535, unit="m") * "Extent of the data: west edge",
    "y_min" / Bounded(-65536, 65535, unit="m") * "Extent of the data: south edge",
    "x_max" / Bounded(-65536, 65535, unit="m") * "Extent of the data: east edge",
    "y_max" / Bounded(-65536, 65535, unit="m") * "Extent of the data: north edge",
    "pending" / Bounded(0, 65535, saturating=True) * "Subgrids waiting to be sent",
    "dropped_k" / Bounded(0, 65535, saturating=True, unit="1000 soundings")
    * "Soundings the map dropped because a budget (memory, disk, tiles) is exhausted, in thousands "
      "rounded up (0: none dropped); topside warns the operator",
)


#: Rice codes: a quotient of this many one-bits or more is sent as an escape instead.
RICE_ESCAPE = 16
#: Escaped values carry their bit length in this many bits, then the value itself.
RICE_ESCAPE_LEN_BITS = 5


def _n_values(ctx: cs.Container) -> int:
    if ctx.encoding == SubgridEncoding.OFFSET and ctx.width == 0:
        return 0
    if ctx.mask is None:
        return int(ctx.side) ** 2
    return int(ctx.mask).bit_count()


def rice_bits(v: int, k: int) -> int:
    """Bits of one value in the Rice code with parameter ``k`` (escape included)."""
    q = v >> k
    if q < RICE_ESCAPE:
        return q + 1 + k
    return RICE_ESCAPE + RICE_ESCAPE_LEN_BITS + v.bit_length()


class SubgridCode(UInt):
    """One cell code of a Subgrid: ``width`` bits for OFFSET, otherwise a Rice code with parameter
    ``width``: ``q = v >> width`` below :data:`RICE_ESCAPE` is ``q`` one-bits, a zero-bit and the
    low ``width`` bits of ``v``; a larger one is :data:`RICE_ESCAPE` one-bits, the bit length ``n``
    of ``v`` in :data:`RICE_ESCAPE_LEN_BITS` bits and ``v`` in ``n`` bits (escapes only when
    needed: any other form is not canonical and is rejected)."""

    def __init__(self) -> None:
        super().__init__(lambda ctx: ctx.width)
        self.coex_spec = FieldSpec("variable", "", note=(
            f"OFFSET: width bits; otherwise a Rice code with parameter width, escape after "
            f"{RICE_ESCAPE} ones: {RICE_ESCAPE_LEN_BITS}-bit length, then the value"),
            coding="OFFSET: unsigned; else Rice (canonical)")

    def _width(self, context: Any) -> int:
        w = int(context.width)
        # For Rice codes this is only the range of values without an escape (used by generators).
        return w if context.encoding == SubgridEncoding.OFFSET else min(w + 4, 24)

    def _parse(self, stream: Any, context: Any, path: str) -> int:
        if context.encoding == SubgridEncoding.OFFSET:
            return super()._parse(stream, context, path)  # type: ignore[no-any-return]
        k = int(context.width)
        q = 0
        while cs.stream_read(stream, 1, path)[0]:
            q += 1
            if q == RICE_ESCAPE:
                nb = _read_uint(stream, RICE_ESCAPE_LEN_BITS, path)
                return _read_uint(stream, nb, path)
        return (q << k) | _read_uint(stream, k, path)

    def _build(self, obj: Any, stream: Any, context: Any, path: str) -> int:
        if context.encoding == SubgridEncoding.OFFSET:
            return super()._build(obj, stream, context, path)  # type: ignore[no-any-return]
        k = int(context.width)
        v = int(obj)
        if v < 0:
            raise cs.ValidationError(f"negative Rice value {v}", path=path)
        q = v >> k
        if q < RICE_ESCAPE:
            bits = [1] * q + [0] + [(v >> (k - 1 - i)) & 1 for i in range(k)]
        else:
            nb = v.bit_length()
            if nb >= 1 << RICE_ESCAPE_LEN_BITS:
                raise cs.ValidationError(f"Rice value {v} too large", path=path)
            bits = [1] * RICE_ESCAPE
            bits += [(nb >> (RICE_ESCAPE_LEN_BITS - 1 - i)) & 1 for i in range(RICE_ESCAPE_LEN_BITS)]
            bits += [(v >> (nb - 1 - i)) & 1 for i in range(nb)]
        cs.stream_write(stream, bytes(bits), len(bits), path)
        return v


def _bitmask(width: str, bits: Any) -> Any:
    c = Bits(bits)
    c.coex_spec = FieldSpec(width, "", coding="bit mask, first bit first")
    return c


def _value_bits(ctx: Any) -> int:
    values = [int(v) for v in ctx["values"]]
    if ctx.encoding == SubgridEncoding.OFFSET:
        return len(values) * int(ctx.width)
    return sum(rice_bits(v, int(ctx.width)) for v in values)


def _read_uint(stream: Any, width: int, path: str) -> int:
    if width == 0:
        return 0
    v = 0
    for b in cs.stream_read(stream, width, path):
        v = (v << 1) | (b & 1)
    return v


SUBGRID = Body(
    "level" / Bounded(0, 15) * "Level (0 = finest; cell size resolution x 2^level)",
    "ix" / SInt(14) * "Subgrid column index at this level",
    "iy" / SInt(14) * "Subgrid row index at this level",
    "stamp" / Stamp() * "Newest update of any cell in the subgrid",
    "resolution" / Choice(RESOLUTIONS, unit="m") * "Cell size at level 0",
    "vertical_resolution" / Choice(VERTICAL_RESOLUTIONS, unit="m") * "Elevation quantum",
    "side" / Bounded(2, 16, unit="cells") * "Subgrid side",
    "encoding" / Enum(SubgridEncoding, bits=2) * "Cell coding (see SubgridEncoding)",
    "z_base" / SInt(20) * "Base elevation in vertical-resolution units (block minimum for OFFSET)",
    "width" / Bounded(0, 24, unit="bits") * "OFFSET: bits per value (0: every present cell equals z_base); "
    "DELTA/PLANE/GRADIENT: Rice parameter (spec/payloads.md)",
    "slope_x" / When("`encoding` = PLANE", cs.this.encoding == SubgridEncoding.PLANE, SInt(12))
    * "Eastward slope, 1/8 vertical units per cell",
    "slope_y" / When("`encoding` = PLANE", cs.this.encoding == SubgridEncoding.PLANE, SInt(12))
    * "Northward slope, 1/8 vertical units per cell",
    "partial" / cs.Rebuild(Bool(), lambda ctx: ctx.mask is not None) * "1 if a presence mask follows (derived)",
    "mask" / When("`partial` = 1", cs.this.partial, _bitmask("side^2", lambda ctx: int(ctx.side) ** 2))
    * "Presence mask, one bit per cell, row-major (spec/payloads.md), 1 = the cell is present",
    "values" / Entries("none when `encoding` = OFFSET and `width` = 0; otherwise one per present cell "
                       "(side^2 without a mask, the mask's 1 bits with one)", _n_values, SubgridCode())
    * "Codes of the present cells, row-major (DELTA: serpentine order); spec/payloads.md",
    Rule(lambda ctx: _value_bits(ctx) <= MAX_SUBGRID_VALUE_BITS,
         f"the `values` take more than {MAX_SUBGRID_VALUE_BITS} bits in all", "too large"),
    Rule(lambda ctx: ctx.encoding != SubgridEncoding.GRADIENT or ctx.mask is None,
         "`encoding` is GRADIENT and `partial` is 1 (a GRADIENT subgrid has no mask)", "GRADIENT"),
)

#: Sides of a PredictedSubgrid: a 2-bit code.
PREDICTED_SIDES = (2, 4, 8, 16)
#: At most this many bits in the coded cells of a PredictedSubgrid.
MAX_PREDICTED_CELL_BITS = 1536


def _table(ctx: Any) -> int:
    """The initial probability table (spec/payloads.md 1.7)."""
    return table_for(ctx.context == SubgridContext.PARENT, int(ctx.level))


def _peek(stream: Any, n: int) -> tuple[list[int], int]:
    """The next ``n`` bits of a construct bit stream without consuming them (0 past its end),
    and how many of them are in the stream."""
    if isinstance(stream, cs.core.RestreamedBytesIO):
        have = bytes(stream.rbuffer)
        sub = stream.substream
        pos = sub.tell()
        more = sub.read((max(0, n - len(have)) + 7) // 8)
        sub.seek(pos)
        bits = list(have) + [(b >> (7 - k)) & 1 for b in more for k in range(8)]
    else:
        pos = stream.tell()
        bits = list(stream.read(n))
        stream.seek(pos)
    bits = bits[:n]
    return bits + [0] * (n - len(bits)), len(bits)


class ArithCells(cs.Construct):  # type: ignore[misc]
    """The arithmetic-coded cells of a PredictedSubgrid (spec/payloads.md 1.7): presence when
    ``partial``, then the residuals; its length follows from the decoding (self-delimiting)."""

    def __init__(self) -> None:
        super().__init__()
        self.coex_spec = FieldSpec("variable", "", note=(
            "the presence of each cell when `partial` = 1, then the residual of each present cell, "
            f"binary arithmetic code (spec/payloads.md 1.7), at most {MAX_PREDICTED_CELL_BITS} bits"),
            coding="arithmetic code")

    def _parse(self, stream: Any, context: Any, path: str) -> dict[str, Any]:
        side = int(context.side)
        ahead, real = _peek(stream, MAX_PREDICTED_CELL_BITS + 64)
        pos = [0]

        def read() -> int:
            k = pos[0]
            pos[0] = k + 1
            return ahead[k] if k < len(ahead) else 0

        try:
            cells, length = decode_cells(read, side, bool(context.partial), int(context.shift), _table(context),
                                         MAX_PREDICTED_CELL_BITS)
        except CodeError as exc:
            if pos[0] > real:  # a rule broken by bits past the end of the input, which were not there
                raise OutOfRange(f"truncated: {exc}", path=path, reason="truncated") from None
            raise OutOfRange(str(exc), path=path, reason=exc.reason) from None
        cs.stream_read(stream, length, path)  # consume the code (an input ending inside it: truncated)
        mask = None
        if cells.present is not None:
            mask = int("".join("1" if p else "0" for p in cells.present), 2)
        return {"mask": mask, "residuals": list(cells.residuals)}

    def _build(self, obj: Any, stream: Any, context: Any, path: str) -> Any:
        side = int(context.side)
        mask = obj["mask"]
        residuals = [int(e) for e in obj["residuals"]]
        n = side * side
        present = None if mask is None else [bool((int(mask) >> (n - 1 - k)) & 1) for k in range(n)]
        if mask is not None and not 0 <= int(mask) < (1 << n):
            raise OutOfRange(f"mask {mask} has more than {n} bits", path=path)
        try:
            bits = encode_cells(side, CodedCells(present, residuals), int(context.shift), _table(context))
        except ValueError as exc:
            raise OutOfRange(str(exc), path=path) from None
        if len(bits) > MAX_PREDICTED_CELL_BITS:
            raise OutOfRange(f"the coded cells take {len(bits)} bits, more than {MAX_PREDICTED_CELL_BITS} "
                             "(too large)", path=path, reason="too large")
        cs.stream_write(stream, bytes(bits), len(bits), path)
        return obj

    def _sizeof(self, context: Any, path: str) -> int:
        raise cs.SizeofError("arithmetic code", path=path)


def _crc(width: int) -> Any:
    c = UInt(width)
    c.coex_spec = FieldSpec(str(width), f"0..{(1 << width) - 1}", coding="CRC-8 (spec/payloads.md 1.9)")
    return c


PREDICTED_SUBGRID = Body(
    "level" / Bounded(0, 15) * "Level (0 = finest; cell size resolution x 2^level)",
    "ix" / SInt(14) * "Subgrid column index at this level",
    "iy" / SInt(14) * "Subgrid row index at this level",
    "stamp" / Stamp() * "Newest update of any cell in the subgrid",
    "side" / Choice(PREDICTED_SIDES, unit="cells") * "Subgrid side",
    "context" / Enum(SubgridContext) * "What the cells are predicted from (spec/payloads.md 1.6)",
    "check" / When("`context` = PARENT", cs.this.context == SubgridContext.PARENT, _crc(8))
    * "CRC-8 of the parent's cells the prediction reads (spec/payloads.md 1.9)",
    "resolution" / When("`context` = NONE", cs.this.context == SubgridContext.NONE,
                        Choice(RESOLUTIONS, unit="m")) * "Cell size at level 0 (PARENT: the parent's)",
    "vertical_resolution" / When("`context` = NONE", cs.this.context == SubgridContext.NONE,
                                 Choice(VERTICAL_RESOLUTIONS, unit="m"))
    * "Elevation quantum (PARENT: the parent's)",
    "z_base" / When("`context` = NONE", cs.this.context == SubgridContext.NONE, SInt(20))
    * "Base elevation in vertical-resolution units",
    "predictor" / Bounded(0, 3) * "The prediction, from the context's table (spec/payloads.md 1.8)",
    "shift" / Bounded(0, 3, unit="bits") * "Low bits of each residual sent raw",
    "partial" / cs.Rebuild(Bool(), lambda ctx: ctx.cells["mask"] is not None)
    * "1 if the presence of each cell is coded (derived)",
    "cells" / ArithCells() * "Presence and residuals (JSON: an object, section 13.1)",
)


MAP_ROI_REQUEST = Body(
    "request_id" / Bounded(0, 255) * "Request id (wraps)",
    "level" / Bounded(0, 15) * "Level requested",
    "x0" / SInt(14) * "First subgrid column",
    "y0" / SInt(14) * "First subgrid row",
    "w" / Bounded(1, 16, unit="subgrids") * "Region width",
    "h" / Bounded(1, 16, unit="subgrids") * "Region height",
    "fill_gaps" / Bool() * "Gap filling: send only what topside lacks (held is then empty)",
    "held" / Entries("w*h entries when `fill_gaps` = 0; none when it is 1",
                     lambda ctx: 0 if ctx.fill_gaps else ctx.w * ctx.h, Stamp(optional=True))
    * "Per subgrid, row-major: newest stamp topside holds, or absent",
    "have" / When("`fill_gaps` = 1", cs.this.fill_gaps, _bitmask("w*h", lambda ctx: int(ctx.w) * int(ctx.h)))
    * "w*h bits, row-major, 1 = topside holds the subgrid",
    Rule(lambda ctx: ctx.fill_gaps or ctx.w * ctx.h <= MAX_ROI_HELD,
         f"`fill_gaps` is 0 and w*h is above {MAX_ROI_HELD}", "too many"),
)

MAP_ROI_REPLY = Body(
    "request_id" / Bounded(0, 255) * "The request answered",
    "level" / Bounded(0, 15) * "Its level",
    "queued" / Bounded(0, 1023, saturating=True) * "Subgrids queued for it (0: nothing newer)",
    "waiting" / Bounded(0, 1023, saturating=True)
    * "Subgrids of the region not surveyed yet: the request stands and they follow when surveyed (0: it does not stand)",
)


def _sub(**kw: object) -> Subgrid:
    base: dict[str, object] = dict(
        level=0, ix=0, iy=0, stamp=0, resolution=1.0, vertical_resolution=0.1, side=8,
        encoding=SubgridEncoding.OFFSET, z_base=0, width=0, mask=None, values=(),
    )
    base.update(kw)
    return Subgrid(**base)  # type: ignore[arg-type]


def _meta(**kw: object) -> MapMetadata:
    base: dict[str, object] = dict(
        stamp=0, resolution=1.0, vertical_resolution=0.1, subgrid_side=8, levels=4, origin_lat=0.0,
        origin_lon=0.0, x_min=0, y_min=0, x_max=0, y_max=0, pending=0, dropped_k=0,
    )
    base.update(kw)
    return MapMetadata(**base)  # type: ignore[arg-type]


#: The largest subgrid: PLANE with slopes, a full mask and 1536 value bits.
_LARGEST_SUBGRID = _sub(side=16, encoding=SubgridEncoding.PLANE, width=5, mask=(1 << 256) - 1,
                        values=(31,) * 256, z_base=-(2**19), slope_x=-2048, slope_y=2047)

register(MessageSpec(
    16, MapMetadata, MAP_METADATA, False, "bathymetry",
    "Map geometry and progress.",
    largest=lambda: _meta(),
    cases=lambda: [
        ("minimum", _meta(resolution=0.125, vertical_resolution=0.01, subgrid_side=2, levels=1,
                          origin_lat=-90.0, origin_lon=-180.0, x_min=-65536, y_min=-65536,
                          x_max=-65536, y_max=-65536)),
        ("nui_2022", _meta(stamp=5400, origin_lat=33.806114, origin_lon=-118.389713, x_min=-256,
                           y_min=-256, x_max=255, y_max=255, pending=311)),
        ("dropping", _meta(stamp=72000, x_min=0, y_min=0, x_max=10000, y_max=10000, pending=4000,
                           dropped_k=38500)),
        ("maximum", _meta(stamp=2**18 - 1, resolution=16.0, vertical_resolution=2.0, subgrid_side=16,
                          levels=16, origin_lat=90.0, origin_lon=180.0, x_min=65535, y_min=65535,
                          x_max=65535, y_max=65535, pending=65535, dropped_k=65535)),
    ],
))
register(MessageSpec(
    17, Subgrid, SUBGRID, False, "bathymetry",
    "A block of side x side cells at one level, decodable on its own.",
    largest=lambda: _LARGEST_SUBGRID,
    cases=lambda: [
        ("flat_all_equal", _sub(z_base=-300, width=0)),
        ("typical_4bit", _sub(level=2, ix=-3, iy=5, stamp=4000, z_base=-298, width=4,
                              values=tuple((i * 7) % 16 for i in range(64)))),
        ("sparse_mask", _sub(level=0, ix=8191, iy=-8192, stamp=2**18 - 1, z_base=2**19 - 1, width=3,
                             mask=0b1011 << 60, values=(1, 7, 0))),
        ("empty_mask", _sub(side=2, width=5, mask=0, values=())),
        ("delta_rice_with_escape", _sub(level=1, ix=4, iy=-2, stamp=1234, encoding=SubgridEncoding.DELTA,
                                        z_base=-305, width=1, mask=((1 << 64) - 1) ^ 0b111,
                                        values=(0, 1, 2, 3, 0, 0, 5) + (2,) * 52 + (200, 1))),
        ("plane_rice", _sub(level=4, ix=0, iy=-1, stamp=99, encoding=SubgridEncoding.PLANE, z_base=-412,
                            width=0, slope_x=-13, slope_y=40, values=tuple((i * 5) % 3 for i in range(64)))),
        ("gradient_complete", _sub(level=3, ix=-7, iy=2, stamp=77, encoding=SubgridEncoding.GRADIENT,
                                   z_base=-2950, width=1, values=(0, *tuple(i * 3 % 5 for i in range(63))))),
        ("largest", _LARGEST_SUBGRID),
    ],
))
def _pred(**kw: object) -> PredictedSubgrid:
    base: dict[str, object] = dict(
        level=0, ix=0, iy=0, stamp=0, side=8, context=SubgridContext.PARENT, predictor=0, shift=0,
        cells=SubgridCells(None, (0,) * 64), check=0,
    )
    base.update(kw)
    if base["context"] == SubgridContext.NONE:
        base.setdefault("resolution", 1.0)
        base.setdefault("vertical_resolution", 0.1)
        base.setdefault("z_base", 0)
        base["check"] = None
    return PredictedSubgrid(**base)  # type: ignore[arg-type]


#: The largest PredictedSubgrid: NONE (geometry and base), side 16, coded cells within 3 bits of
#: the 1536 allowed (so it takes the most bytes any can; a test checks it).
_LARGEST_PREDICTED = _pred(
    level=15, ix=-8192, iy=8191, stamp=2**18 - 1, side=16, context=SubgridContext.NONE, predictor=3, shift=0,
    resolution=16.0, vertical_resolution=2.0, z_base=-(2**19),
    cells=SubgridCells(None, tuple(12 if i % 2 else -12 for i in range(245)) + (0,) * 11))
#: residuals of a typical 1 m subgrid predicted from its parent (0.1 m units)
_TYPICAL = (0, 1, -1, 0, 2, 0, 0, -1, 1, 0, 0, -2, 1, 0, 0, 0, -1, 0, 3, 1, 0, 0, -1, 0, 0, 0, 1, -1, 0,
            2, 0, 0, 1, 0, 0, -1, 0, 0, 0, 1, 0, -3, 1, 0, 0, 0, 1, 0, -1, 0, 0, 2, -1, 0, 0, 0, 1, 0, 0, -1,
            0, 0, 1, 0)

register(MessageSpec(
    20, PredictedSubgrid, PREDICTED_SUBGRID, False, "bathymetry",
    "A block of side x side cells at one level predicted from its parent subgrid as topside holds it "
    "(or from its own base), the residuals arithmetic-coded.",
    largest=lambda: _LARGEST_PREDICTED,
    cases=lambda: [
        ("parent_flat", _pred()),
        ("parent_typical", _pred(level=0, ix=37, iy=-12, stamp=5400, check=0xA7, cells=SubgridCells(None, _TYPICAL))),
        ("parent_bilinear_level_1", _pred(level=1, ix=-5, iy=6, stamp=77, check=0x3C, predictor=1,
                                          cells=SubgridCells(None, tuple((i * 5) % 7 - 3 for i in range(64))))),
        ("parent_cubic_half_shift", _pred(level=3, ix=2, iy=3, stamp=12345, check=0xFF, predictor=3, shift=2,
                                          cells=SubgridCells(None, tuple((i * 37) % 61 - 30 for i in range(64))))),
        ("parent_partial", _pred(level=0, ix=8191, iy=-8192, stamp=2**18 - 1, check=0x00, predictor=2,
                                 cells=SubgridCells((1 << 64) - (1 << 24), tuple(_TYPICAL[:40])))),
        ("parent_escape", _pred(level=2, check=0x5A, cells=SubgridCells(None, (0,) * 30 + (-700, 16, -17) + (0,) * 31))),
        ("none_med", _pred(context=SubgridContext.NONE, level=4, ix=-1, iy=-1, stamp=3000, predictor=1, shift=1,
                           z_base=-4987, cells=SubgridCells(None, tuple((i * 11) % 9 - 4 for i in range(64))))),
        ("none_side_2_partial", _pred(context=SubgridContext.NONE, side=2, resolution=0.125, vertical_resolution=0.01,
                                      z_base=2**19 - 1, predictor=2, cells=SubgridCells(0b1011, (0, -5, 9)))),
        ("empty_mask", _pred(side=4, cells=SubgridCells(0, ()))),
        ("largest", _LARGEST_PREDICTED),
    ],
))
register(MessageSpec(
    18, MapRoiRequest, MAP_ROI_REQUEST, False, "bathymetry",
    "Topside request for a region at a level, with what it holds (implicit ack).",
    largest=lambda: MapRoiRequest(255, 15, 0, 0, 8, 8, False, (2**18 - 1,) * 64),
    cases=lambda: [
        ("single_missing", MapRoiRequest(0, 0, 0, 0, 1, 1, False, (None,))),
        ("two_by_two", MapRoiRequest(3, 1, -2, 4, 2, 2, False, (100, None, 2**18 - 1, 0))),
        ("fill_gaps_max_region", MapRoiRequest(255, 15, -8192, 8191, 16, 16, True, (),
                                                have=((1 << 256) - 1) ^ (0b1011 << 100))),
        ("fill_gaps_holds_nothing", MapRoiRequest(9, 0, 3, -3, 3, 2, True, (), have=0)),
        ("largest", MapRoiRequest(255, 15, 0, 0, 8, 8, False, (2**18 - 1,) * 64)),
    ],
))
register(MessageSpec(
    19, MapRoiReply, MAP_ROI_REPLY, False, "bathymetry",
    "Vehicle answer to a region request: how many subgrids it queued, and how many it waits for.",
    largest=lambda: MapRoiReply(255, 15, 1023, 1023),
    cases=lambda: [
        ("nothing_newer", MapRoiReply(0, 0, 0)),
        ("some_queued", MapRoiReply(17, 2, 12)),
        ("standing", MapRoiReply(40, 0, 3, 61)),
        ("maximum", MapRoiReply(255, 15, 1023, 1023)),
    ],
))
