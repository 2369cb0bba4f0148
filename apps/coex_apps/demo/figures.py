"""The figures of ``report.html``, drawn with matplotlib as inline SVG: line charts of the dive over
time, the decision timeline and north-up maps of the received bathymetry.

Each function returns one ``<svg>`` element (text kept as text, so the page can be searched and
read by a screen reader; the map's raster embedded as a PNG). Figures are built on
:class:`matplotlib.figure.Figure` directly, without pyplot: no global state, no GUI backend, safe
from any thread. The map's colours and hillshade are :mod:`coex_plugins.render`'s, as in the
console and the exported PNGs.
"""

from __future__ import annotations

import functools
import html
import io
import itertools
import math
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, ParamSpec, TypeVar

import numpy as np
import numpy.typing as npt

from coex_plugins.render import depth_cmap, elevation_rgba

if TYPE_CHECKING:  # matplotlib is imported where a figure is drawn
    from matplotlib.typing import RcKeyType

__all__ = ["line_chart", "map_figure", "timeline_chart"]

PALETTE = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#17becf"]

_TARGET, _DECOY, _CAND, _TRACK = "#e3171b", "#ff8c00", "#00d8ff", "#1a1a1a"
#: the vehicle's detections (suggestions)
_DETECT = "#d100d1"
P = ParamSpec("P")
R = TypeVar("R")
_ids = itertools.count(1)  # unique ids for the <defs> of several SVGs inlined in one page
#: matplotlib settings of every figure: text as <text>, fixed ids (no random hash), small fonts
_RC: dict[RcKeyType, Any] = {"svg.fonttype": "none", "font.size": 9.5, "axes.titlesize": 11, "axes.titleweight": "bold",
       "axes.titlelocation": "left", "axes.spines.top": False, "axes.spines.right": False,
       "hatch.color": "#c4c4c4", "hatch.linewidth": 2.5, "legend.frameon": False}


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


def _no_data(title: str) -> str:
    return f"<p><em>{_e(title)}: no data</em></p>"


def _styled(fn: Callable[P, R]) -> Callable[P, R]:
    """Run a figure function under the report's matplotlib settings (read when artists are made)."""

    @functools.wraps(fn)
    def run(*args: P.args, **kwargs: P.kwargs) -> R:
        import matplotlib

        with matplotlib.rc_context(_RC):
            return fn(*args, **kwargs)

    return run


def _figure(width_px: float, height_px: float) -> Any:
    """A pyplot-free figure of about ``width_px`` x ``height_px`` CSS pixels in the page."""
    from matplotlib.figure import Figure

    return Figure(figsize=(width_px / 96.0, height_px / 96.0), dpi=96)


def _svg(fig: Any, label: str, titles: Mapping[str, str] | None = None) -> str:
    """The figure as one responsive ``<svg>`` element; ``titles`` maps an artist's gid to a hover
    text (an SVG ``<title>``)."""
    import matplotlib

    uid = f"coexfig{next(_ids)}"
    buf = io.StringIO()
    with matplotlib.rc_context({"svg.hashsalt": uid, "svg.id": uid}):
        fig.savefig(buf, format="svg", bbox_inches="tight", pad_inches=0.08, metadata={"Date": None})
    svg = buf.getvalue()
    svg = svg[svg.index("<svg"):]
    # points -> CSS pixels at the page's scale (matplotlib writes pt), and shrink to the column
    svg = re.sub(r'<svg ([^>]*?)width="([\d.]+)pt" height="([\d.]+)pt"',
                 lambda m: (f'<svg {m.group(1)}width="{float(m.group(2)) * 4 / 3:.0f}" '
                            f'height="{float(m.group(3)) * 4 / 3:.0f}"'), svg, count=1)
    svg = svg.replace("<svg ", f'<svg role="img" aria-label="{_e(label)}" '
                      'style="max-width:100%;height:auto" ', 1)
    for gid, text in (titles or {}).items():
        svg = svg.replace(f'<g id="{gid}">', f'<g id="{gid}"><title>{_e(text)}</title>', 1)
    return svg


def _halo(width: float = 3.0, colour: str = "#fff", alpha: float = 1.0) -> list[Any]:
    from matplotlib import patheffects

    return [patheffects.withStroke(linewidth=width, foreground=colour, alpha=alpha)]


# ------------------------------------------------------------------------------ charts


