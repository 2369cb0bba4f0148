"""The built-in ``relief`` detector (``coex.detectors: relief``): relief anomalies in the
vehicle's own full-resolution map as it grows.

Every run it looks at the map tiles that changed since it last looked them over (each with a
``margin`` of its neighbours' cells, so that an object on a tile's edge is seen whole) and finds
the bumps standing more than ``threshold`` metres above the local background (a top-hat: the
map less its grey-scale opening with a 9 m square, so that slopes, rolling relief and ripples
stay in the background; :func:`~coex_plugins.bathymetry.export.find_targets`). Each bump is
measured (:func:`~coex_plugins.bathymetry.relief.measure_bump`: height, footprint, length,
width, orientation, flatness of its top) and scored by how well it matches the sizes the
vehicle is told to look for: ranges of ``length``, ``width`` and ``height`` (default 2-8 m
long, 1-3 m wide, 0.6-3 m high: a debris patch or a small car to a container or a small boat's
hull; :func:`~coex_plugins.bathymetry.relief.range_likeness`), or one ``target`` size
(:func:`~coex_plugins.bathymetry.relief.likeness`), with the given ``spread``s.
A bump is judged only once the cells around it have been quiet for ``settle`` seconds (the
swath has passed): a tile with a bump still changing is looked at again at the next run.

It reads only the vehicle's map (the bathymetry sender's view for detectors, a
:class:`coex.MapView`): the soundings as the sonar gave them, outliers rejected, never the
simulation's truth.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np

from coex import Detector, Finding, MapView, Options, Problems, merged_config, persistent
from coex.messages import DetectionSource
from coex.options import anything, integer, number
from coex_plugins.bathymetry.relief import (
    RANGE_FLATNESS_SPREAD,
    SIZES,
    SPREAD,
    bumps,
    likeness,
    range_likeness,
)

__all__ = ["DEFAULTS", "OPTIONS", "ReliefDetector"]

#: the detector's options: the one declaration of their types, ranges and units
OPTIONS = Options(
    threshold=number(0.7, "a bump stands this far above the local background", unit="m", above=0),
    length=anything(list(SIZES[0]), "the lengths looked for: [min, max] (m); the score is 1 inside, "
                                    "falling off outside"),
    width=anything(list(SIZES[1]), "the widths looked for: [min, max] (m)"),
    height=anything(list(SIZES[2]), "the heights looked for: [min, max] (m)"),
    target=anything(None, "or one size [length, width, height] (m) instead of the ranges; none: the ranges"),
    spread=anything(None, "the score's spreads: [length, width, height] (m) and flatness, each > 0 "
                          "(none: 0.2 flatness for one size, 0.35 for ranges)"),
    min_cells=integer(2, "fewest cells of a bump (one cell is a spike)", lo=1),
    max_area=number(40.0, "largest area of a bump (a large one is terrain)", unit="m2", above=0),
    settle=number(20.0, "the cells around a bump are quiet this long before it is judged", unit="s", lo=0),
    margin=number(16.0, "neighbouring cells looked at around a changed tile", unit="m", lo=0),
    neighbourhood=number(12.0, "radius whose 1 m subgrids are sent after a finding", unit="m", lo=0),
)
#: their defaults (a name kept for 0.x code)
DEFAULTS: dict[str, Any] = OPTIONS.defaults()


@persistent("detections.ReliefDetector")
class ReliefDetector(Detector[MapView]):
    """Relief anomalies of the vehicle's bathymetry map (see the module docstring)."""

    name: ClassVar[str] = "relief"
    modality: ClassVar[str] = "bathymetry"
    view = MapView
    source: ClassVar[DetectionSource] = DetectionSource.MAP

    options = OPTIONS

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        cfg = merged_config(config, self.options, "relief detector")
        self.threshold = float(cfg["threshold"])
        self.min_cells = int(cfg["min_cells"])
        self.max_area = float(cfg["max_area"])
        self.settle = float(cfg["settle"])
        self.margin = float(cfg["margin"])
        self.neighbourhood = float(cfg["neighbourhood"])
        p = Problems()
        self.target: tuple[float, ...] | None = (None if cfg["target"] is None
                                                 else _measures(p, "target", cfg["target"], 3))
        sizes = [_measures(p, k, cfg[k], 2) for k in ("length", "width", "height")]
        for k, r in zip(("length", "width", "height"), sizes, strict=True):
            if not 0.0 <= r[0] <= r[1]:
                p.add(k, f"a range [min, max] (m) with 0 <= min <= max, got {cfg[k]!r}")
        flat = SPREAD[3] if self.target is not None else RANGE_FLATNESS_SPREAD
        spread = ((*SPREAD[:3], flat) if cfg["spread"] is None
                  else _measures(p, "spread", cfg["spread"], 4, positive=True))
        p.check("relief detector")
        self.sizes = tuple(sizes)
        self.spread = spread
        #: tile -> the version of it last looked over completely
        self._looked: dict[tuple[int, int], int] = {}

    def detect(self, data: MapView, now: float) -> list[Finding]:
        qmap = data
        out: list[Finding] = []
        span = qmap.tile * qmap.resolution
        cell = qmap.resolution
        for key in qmap.tiles:
            version = qmap.tile_version(key)
            if self._looked.get(key) == version:
                continue
            x0, y0 = key[0] * span, key[1] * span
            grid, updated, wx0, wy0 = qmap.window(x0 - self.margin, y0 - self.margin, x0 + span + self.margin,
                                                  y0 + span + self.margin)
            done = True
            for cand, b in bumps(grid, cell=cell, x0=wx0, y0=wy0, threshold=self.threshold,
                                 min_cells=self.min_cells, max_area=self.max_area):
                if not (x0 <= cand.peak_x < x0 + span and y0 <= cand.peak_y < y0 + span):
                    continue  # its own tile looks at it
                # the cells within 6 m of it, quiet for `settle` seconds
                c = int((cand.peak_x - wx0) / cell)
                r = int((cand.peak_y - wy0) / cell)
                k = max(1, round(6.0 / cell))
                near = updated[max(r - k, 0):r + k + 1, max(c - k, 0):c + k + 1]
                newest = float(np.max(near)) if near.size else -math.inf
                if now - newest < self.settle:
                    done = False  # still changing: look again next run
                    continue
                if self.target is not None:
                    score = likeness(b.height, b.length, b.width, b.flatness, self.target,  # type: ignore[arg-type]
                                     self.spread)  # type: ignore[arg-type]
                else:
                    score = range_likeness(b.height, b.length, b.width, b.flatness, self.sizes,  # type: ignore[arg-type]
                                           self.spread)  # type: ignore[arg-type]
                out.append(Finding(b.x, b.y, round(score, 3), newest, height=b.height, length=b.length,
                                   width=b.width, orientation=b.orientation, footprint=b.footprint))
            if done:
                self._looked[key] = version
        return out


def _measures(p: Problems, key: str, value: Any, n: int, *, positive: bool = False) -> tuple[float, ...]:
    """``value``, a list of ``n`` finite numbers (above 0 when ``positive``), as floats; a
    problem of ``key`` (``key[i]`` for one entry) when it is not."""
    if not isinstance(value, list | tuple) or len(value) != n:
        p.add(key, f"a list of {n} numbers, got {value!r}")
        return (0.0,) * n
    entry = number(0.0, above=0) if positive else number(0.0)
    return tuple(float(entry.checked(p, f"{key}[{i}]", v, 1.0)) for i, v in enumerate(value))
