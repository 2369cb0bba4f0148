"""The transport conformance suite, through two simulated Micromodem-2s and the real driver."""

from coex_conformance import TransportTests
from coex_transports.micromodem.testing import MicromodemFixtures


class TestMicromodem(TransportTests, MicromodemFixtures):
    pass
