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
* :class:`SimLoop` drives :class:`~coex_transports.runner.Runner` objects over a network, with
  timed callbacks, on the network's clock: the loop of every simulation that runs the real
  runners and drivers in one process (the fault suite, the soak with faults).
* :class:`PtySimulator` serves the modems of a network on pseudo-terminals (``os.openpty``) and,
  optionally, TCP ports, in real time (or scaled by ``speed``): what ``coex modem-sim`` runs, and
  what WHOI's ``acomms`` library is pointed at in the interop tests.

Simplifications (documented in ``docs/micromodem.md``): mini-packets (pings, acknowledgements,
the rate-0 cycle-init) travel as one-frame rate-0 packets of the channel; uplink polls (``$CCCYC``
with a third-party SRC) are refused with ``$CAERR``.
"""

from __future__ import annotations

import datetime as _dt
import errno
import functools
import heapq
import itertools
import math
import os
import select
import selectors
import socket
import threading
import time
import tty
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from coex_core.acoustic import RATES as AIR_RATES
from coex_core.acoustic import AcousticChannel, Arrival
from coex_core.errors import ConfigError, TransportError
from coex_core.loopback import SimClock

from . import nmea
from .nmea import FDP_RATES, RATES, FdpFrame, NmeaError, Sentence

__all__ = ["SimulatedModem", "ModemNetwork", "NetworkClock", "PtySimulator", "SimLoop", "DEFAULT_NVRAM",
           "FIRMWARE_VERSION"]

#: Reported by the simulated modems: a Micromodem-2 firmware without the odd-length FDP bug.
FIRMWARE_VERSION = "2.0.35490"

#: NVRAM of a freshly reset simulated modem (names as the Micromodem uses them).
DEFAULT_NVRAM: dict[str, str] = {
    "SRC": "1", "CST": "0", "XST": "0", "REV": "0", "RXP": "0", "ASD": "0", "AGN": "250",
    "DTO": "5", "CTO": "10", "PTO": "30", "CRL": "50", "MCM": "1", "BND": "3",
    "info.firmware_version": FIRMWARE_VERSION, "info.part_number": "201005",
    "psk.packet.mod_hdr_version": "1", "recv.base64data": "0", "uart1.bitrate": "19200",
}

_PACKET_TYPE = {"fsk": 1, "fsk_mini": 2, "psk": 3, "psk_mini": 4, "fdp": 5}
_REV_PERIOD = 10.0


@dataclass
class _Meta:
    """What rode on one channel transmission (the channel only carries frame bytes)."""

    kind: str  # data | ci | fdp | ping | pong | ack
    src_id: int
    dest: int
    rate: int
    ack: bool = False
    nframes: int = 0
    frame_sizes: tuple[int, ...] = ()
    acked: tuple[int, ...] = ()


@dataclass
class _TxCycle:
    src: int
    dest: int
    rate: int
    ack: bool
    nframes: int
    frames: list[bytes] = field(default_factory=list)
    next_frame: int = 1


class SimulatedModem:
    """One simulated Micromodem-2 (sans-I/O; driven by its :class:`ModemNetwork`)."""

    def __init__(self, node: int, network: ModemNetwork, *, snr: float = 15.0, doppler: float = 0.0) -> None:
        self.node = node
        self.network = network
        self.nvram = dict(DEFAULT_NVRAM)
        self.nvram["SRC"] = str(node)
        self.snr = snr
        self.doppler = doppler
        self._splitter = nmea.LineSplitter()
        self._out = bytearray()
        self._timers: list[tuple[float, int, Callable[[float], None]]] = []
        self._seq = itertools.count()
        self._cycle: _TxCycle | None = None
        self._drq_deadline: float | None = None
        self._air_until = -math.inf
        self._next_rev: float | None = None
        self._tdp_uid = 0
        self.host_lines: list[bytes] = []  # every sentence the host wrote (for tests and logs)
        self.keep_host_lines = 1000
        self.errors = 0
        self.orphan = False  # its host went away: output is discarded
        self._detected: set[int] = set()  # packets whose $CARXP went out at their first bit

    # -------------------------------------------------------------------------- identity
    @property
    def id(self) -> int:
        try:
            return int(self.nvram.get("SRC", self.node))
        except ValueError:
            return self.node

    def _on(self, name: str) -> bool:
        return self.nvram.get(name, "0") == "1"

    # -------------------------------------------------------------------------- host side
    def feed(self, data: bytes, now: float) -> None:
        for line in self._splitter.feed(bytes(data)):
            if not line:
                continue
            if len(self.host_lines) < self.keep_host_lines:
                self.host_lines.append(line)
            try:
                s = nmea.parse(line)
            except NmeaError:
                self.errors += 1
                self._emit("CAERR", [nmea.hhmmss(now), "NMEA", 1, "bad sentence"])
                continue
            try:
                self._command(s, now)
            except NmeaError as exc:
                self.errors += 1
                self._emit("CAERR", [nmea.hhmmss(now), "NMEA", 2, str(exc).replace(",", ";")[:60]])

    def data_to_send(self) -> bytes:
        out = bytes(self._out)
        self._out.clear()
        return out

    def next_deadline(self) -> float | None:
        times = [t for t, _, _ in self._timers[:1]]
        if self._drq_deadline is not None:
            times.append(self._drq_deadline)
        if self._next_rev is not None:
            times.append(self._next_rev)
        return min(times) if times else None

    def poll(self, now: float) -> None:
        while self._timers and self._timers[0][0] <= now:
            t, _, action = heapq.heappop(self._timers)
            action(t)
        if self._drq_deadline is not None and now >= self._drq_deadline:
            self._data_timeout(now)
        if self._next_rev is not None and now >= self._next_rev:
            if self._on("REV"):
                self._emit("CAREV", [nmea.hhmmss(now), "AUV", FIRMWARE_VERSION])
                self._next_rev = now + _REV_PERIOD
            else:
                self._next_rev = None

    def busy(self) -> bool:
        return bool(self._timers) or self._cycle is not None

    def reboot(self, now: float) -> None:
        """Power-cycle: in-progress work is lost; the modem reports ``$CAREV,...,INIT``."""
        self._timers.clear()
        self._cycle = None
        self._drq_deadline = None
        self._emit("CAREV", [nmea.hhmmss(now), "INIT", FIRMWARE_VERSION])
        self._next_rev = now + _REV_PERIOD if self._on("REV") else None

    def _emit(self, ident: str, fields: Sequence[object]) -> None:
        self._out += nmea.format_sentence(ident, fields)

    def _emit_raw(self, line: bytes) -> None:
        self._out += line

    def _at(self, t: float, action: Callable[[float], None]) -> None:
        heapq.heappush(self._timers, (t, next(self._seq), action))

    # ---------------------------------------------------------------------------- commands
    def _command(self, s: Sentence, now: float) -> None:
        if s.talker != "CC":
            raise NmeaError(f"${s.ident} is not a host command")
        handler = getattr(self, "_cc_" + s.kind.lower(), None)
        if handler is None:
            self._emit("CAERR", [nmea.hhmmss(now), "NMEA", 3, f"unknown command {s.ident}"])
            return
        handler(s, now)

    def _cc_cfg(self, s: Sentence, now: float) -> None:
        name, value = s.field(0), s.field(1)
        if name == "ALL" and value == "0":
            self.nvram = dict(DEFAULT_NVRAM)
            self.nvram["SRC"] = str(self.node)
        else:
            if name not in self.nvram and not name.isupper() and "." not in name:
                raise NmeaError(f"unknown setting {name}")
            if name == "SRC":
                s.integer(1, 0, 127)
            self.nvram[name] = value
        self._emit("CACFG", [name, value])
        if name == "REV" and value == "1" and self._next_rev is None:
            self._next_rev = now + _REV_PERIOD

    def _cc_cfq(self, s: Sentence, now: float) -> None:
        name = s.field(0)
        if name in ("ALL", "TOP"):
            for k, v in self.nvram.items():
                self._emit("CACFG", [k, v])
        elif name in self.nvram:
            self._emit("CACFG", [name, self.nvram[name]])
        else:
            self._emit("CAERR", [nmea.hhmmss(now), "CFG", 4, f"unknown setting {name}"])

    def _cc_clk(self, s: Sentence, now: float) -> None:
        fields = [s.integer(i) for i in range(6)]
        self._emit("CACLK", fields)

    def _cc_tms(self, s: Sentence, now: float) -> None:
        self._emit("CATMS", [0, s.field(0)])

    def _cc_tmq(self, s: Sentence, now: float) -> None:
        t = _dt.datetime.fromtimestamp(now, _dt.UTC)
        self._emit("CATMQ", [t.strftime("%Y-%m-%dT%H:%M:%S.") + f"{t.microsecond:06d}Z", 0, 0])

    def _cc_msc(self, s: Sentence, now: float) -> None:
        self._emit("CAMSC", list(s.fields))

    def _cc_cyc(self, s: Sentence, now: float) -> None:
        src, dest, rate = s.integer(1, 0, 127), s.integer(2, 0, 127), s.integer(3, 0, 6)
        ack, nframes = s.integer(4, 0, 1) == 1, s.integer(5, 0, 64)
        if self._cycle is not None or now < self._air_until:
            self._emit("CAERR", [nmea.hhmmss(now), "CYC", 5, "modem busy"])
            return
        if src != self.id:
            self._emit("CAERR", [nmea.hhmmss(now), "CYC", 6, "uplink polls are not simulated"])
            return
        nframes = min(max(nframes, 1), RATES[rate].frames)
        self._emit("CACYC", list(s.fields))
        self._cycle = _TxCycle(src, dest, rate, ack, nframes)
        if rate == 0:
            # the cycle-init leaves first as its own FSK mini-packet
            meta = _Meta("ci", src, dest, 0, ack, nframes)
            end = self._transmit(meta, [bytes(2)], 0, now)
            self._at(end, lambda t: self._ci_sent(t))
        else:
            self._request(now)

    def _ci_sent(self, now: float) -> None:
        self._emit("CATXF", [])
        cyc = self._cycle
        if cyc is None:
            return
        self._xst(now, mode=0, rate=0, src=cyc.src, dest=cyc.dest, ack=cyc.ack, expected=1, sent=1,
                  ptype=_PACKET_TYPE["fsk_mini"], nbytes=0)
        self._request(now)

    def _request(self, now: float) -> None:
        cyc = self._cycle
        assert cyc is not None
        self._emit("CADRQ", [nmea.hhmmss(now), cyc.src, cyc.dest, int(cyc.ack), RATES[cyc.rate].frame_bytes,
                             cyc.next_frame])
        self._drq_deadline = now + float(self.nvram.get("DTO", "5") or 5)

    def _cc_txd(self, s: Sentence, now: float) -> None:
        cyc = self._cycle
        data = nmea.unhex_field(s.field(3), ident=s.ident)
        self._emit("CATXD", list(s.fields))
        if cyc is None or self._drq_deadline is None:
            return  # not asked for: the real modem echoes and ignores it
        if len(data) > RATES[cyc.rate].frame_bytes:
            data = data[:RATES[cyc.rate].frame_bytes]
        self._drq_deadline = None
        if data:
            cyc.frames.append(data)
        if data and len(cyc.frames) < cyc.nframes:
            cyc.next_frame += 1
            self._request(now)
        else:
            self._send_cycle(now)

    def _data_timeout(self, now: float) -> None:
        cyc = self._cycle
        self._drq_deadline = None
        if cyc is None:
            return
        self._emit("CAERR", [nmea.hhmmss(now), "DATA_TIMEOUT", cyc.next_frame, "host did not answer CADRQ"])
        if cyc.frames:
            self._send_cycle(now, mode=4)
            return
        self._cycle = None
        self._emit("CATXP", [])
        self._emit("CATXF", [])
        self._xst(now, mode=4, rate=cyc.rate, src=cyc.src, dest=cyc.dest, ack=cyc.ack, expected=cyc.nframes,
                  sent=0, ptype=_PACKET_TYPE["psk"], nbytes=0)

    def _send_cycle(self, now: float, mode: int = 0) -> None:
        cyc = self._cycle
        assert cyc is not None
        self._cycle = None
        frames = cyc.frames or [b""]
        meta = _Meta("data", cyc.src, cyc.dest, cyc.rate, cyc.ack, cyc.nframes, tuple(len(f) for f in frames))
        self._emit("CATXP", [])
        end = self._transmit(meta, frames, cyc.rate, now)
        ptype = _PACKET_TYPE["fsk"] if cyc.rate == 0 else _PACKET_TYPE["psk"]
        nbytes = sum(len(f) for f in cyc.frames)

        def done(t: float) -> None:
            self._emit("CATXF", [])
            self._xst(t, mode=mode, rate=cyc.rate, src=cyc.src, dest=cyc.dest, ack=cyc.ack,
                      expected=cyc.nframes, sent=len(cyc.frames), ptype=ptype, nbytes=nbytes)

        self._at(end, done)

    def _cc_tdp(self, s: Sentence, now: float) -> None:
        dest, rate = s.integer(0, 0, 127), s.integer(1, 0, 15)
        ack, reserved = s.integer(2, 0, 1), s.field(3)
        if rate not in FDP_RATES:
            self._emit("CAERR", [nmea.hhmmss(now), "TDP", 7, f"rate {rate} is not an FDP rate"])
            return
        payload = nmea.unhex_field(s.field(4), ident=s.ident)
        info = FDP_RATES[rate]
        if not payload or len(payload) > info.max_bytes:
            self._emit("CAERR", [nmea.hhmmss(now), "TDP", 8, f"payload of {len(payload)} B"])
            return
        if self._cycle is not None or now < self._air_until:
            self._emit("CAERR", [nmea.hhmmss(now), "TDP", 5, "modem busy"])
            return
        self._tdp_uid = (self._tdp_uid + 1) % 256
        self._emit("CATDP", [0, self._tdp_uid, dest, rate, ack, reserved, "", ""])
        fb = info.frame_bytes
        frames = [payload[i:i + fb] for i in range(0, len(payload), fb)]
        meta = _Meta("fdp", self.id, dest, rate, False, len(frames), tuple(len(f) for f in frames))
        self._emit("CATXP", [])
        end = self._transmit(meta, frames, rate, now)

        def done(t: float) -> None:
            self._emit("CATXF", [])
            self._xst(t, mode=0, rate=rate, src=self.id, dest=dest, ack=False, expected=len(frames),
                      sent=len(frames), ptype=_PACKET_TYPE["fdp"], nbytes=len(payload))

        self._at(end, done)

    def _cc_mpc(self, s: Sentence, now: float) -> None:
        src, dest = s.integer(0, 0, 127), s.integer(1, 0, 127)
        if now < self._air_until or self._cycle is not None:
            self._emit("CAERR", [nmea.hhmmss(now), "MPC", 5, "modem busy"])
            return
        self._emit("CAMPC", [src, dest])
        self._emit("CATXP", [])
        end = self._transmit(_Meta("ping", self.id, dest, 0), [bytes(2)], 0, now)

        def done(t: float) -> None:
            self._emit("CATXF", [])
            self._xst(t, mode=0, rate=0, src=src, dest=dest, ack=False, expected=1, sent=1,
                      ptype=_PACKET_TYPE["fsk_mini"], nbytes=0)

        self._at(end, done)

    def _xst(self, now: float, *, mode: int, rate: int, src: int, dest: int, ack: bool, expected: int,
             sent: int, ptype: int, nbytes: int) -> None:
        if self._on("XST"):
            self._emit_raw(nmea.format_caxst(now, mode=mode, rate=rate, src=src, dest=dest, ack=ack,
                                             frames_expected=expected, frames_sent=sent,
                                             packet_type=ptype, nbytes=nbytes))

    def _transmit(self, meta: _Meta, frames: list[bytes], rate: int, now: float) -> float:
        end = self.network._transmit(self, meta, frames, rate, now)
        self._air_until = max(self._air_until, end)
        return end

    # ---------------------------------------------------------------------------- acoustic
    def _cst(self, now: float, a: Arrival, meta: _Meta, *, frames: int, bad: int, ptype: int,
             mode: int | None = None) -> None:
        if not self._on("CST"):
            return
        distance = self.network.channel.distance(a.src, a.dst)
        snr_in = self.snr - 20.0 * math.log10(max(distance, 100.0) / 1000.0)
        snr_out = snr_in + 6.0 - 3.0 * bad
        if mode is None:
            mode = 1 if bad else 0
        self._emit_raw(nmea.format_cacst(
            now, mode=mode, rate=meta.rate, src=meta.src_id, dest=meta.dest, psk_error=3 if bad else 0,
            packet_type=ptype, frames=frames, bad_frames=bad, snr_in=snr_in, snr_out=snr_out,
            doppler=self.doppler))

    def _rxp(self, meta: _Meta) -> None:
        """``$CARXP`` for this packet, unless it was already reported at its first bit."""
        if id(meta) in self._detected:
            self._detected.discard(id(meta))
            return
        if self._on("RXP"):
            self._emit("CARXP", [])

    def _addressed(self, meta: _Meta) -> bool:
        if meta.kind in ("ping", "pong", "ack"):
            return meta.dest == self.id
        return self._for_me(meta)

    def detect(self, meta: _Meta, now: float) -> None:
        """The first bit of a packet reaches this modem: ``$CARXP`` (unless it is transmitting)."""
        if now < self._air_until or not self._addressed(meta):
            return
        if self._on("RXP"):
            self._emit("CARXP", [])
        self._detected.add(id(meta))
        if len(self._detected) > 64:
            self._detected.clear()

    def _for_me(self, meta: _Meta) -> bool:
        return meta.dest in (self.id, 0)

    def on_arrival(self, a: Arrival, meta: _Meta, now: float) -> None:
        if a.cause or (all(f is None for f in a.frames) and meta.kind in ("ping", "pong", "ack", "ci")):
            if a.cause and self._for_me(meta):
                # the packet was destroyed at this receiver (collision, or we were transmitting)
                self._rxp(meta)
                self._cst(now, a, meta, frames=0, bad=0, ptype=_PACKET_TYPE["psk"], mode=2)
            return
        kind = meta.kind
        if kind == "data":
            self._rx_data(a, meta, now)
        elif kind == "ci":
            if not self._for_me(meta):
                return
            self._rxp(meta)
            self._emit("CACYC", [0, meta.src_id, meta.dest, 0, int(meta.ack), meta.nframes])
            self._cst(now, a, meta, frames=1, bad=0, ptype=_PACKET_TYPE["fsk_mini"])
        elif kind == "fdp":
            self._rx_fdp(a, meta, now)
        elif kind == "ping":
            if meta.dest != self.id:
                return
            self._rxp(meta)
            self._emit("CAMPA", [meta.src_id, meta.dest])
            self._cst(now, a, meta, frames=1, bad=0, ptype=_PACKET_TYPE["fsk_mini"])
            self._emit("CATXP", [])
            end = self._transmit(_Meta("pong", self.id, meta.src_id, 0), [bytes(2)], 0, now)
            self._at(end, lambda t: self._emit("CATXF", []))
        elif kind == "pong":
            if meta.dest != self.id:
                return
            self._rxp(meta)
            owtt = self.network.channel.delay(a.src, a.dst)
            self._emit("CAMPR", [meta.src_id, meta.dest, f"{owtt:.4f}"])
            self._cst(now, a, meta, frames=1, bad=0, ptype=_PACKET_TYPE["fsk_mini"])
        elif kind == "ack":
            if meta.dest != self.id:
                return
            self._rxp(meta)
            for f in meta.acked:
                self._emit("CAACK", [meta.src_id, meta.dest, f, 1])
            self._cst(now, a, meta, frames=1, bad=0, ptype=_PACKET_TYPE["fsk_mini"])

    def _rx_data(self, a: Arrival, meta: _Meta, now: float) -> None:
        if not self._for_me(meta):
            return
        self._rxp(meta)
        if meta.rate != 0:
            self._emit("CACYC", [0, meta.src_id, meta.dest, meta.rate, int(meta.ack), meta.nframes])
        good: list[int] = []
        bad = 0
        for i, f in enumerate(a.frames, start=1):
            if f is None:
                bad += 1
                self._emit("CAMSG", ["BAD_CRC", i])
            else:
                good.append(i)
                self._emit("CARXD", [meta.src_id, meta.dest, int(meta.ack), i, f.hex()])
        ptype = _PACKET_TYPE["fsk"] if meta.rate == 0 else _PACKET_TYPE["psk"]
        self._cst(now, a, meta, frames=len(a.frames), bad=bad, ptype=ptype)
        if meta.ack and good and meta.dest == self.id:
            self._emit("CATXP", [])
            ack_meta = _Meta("ack", self.id, meta.src_id, 0, acked=tuple(good))
            end = self._transmit(ack_meta, [bytes(2)], 0, now)

            def done(t: float) -> None:
                self._emit("CATXF", [])
                self._xst(t, mode=0, rate=0, src=self.id, dest=meta.src_id, ack=False, expected=1, sent=1,
                          ptype=_PACKET_TYPE["fsk_mini"], nbytes=0)

            self._at(end, done)

    def _rx_fdp(self, a: Arrival, meta: _Meta, now: float) -> None:
        if not self._for_me(meta):
            return
        self._rxp(meta)
        frames = []
        for f, size in zip(a.frames, meta.frame_sizes):
            frames.append(FdpFrame(True, len(f), f) if f is not None else FdpFrame(False, size, b""))
        bad = sum(1 for f in frames if not f.crc_ok)
        if self._on("recv.base64data"):
            import base64

            def join(fs: Sequence[FdpFrame]) -> str:
                return ";".join(f"{int(x.crc_ok)};{x.nbytes};{base64.b64encode(x.data).decode()}" for x in fs)

            self._emit("CARDP", [meta.src_id, meta.dest, meta.rate, 0, 0, "", join(frames)])
        else:
            self._emit_raw(nmea.format_cardp(meta.src_id, meta.dest, meta.rate, False, (), frames))
        self._cst(now, a, meta, frames=len(frames), bad=bad, ptype=_PACKET_TYPE["fdp"])


class _Host:
    """An in-process host (driver) wired to a simulated modem's serial port: directly, or through
    a real pseudo-terminal pair (``pty=True``: the driver's bytes are written to the terminal
    side and read by the modem from the master side, and back, in the caller's thread)."""

    def __init__(self, driver: Any, modem: SimulatedModem, pty: bool = False) -> None:
        self.driver = driver
        self.modem = modem
        self.master: int | None = None
        self.slave: int | None = None
        self.path = ""
        if pty:
            self.master, self.slave = os.openpty()
            tty.setraw(self.slave)
            os.set_blocking(self.master, False)
            os.set_blocking(self.slave, False)
            self.path = os.ttyname(self.slave)

    @staticmethod
    def _pipe(src: int, dst: int, data: bytes, timeout: float = 10.0) -> bytes:
        """Write ``data`` into ``src`` and return it as it comes out at ``dst``: all of it (a raw
        terminal passes bytes one for one), however late the kernel moves it across: a read that
        finds the terminal empty waits for the rest instead of leaving it for a later call, so a
        loaded machine runs the same dive as an idle one. OSError when it does not come out."""
        got = bytearray()
        view = memoryview(data)
        poller = select.poll()
        poller.register(dst, select.POLLIN)
        deadline = time.monotonic() + timeout
        while len(got) < len(data):
            if view:
                try:
                    n = os.write(src, view[:1024])
                    view = view[n:]
                except BlockingIOError:
                    pass
            try:
                got += os.read(dst, 4096)
                continue
            except BlockingIOError:
                pass
            left = deadline - time.monotonic()
            if left <= 0:
                raise OSError(f"pseudo-terminal: {len(got)} of {len(data)} bytes came through in {timeout:g} s")
            poller.poll(min(left, 0.05 if view else left) * 1000.0)
        return bytes(got)

    def to_modem(self, data: bytes) -> bytes:
        if self.master is None or self.slave is None:
            return data
        return self._pipe(self.slave, self.master, data)

    def to_host(self, data: bytes) -> bytes:
        if self.master is None or self.slave is None:
            return data
        return self._pipe(self.master, self.slave, data)

    def close(self) -> None:
        for fd in (self.master, self.slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.master = self.slave = None


class ModemNetwork:
    """Simulated modems on one acoustic channel, run on a simulated clock.

    ``positions`` maps node id → (x, y, z) metres; each node gets a :class:`SimulatedModem`
    whose SRC is the node id. Time is POSIX seconds on ``clock`` (default start: 2025-01-01).
    """

    def __init__(
        self,
        positions: dict[int, Sequence[float]] | None = None,
        *,
        channel: AcousticChannel | None = None,
        clock: SimClock | None = None,
        snr: float = 15.0,
        doppler: float = 0.0,
        ptys: bool = False,
    ) -> None:
        #: with ``ptys``, every in-process host talks to its modem through a real pseudo-terminal
        self.ptys = ptys
        self.channel = channel or AcousticChannel()
        self.clock = clock or SimClock(1735689600.0)
        self.modems: dict[int, SimulatedModem] = {}
        #: modems whose serial cable is pulled (:meth:`unplug`)
        self.unplugged: set[int] = set()
        self._hosts: list[_Host] = []
        self._meta: list[tuple[int, float, _Meta]] = []
        positions = positions if positions is not None else {1: (0.0, 0.0, 0.0), 2: (1000.0, 0.0, 0.0)}
        for node, xyz in positions.items():
            self.add_modem(node, xyz, snr=snr, doppler=doppler)

    @property
    def now(self) -> float:
        return self.clock.now

    def add_modem(self, node: int, xyz: Sequence[float], *, snr: float = 15.0, doppler: float = 0.0) -> SimulatedModem:
        if node in self.modems:
            raise ConfigError(f"node {node} already has a modem")
        if not 1 <= node <= 127:
            raise ConfigError(f"node ids are 1..127, got {node}")
        self.channel.set_position(node, xyz)
        modem = SimulatedModem(node, self, snr=snr, doppler=doppler)
        self.modems[node] = modem
        return modem

    def attach(self, node: int, driver: Any) -> None:
        """Wire an in-process host driver (``feed``/``poll``/``data_to_send``/``next_deadline``) to
        ``node``'s modem. :class:`TransportError` while that modem is unplugged (:meth:`unplug`)."""
        if node in self.unplugged:
            raise TransportError(f"cannot open simulated modem {node}: its cable is unplugged")
        if any(h.modem.node == node for h in self._hosts):
            raise ConfigError(f"modem {node} already has a host")
        self._hosts.append(_Host(driver, self.modems[node], pty=self.ptys))
        self.modems[node].orphan = False

    def detach(self, driver: Any) -> None:
        """Unwire a host driver (its modem's output is then discarded)."""
        for h in list(self._hosts):
            if h.driver is driver:
                self._hosts.remove(h)
                h.modem.orphan = True

    def attached(self, driver: Any) -> bool:
        """Whether ``driver`` is wired to its modem (not detached, its cable not pulled)."""
        return any(h.driver is driver for h in self._hosts)

    def unplug(self, node: int) -> None:
        """Pull the serial cable of ``node``'s modem (a USB adapter unplugged, a serial-over-IP
        server gone): the host's transport raises :class:`TransportError` at its next use and
        stays dead, like a real port, and a new one cannot be opened until :meth:`plug`. The
        modem itself keeps its power and settings; what it receives meanwhile is lost."""
        self.unplugged.add(node)
        for h in list(self._hosts):
            if h.modem.node == node:
                self._hosts.remove(h)
                h.close()
                h.modem.orphan = True

    def plug(self, node: int) -> None:
        """Put ``node``'s serial cable back: a transport can be opened on its modem again."""
        self.unplugged.discard(node)

    def open_uri(self, uri: str) -> Any:
        """A ``micromodem:`` URI opened on this network instead of a serial port: the driver, with
        the URI's options, on the simulated modem of its ``src`` (the device path is only a
        name). An opener for :class:`~coex_transports.recovery.ResilientTransport`."""
        import dataclasses

        from .transport import MicromodemTransport, parse_uri

        _, _, config = parse_uri(uri)
        if config.src not in self.modems:
            raise TransportError(f"cannot open {uri}: no simulated modem {config.src}")
        return MicromodemTransport.simulated(self, config.src, **dataclasses.asdict(config))

    def transport(self, node: int, **options: Any) -> Any:
        """A :class:`~.transport.MicromodemTransport` on ``node``'s simulated modem, driven by this
        network's clock (options: those of :class:`~.driver.DriverConfig`; ``src`` defaults to
        ``node``)."""
        from .transport import MicromodemTransport

        return MicromodemTransport.simulated(self, node, **options)

    # ------------------------------------------------------------------------ simulation
    def _transmit(self, modem: SimulatedModem, meta: _Meta, frames: list[bytes], rate: int, now: float) -> float:
        end = self.channel.transmit(modem.node, frames, rate, now)
        start = end - AIR_RATES[rate].packet_airtime(len(frames))
        self._meta.append((modem.node, start, meta))
        for other in self.modems.values():
            if other is not modem:
                t = start + self.channel.delay(modem.node, other.node)
                other._at(t, functools.partial(other.detect, meta))
        return end

    def _lookup(self, a: Arrival) -> _Meta | None:
        tx_start = a.start - self.channel.delay(a.src, a.dst)
        best = None
        for node, start, meta in self._meta:
            if node == a.src and abs(start - tx_start) < 1e-6:
                best = meta
        return best

    def next_event(self) -> float | None:
        times = [self.channel.next_arrival()]
        times += [m.next_deadline() for m in self.modems.values()]
        times += [h.driver.next_deadline() for h in self._hosts]
        found = [t for t in times if t is not None]
        return min(found) if found else None

    def busy(self) -> bool:
        """Anything in flight: a packet on the channel, a modem cycle, a host transmission."""
        if self.channel.next_arrival() is not None:
            return True
        if any(m.busy() for m in self.modems.values()):
            return True
        return any(not h.driver.idle or not h.driver.ready for h in self._hosts)

    def step(self) -> None:
        """Process everything due at the current time."""
        now = self.clock.now
        for _ in range(1000):
            moved = self._exchange(now)
            for a in self.channel.poll(now):
                meta = self._lookup(a)
                modem = self.modems.get(a.dst)
                if meta is not None and modem is not None:
                    modem.on_arrival(a, meta, now)
                    moved = True
            for m in self.modems.values():
                m.poll(now)
            for h in self._hosts:
                h.driver.poll(now)
            moved = self._exchange(now) or moved
            if not moved:
                break
        for m in self.modems.values():
            if m.orphan:
                m.data_to_send()  # nobody listens on this modem's serial port any more
        self._prune(now)

    def _exchange(self, now: float) -> bool:
        moved = False
        for _ in range(1000):
            any_bytes = False
            for h in self._hosts:
                out = h.driver.data_to_send()
                if out:
                    h.modem.feed(h.to_modem(out), now)
                    any_bytes = True
                back = h.modem.data_to_send()
                if back:
                    h.driver.feed(h.to_host(back), now)
                    any_bytes = True
            if not any_bytes:
                break
            moved = True
        return moved

    def pty_paths(self) -> dict[int, str]:
        """The pseudo-terminal of each in-process host's modem (``ptys=True``)."""
        return {h.modem.node: h.path for h in self._hosts if h.path}

    def close(self) -> None:
        """Close the hosts' pseudo-terminals."""
        for h in self._hosts:
            h.close()

    def _prune(self, now: float) -> None:
        if len(self._meta) > 256:
            self._meta = [m for m in self._meta if m[1] > now - 600.0]

    def run_until(self, t: float) -> None:
        """Advance the clock to ``t``, processing every event on the way."""
        self.step()
        while True:
            nxt = self.next_event()
            if nxt is None or nxt > t:
                break
            if nxt <= self.clock.now:
                # something due now that did not clear itself: move on a hair to avoid spinning
                nxt = self.clock.now + 1e-6
                if nxt > t:
                    break
            self.clock.advance_to(nxt)
            self.step()
        self.clock.advance_to(t)
        self.step()

    def as_clock(self) -> NetworkClock:
        """A clock for :class:`coex.Runner` (``time()``/``wait_until(t)``):
        waiting runs this network, returning early when a host driver receives a frame."""
        return NetworkClock(self)

    def received_count(self) -> int:
        """Frames delivered so far to all in-process host drivers."""
        return sum(int(h.driver.received_count) for h in self._hosts)

    def run_for(self, dt: float) -> None:
        self.run_until(self.clock.now + dt)

    def run_while(self, condition: Callable[[], bool], timeout: float) -> bool:
        """Run until ``condition()`` is false or ``timeout`` simulated seconds pass; returns
        whether the condition became false."""
        deadline = self.clock.now + timeout
        self.step()
        while condition():
            nxt = self.next_event()
            if nxt is None or nxt > deadline:
                self.clock.advance_to(deadline)
                self.step()
                return not condition()
            self.clock.advance_to(max(nxt, self.clock.now + 1e-6) if nxt <= self.clock.now else nxt)
            self.step()
        return True


class NetworkClock:
    """``time()`` and ``wait_until(t)`` over a :class:`ModemNetwork` (the runner's Clock protocol)."""

    def __init__(self, network: ModemNetwork) -> None:
        self.network = network

    def time(self) -> float:
        return self.network.now

    def wait_until(self, t: float) -> None:
        net = self.network
        if t <= net.now:
            net.step()
            return
        start = net.received_count()
        net.run_while(lambda: net.received_count() == start, t - net.now)


class SimLoop:
    """:class:`~coex_transports.runner.Runner` objects over a :class:`ModemNetwork`, with timed
    callbacks, on the network's clock (each runner's clock must read that clock).

    Each pass advances the network to the next thing due (a modem or driver deadline, a node's
    next slot, a callback; at most ``max_step`` seconds on), calls the callbacks due, steps every
    runner in :attr:`runners` (a list the caller may change: a node restarted), calls each of
    :attr:`after` with the time, and lets the network take what the runners wrote. ``max_step``
    bounds the jumps for parts the loop cannot see (an autonomy's protocol timers)."""

    def __init__(self, network: ModemNetwork, runners: Sequence[Any] = (), *,
                 max_step: float | None = None) -> None:
        self.network = network
        self.runners: list[Any] = list(runners)
        self.max_step = max_step
        #: called with the time after the runners, every pass
        self.after: list[Callable[[float], Any]] = []
        self._events: list[tuple[float, int, Callable[[float], Any]]] = []
        self._count = itertools.count()
        self.steps = 0

    @property
    def now(self) -> float:
        return self.network.now

    def at(self, t: float, fn: Callable[[float], Any]) -> None:
        """Call ``fn(now)`` at time ``t`` (in the order given, for equal times)."""
        heapq.heappush(self._events, (float(t), next(self._count), fn))

    def every(self, period: float, fn: Callable[[float], Any], start: float | None = None,
              until: float | None = None) -> None:
        """Call ``fn(now)`` every ``period`` seconds from ``start`` (default: now), before ``until``."""
        if period <= 0:
            raise ConfigError("period must be positive")

        def tick(now: float) -> None:
            fn(now)
            if until is None or now + period < until:
                self.at(now + period, tick)

        self.at(self.now if start is None else start, tick)

    def run(self, until: float) -> None:
        """Run to time ``until``."""
        from ..runner import next_wakeup

        net = self.network
        while net.now < until:
            t = next_wakeup(net.now, until, self._events[0][0] if self._events else None,
                            [net.next_event(), *(r.node.next_event(net.now) for r in self.runners)],
                            started=bool(self.steps))
            if self.max_step is not None:
                t = min(t, net.now + self.max_step)
            self.step(t)

    def step(self, t: float) -> None:
        """One pass: the network to ``t``, the callbacks due, every runner, :attr:`after`."""
        net = self.network
        net.run_until(t)
        while self._events and self._events[0][0] <= net.now:
            _, _, fn = heapq.heappop(self._events)
            fn(net.now)
        for r in list(self.runners):
            r.step()
        for fn in self.after:
            fn(net.now)
        net.step()
        self.steps += 1


class PtySimulator:
    """Serve a :class:`ModemNetwork`'s modems on pseudo-terminals (and optional TCP ports).

    ``speed`` scales simulated time (2.0 = twice as fast as real time). The simulated clock
    starts at the real UTC time. Use :meth:`start` (background thread) and :meth:`stop`, or
    :meth:`serve_forever` in the foreground.
    """

    def __init__(
        self, network: ModemNetwork, *, tcp_ports: dict[int, int] | None = None, speed: float = 1.0,
        host: str = "127.0.0.1",
    ) -> None:
        if speed <= 0:
            raise ConfigError("speed must be positive")
        self.network = network
        self.speed = float(speed)
        self._sel = selectors.DefaultSelector()
        self._masters: dict[int, int] = {}
        self._slaves: dict[int, int] = {}
        self.paths: dict[int, str] = {}
        self.tcp_addresses: dict[int, tuple[str, int]] = {}
        self._listeners: dict[int, socket.socket] = {}
        self._clients: dict[int, list[socket.socket]] = {}
        self._pending: dict[int, bytearray] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        for node in network.modems:
            master, slave = os.openpty()
            tty.setraw(slave)
            os.set_blocking(master, False)
            self._masters[node] = master
            self._slaves[node] = slave
            self.paths[node] = os.ttyname(slave)
            self._pending[node] = bytearray()
            self._clients[node] = []
            self._sel.register(master, selectors.EVENT_READ, ("pty", node))
        for node, port in (tcp_ports or {}).items():
            if node not in network.modems:
                raise ConfigError(f"no modem {node} for TCP port {port}")
            srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            srv.bind((host, port))
            srv.listen(4)
            srv.setblocking(False)
            self._listeners[node] = srv
            self.tcp_addresses[node] = srv.getsockname()[:2]
            self._sel.register(srv, selectors.EVENT_READ, ("listen", node))
        self._t0 = time.monotonic()
        self._epoch = time.time()
        network.clock.advance_to(self._epoch)
        self._epoch = network.clock.now

    def sim_now(self) -> float:
        return self._epoch + (time.monotonic() - self._t0) * self.speed

    def call(self, fn: Callable[[ModemNetwork], Any]) -> Any:
        """Run ``fn(network)`` on the simulation, safely from another thread."""
        with self._lock:
            return fn(self.network)

    def start(self) -> None:
        self._thread = threading.Thread(target=self.serve_forever, name="coex-modem-sim", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        self.close()

    def close(self) -> None:
        for fd in [*self._masters.values(), *self._slaves.values()]:
            try:
                os.close(fd)
            except OSError:
                pass
        self._masters.clear()
        self._slaves.clear()
        for s in [*self._listeners.values(), *(c for cs in self._clients.values() for c in cs)]:
            s.close()
        self._listeners.clear()
        self._clients.clear()
        self._sel.close()

    def serve_forever(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                now = self.sim_now()
                self.network.run_until(max(now, self.network.clock.now))
                self._flush_out()
                nxt = self.network.next_event()
            wait = 0.05 if nxt is None else min(0.05, max(0.0, (nxt - now) / self.speed))
            try:
                events = self._sel.select(timeout=wait)
            except (OSError, ValueError):
                break
            with self._lock:
                now = max(self.sim_now(), self.network.clock.now)
                for key, _ in events:
                    kind, node = key.data
                    if kind == "listen":
                        self._accept(node)
                    elif kind == "pty":
                        self._read_pty(node, now)
                    else:
                        self._read_client(key.fileobj, node, now)  # type: ignore[arg-type]

    def _accept(self, node: int) -> None:
        try:
            conn, _ = self._listeners[node].accept()
        except OSError:
            return
        conn.setblocking(False)
        self._clients[node].append(conn)
        self._sel.register(conn, selectors.EVENT_READ, ("tcp", node))

    def _read_pty(self, node: int, now: float) -> None:
        try:
            data = os.read(self._masters[node], 4096)
        except OSError as exc:
            if exc.errno in (errno.EAGAIN, errno.EIO):
                return
            raise
        if data:
            self.network.modems[node].feed(data, now)

    def _read_client(self, conn: socket.socket, node: int, now: float) -> None:
        try:
            data = conn.recv(4096)
        except OSError:
            data = b""
        if not data:
            self._sel.unregister(conn)
            self._clients[node].remove(conn)
            conn.close()
            return
        self.network.modems[node].feed(data, now)

    def _flush_out(self) -> None:
        for node, modem in self.network.modems.items():
            out = modem.data_to_send()
            if out:
                for c in list(self._clients[node]):
                    try:
                        c.sendall(out)
                    except OSError:
                        pass
                buf = self._pending[node]
                buf += out
                if len(buf) > 1 << 16:
                    del buf[: len(buf) - (1 << 16)]  # nobody reads this pty: keep the newest
            buf = self._pending[node]
            if buf:
                try:
                    n = os.write(self._masters[node], bytes(buf))
                    del buf[:n]
                except OSError as exc:
                    if exc.errno not in (errno.EAGAIN, errno.EIO):
                        raise
