"""``report.html`` of a demo run: goal verdicts, plots (inline SVG, no plotting dependency) and the
products (map levels, received images, time series) linked from the output directory."""

from __future__ import annotations

import html
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

__all__ = ["line_chart", "timeline_chart", "write_report"]

PALETTE = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#17becf"]


def _ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    if hi <= lo:
        return [lo]
    span = hi - lo
    raw = span / n
    mag = 10 ** __import__("math").floor(__import__("math").log10(raw))
    step = min((m * mag for m in (1, 2, 5, 10) if m * mag >= raw), default=raw)
    start = (lo // step) * step
    out = []
    t = start
    while t <= hi + 1e-9:
        if t >= lo - 1e-9:
            out.append(round(t, 10))
        t += step
    return out


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
    """An SVG line chart of named (x, y) series, with optional vertical markers (x, label)."""
    pts = [p for s in series.values() for p in s]
    if not pts:
        return f"<p><em>{html.escape(title)}: no data</em></p>"
    xs = [p[0] for p in pts] + [m[0] for m in markers]
    ys = [p[1] for p in pts]
    x0, x1 = min(xs), max(xs)
    y0, y1 = min(0.0, min(ys)), max(ys)
    if x1 == x0:
        x1 = x0 + 1
    if y1 == y0:
        y1 = y0 + 1
    ml, mr, mt, mb = 60, 130, 30, 45
    pw, ph = width - ml - mr, height - mt - mb

    def sx(x: float) -> float:
        return ml + (x - x0) / (x1 - x0) * pw

    def sy(y: float) -> float:
        return mt + ph - (y - y0) / (y1 - y0) * ph

    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
           f'font-family="sans-serif" font-size="11">',
           f'<text x="{ml}" y="18" font-size="13" font-weight="bold">{html.escape(title)}</text>',
           f'<rect x="{ml}" y="{mt}" width="{pw}" height="{ph}" fill="none" stroke="#999"/>']
    for t in _ticks(x0, x1):
        out.append(f'<line x1="{sx(t):.1f}" y1="{mt + ph}" x2="{sx(t):.1f}" y2="{mt + ph + 4}" stroke="#999"/>'
                   f'<text x="{sx(t):.1f}" y="{mt + ph + 16}" text-anchor="middle">{t:g}</text>')
    for t in _ticks(y0, y1):
        out.append(f'<line x1="{ml - 4}" y1="{sy(t):.1f}" x2="{ml + pw}" y2="{sy(t):.1f}" stroke="#eee"/>'
                   f'<text x="{ml - 6}" y="{sy(t) + 4:.1f}" text-anchor="end">{t:g}</text>')
    out.append(f'<text x="{ml + pw / 2}" y="{height - 8}" text-anchor="middle">{html.escape(xlabel)}</text>')
    out.append(f'<text x="14" y="{mt + ph / 2}" transform="rotate(-90 14 {mt + ph / 2})" '
               f'text-anchor="middle">{html.escape(ylabel)}</text>')
    for i, (name, s) in enumerate(series.items()):
        colour = PALETTE[i % len(PALETTE)]
        if not s:
            continue
        coords = []
        prev_y = None
        for x, y in s:
            if step and prev_y is not None:
                coords.append(f"{sx(x):.1f},{sy(prev_y):.1f}")
            coords.append(f"{sx(x):.1f},{sy(y):.1f}")
            prev_y = y
        out.append(f'<polyline fill="none" stroke="{colour}" stroke-width="1.6" points="{" ".join(coords)}"/>')
        out.append(f'<rect x="{ml + pw + 10}" y="{mt + 14 * i}" width="10" height="10" fill="{colour}"/>'
                   f'<text x="{ml + pw + 24}" y="{mt + 9 + 14 * i}">{html.escape(name)}</text>')
    for x, label in markers:
        out.append(f'<line x1="{sx(x):.1f}" y1="{mt}" x2="{sx(x):.1f}" y2="{mt + ph}" stroke="#444" '
                   f'stroke-dasharray="3,3"/><title>{html.escape(label)}</title>')
    out.append("</svg>")
    return "".join(out)


