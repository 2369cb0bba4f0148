"""``report.html`` of a demo run, written for the scientist who has to trust it.

One self-contained HTML file: the outcome in plain words and tables, the received maps as
north-up figures in metres (inline SVG with the raster embedded as a PNG data URI), a gallery of
the received images, charts of the dive over time, the decisions taken and, folded away, the raw
metrics. Plots are drawn here (numpy + Pillow, no plotting dependency).
"""

from __future__ import annotations

import base64
import html
import io
import itertools
import json
import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = ["line_chart", "map_figure", "timeline_chart", "write_report"]

PALETTE = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#17becf"]

#: viridis at nine stops: perceptually uniform, readable in grey and by colour-blind readers
_CMAP_STOPS = np.linspace(0.0, 1.0, 9)
_CMAP_RGB = np.array([
    [68, 1, 84], [71, 45, 123], [59, 82, 139], [44, 114, 142], [33, 145, 140],
    [40, 174, 128], [94, 201, 98], [173, 220, 48], [253, 231, 37],
], np.float64)

_TARGET, _DECOY, _CAND, _TRACK = "#e3171b", "#ff8c00", "#00d8ff", "#1a1a1a"
#: the vehicle's detections (suggestions)
_DETECT = "#d100d1"
_SVG_HEAD = 'xmlns="http://www.w3.org/2000/svg" font-family="Helvetica, Arial, sans-serif"'
_ids = itertools.count(1)  # unique ids for <defs> of several SVGs inlined in one page

GALLERY_CAP = 60


# ------------------------------------------------------------------------------ small helpers


def _e(v: Any) -> str:
    """HTML-escaped text of any value."""
    return html.escape(str(v), quote=True)


def _f(v: Any) -> float | None:
    """``v`` as a finite float, or None."""
    try:
        x = float(v)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def _num(v: Any, fmt: str = ".0f", unit: str = "") -> str:
    """A number for a table cell; an en dash when missing."""
    x = _f(v)
    return "\u2013" if x is None else f"{x:{fmt}}{unit}"


def _pos(x: Any, y: Any, fmt: str = ".1f") -> str:
    """An (x, y) position in metres, or an en dash."""
    fx, fy = _f(x), _f(y)
    return "\u2013" if fx is None or fy is None else f"({fx:{fmt}}, {fy:{fmt}})"


def _tick_label(t: float) -> str:
    """A tick label: no float noise, thousands separated."""
    if t == 0:
        return "0"
    if abs(t) >= 10_000:
        return f"{t:,.0f}"
    return f"{t:.6g}"


def _ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    """Round tick values (steps of 1, 2 or 5 times a power of ten) covering ``lo .. hi``."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo]
    raw = (hi - lo) / n
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 5, 10) if m * mag >= raw * (1 - 1e-9))
    first = math.ceil(lo / step - 1e-9)
    last = math.floor(hi / step + 1e-9)
    return [round(k * step, 10) + 0.0 for k in range(first, last + 1)]


def _nice_length(span: float) -> float:
    """A round length (1, 2 or 5 times a power of ten) of about a fifth of ``span``."""
    target = max(span / 5.0, 1e-9)
    mag = 10.0 ** math.floor(math.log10(target))
    return max((m * mag for m in (1, 2, 5) if m * mag <= target * 1.2), default=mag)


def _png_uri(rgba: npt.NDArray[np.uint8]) -> str:
    """A ``data:image/png;base64,...`` URI of an RGB(A) uint8 array."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(rgba).save(buf, format="PNG", optimize=True)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


# ------------------------------------------------------------------------------ charts


def line_chart(
    series: Mapping[str, Sequence[tuple[float, float]]],
    *,
    title: str,
    xlabel: str,
    ylabel: str,
    width: int = 720,
    height: int = 300,
    step: bool = False,
    markers: Sequence[tuple[float, str]] = (),
) -> str:
    """An SVG line chart of named (x, y) series, with optional labelled vertical markers (x, label)."""
    pts = [p for s in series.values() for p in s]
    if not pts:
        return f"<p><em>{_e(title)}: no data</em></p>"
    xs = [float(p[0]) for p in pts] + [float(m[0]) for m in markers]
    ys = [float(p[1]) for p in pts]
    x0, x1 = min(xs), max(xs)
    y0, y1 = min(0.0, min(ys)), max(ys)
    if x1 == x0:
        x1 = x0 + 1
    if y1 == y0:
        y1 = y0 + 1
    yt = _ticks(y0, y1)
    ylab_w = max(len(_tick_label(t)) for t in yt) * 6.5
    ml, mt, mb = int(max(50, ylab_w + 28)), 30, 45
    legend_w = max(len(n) for n in series) * 6.2 + 34 if series else 0
    mr = int(min(max(legend_w, 40), 260))
    pw, ph = width - ml - mr, height - mt - mb

    def sx(x: float) -> float:
        return ml + (x - x0) / (x1 - x0) * pw

    def sy(y: float) -> float:
        return mt + ph - (y - y0) / (y1 - y0) * ph

    out = [f'<svg {_SVG_HEAD} width="{width}" height="{height}" viewBox="0 0 {width} {height}" '
           f'font-size="11" style="max-width:100%;height:auto">',
           f'<text x="{ml}" y="18" font-size="13" font-weight="bold">{_e(title)}</text>',
           f'<rect x="{ml}" y="{mt}" width="{pw}" height="{ph}" fill="none" stroke="#999"/>']
    for t in _ticks(x0, x1):
        out.append(f'<line x1="{sx(t):.1f}" y1="{mt + ph}" x2="{sx(t):.1f}" y2="{mt + ph + 4}" stroke="#999"/>'
                   f'<text x="{sx(t):.1f}" y="{mt + ph + 16}" text-anchor="middle">{_tick_label(t)}</text>')
    for t in yt:
        out.append(f'<line x1="{ml - 4}" y1="{sy(t):.1f}" x2="{ml + pw}" y2="{sy(t):.1f}" stroke="#eee"/>'
                   f'<text x="{ml - 6}" y="{sy(t) + 4:.1f}" text-anchor="end">{_tick_label(t)}</text>')
    out.append(f'<text x="{ml + pw / 2}" y="{height - 8}" text-anchor="middle">{_e(xlabel)}</text>')
    out.append(f'<text x="14" y="{mt + ph / 2}" transform="rotate(-90 14 {mt + ph / 2})" '
               f'text-anchor="middle">{_e(ylabel)}</text>')
    for i, (name, s) in enumerate(series.items()):
        colour = PALETTE[i % len(PALETTE)]
        out.append(f'<rect x="{ml + pw + 10}" y="{mt + 14 * i}" width="10" height="10" fill="{colour}"/>'
                   f'<text x="{ml + pw + 24}" y="{mt + 9 + 14 * i}">{_e(name)}</text>')
        if not s:
            continue
        coords = []
        prev_y: float | None = None
        for x, y in s:
            if step and prev_y is not None:
                coords.append(f"{sx(x):.1f},{sy(prev_y):.1f}")
            coords.append(f"{sx(x):.1f},{sy(y):.1f}")
            prev_y = y
        out.append(f'<polyline fill="none" stroke="{colour}" stroke-width="1.6" points="{" ".join(coords)}"/>')
    for x, label in markers:
        px = sx(float(x))
        out.append(f'<g><title>{_e(label)} ({float(x):.0f})</title>'
                   f'<line x1="{px:.1f}" y1="{mt}" x2="{px:.1f}" y2="{mt + ph}" stroke="#444" '
                   f'stroke-dasharray="3,3"/>'
                   f'<text x="{px + 3:.1f}" y="{mt + 4}" font-size="9.5" fill="#333" '
                   f'transform="rotate(90 {px + 3:.1f} {mt + 4})" stroke="#fff" stroke-width="3" '
                   f'paint-order="stroke">{_e(label)}</text></g>')
    out.append("</svg>")
    return "".join(out)


