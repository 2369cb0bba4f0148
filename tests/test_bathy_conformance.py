"""The bathymetry plugin against the modality conformance suite."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import pytest

from coex_conformance import ModalityFixtures, ModalityTests
from coex_core.modality import Modality, ModalityReceiver, ModalitySender
from coex_plugins.bathymetry import BathymetryModality, BathymetryReceiver, BathymetrySender

from ._bathy_data import small_survey

LEVELS = 3


class BathymetryFixtures(ModalityFixtures):
    @pytest.fixture
    def modality(self) -> Modality:
        return BathymetryModality()

    @pytest.fixture
    def sample_inputs(self) -> Sequence[tuple[float, Any]]:
        _, survey = small_survey(48.0, 64)
        return list(survey.pings(batch=20))

    @pytest.fixture
    def sender_config(self) -> dict[str, Any]:
        return {"levels": LEVELS}

    @pytest.fixture
    def receiver_config(self) -> dict[str, Any]:
        return {"levels": LEVELS}

    @pytest.fixture
    def converged(self) -> Callable[[ModalitySender, ModalityReceiver], bool]:
        def done(sender: ModalitySender, receiver: ModalityReceiver) -> bool:
            assert isinstance(sender, BathymetrySender) and isinstance(receiver, BathymetryReceiver)
            held = {level: receiver.holdings(level) for level in range(LEVELS)}
            return all(held[lv].get((ix, iy)) == st for (lv, ix, iy), st in sender.inventory().items())

        return done


class TestBathymetryConformance(ModalityTests, BathymetryFixtures):
    pass
