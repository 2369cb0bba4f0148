"""Conformance fixtures: a transport pair through two simulated Micromodem-2s.

Used by ``tests/test_micromodem_conformance.py``::

    class TestMicromodem(TransportTests, MicromodemFixtures):
        pass

The pair runs the real driver over NMEA to two :class:`~.simulator.SimulatedModem` s joined by a
lossless :class:`~coex_core.acoustic.AcousticChannel` 1 km apart, on a simulated clock (rate 5:
256-byte frames, up to 8 per packet).
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from coex_conformance import TransportFixtures  # type: ignore[import-untyped]

from .transport import MicromodemTransport

__all__ = ["MicromodemFixtures"]


class MicromodemFixtures(TransportFixtures):  # type: ignore[misc]
    @pytest.fixture
    def transport_pair(self) -> Iterator[tuple[MicromodemTransport, MicromodemTransport]]:
        from coex_core.acoustic import AcousticChannel

        from .simulator import ModemNetwork

        network = ModemNetwork({1: (0.0, 0.0, 0.0), 2: (1000.0, 0.0, 0.0)}, channel=AcousticChannel(seed=1))
        a = network.transport(1, dest=2, rate=5)
        b = network.transport(2, dest=1, rate=5)
        yield a, b
        a.close()
        b.close()
