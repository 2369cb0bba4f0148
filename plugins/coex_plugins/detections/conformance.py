"""The detections modality's conformance inputs (entry point ``coex.conformance: detections``):
findings made outside CoEx (ingested) and the built-in relief detector on whatever map the
node's bathymetry sender holds; convergence: topside holds the newest version of every
detection the vehicle sends."""

from __future__ import annotations

from typing import Any

from coex import ModalityReceiver, ModalitySender
from coex_conformance.companions import Companion


def detection_inputs() -> list[tuple[float, Any]]:
    from coex import Finding
    from coex.messages import DetectionSource

    return [(10.0, Finding(12.0, 30.5, 0.9, 8.0, height=1.4, length=4.4, width=1.9, orientation=35.0,
                           footprint=8.0)),
            (20.0, [Finding(-40.0, 2.0, 0.3, 19.0, height=0.8), Finding(5.0, 5.0, 0.01, 19.0)]),
            (30.0, Finding(12.2, 30.4, 0.95, 29.0, height=1.5, length=4.6, width=1.8, orientation=33.0,
                           footprint=9.0)),
            (40.0, Finding(70.0, -3.0, 0.6, 39.0, image_id=4, source=DetectionSource.IMAGE))]


def detections_converged(sender: ModalitySender, receiver: ModalityReceiver) -> bool:
    """Topside holds, for every detection the vehicle scores high enough to send, the version
    it sent last, and the vehicle has nothing left to send."""
    from . import DetectionsReceiver, DetectionsSender, detection_message

    assert isinstance(sender, DetectionsSender) and isinstance(receiver, DetectionsReceiver)
    sent = [d for d in sender.detections.values() if d.finding.score >= sender.min_score]
    for d in sent:
        row = receiver.detections.get(d.detection_id)
        if row is None or row["message"] != detection_message(d.detection_id, d.source, d.finding):
            return False
    return bool(sent) and sender.pending_bytes() == 0


def companion() -> Companion:
    """Entry point ``coex.conformance: detections``."""
    from . import DetectionsModality

    return Companion("detections", DetectionsModality, detection_inputs, detections_converged)