@_styled
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
        return _no_data(title)
    fig = _figure(width, height)
    ax = fig.add_subplot()
    ax.set_title(title)
    ys = [float(p[1]) for p in pts]
    for i, (name, s) in enumerate(series.items()):
        xy = np.asarray(s, np.float64).reshape(-1, 2)
        ax.plot(xy[:, 0], xy[:, 1], color=PALETTE[i % len(PALETTE)], lw=1.6, label=name,
                drawstyle="steps-post" if step else "default")
    y0, y1 = min(0.0, min(ys)), max(ys)
    ax.set_ylim(y0, y1 if y1 > y0 else y0 + 1)
    for x, label in markers:
        ax.axvline(float(x), color="#444", lw=0.8, ls=(0, (3, 3)))
        ax.annotate(label, (float(x), 1.0), xycoords=("data", "axes fraction"), xytext=(3, -3),
                    textcoords="offset points", rotation=-90, va="top", ha="left", fontsize=8,
                    color="#333", path_effects=_halo())
    ax.grid(axis="y", color="#eee")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.ticklabel_format(axis="both", style="plain", useOffset=False)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8.5, handlelength=1.2)
    return _svg(fig, title)


@_styled
def timeline_chart(events: Sequence[Mapping[str, Any]], *, t_end: float, width: int = 720) -> str:
    """A decision timeline: one row per event kind, a dot per event (its text on hover)."""
    if not events:
        return "<p><em>no decisions</em></p>"
    kinds = list(dict.fromkeys(str(e["kind"]) for e in events))
    t_end = max([float(t_end), 1.0] + [float(e["t"]) for e in events])
    fig = _figure(width, 58 + 26 * len(kinds))
    ax = fig.add_subplot()
    uid = f"coexev{next(_ids)}"
    titles: dict[str, str] = {}
    for n, e in enumerate(events):
        i = kinds.index(str(e["kind"]))
        gid = f"{uid}-{n}"
        ax.plot([float(e["t"])], [i], "o", ms=7, color=PALETTE[i % len(PALETTE)], alpha=0.8, gid=gid)
        titles[gid] = f"{float(e['t']):.0f} s: {e.get('text', '')}"
    ax.set_yticks(range(len(kinds)), kinds)
    ax.set_ylim(len(kinds) - 0.5, -0.5)
    ax.grid(axis="y", color="#ddd")
    ax.spines["left"].set_visible(False)
    ax.tick_params(axis="y", length=0)
    ax.set_xlim(0, t_end)
    ax.set_xlabel("dive time (s)")
    return _svg(fig, "decision timeline", titles)


# ------------------------------------------------------------------------------ maps


def _colour_range(vals: npt.NDArray[np.float64]) -> tuple[float, float, bool, bool]:
    """The colour scale: the data range rounded out to tick values; only when a few outliers would
    squash it, a robust range (the clipped ends shown as triangles on the colour bar). Returns lo,
    hi and whether data lies below / above them."""
    from matplotlib.ticker import MaxNLocator

    zmin, zmax = float(vals.min()), float(vals.max())
    lo, hi = (float(v) for v in np.percentile(vals, [0.2, 99.8]))
    if hi - lo >= 0.8 * (zmax - zmin):
        lo, hi = zmin, zmax
    if hi - lo < 0.05:
        mid = 0.5 * (hi + lo)
        lo, hi = mid - 0.5, mid + 0.5
    ticks = MaxNLocator(6, steps=[1, 2, 5, 10]).tick_values(lo, hi)
    step = float(ticks[1] - ticks[0]) if len(ticks) > 1 else hi - lo
    lo, hi = math.floor(lo / step + 1e-9) * step, math.ceil(hi / step - 1e-9) * step
    return lo, hi, zmin < lo - 1e-9, zmax > hi + 1e-9


def _nice_length(span: float) -> float:
    """A round length (1, 2 or 5 times a power of ten) of about a fifth of ``span``."""
    target = max(span / 5.0, 1e-9)
    mag = 10.0 ** math.floor(math.log10(target))
    return max((m * mag for m in (1, 2, 5) if m * mag <= target * 1.2), default=mag)


