"""The bathymetry modality passes the CoEx modality conformance suite, with the inputs the suite
runs it on beside other plugins (coex_conformance.companions: one source of truth)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import pytest

from coex_conformance import ModalityFixtures, ModalityTests
from coex_conformance.companions import Companion, registered
from coex_core.modality import Modality, ModalityReceiver, ModalitySender

_C = registered("bathymetry")
assert _C is not None, "the bathymetry plugin registers its conformance inputs (coex.conformance)"
COMPANION: Companion = _C


class BathymetryFixtures(ModalityFixtures):
    @pytest.fixture
    def modality(self) -> Modality:
        return COMPANION.modality()

    @pytest.fixture
    def sample_inputs(self) -> Sequence[tuple[float, Any]]:
        return COMPANION.sample_inputs()

    @pytest.fixture
    def sender_config(self) -> Any:
        return COMPANION.sender_config()

    @pytest.fixture
    def receiver_config(self) -> Any:
        return COMPANION.receiver_config()

    @pytest.fixture
    def start_requests(self) -> Callable[[ModalityReceiver, float], None] | None:
        return COMPANION.start_requests

    @pytest.fixture
    def converged(self) -> Callable[[ModalitySender, ModalityReceiver], bool]:
        return COMPANION.converged


class TestBathymetryConformance(ModalityTests, BathymetryFixtures):
    pass
