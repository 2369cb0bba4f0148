"""WHOI Micromodem / Micromodem-2 transport (NMEA over serial) and its simulator.

* :mod:`.nmea` — pure sentence codec (checksums, typed parsers, builders), no ports.
* :mod:`.driver` — :class:`MicromodemDriver`, the sans-I/O host driver.
* :mod:`.transport` — :class:`MicromodemTransport` (URI ``micromodem:///dev/ttyUSB0?rate=5``).
* :mod:`.simulator` — :class:`SimulatedModem`, :class:`ModemNetwork` (simulated time) and
  :class:`PtySimulator` (pseudo-terminals / TCP, what ``coex modem-sim`` runs).
"""

from __future__ import annotations

from typing import Any

from .driver import DriverConfig, MicromodemDriver, ReceivedFrame
from .transport import MicromodemTransport, parse_uri

__all__ = [
    "DriverConfig",
    "MicromodemDriver",
    "MicromodemTransport",
    "ModemNetwork",
    "PtySimulator",
    "ReceivedFrame",
    "SimulatedModem",
    "parse_uri",
]


def __getattr__(name: str) -> Any:
    # the simulator pulls in coex_core.acoustic (numpy): import it only when asked for
    if name in ("ModemNetwork", "PtySimulator", "SimulatedModem"):
        from . import simulator

        return getattr(simulator, name)
    raise AttributeError(name)
