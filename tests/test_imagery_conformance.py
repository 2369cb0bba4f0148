"""The conformance suite for the imagery plugin (small generated images, so it runs fast)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import pytest

from coex_conformance import ModalityFixtures, ModalityTests
from coex_core.modality import Modality, ModalityReceiver, ModalitySender
from coex_plugins.imagery import ImageInput, ImageryModality, ImageryReceiver, ImagerySender
from coex_plugins.imagery.synth import seafloor


class ImageryFixtures(ModalityFixtures):
    @pytest.fixture
    def modality(self) -> Modality:
        return ImageryModality()

    @pytest.fixture
    def sample_inputs(self) -> Sequence[tuple[float, Any]]:
        return [(10.0 * (i + 1), ImageInput(seafloor(48, 64, seed=i), x=1.5 * i, y=-2.0))
                for i in range(3)]

    @pytest.fixture
    def sender_config(self) -> dict[str, Any]:
        return {"layer_bytes": [30, 60, 120, 240, 480, 900], "default_goal": "layer:4", "rto": 12.0}

    @pytest.fixture
    def converged(self) -> Callable[[ModalitySender, ModalityReceiver], bool]:
        def done(sender: ModalitySender, receiver: ModalityReceiver) -> bool:
            assert isinstance(sender, ImagerySender) and isinstance(receiver, ImageryReceiver)
            for image_id, tx in sender.images.items():
                rx = receiver.images.get(image_id)
                if rx is None or rx.contiguous() < tx.goal or rx.image is None:
                    return False
            return bool(sender.images)

        return done


class TestImageryConformance(ModalityTests, ImageryFixtures):
    pass
