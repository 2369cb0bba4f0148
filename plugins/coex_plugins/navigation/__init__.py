"""Navigation that holds (issue 56, ``docs/navigation.md``): the ship's USBL fixes read topside
(:mod:`.usbl`), the local frame through pyproj (:mod:`.frame`), one smooth and robust estimate of
each vehicle's dead-reckoning drift (:mod:`.estimator`: a Kalman filter and a Rauch-Tung-Striebel
smoother), and what topside does with it (:mod:`.topside`: the corrected map, images, detections
and tracks; survey commands put into the vehicle's own frame)."""

from __future__ import annotations

from .estimator import DriftEstimator, NavConfig, Solution
from .frame import LocalFrame
from .topside import (
    Aid,
    AidConfig,
    CorrectedDetections,
    CorrectedImages,
    CorrectedMap,
    Navigation,
    VehicleFrameSurveys,
    bridge_gaps,
)
from .usbl import UsblInput, gga_sentence, psimssb_sentence, resolve_time, tll_sentence

__all__ = ["Aid", "AidConfig", "CorrectedDetections", "CorrectedImages", "CorrectedMap", "DriftEstimator", "LocalFrame", "NavConfig",
           "Navigation", "Solution", "UsblInput", "VehicleFrameSurveys", "bridge_gaps", "gga_sentence", "psimssb_sentence",
           "resolve_time", "tll_sentence"]
