"""A third-party onboard detector: dark spots in the vehicle's own camera frames.

What a vehicle team writes to bring its own detector (entry-point group ``coex.detectors``,
``docs/plugins.md`` section 5a): a :class:`coex.Detector` subclass that names the modality whose
vehicle-side data it looks at (``imagery``) and the view of it it takes (``coex.ImageFrames``: the
frames the imagery sender holds, through their ``frames(since)``), says what its findings are
found in (IMAGE), and returns
:class:`coex.Finding` objects from :meth:`DarkSpotDetector.detect`. The ``detections`` modality
runs it every few seconds and sends what it finds topside as suggestions. Its state (the
capture time of the last frame it looked at) is saved with the vehicle's node: the class is
registered with ``@coex.persistent``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np

from coex import ConfigError, Detector, Finding, ImageFrames, merged_config, persistent
from coex.messages import DetectionSource

__all__ = ["DarkSpotDetector"]

DEFAULTS = {
    #: a pixel is dark below this share of the frame's median brightness
    "darkness": 0.5,
    #: a frame is reported when at least this share of its pixels is dark
    "min_share": 0.05,
}


@persistent("sample.DarkSpotDetector")
class DarkSpotDetector(Detector[ImageFrames]):
    """Frames with a dark spot (a hull, a hole, a dark rock) covering ``min_share`` of them."""

    name: ClassVar[str] = "darkspot"
    modality: ClassVar[str] = "imagery"
    view = ImageFrames
    source: ClassVar[DetectionSource] = DetectionSource.IMAGE

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        cfg = merged_config(config, DEFAULTS, "darkspot detector")
        self.darkness = float(cfg["darkness"])
        self.min_share = float(cfg["min_share"])
        if not (0 < self.darkness < 1 and 0 < self.min_share < 1):
            raise ConfigError("darkspot detector: darkness and min_share in (0, 1)")
        #: capture time of the newest frame looked at
        self.seen = -math.inf

    def detect(self, data: ImageFrames, now: float) -> list[Finding]:
        out = []
        for f in data.frames(self.seen):
            self.seen = max(self.seen, f.time)
            a = np.asarray(f.image, float)
            if a.ndim == 3:
                a = a.mean(-1)
            if f.x is None or f.y is None or a.size == 0:
                continue
            share = float(np.mean(a < self.darkness * max(float(np.median(a)), 1.0)))
            if share >= self.min_share:
                out.append(Finding(f.x, f.y, round(min(1.0, 4 * share), 3), f.time, image_id=f.image_id))
        return out
