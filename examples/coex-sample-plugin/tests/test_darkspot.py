"""The sample's onboard detector, as a vehicle team tests its own: registered under
``coex.detectors``, run by the detections modality on the frames the vehicle's imagery sender
holds, it points at the frame with a dark hull and at no frame of sand."""

from __future__ import annotations

import numpy as np

import coex
from coex.messages import Detection, DetectionSource
from coex_sample_plugin.darkspot import DarkSpotDetector


def _frame(k: int, hull: bool) -> np.ndarray:
    rng = np.random.default_rng(k)
    img = 150 + rng.normal(0, 12, (120, 160))
    if hull:
        img[40:80, 50:110] = 40
    return np.clip(img, 0, 255).astype(np.uint8)


def test_the_detector_is_found_by_name_and_points_at_the_dark_frame() -> None:
    assert coex.load_detector("darkspot") is DarkSpotDetector
    imagery, detections = coex.load_modality("imagery"), coex.load_modality("detections")
    node = coex.Node(coex.ChannelManager(2, [coex.LinkConfig(0, coex.Schedule.simple([1, 2], 20.0, 2.0), dst=1)]))
    frames = imagery().sender({"layer_bytes": [40, 200], "default_goal": "layer:1"})
    finder = detections().sender({"detectors": [{"type": "darkspot", "min_share": 0.1}]})
    node.add_sender(imagery, frames, coex.StreamConfig(4, "images"))
    node.add_sender(detections, finder, coex.StreamConfig(8, "detections", priority=100))
    for k in range(5):
        frames.ingest(coex_input(_frame(k, hull=k == 3), 100.0 + 6 * k, x=10.0 + k, y=20.0), 100.0 + 6 * k)
    sent = [m for m in finder.fill(64, 200.0) if isinstance(m, Detection)]
    assert [(m.source, m.image_id, m.x) for m in sent] == [(DetectionSource.IMAGE, 3, 13.0)]
    assert finder.fill(64, 300.0) == []  # nothing new since


def coex_input(image: np.ndarray, t: float, x: float, y: float) -> object:
    from coex_plugins.imagery import ImageInput

    return ImageInput(image, time=t, x=x, y=y)
