"""The imagery modality's conformance inputs (entry point ``coex.conformance: imagery``):
what ``coex plugins check imagery`` and the suite's two-node tests run it on, and what its own
conformance tests use (one source of truth)."""

from __future__ import annotations

from typing import Any

from coex_conformance.companions import Companion
from coex_core.modality import ModalityReceiver, ModalitySender


def imagery_inputs() -> list[tuple[float, Any]]:
    from . import ImageInput
    from .synth import seafloor

    return [(10.0 * (i + 1), ImageInput(seafloor(48, 64, seed=i), x=1.5 * i, y=-2.0)) for i in range(3)]


def imagery_config() -> dict[str, Any]:
    return {"layer_bytes": [30, 60, 120, 240, 480, 900], "default_goal": "layer:4", "rto": 12.0}


def imagery_converged(sender: ModalitySender, receiver: ModalityReceiver) -> bool:
    """Topside holds every image up to its goal, decodable."""
    from . import ImageryReceiver, ImagerySender

    assert isinstance(sender, ImagerySender) and isinstance(receiver, ImageryReceiver)
    for image_id, tx in sender.images.items():
        rx = receiver.images.get(image_id)
        if rx is None or rx.contiguous() < tx.goal or rx.image is None:
            return False
    return bool(sender.images)


def companion() -> Companion:
    """Entry point ``coex.conformance: imagery``."""
    from . import ImageryModality

    return Companion("imagery", ImageryModality, imagery_inputs, imagery_converged, imagery_config)
