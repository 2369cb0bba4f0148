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

from coex import ConfigError, Detector, Finding, MapView, merged_config, persistent
from coex.messages import DetectionSource
from coex_plugins.bathymetry.relief import (
    RANGE_FLATNESS_SPREAD,
    SIZES,
    SPREAD,
    bumps,
    likeness,
    range_likeness,
)

__all__ = ["DEFAULTS", "ReliefDetector"]

DEFAULTS: dict[str, Any] = {
    #: metres above the local background a bump must stand
    "threshold": 0.7,
    #: what the vehicle looks for: ranges of length, width and height (m); the score is 1 inside
    #: them and falls off outside
    "length": list(SIZES[0]),
    "width": list(SIZES[1]),
    "height": list(SIZES[2]),
    #: or one size (length, width, height, m) instead of the ranges; None: the ranges
    "target": None,
    #: spreads of the score's Gaussians: length, width, height (m) and flatness (None: 0.2 for
    #: one target size, 0.35 for ranges: a hull or a debris patch is less flat than a car)
    "spread": None,
    #: fewest cells and largest area (m²) of a bump (one cell is a spike; a large one is terrain)
    "min_cells": 2,
    "max_area": 40.0,
    #: seconds the cells around a bump must have been quiet before it is judged
    "settle": 20.0,
    #: metres of neighbouring cells looked at around a changed tile
    "margin": 16.0,
    #: radius (m) of the neighbourhood whose 1 m subgrids are sent after a finding
    "neighbourhood": 12.0,
}


@persistent("detections.ReliefDetector")
class ReliefDetector(Detector[MapView]):
    """Relief anomalies of the vehicle's bathymetry map (see the module docstring)."""

    name: ClassVar[str] = "relief"
    modality: ClassVar[str] = "bathymetry"
    view = MapView
    source: ClassVar[DetectionSource] = DetectionSource.MAP

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        cfg = merged_config(config, DEFAULTS, "relief detector")
        try:
            self.threshold = float(cfg["threshold"])
            self.target = None if cfg["target"] is None else tuple(float(v) for v in cfg["target"])
            self.sizes = tuple(tuple(float(v) for v in cfg[k]) for k in ("length", "width", "height"))
            flat = SPREAD[3] if self.target is not None else RANGE_FLATNESS_SPREAD
            self.spread = tuple(float(v) for v in cfg["spread"]) if cfg["spread"] is not None else (*SPREAD[:3], flat)
            self.min_cells = int(cfg["min_cells"])
            self.max_area = float(cfg["max_area"])
            self.settle = float(cfg["settle"])
            self.margin = float(cfg["margin"])
            self.neighbourhood = float(cfg["neighbourhood"])
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"relief detector: {exc}") from exc
        if (self.target is not None and len(self.target) != 3) or len(self.spread) != 4 or min(self.spread) <= 0:
            raise ConfigError("relief detector: target is [length, width, height] and spread "
                              "[length, width, height, flatness], spreads > 0")
        if any(len(r) != 2 or not 0.0 <= r[0] <= r[1] for r in self.sizes):
            raise ConfigError("relief detector: length, width and height are [min, max] ranges (m), 0 <= min <= max")
        if self.threshold <= 0 or self.margin < 0 or self.neighbourhood < 0 or self.settle < 0:
            raise ConfigError("relief detector: threshold > 0; margin, neighbourhood and settle >= 0")
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