def _map_subtitle(z: npt.NDArray[np.float64], ok: npt.NDArray[np.bool_], cell: float, n_gap: int) -> str:
    """Grid size, cell size and how much of it holds data."""
    ny, nx = z.shape
    frac = 100.0 * ok.sum() / z.size
    return (f"{nx} \u00d7 {ny} cells of {cell:g} m ({nx * cell:g} m \u00d7 {ny * cell:g} m), "
            f"{frac:.1f}% with data" + ("" if n_gap else ", no gaps") + "; north up")


#: marker kind -> (matplotlib marker, size, edge colour, label colour, side, dy (pt))
_MARKERS = {
    "detection": ("^", 15, _DETECT, "#8a008a", "left", 12.0),
    "candidate": ("o", 18, _CAND, "#005f73", "left", -18.0),
    "decoy": ("D", 12, _DECOY, "#a34f00", "right", -14.0),
    "target": ("s", 14, _TARGET, "#b30000", "right", 8.0),
}
_NAMES = {"target": "true target", "decoy": "decoy", "candidate": "flagged candidate",
          "detection": "vehicle's detection"}


def _marker(ax: Any, kind: str, x: float, y: float, filled: bool = False, label: str | None = None) -> Any:
    """One map marker with a halo so it reads on any colour; returns the artist (for a legend)."""
    shape, size, colour, *_ = _MARKERS[kind]
    halo = (0.0, 0.0, 0.0, 0.7) if kind == "candidate" else "#fff"
    face = (0.0, 0.85, 1.0, 0.3) if filled else "none"
    ax.plot([x], [y], ls="none", marker=shape, ms=size, mfc="none", mec=halo, mew=4.5, zorder=5)
    (line,) = ax.plot([x], [y], ls="none", marker=shape, ms=size, mfc=face, mec=colour, mew=2.0,
                      label=label, zorder=5)
    return line


@_styled
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
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch, Rectangle

    z = np.asarray(grid, np.float64)
    if z.ndim != 2 or z.size == 0:
        return _no_data(title)
    ok = np.isfinite(z)
    if not ok.any():
        return _no_data(title)
    cell, x0, y0 = float(cell), float(x0), float(y0)
    ny, nx = int(z.shape[0]), int(z.shape[1])
    x1, y1 = x0 + nx * cell, y0 + ny * cell
    lo, hi, below, above = _colour_range(z[ok])
    n_gap = int((~ok).sum())

    aspect = min(ny / nx, 1.25)
    fig = _figure(width + 130, width * aspect + 170)
    ax = fig.add_subplot()
    ax.set_title(title, pad=22)
    ax.text(0.0, 1.02, _map_subtitle(z, ok, cell, n_gap), transform=ax.transAxes, fontsize=8.5,
            color="#555", va="bottom")
    ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, facecolor="#f4f4f4", edgecolor="#c4c4c4",
                           hatch="//", lw=0, zorder=0))  # the gaps show through the raster
    ax.imshow(elevation_rgba(z, lo, hi, cell), extent=(x0, x1, y0, y1), origin="upper",
              interpolation="none", zorder=1)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    for side in ("top", "right"):
        ax.spines[side].set_visible(True)

    handles: list[Any] = _draw_track(ax, track)

    # --- markers and their labels: candidates underneath (the largest rings), true targets on top
    legend = _draw_markers(ax, (x0, x1, y0, y1), (("detection", detections), ("candidate", candidates),
                                                  ("decoy", decoys), ("target", targets)))
    order = ["true target", "decoy", "flagged candidate", "candidate, imaged", "vehicle's detection"]
    handles += [legend[k] for k in order if k in legend]
    if n_gap:
        handles.append(Patch(facecolor="#f4f4f4", edgecolor="#c4c4c4", hatch="//", label="no data"))

    _depth_bar(fig, ax, z[ok], lo, hi, below, above)
    if handles:
        ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.1), fontsize=9,
                  ncol=min(4, len(handles)), borderaxespad=0.0, handletextpad=0.6, columnspacing=1.6,
                  handler_map={Line2D: _legend_marker()})

    _north_and_scale(ax, x0, x1, y0, y1)
    return _svg(fig, title)


