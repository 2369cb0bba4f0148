"""How a plugin author runs the CoEx conformance suite: fixtures plus a two-line subclass."""

from __future__ import annotations

import pytest

from coex_conformance import ModalityFixtures, ModalityTests
from coex_sample_plugin import PingModality


class PingFixtures(ModalityFixtures):
    @pytest.fixture
    def modality(self):
        return PingModality()

    @pytest.fixture
    def sample_inputs(self):
        return [(10.0 + i, (10.0 + i, 20.0 + i / 10)) for i in range(60)]

    @pytest.fixture
    def converged(self):
        return lambda sender, receiver: len(receiver.records) == len(sender.records)


class TestPingModality(ModalityTests, PingFixtures):
    pass