def timeline_chart(events: Sequence[Mapping[str, Any]], *, t_end: float, width: int = 720) -> str:
    """A decision timeline: one row per event kind, a dot per event, labelled."""
    if not events:
        return "<p><em>no decisions</em></p>"
    kinds = list(dict.fromkeys(str(e["kind"]) for e in events))
    ml, mr, row = 170, 20, 26
    height = 40 + row * len(kinds)
    pw = width - ml - mr

    def sx(t: float) -> float:
        return ml + t / max(t_end, 1.0) * pw

    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
           f'font-family="sans-serif" font-size="11">']
    for i, k in enumerate(kinds):
        y = 20 + row * i
        out.append(f'<text x="{ml - 8}" y="{y + 4}" text-anchor="end">{html.escape(k)}</text>'
                   f'<line x1="{ml}" y1="{y}" x2="{ml + pw}" y2="{y}" stroke="#ddd"/>')
    for e in events:
        i = kinds.index(str(e["kind"]))
        colour = PALETTE[i % len(PALETTE)]
        out.append(f'<circle cx="{sx(float(e["t"])):.1f}" cy="{20 + row * i}" r="5" fill="{colour}">'
                   f'<title>{float(e["t"]):.0f} s: {html.escape(str(e.get("text", "")))}</title></circle>')
    for t in _ticks(0, t_end):
        out.append(f'<text x="{sx(t):.1f}" y="{height - 6}" text-anchor="middle">{t:g}</text>')
    out.append("</svg>")
    return "".join(out)


def _verdict(ok: bool | None) -> str:
    if ok is None:
        return '<span style="color:#888">n/a</span>'
    return '<b style="color:#2a2">MET</b>' if ok else '<b style="color:#c22">NOT MET</b>'


def write_report(out: Path, metrics: Mapping[str, Any], charts: Sequence[str],
                 events: Sequence[Mapping[str, Any]], files: Mapping[str, Sequence[str]]) -> Path:
    """Write ``out/report.html``; ``files`` maps a section name to paths relative to ``out``."""
    goals = metrics.get("goals", {})
    rows = "".join(
        f"<tr><td>{html.escape(name)}</td><td>{_verdict(g.get('met'))}</td>"
        f"<td>{html.escape(str(g.get('detail', '')))}</td></tr>"
        for name, g in goals.items()
    )
    gallery = []
    for section, paths in files.items():
        items = "".join(
            f'<figure style="display:inline-block;margin:4px"><a href="{html.escape(p)}">'
            f'<img src="{html.escape(p)}" style="max-width:220px;max-height:180px"></a>'
            f'<figcaption style="font-size:11px">{html.escape(Path(p).name)}</figcaption></figure>'
            if p.endswith(".png") else f'<li><a href="{html.escape(p)}">{html.escape(p)}</a></li>'
            for p in paths
        )
        gallery.append(f"<h3>{html.escape(section)}</h3><div>{items}</div>")
    log = "".join(f"<li>{float(e['t']):7.0f} s &mdash; {html.escape(str(e.get('text', '')))}</li>" for e in events)
    doc = f"""<!doctype html>
<html><head><meta charset="utf-8"><title>CoEx demo report</title>
<style>body{{font-family:sans-serif;max-width:1000px;margin:2em auto;color:#222}}
table{{border-collapse:collapse}}td,th{{border:1px solid #ccc;padding:4px 8px}}
pre{{background:#f6f6f6;padding:8px;overflow:auto}}</style></head><body>
<h1>CoEx demo: nested survey over a simulated acoustic link</h1>
<h2>Goals</h2><table><tr><th>goal</th><th>result</th><th>detail</th></tr>{rows}</table>
<h2>Plots</h2>{"".join(f"<div>{c}</div>" for c in charts)}
<h2>Decisions</h2><ol>{log}</ol>
<h2>Products</h2>{"".join(gallery)}
<h2>Metrics</h2><pre>{html.escape(json.dumps(metrics, indent=2, default=str))}</pre>
</body></html>
"""
    path = out / "report.html"
    path.write_text(doc)
    return path
