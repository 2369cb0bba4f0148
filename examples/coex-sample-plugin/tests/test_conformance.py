"""How a plugin author runs the CoEx conformance suite: fixtures plus a two-line subclass. The
inputs are the ones the plugin registers for `coex plugins check pings` (one source of truth)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import pytest

from coex import Modality, ModalityReceiver, ModalitySender
from coex_conformance import ModalityFixtures, ModalityTests
from coex_sample_plugin import PingModality, conformance

INPUTS = conformance()


class PingFixtures(ModalityFixtures):
    @pytest.fixture
    def modality(self) -> Modality:
        return PingModality()

    @pytest.fixture
    def sample_inputs(self) -> Sequence[tuple[float, Any]]:
        return INPUTS.sample_inputs()

    @pytest.fixture
    def converged(self) -> Callable[[ModalitySender, ModalityReceiver], bool]:
        return INPUTS.converged


class TestPingModality(ModalityTests, PingFixtures):
    pass
