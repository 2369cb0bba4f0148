"""Topside products: GeoTIFF and PNG export of a level, and candidate-target flagging.

GeoTIFF: float32, NaN = no data (``GDAL_NODATA`` tag ``nan``), north-up. The CRS is a local metric
Transverse Mercator centred on the survey's origin (``origin_lat``, ``origin_lon``, WGS 84, scale
1, no false easting/northing), so map x/y (metres east/north of the origin) are the projected
coordinates. Written with ``tifffile`` and the GeoTIFF keys (ModelPixelScale, ModelTiepoint,
GeoKeyDirectory, GeoDoubleParams). :func:`write_level_geotiff` writes a receiver's level the same
way, tiled (256 x 256) and deflate-compressed, streamed from the receiver's tiles: a 100 km² level
at 1 m is never one array in memory.

PNG: elevation through the depth colour map, multiplied by a hillshade (sun from the north-west,
45 deg), drawn by :mod:`coex_plugins.render` as the console and the demo report draw it.

Targets: cells higher than the background around them (a grey-scale opening, the "top-hat"
transform) by more than ``threshold`` metres, grouped into 8-connected candidates with position,
height above the background and size.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from coex_plugins.render import elevation_rgba, hillshade
from coex_plugins.render import write_png as _write_png

__all__ = ["Candidate", "find_targets", "hillshade", "opening", "read_geotiff", "write_geotiff",
           "write_geotiff_tiled", "write_level_geotiff", "write_png"]

FloatArray = npt.NDArray[np.float64]

# GeoKey ids and codes (GeoTIFF 1.1).
_GT_MODEL_TYPE, _GT_RASTER_TYPE, _GT_CITATION = 1024, 1025, 1026
_GEOGRAPHIC_TYPE, _GEOG_ANGULAR_UNITS = 2048, 2054
_PROJECTED_CS_TYPE, _PROJECTION, _PROJ_COORD_TRANS, _PROJ_LINEAR_UNITS = 3072, 3074, 3075, 3076
_PROJ_NAT_ORIGIN_LONG, _PROJ_NAT_ORIGIN_LAT = 3080, 3081
_PROJ_FALSE_EASTING, _PROJ_FALSE_NORTHING, _PROJ_SCALE_AT_NAT_ORIGIN = 3082, 3083, 3092
_USER_DEFINED = 32767
_CT_TRANSVERSE_MERCATOR = 1


def _geokeys(origin_lat: float, origin_lon: float) -> tuple[list[int], list[float]]:
    doubles = [origin_lon, origin_lat, 0.0, 0.0, 1.0]
    keys = [
        (_GT_MODEL_TYPE, 0, 1, 1),  # projected
        (_GT_RASTER_TYPE, 0, 1, 1),  # pixel is area
        (_GEOGRAPHIC_TYPE, 0, 1, 4326),  # WGS 84
        (_GEOG_ANGULAR_UNITS, 0, 1, 9102),  # degree
        (_PROJECTED_CS_TYPE, 0, 1, _USER_DEFINED),
        (_PROJECTION, 0, 1, _USER_DEFINED),
        (_PROJ_COORD_TRANS, 0, 1, _CT_TRANSVERSE_MERCATOR),
        (_PROJ_LINEAR_UNITS, 0, 1, 9001),  # metre
        (_PROJ_NAT_ORIGIN_LONG, 34736, 1, 0),
        (_PROJ_NAT_ORIGIN_LAT, 34736, 1, 1),
        (_PROJ_FALSE_EASTING, 34736, 1, 2),
        (_PROJ_FALSE_NORTHING, 34736, 1, 3),
        (_PROJ_SCALE_AT_NAT_ORIGIN, 34736, 1, 4),
    ]
    keys.sort()
    directory = [1, 1, 0, len(keys)]
    for k in keys:
        directory.extend(k)
    return directory, doubles


def write_geotiff(
    path: str | Path,
    grid: npt.ArrayLike,
    *,
    x0: float,
    y0: float,
    cell: float,
    origin_lat: float = 0.0,
    origin_lon: float = 0.0,
) -> Path:
    """Write ``grid`` (row 0 = south, as the map holds it) with south-west corner ``(x0, y0)``."""
    import tifffile

    arr = np.flipud(np.asarray(grid, np.float64)).astype(np.float32)
    tags = _geotags(x0, y0, cell, arr.shape[0], origin_lat, origin_lon)
    out = Path(path)
    tifffile.imwrite(out, arr, photometric="minisblack", extratags=tags)
    return out


def _geotags(x0: float, y0: float, cell: float, rows: int, origin_lat: float,
             origin_lon: float) -> list[tuple[int, str, int, Any, bool]]:
    directory, doubles = _geokeys(origin_lat, origin_lon)
    return [
        (33550, "d", 3, (cell, cell, 0.0), True),  # ModelPixelScale
        (33922, "d", 6, (0.0, 0.0, 0.0, x0, y0 + rows * cell, 0.0), True),  # ModelTiepoint (top-left)
        (34735, "H", len(directory), tuple(directory), True),  # GeoKeyDirectory
        (34736, "d", len(doubles), tuple(doubles), True),  # GeoDoubleParams
        (42113, "s", 4, "nan", True),  # GDAL_NODATA
    ]


def write_geotiff_tiled(
    path: str | Path,
    read: Callable[[int, int, int, int], npt.ArrayLike],
    *,
    width: int,
    height: int,
    x0: float,
    y0: float,
    cell: float,
    origin_lat: float = 0.0,
    origin_lon: float = 0.0,
    tile: int = 256,
) -> Path:
    """Write a ``width x height`` raster as :func:`write_geotiff` does (same tags), but tiled
    (``tile x tile``, a multiple of 16) and deflate-compressed, fetching it a tile at a time:
    ``read(col, row, w, h)`` returns the ``h x w`` cells from column ``col`` and row ``row``
    counted from the south-west corner (row 0 = south, NaN = no data). Only one tile is in
    memory at a time."""
    import tifffile

    if tile <= 0 or tile % 16:
        raise ValueError("tile must be a positive multiple of 16")
    if width <= 0 or height <= 0:
        raise ValueError("empty raster")

    def tiles() -> Iterator[npt.NDArray[np.float32]]:
        for top in range(height, 0, -tile):  # TIFF tile rows, north first
            r0 = max(0, top - tile)
            for c0 in range(0, width, tile):
                w = min(tile, width - c0)
                block = np.asarray(read(c0, r0, w, top - r0), np.float64)
                if block.shape != (top - r0, w):
                    raise ValueError(f"read({c0}, {r0}, {w}, {top - r0}) gave {block.shape}")
                out = np.full((tile, tile), np.nan, np.float32)
                out[:top - r0, :w] = block[::-1]
                yield out

    out = Path(path)
    tifffile.imwrite(out, tiles(), shape=(height, width), dtype=np.float32, tile=(tile, tile),
                     compression="zlib", photometric="minisblack",
                     extratags=_geotags(x0, y0, cell, height, origin_lat, origin_lon))
    return out


def write_level_geotiff(path: str | Path, receiver: Any, level: int, *, tile: int = 256,
                        origin_lat: float | None = None, origin_lon: float | None = None) -> Path:
    """Level ``level`` of a bathymetry receiver (:class:`~coex_plugins.bathymetry.BathymetryReceiver`)
    at full resolution over everything it received, as a tiled, compressed GeoTIFF
    (:func:`write_geotiff_tiled`) read from its tiles through :meth:`window`: memory stays
    bounded by the receiver's budget and one GeoTIFF tile. The origin defaults to the
    receiver's. :class:`ValueError` if nothing of the level is held."""
    summary = receiver.level_summary(level)
    if summary is None or summary["extent"] is None:
        raise ValueError(f"nothing held at level {level}")
    ix0, iy0, ix1, iy1 = summary["extent"]
    cell, side = float(summary["cell"]), int(summary["side"])
    x0, y0 = ix0 * side * cell, iy0 * side * cell
    lat, lon = receiver.origin()

    def read(col: int, row: int, w: int, h: int) -> npt.NDArray[np.float64]:
        grid, _ = receiver.window(level, x0 + col * cell, y0 + row * cell, x0 + (col + w) * cell,
                                  y0 + (row + h) * cell, max_cells=w * h)
        return np.asarray(grid)

    return write_geotiff_tiled(path, read, width=(ix1 - ix0) * side, height=(iy1 - iy0) * side,
                               x0=x0, y0=y0, cell=cell, tile=tile,
                               origin_lat=lat if origin_lat is None else origin_lat,
                               origin_lon=lon if origin_lon is None else origin_lon)


