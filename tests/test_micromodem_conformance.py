"""The transport conformance suite, through two simulated Micromodem-2s and the real driver.

The pair runs the real driver over NMEA to two simulated modems joined by a lossless acoustic
channel 1 km apart, on a simulated clock (rate 5: 256-byte frames, up to 8 per packet)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from coex_conformance import TransportFixtures, TransportTests
from coex_core.acoustic import AcousticChannel
from coex_transports.micromodem import MicromodemTransport
from coex_transports.micromodem.simulator import ModemNetwork


class MicromodemFixtures(TransportFixtures):  # type: ignore[misc]
    @pytest.fixture
    def transport_pair(self) -> Iterator[tuple[MicromodemTransport, MicromodemTransport]]:
        network = ModemNetwork({1: (0.0, 0.0, 0.0), 2: (1000.0, 0.0, 0.0)}, channel=AcousticChannel(seed=1))
        a = network.transport(1, dest=2, rate=5)
        b = network.transport(2, dest=1, rate=5)
        yield a, b
        a.close()
        b.close()


class TestMicromodem(TransportTests, MicromodemFixtures):
    pass
