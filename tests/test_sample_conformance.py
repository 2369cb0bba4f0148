"""The conformance suite's sample third-party plugin passes the suite (it is what the suite runs
beside every plugin under test)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import pytest

from coex_conformance import ModalityFixtures, ModalityTests
from coex_conformance.sample import SampleModality, sample_converged, sample_inputs
from coex_core.modality import Modality, ModalityReceiver, ModalitySender


class SampleFixtures(ModalityFixtures):
    @pytest.fixture
    def modality(self) -> Modality:
        return SampleModality()

    @pytest.fixture
    def sample_inputs(self) -> Sequence[tuple[float, Any]]:
        return sample_inputs()

    @pytest.fixture
    def converged(self) -> Callable[[ModalitySender, ModalityReceiver], bool]:
        return sample_converged


class TestSampleConformance(ModalityTests, SampleFixtures):
    pass
