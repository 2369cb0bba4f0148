"""The imagery modality's conformance inputs (entry point ``coex.conformance: imagery``):
what ``coex plugins check imagery`` and the suite's two-node tests run it on, and what its own
conformance tests use (one source of truth)."""

from __future__ import annotations

from typing import Any

from coex import ModalityReceiver, ModalitySender
from coex_conformance.companions import Companion


def imagery_inputs() -> list[tuple[float, Any]]:
    from . import ImageInput
    from .synth import seafloor

    return [(10.0 * (i + 1), ImageInput(seafloor(48, 64, seed=i), x=1.5 * i, y=-2.0)) for i in range(3)]


def imagery_config() -> dict[str, Any]:
    # crops = always: the region the suite asks for (imagery_start_requests) is answered with a
    # crop, so ImageCrop travels through every two-node test too
    return {"layer_bytes": [30, 60, 120, 240, 480, 900], "default_goal": "layer:4", "rto": 12.0,
            "crops": "always"}


def imagery_start_requests(receiver: ModalityReceiver, now: float) -> None:
    """Once topside hears the first image, it asks for its top-left quarter at 30 dB (one
    ``ImageRegionRequest``; the vehicle answers with a crop)."""
    from . import ImageryReceiver

    assert isinstance(receiver, ImageryReceiver)
    asked: list[Any] = []

    def ask(product: Any) -> None:
        if asked or product.kind != "image":
            return
        meta = product.meta
        asked.append(receiver.request_region(int(meta["image_id"]), (0, 0, int(meta["width"]) // 2,
                                                                     int(meta["height"]) // 2), "quality", 30.0, now))

    receiver.listeners.append(ask)


def imagery_converged(sender: ModalitySender, receiver: ModalityReceiver) -> bool:
    """Topside holds every image and crop up to its goal, decodable, and the vehicle answered
    every region request topside made."""
    from . import ImageryReceiver, ImagerySender

    assert isinstance(sender, ImagerySender) and isinstance(receiver, ImageryReceiver)
    for image_id, tx in sender.images.items():
        rx = receiver.images.get(image_id)
        if rx is None or rx.contiguous() < tx.goal or rx.image is None:
            return False
    if any(reg["state"] == "requested" for rx in receiver.images.values() for reg in rx.regions):
        return False
    return bool(sender.images)


def companion() -> Companion:
    """Entry point ``coex.conformance: imagery``."""
    from . import ImageryModality

    return Companion("imagery", ImageryModality, imagery_inputs, imagery_converged, imagery_config,
                     start_requests=imagery_start_requests)