def timeline_chart(events: Sequence[Mapping[str, Any]], *, t_end: float, width: int = 720) -> str:
    """A decision timeline: one row per event kind, a dot per event (its text on hover)."""
    if not events:
        return "<p><em>no decisions</em></p>"
    kinds = list(dict.fromkeys(str(e["kind"]) for e in events))
    t_end = max([float(t_end), 1.0] + [float(e["t"]) for e in events])
    ml, mr, row = 170, 20, 26
    height = 58 + row * len(kinds)
    pw = width - ml - mr

    def sx(t: float) -> float:
        return ml + t / t_end * pw

    out = [f'<svg {_SVG_HEAD} width="{width}" height="{height}" viewBox="0 0 {width} {height}" '
           f'font-size="11" style="max-width:100%;height:auto">']
    for i, k in enumerate(kinds):
        y = 20 + row * i
        out.append(f'<text x="{ml - 8}" y="{y + 4}" text-anchor="end">{_e(k)}</text>'
                   f'<line x1="{ml}" y1="{y}" x2="{ml + pw}" y2="{y}" stroke="#ddd"/>')
    for e in events:
        i = kinds.index(str(e["kind"]))
        colour = PALETTE[i % len(PALETTE)]
        out.append(f'<circle cx="{sx(float(e["t"])):.1f}" cy="{20 + row * i}" r="5" fill="{colour}" '
                   f'fill-opacity="0.8"><title>{float(e["t"]):.0f} s: {_e(e.get("text", ""))}</title></circle>')
    base = 20 + row * len(kinds) - 8
    out.append(f'<line x1="{ml}" y1="{base}" x2="{ml + pw}" y2="{base}" stroke="#999"/>')
    for t in _ticks(0, t_end):
        out.append(f'<line x1="{sx(t):.1f}" y1="{base}" x2="{sx(t):.1f}" y2="{base + 4}" stroke="#999"/>'
                   f'<text x="{sx(t):.1f}" y="{base + 16}" text-anchor="middle">{_tick_label(t)}</text>')
    out.append(f'<text x="{ml + pw / 2}" y="{height - 6}" text-anchor="middle">dive time (s)</text>')
    out.append("</svg>")
    return "".join(out)


# ------------------------------------------------------------------------------ maps


