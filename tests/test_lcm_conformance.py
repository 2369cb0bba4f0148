"""The transport conformance suite on LCM: memq:// (one shared instance) and udpm:// on loopback."""

from coex_conformance import TransportTests
from coex_transports.lcm.testing import LcmMemqFixtures, LcmUdpmFixtures


class TestLcmMemq(TransportTests, LcmMemqFixtures):
    pass


class TestLcmUdpm(TransportTests, LcmUdpmFixtures):
    pass