def read_geotiff(path: str | Path) -> tuple[FloatArray, dict[str, Any]]:
    """Read back a GeoTIFF written by :func:`write_geotiff`: grid (row 0 = south) and geo tags."""
    import tifffile

    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        arr = np.flipud(page.asarray().astype(np.float64))
        tags = {t.name: t.value for t in page.tags.values()}  # type: ignore[union-attr]
    scale = tags["ModelPixelScaleTag"]
    tie = tags["ModelTiepointTag"]
    geo = {
        "cell": float(scale[0]),
        "x0": float(tie[3]),
        "y0": float(tie[4]) - arr.shape[0] * float(scale[1]),
        "geokeys": tags.get("GeoKeyDirectoryTag"),
        "geodoubles": tags.get("GeoDoubleParamsTag"),
        "nodata": tags.get("GDAL_NODATA"),
    }
    return arr, geo


def write_png(path: str | Path, grid: npt.ArrayLike, cell: float = 1.0) -> Path:
    """Elevation through the depth colour map (1st to 99th percentile) times a hillshade, north up;
    no-data cells are transparent (:func:`coex_plugins.render.elevation_rgba`)."""
    z = np.asarray(grid, np.float64)
    ok = np.isfinite(z)
    lo, hi = (float(v) for v in np.percentile(z[ok], [1, 99])) if ok.any() else (0.0, 1.0)
    return _write_png(path, elevation_rgba(z, lo, hi, cell))