def _colourise(t: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """RGB (0..255) of colour-map positions ``t`` in 0..1."""
    return np.stack([np.interp(t, _CMAP_STOPS, _CMAP_RGB[:, c]) for c in range(3)], axis=-1)


def _shade(z: npt.NDArray[np.float64], cell: float, azimuth: float = 315.0,
           altitude: float = 45.0, strength: float = 0.6) -> npt.NDArray[np.float64]:
    """A brightness factor from a hillshade (row 0 = south), 1.0 on flat ground and next to gaps."""
    from coex_plugins.bathymetry import hillshade  # the one hillshade

    lit = hillshade(z, cell, azimuth, altitude)
    factor = 1.0 + strength * (lit - math.sin(math.radians(altitude)))
    return np.where(np.isfinite(z), np.clip(factor, 0.55, 1.25), 1.0)


def _marker(kind: str, x: float, y: float, filled: bool = False) -> str:
    """One map marker centred on (x, y) pixels, with a halo so it reads on any colour."""
    if kind == "target":
        r = 7.5
        return (f'<rect x="{x - r:.1f}" y="{y - r:.1f}" width="{2 * r}" height="{2 * r}" fill="none" '
                f'stroke="#fff" stroke-width="4.5"/>'
                f'<rect x="{x - r:.1f}" y="{y - r:.1f}" width="{2 * r}" height="{2 * r}" fill="none" '
                f'stroke="{_TARGET}" stroke-width="2.2"/>')
    if kind == "decoy":
        r = 8.5
        pts = f"{x:.1f},{y - r:.1f} {x + r:.1f},{y:.1f} {x:.1f},{y + r:.1f} {x - r:.1f},{y:.1f}"
        return (f'<polygon points="{pts}" fill="none" stroke="#fff" stroke-width="4.5"/>'
                f'<polygon points="{pts}" fill="none" stroke="{_DECOY}" stroke-width="2.2"/>')
    if kind == "track":
        return (f'<line x1="{x - 9:.1f}" y1="{y:.1f}" x2="{x + 9:.1f}" y2="{y:.1f}" stroke="#fff" '
                f'stroke-width="3" stroke-opacity="0.7"/>'
                f'<line x1="{x - 9:.1f}" y1="{y:.1f}" x2="{x + 9:.1f}" y2="{y:.1f}" stroke="{_TRACK}" '
                f'stroke-width="1.1"/>')
    if kind == "nodata":
        return ""
    if kind == "detection":  # a suggestion of the vehicle's: a dashed triangle
        r = 10.0
        pts = f"{x:.1f},{y - r:.1f} {x + 0.87 * r:.1f},{y + 0.5 * r:.1f} {x - 0.87 * r:.1f},{y + 0.5 * r:.1f}"
        return (f'<polygon points="{pts}" fill="none" stroke="#fff" stroke-width="4.2"/>'
                f'<polygon points="{pts}" fill="none" stroke="{_DETECT}" stroke-width="2" '
                f'stroke-dasharray="4 2"/>')
    fill = f'fill="{_CAND}" fill-opacity="0.3"' if filled else 'fill="none"'
    return (f'<circle cx="{x:.1f}" cy="{y:.1f}" r="12" fill="none" stroke="#000" stroke-width="4.2" '
            f'stroke-opacity="0.7"/>'
            f'<circle cx="{x:.1f}" cy="{y:.1f}" r="12" {fill} stroke="{_CAND}" stroke-width="2"/>')


def _label(text: str, x: float, y: float, side: str, dy: float, colour: str,
           left: float, right: float, top: float, bottom: float) -> str:
    """A marker label beside (x, y) on ``side`` ("right" or "left"), moved inside the plot edges."""
    width = 7.0 * len(text)
    if side == "right" and x + 11 + width > right:
        side = "left"
    elif side == "left" and x - 11 - width < left:
        side = "right"
    anchor, tx = ("start", x + 11) if side == "right" else ("end", x - 11)
    ty = y + dy
    if ty < top + 12:
        ty = y + abs(dy) + 8
    elif ty > bottom - 3:
        ty = y - abs(dy)
    return (f'<text x="{tx:.1f}" y="{ty:.1f}" text-anchor="{anchor}" font-size="11.5" '
            f'font-weight="bold" fill="{colour}" stroke="#fff" stroke-width="3.2" stroke-linejoin="round" '
            f'paint-order="stroke">{_e(text)}</text>')


def map_figure(
    grid: npt.ArrayLike,
    *,
    cell: float,
    x0: float,
    y0: float,
    title: str,
    track: Iterable[Sequence[float]] | npt.NDArray[Any] = (),
    targets: Sequence[Mapping[str, Any]] = (),
    decoys: Sequence[Mapping[str, Any]] = (),
    candidates: Sequence[Mapping[str, Any]] = (),
    detections: Sequence[Mapping[str, Any]] = (),
    width: int = 640,
) -> str:
    """A north-up map of an elevation grid as an inline ``<svg>``.

    ``grid`` holds elevations in metres (z up, NaN = no data); row 0 is the south edge
    (``y0 .. y0 + cell``), column 0 the west edge. The figure has axes in metres, a colour bar of
    depth, a subtle hillshade, hatched gaps, a north arrow, a scale bar and a legend; ``track`` is
    a sequence of (x, y) vehicle positions, ``targets`` and ``decoys`` dicts with ``x``, ``y``,
    ``label``, ``candidates`` the same plus ``visited``, ``detections`` (the vehicle's
    suggestions) the same. Anything outside the grid is clipped.
    """
    z = np.asarray(grid, np.float64)
    if z.ndim != 2 or z.size == 0:
        return f"<p><em>{_e(title)}: no data</em></p>"
    ok = np.isfinite(z)
    if not ok.any():
        return f"<p><em>{_e(title)}: no data</em></p>"
    cell, x0, y0 = float(cell), float(x0), float(y0)
    ny, nx = int(z.shape[0]), int(z.shape[1])
    ext_w, ext_h = nx * cell, ny * cell
    x1, y1 = x0 + ext_w, y0 + ext_h

    # --- colour scale: the data range rounded out to tick values; only when a few outliers would
    # squash it, a robust range, with the clipped ends shown as triangles on the colour bar
    vals = z[ok]
    zmin, zmax = float(vals.min()), float(vals.max())
    lo, hi = (float(v) for v in np.percentile(vals, [0.2, 99.8]))
    if hi - lo >= 0.8 * (zmax - zmin):
        lo, hi = zmin, zmax
    if hi - lo < 0.05:
        mid = 0.5 * (hi + lo)
        lo, hi = mid - 0.5, mid + 0.5
    cticks = _ticks(lo, hi, 6)
    cstep = cticks[1] - cticks[0] if len(cticks) > 1 else hi - lo
    lo, hi = math.floor(lo / cstep + 1e-9) * cstep, math.ceil(hi / cstep - 1e-9) * cstep
    below, above = zmin < lo - 1e-9, zmax > hi + 1e-9

    # --- raster: colour x hillshade, transparent gaps, flipped north up, nearest-neighbour upscaled
    t = np.clip((np.where(ok, z, lo) - lo) / (hi - lo), 0.0, 1.0)
    rgb = _colourise(t) * _shade(z, cell)[..., None]
    rgba = np.concatenate([rgb, np.where(ok, 255.0, 0.0)[..., None]], axis=-1)
    rgba = np.flipud(np.clip(np.rint(rgba), 0, 255).astype(np.uint8))
    k = max(1, min(16, math.ceil(width / max(nx, ny))))
    if k > 1:
        rgba = np.repeat(np.repeat(rgba, k, axis=0), k, axis=1)
    href = _png_uri(np.ascontiguousarray(rgba))

    # --- layout (pixels)
    scale = width / ext_w  # px per metre
    if ext_h * scale > 1.25 * width:
        scale = 1.25 * width / ext_h
    pw, ph = ext_w * scale, ext_h * scale
    yt = _ticks(y0, y1)
    ml = int(28 + 7 * max(len(_tick_label(v)) for v in yt)) + 14
    mt, mb = 52, 50
    col = ml + pw + 28  # right-hand column: colour bar, legend, north arrow, scale bar
    subtitle = _map_subtitle(z, ok, cell, int((~ok).sum()))
    svg_w = int(max(col + 190, ml + 8.0 * len(title) + 10, ml + 6.0 * len(subtitle) + 10))

    def px(x: float) -> float:
        return ml + (x - x0) * scale

    def py(y: float) -> float:
        return mt + (y1 - y) * scale

    uid = f"coexmap{next(_ids)}"
    n_gap = int((~ok).sum())
    parts: list[str] = [
        f'<defs><pattern id="{uid}-gap" width="8" height="8" patternUnits="userSpaceOnUse" '
        f'patternTransform="rotate(45)"><rect width="8" height="8" fill="#f4f4f4"/>'
        f'<line x1="0" y1="0" x2="0" y2="8" stroke="#c4c4c4" stroke-width="3"/></pattern>'
        f'<clipPath id="{uid}-clip"><rect x="{ml}" y="{mt}" width="{pw:.2f}" height="{ph:.2f}"/></clipPath>'
        f'<linearGradient id="{uid}-cbar" x1="0" y1="1" x2="0" y2="0">'
        + "".join(f'<stop offset="{s:.4f}" stop-color="rgb({int(c[0])},{int(c[1])},{int(c[2])})"/>'
                  for s, c in zip(_CMAP_STOPS, _CMAP_RGB))
        + "</linearGradient></defs>",
        f'<text x="{ml}" y="18" font-size="14" font-weight="bold">{_e(title)}</text>',
        f'<text x="{ml}" y="35" font-size="11" fill="#555">{_e(subtitle)}</text>',
        f'<rect x="{ml}" y="{mt}" width="{pw:.2f}" height="{ph:.2f}" fill="url(#{uid}-gap)"/>',
        f'<image x="{ml}" y="{mt}" width="{pw:.2f}" height="{ph:.2f}" preserveAspectRatio="none" '
        f'style="image-rendering:pixelated" href="{href}"/>',
    ]

    # --- axes: ticks and labels in metres
    for v in _ticks(x0, x1):
        p = px(v)
        parts.append(f'<line x1="{p:.1f}" y1="{mt + ph:.1f}" x2="{p:.1f}" y2="{mt + ph + 5:.1f}" stroke="#444"/>'
                     f'<text x="{p:.1f}" y="{mt + ph + 18:.1f}" text-anchor="middle" font-size="11.5">'
                     f'{_tick_label(v)}</text>')
    for v in yt:
        p = py(v)
        parts.append(f'<line x1="{ml - 5}" y1="{p:.1f}" x2="{ml}" y2="{p:.1f}" stroke="#444"/>'
                     f'<text x="{ml - 8}" y="{p + 4:.1f}" text-anchor="end" font-size="11.5">'
                     f'{_tick_label(v)}</text>')
    parts.append(f'<rect x="{ml}" y="{mt}" width="{pw:.2f}" height="{ph:.2f}" fill="none" stroke="#444"/>')
    parts.append(f'<text x="{ml + pw / 2:.1f}" y="{mt + ph + 40:.1f}" text-anchor="middle" font-size="12.5">'
                 f'x east (m)</text>')
    cy = mt + ph / 2
    parts.append(f'<text x="16" y="{cy:.1f}" transform="rotate(-90 16 {cy:.1f})" text-anchor="middle" '
                 f'font-size="12.5">y north (m)</text>')

    # --- overlays, clipped to the map
    def inside(x: float | None, y: float | None) -> bool:
        return x is not None and y is not None and x0 <= x <= x1 and y0 <= y <= y1

    over: list[str] = []
    labels: list[str] = []
    has_track = False
    tr = np.asarray(track if isinstance(track, np.ndarray) else list(track), np.float64)
    if tr.ndim == 2 and tr.shape[0] > 1 and tr.shape[1] >= 2:
        tr = tr[:, :2]
        if tr.shape[0] > 6000:  # keep the page light: thin a very long track
            idx = np.unique(np.r_[np.arange(0, tr.shape[0], math.ceil(tr.shape[0] / 6000)), tr.shape[0] - 1])
            tr = tr[idx]
        good: npt.NDArray[np.bool_] = np.asarray(np.isfinite(tr).all(axis=1))
        # split at missing positions, draw each run
        runs = np.split(np.arange(tr.shape[0]), np.flatnonzero(np.diff(good.astype(np.int8)) != 0) + 1)
        pts_px = np.column_stack([ml + (tr[:, 0] - x0) * scale, mt + (y1 - tr[:, 1]) * scale])
        for r in runs:
            if len(r) < 2 or not bool(good[int(r[0])]):
                continue
            pts = " ".join(f"{a:.1f},{b:.1f}" for a, b in pts_px[r])
            over.append(f'<polyline points="{pts}" fill="none" stroke="#fff" stroke-width="2.6" '
                        f'stroke-opacity="0.55" stroke-linejoin="round"/>'
                        f'<polyline points="{pts}" fill="none" stroke="{_TRACK}" stroke-width="1" '
                        f'stroke-linejoin="round"/>')
            has_track = True
    kinds_present: list[str] = []
    visited_present: set[bool] = set()
    # candidates underneath (the largest rings), true targets on top
    for kind, items, colour, side, dy in (("detection", detections, "#8a008a", "left", -14.0),
                                          ("candidate", candidates, "#005f73", "left", 21.0),
                                          ("decoy", decoys, "#a34f00", "right", 17.0),
                                          ("target", targets, "#b30000", "right", -10.0)):
        for it in items:
            x, y = _f(it.get("x")), _f(it.get("y"))
            if not inside(x, y):
                continue
            assert x is not None and y is not None
            visited = bool(it.get("visited", False))
            over.append(_marker(kind, px(x), py(y), filled=visited))
            if kind not in kinds_present:
                kinds_present.append(kind)
            if kind == "candidate":
                visited_present.add(visited)
            labels.append(_label(str(it.get("label", "")), px(x), py(y), side, dy, colour,
                                 ml, ml + pw, mt, mt + ph))
    parts.append(f'<g clip-path="url(#{uid}-clip)">{"".join(over)}</g>')
    parts.append("".join(labels))

    # --- colour bar of depth (positive down), shallow at the top
    cb_x, cb_top = col, mt + 22
    cb_h = min(max(ph * 0.45, 120.0), 260.0)
    parts.append(f'<text x="{cb_x - 2}" y="{mt + 6}" font-size="12" font-weight="bold">depth (m)</text>')
    parts.append(f'<rect x="{cb_x}" y="{cb_top:.1f}" width="16" height="{cb_h:.1f}" fill="url(#{uid}-cbar)" '
                 f'stroke="#444" stroke-width="0.8"/>')
    c_top = _CMAP_RGB[-1]
    c_bot = _CMAP_RGB[0]
    if above:
        parts.append(f'<polygon points="{cb_x},{cb_top - 1:.1f} {cb_x + 16},{cb_top - 1:.1f} {cb_x + 8},{cb_top - 12:.1f}" '
                     f'fill="rgb({int(c_top[0])},{int(c_top[1])},{int(c_top[2])})" stroke="#444" '
                     f'stroke-width="0.8"><title>shallower than {-hi:.2f} m</title></polygon>')
    if below:
        yb = cb_top + cb_h
        parts.append(f'<polygon points="{cb_x},{yb + 1:.1f} {cb_x + 16},{yb + 1:.1f} {cb_x + 8},{yb + 12:.1f}" '
                     f'fill="rgb({int(c_bot[0])},{int(c_bot[1])},{int(c_bot[2])})" stroke="#444" '
                     f'stroke-width="0.8"><title>deeper than {-lo:.2f} m</title></polygon>')
    for d in _ticks(-hi, -lo, 6):
        yy = cb_top + (d + hi) / (hi - lo) * cb_h  # depth d = -z: shallow (z = hi) at the top
        parts.append(f'<line x1="{cb_x + 16}" y1="{yy:.1f}" x2="{cb_x + 21}" y2="{yy:.1f}" stroke="#444"/>'
                     f'<text x="{cb_x + 24}" y="{yy + 4:.1f}" font-size="11.5">{_tick_label(d)}</text>')
    range_note = f"data: {-zmax:.1f} to {-zmin:.1f} m deep"
    parts.append(f'<text x="{cb_x - 2}" y="{cb_top + cb_h + 28:.1f}" font-size="10" fill="#555">{_e(range_note)}</text>')

    # --- legend
    ly = cb_top + cb_h + 52
    entries: list[tuple[str, str]] = []
    if has_track:
        entries.append(("track", "vehicle track"))
    names = {"target": "true target", "decoy": "decoy", "candidate": "flagged candidate",
             "detection": "vehicle's detection"}
    for kind in ("target", "decoy", "candidate", "detection"):
        if kind not in kinds_present:
            continue
        if kind == "candidate":
            if False in visited_present:
                entries.append(("candidate", "flagged candidate"))
            if True in visited_present:
                entries.append(("candidate-visited", "candidate, imaged"))
        else:
            entries.append((kind, names[kind]))
    if n_gap:
        entries.append(("nodata", "no data"))
    for i, (kind, text) in enumerate(entries):
        yy = ly + 28 * i
        if kind == "nodata":
            parts.append(f'<rect x="{col}" y="{yy - 8:.1f}" width="18" height="16" fill="url(#{uid}-gap)" '
                         f'stroke="#999" stroke-width="0.8"/>')
        elif kind == "candidate-visited":
            parts.append(_marker("candidate", col + 9, yy, filled=True))
        else:
            parts.append(_marker(kind, col + 9, yy))
        parts.append(f'<text x="{col + 28}" y="{yy + 4:.1f}" font-size="11.5">{_e(text)}</text>')
    ly += 28 * len(entries) + 6

    # --- north arrow and scale bar
    ax = col + 12
    parts.append(f'<text x="{ax}" y="{ly + 12:.1f}" text-anchor="middle" font-size="13" font-weight="bold">N</text>'
                 f'<polygon points="{ax},{ly + 16:.1f} {ax + 7},{ly + 42:.1f} {ax},{ly + 36:.1f} {ax - 7},{ly + 42:.1f}" '
                 f'fill="#222"/>')
    sb_len = _nice_length(max(ext_w, ext_h))
    sb_px = sb_len * scale
    if sb_px > 170:
        sb_len = _nice_length(170 / scale * 5 / 1.2)
        sb_px = sb_len * scale
    sy0 = ly + 62
    half = sb_px / 2
    parts.append(f'<rect x="{col}" y="{sy0:.1f}" width="{half:.1f}" height="6" fill="#222" stroke="#222"/>'
                 f'<rect x="{col + half:.1f}" y="{sy0:.1f}" width="{half:.1f}" height="6" fill="#fff" stroke="#222"/>'
                 f'<text x="{col}" y="{sy0 + 19:.1f}" text-anchor="middle" font-size="11">0</text>'
                 f'<text x="{col + sb_px:.1f}" y="{sy0 + 19:.1f}" text-anchor="middle" font-size="11">'
                 f'{_tick_label(sb_len)} m</text>')
    bottom = max(mt + ph + mb, sy0 + 30)
    svg_h = math.ceil(bottom)
    return (f'<svg {_SVG_HEAD} width="{svg_w}" height="{svg_h}" viewBox="0 0 {svg_w} {svg_h}" '
            f'font-size="11" style="max-width:100%;height:auto" role="img" aria-label="{_e(title)}">'
            + "".join(parts) + "</svg>")


def _map_subtitle(z: npt.NDArray[np.float64], ok: npt.NDArray[np.bool_], cell: float, n_gap: int) -> str:
    """Grid size, cell size and how much of it holds data."""
    ny, nx = z.shape
    frac = 100.0 * ok.sum() / z.size
    cell_s = f"{cell:g} m"
    return (f"{nx} \u00d7 {ny} cells of {cell_s} ({nx * cell:g} m \u00d7 {ny * cell:g} m), "
            f"{frac:.1f}% with data" + ("" if n_gap else ", no gaps") + "; north up")


# ------------------------------------------------------------------------------ page sections


def _verdict(ok: Any) -> str:
    """MET / NOT MET, coloured; n/a when unknown."""
    if ok is None:
        return '<span class="na">n/a</span>'
    return '<span class="met">MET</span>' if ok else '<span class="notmet">NOT MET</span>'


def _scenario_line(sc: Any) -> str:
    """One line describing the scenario, tolerant of missing keys."""
    if not isinstance(sc, Mapping):
        return ""
    bits = []
    if sc.get("name") is not None:
        bits.append(f"scenario \u201c{sc['name']}\u201d")
    area = _f(sc.get("area"))
    if area is not None:
        bits.append(f"survey area {area:g} m \u00d7 {area:g} m")
    depth = _f(sc.get("water_depth"))
    if depth is not None:
        bits.append(f"water depth {depth:g} m")
    loss = sc.get("loss")
    if sc.get("loss_description"):
        bits.append(f"link: {sc['loss_description']}")
        if sc.get("modem_rate") is not None:
            bits.append(f"Micromodem rate {sc['modem_rate']}")
    elif isinstance(loss, Mapping):
        model = loss.get("model", "?")
        extra = ", ".join(f"{k} {v}" for k, v in loss.items() if k != "model" and not isinstance(v, Mapping | list))
        bits.append(f"link loss: {model}" + (f" ({extra})" if extra else ""))
    elif loss is not None:
        bits.append(f"link loss: {loss}")
    return " \u00b7 ".join(bits)


def _goals_table(goals: Any) -> str:
    """The goals with MET / NOT MET and the detail behind each."""
    if not isinstance(goals, Mapping) or not goals:
        return "<p><em>No goals were recorded.</em></p>"
    rows = "".join(
        f"<tr><td>{_e(name)}</td><td class='c'>{_verdict(g.get('met') if isinstance(g, Mapping) else None)}</td>"
        f"<td>{_e(g.get('detail', '') if isinstance(g, Mapping) else g)}</td></tr>"
        for name, g in goals.items())
    return f"<table><tr><th>goal</th><th>result</th><th>detail</th></tr>{rows}</table>"


def _targets_table(targets: Any) -> str:
    """One row per true target: when it became identifiable and when an image confirmed it."""
    if not isinstance(targets, Sequence) or not targets:
        return "<p><em>No targets in this scenario.</em></p>"
    rows = []
    for i, t in enumerate(targets):
        if not isinstance(t, Mapping):
            continue
        name = t.get("name", f"target {i + 1}")
        seen = t.get("identifiable_at_1m_s")
        seen_s = _num(seen) if _f(seen) is not None else '<span class="bad">never</span>'
        c = t.get("confirmation")
        if isinstance(c, Mapping):
            conf = (f"<td class='r'>{_num(c.get('image_id'))}</td><td class='r'>{_num(c.get('confirmed_at_s'))}</td>"
                    f"<td class='r'>{_num(c.get('bytes'), ',.0f')}</td><td class='r'>{_num(c.get('tdma_cycles'), '.2f')}</td>")
        else:
            conf = "<td colspan='4' class='bad c'>never confirmed</td>"
        rows.append(f"<tr><td>{_e(name)}</td><td>{_pos(t.get('x'), t.get('y'))}</td>"
                    f"<td class='r'>{seen_s}</td>{conf}</tr>")
    return ("<table><tr><th>target</th><th>position (m)</th><th>identifiable at 1 m (s)</th>"
            "<th>confirming image (id)</th><th>confirmed at (s)</th><th>bytes</th>"
            "<th>TDMA cycles after request</th></tr>" + "".join(rows) + "</table>")


def _detections_table(items: Any, cost: Any, targets: Any) -> str:
    """The vehicle's detections as topside received them, judged against the truth, what they
    cost on the link, and per target the time from its first detection to its confirming image."""
    if not isinstance(items, Sequence) or not items:
        return "<p>Detections: <em>none received</em> (no detector on the vehicle, or nothing stood out).</p>"
    rows = []
    for d in items:
        if not isinstance(d, Mapping):
            continue
        truth = str(d.get("truth", "none"))
        cls = "ok" if truth.startswith("target") else ("bad" if truth == "none" else "")
        size = "" if d.get("length") is None else f"{_num(d.get('length'), '.1f')} x {_num(d.get('width'), '.1f')}"
        rows.append(f"<tr><td class='r'>{_num(d.get('id'))}</td><td>{_e(d.get('source'))}</td>"
                    f"<td>{_pos(d.get('x'), d.get('y'))}</td><td class='r'>{_num(d.get('score'), '.2f')}</td>"
                    f"<td class='r'>{_num(d.get('height'), '.1f')}</td><td class='r'>{size}</td>"
                    f"<td class='r'>{_num(d.get('orientation'))}</td><td class='r'>{_num(d.get('first_at_s'))}</td>"
                    f"<td class='{cls}'>{_e(truth)}</td></tr>")
    c = cost if isinstance(cost, Mapping) else {}
    words = (f"{_num(c.get('received'))} detections received: {_num(c.get('true'))} of a true target, "
             f"{_num(c.get('decoys'))} of a decoy, {_num(c.get('false'))} of nothing. They cost "
             f"{_num(c.get('bytes_sent'), ',.0f')} B of Detection messages sent by the vehicle "
             f"({_num(c.get('bytes_received'), ',.0f')} B received) and "
             f"{_num(c.get('neighbourhood_bytes_sent'), ',.0f')} B of 1 m subgrids sent around them.")
    per = []
    for t in targets if isinstance(targets, Sequence) else ():
        if not isinstance(t, Mapping):
            continue
        fd = t.get("first_detection")
        dc = t.get("detection_to_confirmation_s")
        per.append(f"{_e(t.get('name'))}: " + ("never detected" if not isinstance(fd, Mapping) else
                   f"first detected topside at {_num(fd.get('first_at_s'))} s"
                   + (f", confirmed {_num(dc)} s later" if _f(dc) is not None else ", not confirmed")))
    return (f'<p class="note">{words} {"; ".join(per)}.</p>'
            "<table><tr><th>id</th><th>found in</th><th>position (m)</th><th>score</th><th>height (m)</th>"
            "<th>length x width (m)</th><th>orientation (deg)</th><th>first received (s)</th>"
            "<th>what is really there</th></tr>" + "".join(rows) + "</table>")


def _false_table(items: Any) -> str:
    """Candidates confirmed by an image that showed something other than a target."""
    if not items:
        return '<p>False confirmations: <span class="ok">none</span>.</p>'
    rows = "".join(
        f"<tr><td>{_pos(f.get('x'), f.get('y'))}</td><td class='r'>{_num(f.get('image_id'))}</td>"
        f"<td class='r'>{_num(f.get('confirmed_at_s'))}</td><td>{_e(f.get('shows', '?'))}</td></tr>"
        for f in items if isinstance(f, Mapping))
    return (f'<p class="bad">False confirmations: {len(items)}</p><table class="false">'
            "<tr><th>candidate position (m)</th><th>image id</th><th>confirmed at (s)</th>"
            f"<th>what the image showed</th></tr>{rows}</table>")


def _surveys_table(items: Any) -> str:
    """Every survey command topside sent: what it asked, each state as topside heard it, and what
    the vehicle really did (the truth)."""
    if not items:
        return "<p><em>No survey command was sent: the vehicle was never retargeted.</em></p>"
    rows = []
    for s in items:
        if not isinstance(s, Mapping):
            continue
        a = s.get("asked") or {}
        c = s.get("candidate") or {}
        t = s.get("truth") or {}
        what = f"{a.get('kind', '?')} from {_pos(a.get('x'), a.get('y'))}"
        if a.get("length") is not None:
            what += f", {_num(a.get('length'))} m at {_num(a.get('heading'))}°"
        if c:
            what += f", over {_pos(c.get('x'), c.get('y'))}"
        state = str(s.get("final_state", "?")) + (f": {s.get('text')}" if s.get("text") else "")
        flown = ("not flown" if t.get("set_off_s") is None else
                 f"set off {_num(t.get('set_off_s'))} s, done {_num(t.get('completed_s'))} s"
                 + (f", stopped {_num(t.get('stopped_s'))} s" if t.get("stopped_s") is not None else ""))
        rows.append(f"<tr><td class='r'>{_num(s.get('id'))}</td><td>{_e(what)}</td>"
                    f"<td class='r'>{_num(s.get('sent_at_s'))}</td><td class='r'>{_num(s.get('accepted_at_s'))}</td>"
                    f"<td class='r'>{_num(s.get('started_at_s'))}</td><td class='r'>{_num(s.get('completed_at_s'))}</td>"
                    f"<td>{_e(state)}</td><td class='r'>{_num(t.get('received_by_vehicle_s'))}</td>"
                    f"<td>{_e(flown)}</td></tr>")
    return ('<h3>Survey commands</h3><p class="note">The camera pass as it crossed the acoustic link: each '
            "survey command topside sent, when the vehicle's answers reached topside (dive seconds; "
            "started and completed are the vehicle's stamps), and, from the simulation, when the command "
            'reached the vehicle and when the vehicle flew it.</p><table class="surveys"><tr><th>survey</th>'
            "<th>asked</th><th>sent (s)</th><th>accepted (s)</th><th>started (s)</th><th>completed (s)</th>"
            "<th>final state topside</th><th>reached the vehicle (s)</th><th>flown (truth)</th></tr>"
            + "".join(rows) + "</table>")


def _thumb_src(path: Path) -> tuple[str | None, bool]:
    """A data URI of a thumbnail of ``path`` (about 200 px wide) and whether it is upscaled."""
    try:
        from PIL import Image

        with Image.open(path) as im:
            im.load()
            w = im.width
            if w <= 400:
                data = path.read_bytes()
                if path.suffix.lower() != ".png":
                    buf = io.BytesIO()
                    im.convert("RGB").save(buf, format="PNG")
                    data = buf.getvalue()
                return "data:image/png;base64," + base64.b64encode(data).decode("ascii"), w < 200
            small = im.convert("RGB")
            small.thumbnail((200, 200 * im.height // max(w, 1) + 1))
            buf = io.BytesIO()
            small.save(buf, format="JPEG", quality=85)
            return "data:image/jpeg;base64," + base64.b64encode(buf.getvalue()).decode("ascii"), False
    except Exception:
        return None, False


def _gallery(out: Path, images: Sequence[Mapping[str, Any]]) -> str:
    """Thumbnails of received images: confirming and requested ones first, then by time."""
    if not images:
        return "<p><em>No images were received.</em></p>"

    def key(m: Mapping[str, Any]) -> tuple[int, float]:
        rank = 0 if m.get("confirms") else 1 if m.get("requested") else 2
        return rank, _f(m.get("time_s")) or 0.0

    ordered = sorted(images, key=key)
    shown, left = ordered[:GALLERY_CAP], len(ordered) - GALLERY_CAP
    n_conf = sum(1 for m in images if m.get("confirms"))
    n_req = sum(1 for m in images if m.get("requested"))
    cards = []
    for m in shown:
        file = str(m.get("file", ""))
        src, small = _thumb_src(out / file) if file else (None, False)
        cls = "card conf" if m.get("confirms") else "card req" if m.get("requested") else "card"
        pix = ' style="image-rendering:pixelated"' if small else ""
        img = (f'<a href="{_e(file)}"><img src="{src}" alt="image {_e(m.get("image_id", "?"))}"{pix}></a>'
               if src else '<div class="missing">image file missing</div>')
        caption = " \u00b7 ".join([
            f"image {m.get('image_id', '?')}",
            f"{_num(m.get('time_s'))} s",
            _pos(m.get("x"), m.get("y"), ".0f"),
            f"{_num(m.get('bytes'), ',.0f')} B",
            f"{_num(m.get('layers'))} layers",
        ])
        flags = ""
        if m.get("confirms"):
            flags += f'<div class="flag conf">confirms {_e(m["confirms"])}</div>'
        if m.get("requested"):
            flags += '<div class="flag req">requested</div>'
        cards.append(f'<figure class="{cls}">{img}<figcaption>{_e(caption)}{flags}</figcaption></figure>')
    head = (f"<p>{len(images)} image(s) received; {n_conf} confirm a target, {n_req} were requested by "
            "the operator. Confirming and requested images come first (green border: confirms a "
            "target). Positions are the vehicle's (x, y) in metres; bytes are those sent over the link.")
    if left > 0:
        head += f" Showing {GALLERY_CAP}; {left} more are not shown (all are in <code>images/</code>)."
    return head + f'</p><div class="gallery">{"".join(cards)}</div>'


def _regions_section(out: Path, regions: Sequence[Mapping[str, Any]]) -> str:
    """The image regions asked during the dive: what was asked, how the vehicle served it (a
    crop: the region coded on its own and pasted over the image; or the image's packets) and
    its bytes, with the image as shown topside (the region outlined) and the crop itself."""
    if not regions:
        return ('<h3 id="regions">Image regions</h3><p class="note">No image region was asked for: no '
                "image showed an object too blurry to tell.</p>")
    rows, cards = [], []
    for r in regions:
        goal = r.get("goal") or {}
        unit = {"quality": " dB", "layer": " layers", "bytes": " B"}.get(str(goal.get("kind")), "")
        x0, y0, x1, y1 = r["box"]
        crop = r.get("crop")
        how = "-"
        if r.get("served") == "crop" and crop:
            how = (f"crop {crop['width']} x {crop['height']} px (image {crop['image_id']}), "
                   f"{_num(crop['held_bytes'], ',.0f')} of {_num(crop['total_bytes'], ',.0f')} B"
                   + (", shown over the image" if crop.get("shown") else ", the image as good there by now"))
        elif r.get("served") == "packets":
            how = f"the image's packets, {_num(r.get('bytes'), ',.0f')} B"
        rows.append(
            f"<tr><td class='r'>{_num(r.get('asked_s'))}</td><td>{_e(r.get('by', ''))}</td>"
            f"<td class='r'>{_e(r['image_id'])}</td><td>x {x0}..{x1}, y {y0}..{y1} ({x1 - x0} x {y1 - y0} px)</td>"
            f"<td>{_e(goal.get('value'))}{unit}</td><td>{_e(r.get('state', ''))}</td><td>{_e(how)}</td>"
            f"<td class='r'>{_num(r.get('bytes'), ',.0f')}</td>"
            f"<td class='r'>{_num(r.get('layers_complete'))} of {_num(r.get('layers'))}</td>"
            f"<td class='r'>{_num(r.get('image_bytes'), ',.0f')}</td></tr>")
        for key, label in (("file", f"image {r['image_id']} as shown, region outlined"),
                           ("crop_file", "the crop")):
            file = r.get(key)
            src, small = _thumb_src(out / str(file)) if file else (None, False)
            if src:
                pix = ' style="image-rendering:pixelated"' if small else ""
                cards.append(f'<figure class="card"><a href="{_e(file)}"><img src="{src}" alt="{_e(label)}"{pix}></a>'
                             f"<figcaption>{_e(label)} (command {r['command_id']})</figcaption></figure>")
    return ('<h3 id="regions">Image regions</h3><p class="note">Regions of images the operator asked to see '
            "sharper (around an object too blurry to tell). The vehicle serves each the cheaper way it "
            "measures: a crop (the region coded on its own as the difference to what topside holds, "
            "pasted over the image) or the image's own packets. Bytes: the crop's body, or the region's "
            "packets, that arrived; the image's bytes are all it holds. Asked at dive seconds.</p>"
            '<table class="regions"><tr><th>asked (s)</th><th>by</th><th>image</th><th>region</th>'
            "<th>goal</th><th>answer</th><th>served as</th><th>bytes</th><th>layers inside</th>"
            "<th>image bytes</th></tr>" + "".join(rows) + "</table>"
            + (f'<div class="gallery">{"".join(cards)}</div>' if cards else ""))


def _decisions_table(decisions: Sequence[Mapping[str, Any]]) -> str:
    """Every decision in time order; rows by a person highlighted."""
    if not decisions:
        return "<p><em>No decisions were recorded.</em></p>"
    rows = []
    for d in sorted(decisions, key=lambda d: _f(d.get("t")) or 0.0):
        who = str(d.get("who", ""))
        cls = f' class="who-{_e(who)}"' if who in ("person", "script", "system") else ""
        rows.append(f"<tr{cls}><td class='r'>{_num(d.get('t'))}</td><td>{_e(who)}</td>"
                    f"<td>{_e(d.get('kind', ''))}</td><td>{_e(d.get('text', ''))}</td></tr>")
    n_person = sum(1 for d in decisions if d.get("who") == "person")
    note = (f"<p>{len(decisions)} decision(s); {n_person} taken by a person (highlighted), the rest by the "
            "operator script or the system.</p>")
    return (note + '<div class="scroll"><table class="decisions"><tr><th>time (s)</th><th>who</th>'
            "<th>kind</th><th>what</th></tr>" + "".join(rows) + "</table></div>")


_CSS = """
body{font-family:Helvetica,Arial,sans-serif;max-width:1100px;margin:1.5em auto;padding:0 1em;
 color:#222;line-height:1.45;font-size:15px}
h1{font-size:1.6em;margin-bottom:.2em}h2{border-bottom:2px solid #ddd;padding-bottom:.15em;margin-top:1.8em}
.sub{color:#555;margin-top:0}.nav{font-size:.9em;color:#666}.nav a{color:#2a6ebb;margin-right:.8em}
table{border-collapse:collapse;margin:.6em 0}td,th{border:1px solid #ccc;padding:4px 9px;vertical-align:top}
th{background:#f2f2f2;text-align:left;font-weight:600}td.r{text-align:right;font-variant-numeric:tabular-nums}
td.c{text-align:center}.met{color:#fff;background:#2e8b3a;padding:1px 6px;border-radius:3px;font-weight:bold}
.notmet{color:#fff;background:#c62828;padding:1px 6px;border-radius:3px;font-weight:bold;white-space:nowrap}.na{color:#888}
.bad{color:#c62828;font-weight:bold}.ok{color:#2e8b3a;font-weight:bold}table.false th{background:#fde8e8}
.summary{font-size:1.05em;background:#f7f9fc;border-left:4px solid #2a6ebb;padding:.6em 1em}
.gallery{display:flex;flex-wrap:wrap;gap:10px}.card{margin:0;width:204px;border:1px solid #ccc;padding:3px;
 background:#fafafa}.card img{width:200px;display:block}.card.conf{border:4px solid #2e8b3a;padding:1px}
.card.req{border:2px solid #2a6ebb;padding:2px}.card.conf.req{border:4px solid #2e8b3a}
figcaption{font-size:11.5px;color:#333;margin-top:3px}.flag{font-weight:bold;font-size:12px}
.flag.conf{color:#2e8b3a}.flag.req{color:#2a6ebb}.missing{width:200px;height:120px;background:#eee;color:#888;
 display:flex;align-items:center;justify-content:center;font-size:12px}
.scroll{max-height:640px;overflow:auto;border:1px solid #eee}table.decisions{margin:0;width:100%}
tr.who-person td{background:#fff3c4;font-weight:600}tr.who-system td{color:#666}
.fig{margin:1em 0}pre{background:#f6f6f6;padding:8px;overflow:auto;font-size:12px}
details summary{cursor:pointer;font-weight:600}.note{color:#555;font-size:.92em}
"""


def _link_note(metrics: dict[str, Any]) -> str:
    """One paragraph on how the vehicle used its link: fill, spare and redundant bytes, request
    to first answer, the map ten minutes after the survey."""
    link = metrics.get("link") or {}
    parts = []
    if _f(link.get("fill")) is not None:
        parts.append(f"vehicle link use {float(link['fill']):.0%} of the packets it sent")
    if _f(link.get("fill_with_work")) is not None:
        parts.append(f"{float(link['fill_with_work']):.0%} while work was ready")
    if _f(link.get("spare_bytes")) is not None:
        parts.append(f"{int(link['spare_bytes']):,} B of spare work (re-sends, provisional subgrids, further "
                     f"image layers, refinements) and {int(link.get('redundant_bytes') or 0):,} B of redundant "
                     "copies of acks, commands and first answers")
    if _f(link.get("frame_loss")) is not None:
        parts.append(f"frame loss {float(link['frame_loss']):.0%}")
    resp = metrics.get("responses") or {}
    if resp.get("requests"):
        med = resp.get("median_vehicle_slots")
        parts.append(f"{resp['requests']} requests, first answer "
                     + ("never, in the median" if med is None else f"after {med:g} vehicle slot(s) in the median")
                     + f" ({float(resp.get('at_next_vehicle_slot') or 0):.0%} at the next vehicle slot)")
    cov = metrics.get("map_coverage_after_survey") or {}
    if cov:
        parts.append("map ten minutes after the survey: " + ", ".join(
            f"level {k} {float(v):.1%}" for k, v in sorted(cov.items(), key=lambda kv: int(kv[0]))))
    return f'<p class="note">Link: {_e("; ".join(parts))}.</p>' if parts else ""


def write_report(
    out: Path,
    metrics: Mapping[str, Any],
    *,
    charts: Sequence[str],
    maps: Sequence[str],
    images: Sequence[Mapping[str, Any]],
    decisions: Sequence[Mapping[str, Any]],
    regions: Sequence[Mapping[str, Any]] = (),
) -> Path:
    """Write ``out/report.html`` (one self-contained file) and return its path.

    ``charts`` and ``maps`` are SVG/HTML fragments (from :func:`line_chart`, :func:`timeline_chart`,
    :func:`map_figure`), ``images`` one dict per received image (``file`` relative to ``out``),
    ``decisions`` dicts with ``t``, ``kind``, ``text`` and ``who``, ``regions`` the image
    regions asked (see ``outcome._regions``).
    """
    out = Path(out)
    sc_line = _scenario_line(metrics.get("scenario"))
    summary = metrics.get("summary")
    summary_html = f'<p class="summary">{_e(summary)}</p>' if summary else ""
    facts = []
    for key, label, unit in (("dive_seconds", "dive length", " s"), ("survey_end_s", "survey ended at", " s"),
                             ("images_received", "images received", ""),
                             ("images_captured", "images taken", "")):
        if _f(metrics.get(key)) is not None:
            facts.append(f"{label} {_num(metrics.get(key), ',.0f')}{unit}")
    facts_html = f'<p class="note">{_e(" · ".join(facts))}</p>' if facts else ""
    link_html = _link_note(metrics)
    maps_html = "".join(f'<div class="fig">{m}</div>' for m in maps) or "<p><em>No map was received.</em></p>"
    charts_html = "".join(f'<div class="fig">{c}</div>' for c in charts) or "<p><em>No charts.</em></p>"
    doc = f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><meta name="viewport" content="width=device-width,initial-scale=1">
<title>CoEx demo report</title><style>{_CSS}</style></head><body>
<h1>CoEx demo: nested survey over a simulated acoustic link</h1>
<p class="sub">{_e(sc_line)}</p>
<p class="nav"><a href="#outcome">Outcome</a><a href="#map">Map</a><a href="#images">Images</a>
<a href="#time">The dive over time</a><a href="#decisions">Decisions</a><a href="#raw">Raw metrics</a></p>
<h2 id="outcome">Outcome</h2>
{summary_html}{facts_html}
<h3>Goals</h3>
{_goals_table(metrics.get("goals"))}
<h3>Targets</h3>
<p class="note">Identifiable at 1 m: when the 1 m map held topside first showed the target. Confirmed at:
when a received image showing it was accepted; TDMA cycles are counted from the image request.</p>
{_targets_table(metrics.get("targets"))}
{_false_table(metrics.get("false_confirmations"))}
<h3>Detections</h3>
<p class="note">What the vehicle's own detectors found in its full-resolution data and sent as
suggestions (the operator decides), judged here against the truth.</p>
{_detections_table(metrics.get("detections"), metrics.get("detection_cost"), metrics.get("targets"))}
<h2 id="map">Map</h2>
<p class="note">The bathymetry as received topside, finest level first. Colour is depth (with light
hillshading from the north-west); hatched grey areas hold no data. Red squares are the true targets,
orange diamonds decoys, cyan circles the candidates the operator flagged in the received map
(filled once imaged), dashed magenta triangles the vehicle's detections.</p>
{maps_html}
<h2 id="images">Images</h2>
{_gallery(out, images)}
{_regions_section(out, regions)}
<h2 id="time">The dive over time</h2>
{link_html}
{charts_html}
{_surveys_table(metrics.get("surveys"))}
<h2 id="decisions">Decisions</h2>
{_decisions_table(decisions)}
<h2 id="raw">Raw metrics</h2>
<details><summary>Raw metrics (metrics.json)</summary><pre>{_e(json.dumps(metrics, indent=2, default=str))}</pre></details>
</body></html>
"""
    path = out / "report.html"
    path.write_text(doc, encoding="utf-8")
    return path
