"""The transport conformance suite on LCM: memq:// (one shared instance) and udpm:// on loopback."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest

from coex_conformance import TransportFixtures, TransportTests
from coex_transports.lcm import LcmConfig, LcmTransport
from coex_transports.lcm.testing import TEST_UDPM_URL, ensure_multicast_route, unique_channel


class LcmMemqFixtures(TransportFixtures):
    """Conformance fixtures: two ends sharing one ``memq://`` instance."""

    @pytest.fixture
    def transport_pair(self) -> Iterator[tuple[LcmTransport, LcmTransport]]:
        a, b = LcmTransport.pair(LcmConfig(url="memq://", tx=unique_channel("UP"), rx=unique_channel("DOWN")))
        yield a, b
        a.close()
        b.close()

    @pytest.fixture
    def recv_timeout(self) -> float:
        return 2.0


class LcmUdpmFixtures(TransportFixtures):
    """Conformance fixtures: two ends with their own ``udpm://`` instances on one channel."""

    @pytest.fixture(scope="class")
    @classmethod
    def multicast(cls) -> Iterator[None]:
        undo = ensure_multicast_route()
        yield
        if not os.environ.get("PYTEST_XDIST_WORKER"):  # other workers may still need the route
            undo()

    @pytest.fixture
    def transport_pair(self, multicast: None) -> Iterator[tuple[LcmTransport, LcmTransport]]:
        # UDP drops fragmented datagrams once the socket buffer is full: bursts of 4 frames of
        # up to 16 KiB fit a 1 MiB buffer (a single 64 KiB frame is tested separately)
        channel = unique_channel()
        config = LcmConfig(url=TEST_UDPM_URL + "&recv_buf_size=1048576", tx=channel, rx=channel, mtu=16384)
        a = LcmTransport(config)
        b = LcmTransport(config)
        yield a, b
        a.close()
        b.close()

    @pytest.fixture
    def recv_timeout(self) -> float:
        return 5.0


class TestLcmMemq(TransportTests, LcmMemqFixtures):
    pass


class TestLcmUdpm(TransportTests, LcmUdpmFixtures):
    pass
