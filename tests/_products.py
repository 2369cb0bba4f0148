"""Typed products for tests that feed a console or a ROS view without a receiver: every field
the product declares, with plain defaults a test overrides."""

from __future__ import annotations

from typing import Any

from coex_plugins.bathymetry import MapLevel
from coex_plugins.imagery import ImageProduct
from coex_plugins.survey import SurveyProduct
from coex_plugins.timeseries import SeriesProduct


def map_level(level: int, data: Any, version: int = 1, **fields: Any) -> MapLevel:
    f: dict[str, Any] = {"cell_size": 1.0, "step": 1, "level_cell": 1.0, "x0": 0.0, "y0": 0.0, "subgrids": 1,
                         "cells": 1, "newest": 0.0, "origin_lat": 0.0, "origin_lon": 0.0, **fields}
    return MapLevel("map-level", f"level-{level}", version, data, level=level, **f)


def image(image_id: int, data: Any, time: float, version: int = 1, **fields: Any) -> ImageProduct:
    h, w = (getattr(data, "shape", None) or (0, 0))[:2]
    f: dict[str, Any] = {"stamp": 0, "x": None, "y": None, "width": w, "height": h, "grey": True,
                         "total_bytes": 100, "held_bytes": 100, "contiguous": 100, "packets_used": 1,
                         "packets": 1, "bytes_used": 100, "layers_complete": 1, "layers": 1,
                         "complete": True, "precincts": 0, "regions": [], "crops": [], **fields}
    return ImageProduct("image", str(image_id), version, data, image_id=image_id, time=time, **f)


def series(name: str, data: Any, version: int = 1, **fields: Any) -> SeriesProduct:
    f: dict[str, Any] = {"channel": 0, "unit": "", "samples": len(getattr(data, "times", ())), "blocks": 1,
                         "max_bound": None, **fields}
    return SeriesProduct("series", name, version, data, name=name, **f)


def survey(survey_id: int, state: str, time: float, version: int = 1, **fields: Any) -> SurveyProduct:
    f: dict[str, Any] = {"text": "", "reason": None, "index": None, "history": [], **fields}
    return SurveyProduct("survey", str(survey_id), version, None, survey_id=survey_id, state=state, time=time, **f)