@dataclass(frozen=True)
class Candidate:
    """A candidate target: centre (x, y) in metres, height above its surroundings, cells flagged."""

    x: float
    y: float
    height: float
    cells: int
    peak_x: float
    peak_y: float

    def to_dict(self) -> dict[str, float | int]:
        return asdict(self)


def _box_sum(a: FloatArray, r: int) -> FloatArray:
    """Sum over the (2r+1) square around every cell (zero padding), via 2-D cumulative sums."""
    p = np.pad(a, ((r + 1, r), (r + 1, r)))
    c = p.cumsum(0).cumsum(1)
    k = 2 * r + 1
    return np.asarray(c[k:, k:] - c[:-k, k:] - c[k:, :-k] + c[:-k, :-k], np.float64)


def _filter1d(a: FloatArray, r: int, axis: int, fn: Any, pad: float) -> FloatArray:
    """Running min or max over 2r+1 cells along ``axis`` (``pad`` outside the grid)."""
    widths = [(0, 0), (0, 0)]
    widths[axis] = (r, r)
    p = np.pad(a, widths, constant_values=pad)
    win = np.lib.stride_tricks.sliding_window_view(p, 2 * r + 1, axis=axis)
    return np.asarray(fn(win, axis=-1), np.float64)


def opening(grid: npt.ArrayLike, r: int) -> FloatArray:
    """Grey-scale opening with a (2r+1)-cell square (a min filter, then a max filter), ignoring
    NaN: the surface with every bump narrower than the square shaved off."""
    z = np.asarray(grid, np.float64)
    lo = np.where(np.isfinite(z), z, np.inf)
    for axis in (0, 1):
        lo = _filter1d(lo, r, axis, np.min, np.inf)
    hi = np.where(np.isfinite(lo), lo, -np.inf)
    for axis in (0, 1):
        hi = _filter1d(hi, r, axis, np.max, -np.inf)
    return np.where(np.isfinite(hi) & np.isfinite(z), hi, np.nan)