def _draw_track(ax: Any, track: Iterable[Sequence[float]] | npt.NDArray[Any]) -> list[Any]:
    """The vehicle's track (thinned when very long); its legend handle, if drawn."""
    tr = np.asarray(track if isinstance(track, np.ndarray) else list(track), np.float64)
    if not (tr.ndim == 2 and tr.shape[0] > 1 and tr.shape[1] >= 2):
        return []
    tr = tr[:, :2]
    if tr.shape[0] > 6000:  # keep the page light: thin a very long track
        idx = np.unique(np.r_[np.arange(0, tr.shape[0], math.ceil(tr.shape[0] / 6000)), tr.shape[0] - 1])
        tr = tr[idx]
    (line,) = ax.plot(tr[:, 0], tr[:, 1], color=_TRACK, lw=1.0, zorder=3, label="vehicle track",
                      path_effects=_halo(2.6, "#fff", 0.55))
    return [line]


def _draw_markers(ax: Any, extent: tuple[float, float, float, float],
                  groups: Iterable[tuple[str, Sequence[Mapping[str, Any]]]]) -> dict[str, Any]:
    """Each group's markers (kind, items with ``x``, ``y``, ``label``, ``visited``) inside
    ``extent`` (x0, x1, y0, y1), labelled on the side with room; the legend's artists by name."""
    x0, x1, y0, y1 = extent
    legend: dict[str, Any] = {}
    for kind, items in groups:
        *_, colour, side, dy = _MARKERS[kind]
        for it in items:
            x, y = _f(it.get("x")), _f(it.get("y"))
            if x is None or y is None or not (x0 <= x <= x1 and y0 <= y <= y1):
                continue
            visited = bool(it.get("visited", False))
            key = "candidate, imaged" if kind == "candidate" and visited else _NAMES[kind]
            art = _marker(ax, kind, x, y, filled=visited, label=key)
            legend.setdefault(key, art)
            right = side == "right"
            if right and x > x1 - 0.25 * (x1 - x0):
                right = False
            elif not right and x < x0 + 0.25 * (x1 - x0):
                right = True
            ax.annotate(str(it.get("label", "")), (x, y), xytext=(11 if right else -11, dy),
                        textcoords="offset points", ha="left" if right else "right", va="center",
                        fontsize=9.5, fontweight="bold", color=colour, zorder=6,
                        path_effects=_halo(3.2), annotation_clip=True)
    return legend


def _depth_bar(fig: Any, ax: Any, held: npt.NDArray[np.float64], lo: float, hi: float, below: bool,
               above: bool) -> None:
    """The colour bar of depth (positive down), shallow at the top, with the data's range
    (``held``: the grid's finite elevations)."""
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    extend = {(True, True): "both", (True, False): "max", (False, True): "min"}.get((below, above), "neither")
    sm = ScalarMappable(norm=Normalize(-hi, -lo), cmap=depth_cmap().reversed())
    cbar = fig.colorbar(sm, ax=ax, fraction=0.035, pad=0.03, extend=extend, shrink=0.7, anchor=(0.0, 1.0))
    cbar.ax.invert_yaxis()
    cbar.ax.set_title("depth (m)", fontsize=9.5, fontweight="bold", loc="left", pad=10)
    cbar.ax.set_xlabel(f"data: {-float(held.max()):.1f} to {-float(held.min()):.1f} m deep",
                       fontsize=8, color="#555", loc="left")


def _north_and_scale(ax: Any, x0: float, x1: float, y0: float, y1: float) -> None:
    """The north arrow (top left) and a scale bar of a round length (bottom right)."""
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    ax.annotate("N", xy=(0.05, 0.97), xytext=(0.05, 0.84), xycoords="axes fraction", ha="center",
                va="top", fontsize=11, fontweight="bold", path_effects=_halo(3.0), zorder=7,
                arrowprops={"facecolor": "#222", "edgecolor": "#fff", "width": 2.5, "headwidth": 10,
                            "headlength": 10, "shrink": 0.0})
    span = max(x1 - x0, y1 - y0)
    sb_len = min(_nice_length(span), _nice_length(0.4 * (x1 - x0) * 5 / 1.2))
    ax.add_artist(AnchoredSizeBar(ax.transData, sb_len, f"{sb_len:g} m", "lower right", pad=0.4,
                                  sep=3, frameon=True, size_vertical=0.012 * (y1 - y0),
                                  color="#222", fontproperties={"size": 8.5}))


def _legend_marker() -> Any:
    """Legend entries drawn as the marker alone (with its halo), not a line through it."""
    from matplotlib.legend_handler import HandlerLine2D

    return HandlerLine2D(numpoints=1, marker_pad=0.3)
