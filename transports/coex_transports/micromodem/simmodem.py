"""One simulated Micromodem-2, sans-I/O: host bytes in, host bytes out, timers run by ``now``
(see :mod:`.simulator` for what it answers and what it simplifies)."""

from __future__ import annotations

import datetime as _dt
import heapq
import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from coex_core.acoustic import Arrival

from . import nmea
from .nmea import FDP_RATES, RATES, FdpFrame, NmeaError, Sentence

__all__ = ['SimulatedModem', 'DEFAULT_NVRAM', 'FIRMWARE_VERSION']

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
    """One simulated Micromodem-2 (sans-I/O; driven by its ``network``, a
    :class:`~.simnetwork.ModemNetwork`)."""

    def __init__(self, node: int, network: Any, *, snr: float = 15.0, doppler: float = 0.0) -> None:
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
        handler = _COMMANDS.get(s.kind)
        if handler is None:
            self._emit("CAERR", [nmea.hhmmss(now), "NMEA", 3, f"unknown command {s.ident}"])
            return
        handler(self, s, now)

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


#: the host commands the simulated modem answers (``$CC<kind>``), each by its handler; any other
#: is answered with ``$CAERR`` ("unknown command")
_COMMANDS: dict[str, Callable[[SimulatedModem, Sentence, float], None]] = {
    "CFG": SimulatedModem._cc_cfg, "CFQ": SimulatedModem._cc_cfq, "CLK": SimulatedModem._cc_clk,
    "TMS": SimulatedModem._cc_tms, "TMQ": SimulatedModem._cc_tmq, "MSC": SimulatedModem._cc_msc,
    "CYC": SimulatedModem._cc_cyc, "TXD": SimulatedModem._cc_txd, "TDP": SimulatedModem._cc_tdp,
    "MPC": SimulatedModem._cc_mpc,
}
