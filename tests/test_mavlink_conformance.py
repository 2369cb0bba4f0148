"""The transport conformance suite, run on two MavlinkTransport ends over UDP on 127.0.0.1."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from coex_conformance import TransportFixtures, TransportTests
from coex_transports.mavlink import MavlinkTransport


class MavlinkUdpFixtures(TransportFixtures):
    @pytest.fixture
    def transport_pair(self) -> Iterator[tuple[MavlinkTransport, MavlinkTransport]]:
        a = MavlinkTransport.from_uri("mavlink:udpin:127.0.0.1:0?sysid=1&compid=191&mtu=2048")
        port = a.link.local[1]  # type: ignore[attr-defined]
        b = MavlinkTransport.from_uri(f"mavlink:udpout:127.0.0.1:{port}?sysid=2&compid=191&mtu=2048")
        assert a.recv(timeout=0.3) is None  # a hears b's heartbeat, so it knows where b is
        assert a.mtu == b.mtu == 2048
        yield a, b
        a.close()
        b.close()


class TestMavlinkTransport(TransportTests, MavlinkUdpFixtures):
    pass
