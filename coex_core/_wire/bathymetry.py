"""Bathymetry messages: map metadata, subgrids, region-of-interest requests."""

from __future__ import annotations

import construct as cs

from ..messages import MapMetadata, MapRoiRequest, Subgrid
from ._primitives import Body, Bool, Bounded, Choice, SInt, Stamp, UInt
from ._registry import MessageSpec, register

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
)


def _n_values(ctx: cs.Container) -> int:
    if ctx.width == 0:
        return 0
    if ctx.mask is None:
        return int(ctx.side) ** 2
    return int(ctx.mask).bit_count()


SUBGRID = Body(
    "level" / Bounded(0, 15) * "Level (0 = finest; cell size resolution x 2^level)",
    "ix" / SInt(14) * "Subgrid column index at this level",
    "iy" / SInt(14) * "Subgrid row index at this level",
    "stamp" / Stamp() * "Newest update of any cell in the subgrid",
    "resolution" / Choice(RESOLUTIONS, unit="m") * "Cell size at level 0",
    "vertical_resolution" / Choice(VERTICAL_RESOLUTIONS, unit="m") * "Elevation quantum",
    "side" / Bounded(2, 16, unit="cells") * "Subgrid side",
    "encoding" / Bounded(0, 3) * "Cell coding: 0 = offset above z_min",
    "z_min" / SInt(20) * "Block minimum, in vertical-resolution units",
    "width" / Bounded(0, 24, unit="bits") * "Bits per cell value (0: every present cell equals z_min)",
    "partial" / cs.Rebuild(Bool(), lambda ctx: ctx.mask is not None) * "1 if a presence mask follows (derived)",
    "mask" / cs.If(cs.this.partial, UInt(lambda ctx: int(ctx.side) ** 2)) * "Presence mask, side^2 bits, row-major",
    "values" / cs.Array(_n_values, UInt(cs.this.width)) * "Cell codes of the present cells, width bits each",
    cs.Check(lambda ctx: len(ctx["values"]) * ctx.width <= MAX_SUBGRID_VALUE_BITS),
)

MAP_ROI_REQUEST = Body(
    "request_id" / Bounded(0, 255) * "Request id (wraps)",
    "level" / Bounded(0, 15) * "Level requested",
    "x0" / SInt(14) * "First subgrid column",
    "y0" / SInt(14) * "First subgrid row",
    "w" / Bounded(1, 16, unit="subgrids") * "Region width",
    "h" / Bounded(1, 16, unit="subgrids") * "Region height",
    "fill_gaps" / Bool() * "Send only what topside lacks (held is then empty)",
    "held" / cs.Array(lambda ctx: 0 if ctx.fill_gaps else ctx.w * ctx.h, Stamp(optional=True))
    * "Per subgrid, row-major: newest stamp topside holds, or absent",
    cs.Check(lambda ctx: ctx.fill_gaps or ctx.w * ctx.h <= MAX_ROI_HELD),
)


def _sub(**kw: object) -> Subgrid:
    base: dict[str, object] = dict(
        level=0, ix=0, iy=0, stamp=0, resolution=1.0, vertical_resolution=0.1, side=8, encoding=0,
        z_min=0, width=0, mask=None, values=(),
    )
    base.update(kw)
    return Subgrid(**base)  # type: ignore[arg-type]


def _meta(**kw: object) -> MapMetadata:
    base: dict[str, object] = dict(
        stamp=0, resolution=1.0, vertical_resolution=0.1, subgrid_side=8, levels=4, origin_lat=0.0,
        origin_lon=0.0, x_min=0, y_min=0, x_max=0, y_max=0, pending=0,
    )
    base.update(kw)
    return MapMetadata(**base)  # type: ignore[arg-type]


_LARGEST_SUBGRID = _sub(side=16, width=6, mask=(1 << 256) - 1, values=(63,) * 256, z_min=-(2**19))

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
        ("maximum", _meta(stamp=2**18 - 1, resolution=16.0, vertical_resolution=2.0, subgrid_side=16,
                          levels=16, origin_lat=90.0, origin_lon=180.0, x_min=65535, y_min=65535,
                          x_max=65535, y_max=65535, pending=65535)),
    ],
))
register(MessageSpec(
    17, Subgrid, SUBGRID, False, "bathymetry",
    "A block of side x side cells at one level, decodable on its own.",
    largest=lambda: _LARGEST_SUBGRID,
    cases=lambda: [
        ("flat_all_equal", _sub(z_min=-300, width=0)),
        ("typical_4bit", _sub(level=2, ix=-3, iy=5, stamp=4000, z_min=-298, width=4,
                              values=tuple((i * 7) % 16 for i in range(64)))),
        ("sparse_mask", _sub(level=0, ix=8191, iy=-8192, stamp=2**18 - 1, z_min=2**19 - 1, width=3,
                             mask=0b1011 << 60, values=(1, 7, 0))),
        ("empty_mask", _sub(side=2, width=5, mask=0, values=())),
        ("largest", _LARGEST_SUBGRID),
    ],
))
register(MessageSpec(
    18, MapRoiRequest, MAP_ROI_REQUEST, False, "bathymetry",
    "Topside request for a region at a level, with what it holds (implicit ack).",
    largest=lambda: MapRoiRequest(255, 15, 0, 0, 8, 8, False, (2**18 - 1,) * 64),
    cases=lambda: [
        ("single_missing", MapRoiRequest(0, 0, 0, 0, 1, 1, False, (None,))),
        ("two_by_two", MapRoiRequest(3, 1, -2, 4, 2, 2, False, (100, None, 2**18 - 1, 0))),
        ("fill_gaps_max_region", MapRoiRequest(255, 15, -8192, 8191, 16, 16, True, ())),
        ("largest", MapRoiRequest(255, 15, 0, 0, 8, 8, False, (2**18 - 1,) * 64)),
    ],
))