def find_targets(
    grid: npt.ArrayLike,
    *,
    cell: float,
    x0: float = 0.0,
    y0: float = 0.0,
    threshold: float = 0.8,
    window: float = 9.0,
    min_cells: int = 2,
    max_area: float = 60.0,
    min_coverage: float = 0.6,
) -> list[Candidate]:
    """Cells standing out from their neighbourhood by more than ``threshold`` metres.

    The background is the grey-scale opening of the map with a square of about ``window``
    metres (a "top-hat" transform): smooth terrain, slopes and ripples stay in the background,
    an object narrower than the window (a car: 4.5 x 1.8 m) does not. Cells whose window is less
    than ``min_coverage`` covered (swath edges, holes) are not judged. Flagged cells are grouped
    (8-connected) into candidates, highest first. Groups of fewer than ``min_cells`` cells
    (single-cell spikes are what swath-edge outliers look like) or larger than ``max_area``
    square metres (terrain, not an object) are left out."""
    z = np.asarray(grid, np.float64)
    if z.size == 0 or min(z.shape) < 2:
        return []
    r = max(1, round(window / cell / 2))
    ok = np.isfinite(z)
    background = opening(z, r)
    coverage = _box_sum(ok.astype(np.float64), r) / (2 * r + 1) ** 2
    with np.errstate(invalid="ignore"):
        excess = z - background
        flag = ok & (coverage >= min_coverage) & (excess > threshold)
    if not flag.any():
        return []
    labels = _label(flag)
    ids = labels[flag]
    ex = excess[flag]
    rows, cols = np.nonzero(flag)
    n = int(ids.max()) + 1
    count = np.bincount(ids, minlength=n)
    height = np.full(n, -np.inf)
    np.maximum.at(height, ids, ex)
    cx = np.bincount(ids, weights=cols, minlength=n) / np.maximum(count, 1)
    cy = np.bincount(ids, weights=rows, minlength=n) / np.maximum(count, 1)
    # peak cell per component: the flagged cell with the highest excess
    order = np.lexsort((-ex, ids))
    first = order[np.flatnonzero(np.diff(ids[order], prepend=-1))]
    out = []
    for i in first:
        lab = int(ids[i])
        if count[lab] < min_cells or count[lab] * cell * cell > max_area:
            continue
        out.append(Candidate(
            x=float(x0 + (cx[lab] + 0.5) * cell), y=float(y0 + (cy[lab] + 0.5) * cell),
            height=float(height[lab]), cells=int(count[lab]),
            peak_x=float(x0 + (cols[i] + 0.5) * cell), peak_y=float(y0 + (rows[i] + 0.5) * cell),
        ))
    out.sort(key=lambda c: -c.height)
    return out


def _label(mask: npt.NDArray[np.bool_]) -> npt.NDArray[np.int64]:
    """8-connected component labels (0..n-1 on ``mask``, -1 elsewhere) by min-label propagation."""
    big = np.iinfo(np.int64).max
    lab = np.where(mask, np.arange(mask.size).reshape(mask.shape), big)
    while True:
        p = np.pad(lab, 1, constant_values=big)
        h, w = mask.shape
        best = lab.copy()
        for dy in (0, 1, 2):
            for dx in (0, 1, 2):
                best = np.minimum(best, p[dy:dy + h, dx:dx + w])
        best = np.where(mask, best, big)
        if np.array_equal(best, lab):
            break
        lab = best
    flat = lab[mask]
    _, dense = np.unique(flat, return_inverse=True)
    out = np.full(mask.shape, -1, np.int64)
    out[mask] = dense.ravel()
    return out
