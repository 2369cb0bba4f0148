"""Simulated Micromodem-2s joined through :class:`coex_core.acoustic.AcousticChannel`.

* :class:`SimulatedModem` is one modem, sans-I/O: host bytes in (:meth:`~SimulatedModem.feed`),
  host bytes out (:meth:`~SimulatedModem.data_to_send`), timers run by ``now``. It answers the
  sentences a real Micromodem-2 answers, in the orders of the reference note ``micromodem.md`` §3:
  echoes, the ``$CADRQ`` loop (with ``DATA_TIMEOUT`` after ``DTO`` seconds), ``$CATXP`` and, one
  airtime later, ``$CATXF`` and a version-6 ``$CAXST``; at the far end ``$CARXP``, ``$CACYC``, one
  ``$CARXD`` per good frame or ``$CAMSG,BAD_CRC,<frame>`` per failed one, and a version-6
  ``$CACST`` (MODE 1 / PSK_ERROR 3 when a frame failed); ``$CCTDP`` → ``$CARDP`` with per-frame CRC
  flags; acknowledgement mini-packets → ``$CAACK``; ``$CCMPC`` pings → ``$CAMPA`` / ``$CAMPR`` with
  the one-way travel time; ``$CAREV`` (``INIT`` on reboot, ``AUV`` every 10 s with ``REV,1``).
* :class:`ModemNetwork` owns the channel, the modems and a :class:`~coex_core.loopback.SimClock`;
  it runs everything in simulated time. :meth:`ModemNetwork.transport` gives a
  :class:`~.transport.MicromodemTransport` whose driver talks NMEA to a simulated modem in
  process, so a two-hour dive runs in seconds through the real driver code;
  :meth:`ModemNetwork.open_uri` opens a ``micromodem:`` URI there instead of on a serial port, and
  :meth:`ModemNetwork.unplug` / :meth:`~ModemNetwork.plug` pull a modem's serial cable and put it
  back (the host's transport fails as a real port does, and cannot be opened again meanwhile).
* :class:`SimLoop` drives :class:`~coex_runtime.runner.Runner` objects over a network, with
  timed callbacks, on the network's clock: the loop of every simulation that runs the real
  runners and drivers in one process (the fault suite, the soak with faults).
* :class:`PtySimulator` serves the modems of a network on pseudo-terminals (``os.openpty``) and,
  optionally, TCP ports, in real time (or scaled by ``speed``): what ``coex modem-sim`` runs, and
  what WHOI's ``acomms`` library is pointed at in the interop tests.

Simplifications (documented in ``docs/micromodem.md``): mini-packets (pings, acknowledgements,
the rate-0 cycle-init) travel as one-frame rate-0 packets of the channel; uplink polls (``$CCCYC``
with a third-party SRC) are refused with ``$CAERR``.

The modem lives in :mod:`.simmodem`, the network, its clock and :class:`SimLoop` in
:mod:`.simnetwork`, the pseudo-terminal server in :mod:`.simpty`; this module gathers them (import
them from here).
"""

from __future__ import annotations

from .simmodem import DEFAULT_NVRAM, FIRMWARE_VERSION, SimulatedModem
from .simnetwork import ModemNetwork, NetworkClock, SimLoop
from .simpty import PtySimulator

__all__ = ["SimulatedModem", "ModemNetwork", "NetworkClock", "PtySimulator", "SimLoop", "DEFAULT_NVRAM",
           "FIRMWARE_VERSION"]
