"""Sans-I/O host driver of a WHOI Micromodem / Micromodem-2.

:class:`MicromodemDriver` never touches a port or a clock: the caller feeds it the bytes read
from the modem with :meth:`~MicromodemDriver.feed` and the current time ``now`` (POSIX seconds,
real or simulated), calls :meth:`~MicromodemDriver.poll` for its timers, and writes whatever
:meth:`~MicromodemDriver.data_to_send` returns to the modem. The serial transport
(:mod:`.transport`) and the in-process simulator (:mod:`.simulator`) run this same code.

What it does (sentence orders from the reference note ``micromodem.md`` §1, §3, §5):

* **Startup** with echo-and-retry: ``$CCCFG`` CST, XST, the user's NVRAM items, SRC, REV, RXP
  (+ ``recv.base64data`` for base64 FDP), then the clock (``$CCTMS`` on a Micromodem-2, ``$CCCLK``
  on a Micromodem-1). Every command waits for its echo; it is resent after ``reply_timeout``
  up to ``retries`` times, and abandoned at once on ``$CAERR,...,NMEA``. A keep-alive
  (``$CCTMQ,0`` / ``$CCCFQ,SRC``) goes out every ``keepalive`` seconds.
* **Transmit**, one packet at a time: the legacy cycle (``$CCCYC``, one ``$CCTXD`` per ``$CADRQ``,
  done at ``$CATXF``) or Micromodem-2 FDP (``$CCTDP``, done at ``$CATXF``). A packet that fails
  (``DATA_TIMEOUT``, ``$CAXST`` mode 4, a modem reboot, no ``$CATXF`` within ``tx_timeout``) is
  retried up to ``max_attempts`` times, then reported as a :class:`TxFailed` event.
* **Receive**: each good ``$CARXD`` frame and each ``crc_ok`` FDP data frame of ``$CARDP`` is
  delivered at once, so the good frames of a packet with bad ones are never lost; ``$CAMSG,BAD_CRC``
  and failed FDP frames are counted. ``$CACST`` (versions 0, 6, 7, 8) becomes link statistics and a
  :class:`~coex_core.messages.LinkStatus`; ``$CAACK``, ``$CAXST``, ``$CAREV`` (``INIT`` = reboot:
  the startup runs again), ``$CAERR`` and ``$CAMPR`` (ping) are handled too.
* Lines with a bad checksum, malformed fields or garbage are counted and dropped; :meth:`feed`
  never raises.

The frames are carried as they are: the CoEx frame format is self-delimiting, so the driver
never depends on the frame length a modem reports (some firmware pads frames with zeros).
"""

from __future__ import annotations

import datetime as _dt
import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from coex_core.errors import ConfigError, TransportError
from coex_core.messages import LinkStatus
from coex_core.timefmt import to_stamp

from . import nmea
from .events import (
    Acked,
    DriverConfig,
    Event,
    ModemErrorEvent,
    PingResult,
    Rebooted,
    ReceivedFrame,
    TxDone,
    TxFailed,
)
from .nmea import FDP_RATES, RATES, NmeaError, Sentence

__all__ = [
    "DriverConfig",
    "MicromodemDriver",
    "ReceivedFrame",
    "TxDone",
    "TxFailed",
    "Acked",
    "PingResult",
    "Rebooted",
    "ModemErrorEvent",
]


# ---------------------------------------------------------------------------------- internals
@dataclass
class _Packet:
    frames: tuple[bytes, ...]
    rate: int
    dest: int
    ack: bool
    fdp: bool
    attempts: int = 0


@dataclass
class _Command:
    """A command that waits for its echo (and is resent without one)."""

    build: Callable[[float], bytes]
    expect: str  # sentence id of the echo, e.g. CACFG
    match: Callable[[Sentence], bool]
    retry: bool = True
    tries: int = 0
    deadline: float = 0.0
    align: bool = False  # send 50 ms after the top of a second (clock set, as goby3 does)
    on_done: Callable[[float], None] | None = None
    on_fail: Callable[[float, str], None] | None = None


@dataclass
class _RxPacket:
    src: int
    dest: int
    rate: int
    frames: int
    next_frame: int = 1


@dataclass
class _Stats:
    lines: int = 0
    bad_checksum: int = 0
    malformed: int = 0
    unknown: int = 0
    handler_errors: int = 0  # bugs, not bad input: should stay 0 (bench/fuzz_nmea.py checks)
    garbage_bytes: int = 0
    overlong: int = 0
    packets_sent: int = 0
    frames_sent: int = 0
    tx_retries: int = 0
    tx_failed: int = 0
    packets_received: int = 0
    frames_received: int = 0
    bad_frames: int = 0
    packet_timeouts: int = 0
    acks: int = 0
    reboots: int = 0
    modem_errors: int = 0
    command_retries: int = 0
    command_failures: int = 0
    pings: int = 0
    last_snr_in: float | None = None
    last_snr_out: float | None = None
    last_doppler: float | None = None
    last_cst_mode: int | None = None
    last_owtt: float | None = None
    firmware_version: str | None = None
    last_error: str | None = None


def _iso(now: float) -> str:
    return _dt.datetime.fromtimestamp(now, _dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def _clock_fields(now: float) -> list[object]:
    t = _dt.datetime.fromtimestamp(now, _dt.UTC)
    return [t.year, t.month, t.day, t.hour, t.minute, t.second]


class MicromodemDriver:
    """The host side of one modem: sentences in, sentences out, frames and events out."""

    def __init__(self, config: DriverConfig | None = None) -> None:
        self.config = config or DriverConfig()
        self._splitter = nmea.LineSplitter()
        self._out = bytearray()
        self._commands: deque[_Command] = deque()
        self._current_cmd: _Command | None = None
        self._started = False
        self._ready = False
        self._resume_at: float | None = None
        self._singles: deque[bytes] = deque()
        self._packets: deque[_Packet] = deque()
        self._tx: _Packet | None = None
        self._tx_state = "idle"  # idle | wait_cyc | drq | wait_tdp | air
        self._tx_deadline = 0.0
        self._tx_failed_reason: str | None = None
        self._tx_drq_seen = False
        self._rx: _RxPacket | None = None
        self._received: deque[ReceivedFrame] = deque()
        self._link_status: LinkStatus | None = None
        self._last_keepalive: float | None = None
        self.last_heard: float | None = None
        self.events: deque[Event] = deque(maxlen=10000)
        self.config_values: dict[str, str] = {}
        self._s = _Stats()

    # ---------------------------------------------------------------------------- host API
    @property
    def mtu(self) -> int:
        return self.config.mtu

    @property
    def ready(self) -> bool:
        """True once the startup sequence has finished (packets wait until then)."""
        return self._ready

    @property
    def idle(self) -> bool:
        """Nothing queued and nothing being transmitted."""
        return self._tx is None and not self._packets and not self._singles

    def start(self, now: float) -> None:
        """Queue the startup sequence (call once, after opening the port)."""
        self._started = True
        self._ready = False
        self._commands.clear()
        self._current_cmd = None
        c = self.config
        items: list[tuple[str, str]] = []
        if c.reset_nvram:
            items.append(("ALL", "0"))
        items += [("CST", "1"), ("XST", "1"), *c.nvram, ("SRC", str(c.src)), ("REV", "1"), ("RXP", "1")]
        if c.base64 and c.firmware == "mm2":
            items.append(("recv.base64data", "1"))
        for name, value in items:
            self._commands.append(self._cfg_command(name, value))
        if c.firmware == "mm2":
            self._commands.append(_Command(
                build=lambda t: nmea.format_sentence("CCCFQ", ["info.firmware_version"]),
                expect="CACFG", match=lambda s: bool(s.fields) and s.fields[0] == "info.firmware_version"))
        if c.set_clock:
            if c.firmware == "mm2":
                self._commands.append(_Command(
                    build=lambda t: nmea.format_sentence("CCTMS", [_iso(t + 1.0), 0]),
                    expect="CATMS", match=lambda s: True, align=True))
            else:
                self._commands.append(_Command(
                    build=lambda t: nmea.format_sentence("CCCLK", _clock_fields(t + 1.0)),
                    expect="CACLK", match=lambda s: True, align=True))
        self._last_keepalive = now
        self._next_command(now)

    def feed(self, data: bytes, now: float) -> None:
        """Bytes read from the modem. Never raises: bad lines are counted and dropped."""
        for line in self._splitter.feed(bytes(data)):
            if not line:
                continue
            self._s.lines += 1
            try:
                sentence = nmea.parse(line)
            except NmeaError as exc:
                if "checksum" in str(exc):
                    self._s.bad_checksum += 1
                else:
                    self._s.malformed += 1
                continue
            self.last_heard = now
            try:
                self._handle(sentence, now)
            except NmeaError as exc:
                self._s.malformed += 1
                self._s.last_error = str(exc)
            except Exception as exc:  # last line of defence: a bad line never stops the link
                self._s.handler_errors += 1
                self._s.last_error = f"{type(exc).__name__} handling {line[:40]!r}: {exc}"
        self._s.garbage_bytes = self._splitter.garbage_bytes
        self._s.overlong = self._splitter.overlong
        self._pump(now)

    def poll(self, now: float) -> None:
        """Run the timers (retries, keep-alive, transmit timeout) and start queued packets."""
        cmd = self._current_cmd
        if cmd is not None and now >= cmd.deadline:
            if cmd.tries == 0:
                self._send_command(cmd, now)
            elif cmd.retry and cmd.tries <= self.config.retries:
                self._s.command_retries += 1
                self._send_command(cmd, now)
            else:
                self._command_failed(cmd, now, "no echo")
        if self._tx is not None and self._tx_state != "idle" and self._current_cmd is None \
                and now >= self._tx_deadline:
            self._fail_tx(now, f"no $CATXF within {self.config.tx_timeout} s")
        if self._resume_at is not None and now >= self._resume_at:
            self._resume_at = None
            self.start(now)
        if (self._ready and self._tx is None and self._current_cmd is None
                and self._last_keepalive is not None and now - self._last_keepalive >= self.config.keepalive):
            self._last_keepalive = now
            if self.config.firmware == "mm2":
                self._write(nmea.format_sentence("CCTMQ", [0]))
            else:
                self._write(nmea.format_sentence("CCCFQ", ["SRC"]))
        self._pump(now)

    def next_deadline(self) -> float | None:
        """The earliest time :meth:`poll` has something to do (``None``: nothing scheduled)."""
        times = []
        if self._current_cmd is not None:
            times.append(self._current_cmd.deadline)
        if self._tx is not None and self._tx_state != "idle" and self._current_cmd is None:
            times.append(self._tx_deadline)
        if self._resume_at is not None:
            times.append(self._resume_at)
        if (self._ready and self._tx is None and self._current_cmd is None
                and self._last_keepalive is not None):
            times.append(self._last_keepalive + self.config.keepalive)
        return min(times) if times else None

    def data_to_send(self) -> bytes:
        """Bytes to write to the modem (drains the output buffer)."""
        out = bytes(self._out)
        self._out.clear()
        return out

    def send_frame(self, frame: bytes) -> None:
        """Queue one frame at the configured rate; queued frames share packets."""
        self._check_frame(frame, self.config.rate)
        self._singles.append(bytes(frame))

    def send_packet(
        self, frames: Sequence[bytes], rate: int | None = None, *, dest: int | None = None,
        ack: bool | None = None, fdp: bool | None = None,
    ) -> None:
        """Queue one multi-frame packet (for the channel manager): at most the rate's frame count
        of frames, each at most the rate's frame size."""
        c = self.config
        rate = c.rate if rate is None else rate
        fdp = (c.mode == "fdp") if fdp is None else fdp
        table = FDP_RATES if fdp else RATES
        if rate not in table:
            raise ConfigError(f"rate {rate} is not valid ({'FDP' if fdp else 'legacy'} rates: {sorted(table)})")
        frames = tuple(bytes(f) for f in frames)
        if not 1 <= len(frames) <= table[rate].frames:
            raise TransportError(f"a rate-{rate} packet holds 1..{table[rate].frames} frames, got {len(frames)}")
        for f in frames:
            self._check_frame(f, rate)
        self._packets.append(_Packet(frames, rate, c.dest if dest is None else dest,
                                     c.ack if ack is None else ack, fdp))

    def ping(self, dest: int, now: float) -> None:
        """Two-way ping (``$CCMPC``); the travel time arrives as a :class:`PingResult` event."""
        self._s.pings += 1
        self._write(nmea.format_sentence("CCMPC", [self.config.src, dest]))

    def receive(self) -> ReceivedFrame | None:
        """The next received frame, or ``None``."""
        return self._received.popleft() if self._received else None

    @property
    def failed_count(self) -> int:
        """Packets given up after ``max_attempts`` (each also a :class:`TxFailed` event)."""
        return self._s.tx_failed

    @property
    def received_count(self) -> int:
        """Frames delivered since the start (good ``$CARXD`` / FDP data frames)."""
        return self._s.frames_received

    def pending_received(self) -> int:
        return len(self._received)

    def link_status(self) -> LinkStatus | None:
        """The latest receive statistics as a :class:`~coex_core.messages.LinkStatus`."""
        return self._link_status

    def stats(self) -> dict[str, Any]:
        """Counters and the latest link statistics (SNR, Doppler, bad frames ...)."""
        out = dict(vars(self._s))
        out["ready"] = self._ready
        out["queued_frames"] = len(self._singles) + sum(len(p.frames) for p in self._packets)
        out["transmitting"] = self._tx is not None
        return out

    # ------------------------------------------------------------------------- commands
    def _cfg_command(self, name: str, value: str) -> _Command:
        def done(now: float) -> None:
            self.config_values[name] = value

        return _Command(
            build=lambda t: nmea.format_sentence("CCCFG", [name, value]),
            expect="CACFG", match=lambda s: bool(s.fields) and s.fields[0] == name, on_done=done)

    def _send_command(self, cmd: _Command, now: float) -> None:
        cmd.tries += 1
        cmd.deadline = now + self.config.reply_timeout
        self._write(cmd.build(now))

    def _next_command(self, now: float) -> None:
        if self._current_cmd is not None:
            return
        if self._commands:
            cmd = self._current_cmd = self._commands.popleft()
            if cmd.align:
                # goby3: the time goes out 50-100 ms after the top of a second, as the next second
                top = math.floor(now)
                cmd.deadline = top + 0.05 if now - top <= 0.05 else top + 1.05
            else:
                self._send_command(cmd, now)
        elif self._started and not self._ready and self._resume_at is None:
            self._ready = True

    def _command_done(self, now: float) -> None:
        cmd = self._current_cmd
        self._current_cmd = None
        if cmd is not None and cmd.on_done is not None:
            cmd.on_done(now)
        self._next_command(now)

    def _command_failed(self, cmd: _Command, now: float, reason: str) -> None:
        self._current_cmd = None
        self._s.command_failures += 1
        self._s.last_error = f"{cmd.expect}: {reason}"
        if cmd.on_fail is not None:
            cmd.on_fail(now, reason)
        self._next_command(now)

    # ------------------------------------------------------------------------- transmit
    def _check_frame(self, frame: bytes, rate: int) -> None:
        if not isinstance(frame, bytes | bytearray):
            raise TypeError("a frame is bytes")
        if not frame:
            raise TransportError("an empty frame cannot be sent (a blank $CCTXD means 'no data')")
        if len(frame) > RATES[rate].frame_bytes:
            from coex_core.errors import FrameTooLarge

            raise FrameTooLarge(f"frame of {len(frame)} B exceeds the rate-{rate} frame of {RATES[rate].frame_bytes} B")

    def _pump(self, now: float) -> None:
        if not self._ready or self._tx is not None or self._current_cmd is not None:
            return
        if self._packets:
            packet = self._packets.popleft()
        elif self._singles:
            c = self.config
            table = FDP_RATES if c.mode == "fdp" else RATES
            n = table[c.rate].frames
            frames = tuple(self._singles.popleft() for _ in range(min(n, len(self._singles))))
            packet = _Packet(frames, c.rate, c.dest, c.ack, c.mode == "fdp")
        else:
            return
        self._start_tx(packet, now)

    def _start_tx(self, packet: _Packet, now: float) -> None:
        self._tx = packet
        packet.attempts += 1
        self._tx_failed_reason = None
        self._tx_drq_seen = False
        c = self.config
        if packet.fdp:
            self._tx_state = "wait_tdp"
            payload = _fdp_payload(packet.frames, RATES[packet.rate].frame_bytes)
            if len(payload) % 2 and _odd_fdp_bug(self._s.firmware_version):
                payload += b"\x00"  # goby3 fe462bff: firmware 2.0.x < 35490 mishandles odd lengths
            line = nmea.format_sentence("CCTDP", [packet.dest, packet.rate, 0, 0, payload.hex()])
            cmd = _Command(build=lambda t: line, expect="CATDP", match=lambda s: True,
                           on_done=self._tx_accepted, on_fail=self._tx_rejected)
        else:
            self._tx_state = "wait_cyc"
            cyc = [0, c.src, packet.dest, packet.rate, int(packet.ack), len(packet.frames)]
            line = nmea.format_sentence("CCCYC", cyc)

            def match(s: Sentence) -> bool:
                try:
                    ci = nmea.parse_cacyc(s)
                except NmeaError:
                    return False
                return (ci.src, ci.dest, ci.rate, ci.frames) == (c.src, packet.dest, packet.rate, len(packet.frames))

            cmd = _Command(build=lambda t: line, expect="CACYC", match=match,
                           on_done=self._tx_accepted, on_fail=self._tx_rejected)
        self._tx_deadline = now + c.tx_timeout
        self._current_cmd = cmd
        self._send_command(cmd, now)

    def _tx_accepted(self, now: float) -> None:
        self._tx_state = "drq" if self._tx is not None and not self._tx.fdp else "air"
        self._tx_deadline = now + self.config.tx_timeout

    def _tx_rejected(self, now: float, reason: str) -> None:
        self._fail_tx(now, f"modem did not accept the packet ({reason})")

    def _finish_tx(self, now: float) -> None:
        packet = self._tx
        if packet is None:
            return
        if self._tx_failed_reason is not None:
            self._fail_tx(now, self._tx_failed_reason)
            return
        self._tx = None
        self._tx_state = "idle"
        self._s.packets_sent += 1
        self._s.frames_sent += len(packet.frames)
        self.events.append(TxDone(packet.frames, packet.rate, packet.dest, now))
        self._pump(now)

    def _fail_tx(self, now: float, reason: str) -> None:
        packet = self._tx
        self._tx = None
        self._tx_state = "idle"
        self._tx_failed_reason = None
        if self._current_cmd is not None and self._current_cmd.expect in ("CACYC", "CATDP"):
            self._current_cmd = None
            self._next_command(now)
        if packet is None:
            return
        if packet.attempts < self.config.max_attempts:
            self._s.tx_retries += 1
            self._packets.appendleft(packet)
        else:
            self._s.tx_failed += 1
            self._s.last_error = reason
            self.events.append(TxFailed(packet.frames, packet.rate, packet.dest, reason, now))
        self._pump(now)

    # -------------------------------------------------------------------------- receive
    def _handle(self, s: Sentence, now: float) -> None:
        if s.talker != "CA":
            if s.talker in ("CC", "SN", "UP", "GP"):
                return  # our own echo on a loop-back line, navigation output ...
            self._s.unknown += 1
            return
        cmd = self._current_cmd
        if cmd is not None and s.ident == cmd.expect and cmd.match(s):
            self._command_done(now)
            if s.kind == "CFG":
                self._on_cfg(s, now)
            return
        handler = _HANDLERS.get(s.kind)
        if handler is None:
            self._s.unknown += 1
            return
        handler(self, s, now)

    def _on_cyc(self, s: Sentence, now: float) -> None:
        ci = nmea.parse_cacyc(s)
        if ci.src == self.config.src:
            return  # a remote poll of us, or a stale echo: CADRQs are answered as they come
        self._rx = _RxPacket(ci.src, ci.dest, ci.rate, ci.frames)
        self._s.packets_received += 1

    def _on_drq(self, s: Sentence, now: float) -> None:
        drq = nmea.parse_cadrq(s)
        packet = self._tx
        if (packet is not None and not packet.fdp and self._tx_state == "wait_cyc"
                and (drq.src, drq.dest) == (self.config.src, packet.dest)
                and self._current_cmd is not None and self._current_cmd.expect == "CACYC"):
            self._command_done(now)  # the $CACYC echo was lost on the serial line: the request says it all
        if packet is None or packet.fdp or self._tx_state not in ("drq", "air"):
            # remote poll or stale request: a blank frame suppresses further requests
            self._write(nmea.format_sentence("CCTXD", [drq.src, drq.dest, int(drq.ack), ""]))
            return
        data = packet.frames[drq.frame - 1] if drq.frame <= len(packet.frames) else b""
        self._tx_drq_seen = True
        self._tx_deadline = now + self.config.tx_timeout
        self._write(nmea.format_sentence("CCTXD", [self.config.src, packet.dest, int(packet.ack), data.hex()]))

    def _on_txf(self, s: Sentence, now: float) -> None:
        packet = self._tx
        if packet is None or self._tx_state not in ("drq", "air"):
            return
        if not packet.fdp and packet.rate == 0 and not self._tx_drq_seen:
            return  # rate 0: the cycle-init left as its own FSK mini-packet; data comes next
        self._finish_tx(now)

    def _on_txp(self, s: Sentence, now: float) -> None:
        if self._tx is not None and self._tx_state in ("drq", "air"):
            self._tx_state = "air"
            self._tx_deadline = now + self.config.tx_timeout

    def _on_xst(self, s: Sentence, now: float) -> None:
        xst = nmea.parse_caxst(s)
        if xst.mode == 4 and self._tx is not None:
            self._tx_failed_reason = "DATA_TIMEOUT (CAXST mode 4)"

    def _on_rxd(self, s: Sentence, now: float) -> None:
        rx = nmea.parse_carxd(s)
        if self._rx is not None:
            self._rx.next_frame = rx.frame + 1
        if not rx.data:
            return  # blank frame: the sender had no more data
        self._deliver(ReceivedFrame(rx.data, rx.src, rx.dest, self._rx.rate if self._rx else -1, rx.frame, now))

    def _on_msg(self, s: Sentence, now: float) -> None:
        kind = s.field(0).upper().replace(" ", "_")
        if kind == "BAD_CRC":
            self._s.bad_frames += 1
            if self._rx is not None:
                self._rx.next_frame += 1
        elif kind == "PACKET_TIMEOUT":
            self._s.packet_timeouts += 1

    def _on_rdp(self, s: Sentence, now: float) -> None:
        rdp = nmea.parse_cardp(s, base64data=self.config.base64)
        self._s.packets_received += 1
        for i, f in enumerate(rdp.data, start=1):
            if not f.crc_ok:
                self._s.bad_frames += 1
            elif f.data:
                self._deliver(ReceivedFrame(f.data, rdp.src, rdp.dest, rdp.rate, i, now, fdp=True))
        self._s.bad_frames += sum(1 for f in rdp.mini if not f.crc_ok)

    def _on_cst(self, s: Sentence, now: float) -> None:
        cst = nmea.parse_cacst(s)
        self._rx = None
        st = self._s
        st.last_cst_mode = cst.mode
        if cst.mode == 2:
            st.packet_timeouts += 1
            snr = doppler = None
        else:
            snr, doppler = cst.snr_out, cst.doppler
            st.last_snr_in, st.last_snr_out, st.last_doppler = cst.snr_in, cst.snr_out, cst.doppler
        status = LinkStatus(
            stamp=to_stamp(now), link=self.config.link, frames=min(cst.frames, 63),
            bad_frames=min(cst.bad_frames, 63),
            snr=None if snr is None else min(50.0, max(-20.0, round(snr * 2) / 2)),
            doppler=None if doppler is None else min(12.7, max(-12.7, round(doppler, 1))),
        )
        self._link_status = status
        self.events.append(status)

    def _on_ack(self, s: Sentence, now: float) -> None:
        ack = nmea.parse_caack(s)
        if ack.dest not in (self.config.src, 0):
            return
        self._s.acks += 1
        self.events.append(Acked(ack.src, ack.frame, now))

    def _on_rev(self, s: Sentence, now: float) -> None:
        rev = nmea.parse_carev(s)
        if rev.ident.upper() == "INIT":
            self._s.reboots += 1
            self.events.append(Rebooted(now))
            self._rx = None
            self._ready = False
            self._current_cmd = None
            self._commands.clear()
            self._resume_at = now + self.config.reboot_pause
            if self._tx is not None:
                self._fail_tx(now, "modem rebooted")
        elif rev.version:
            self._s.firmware_version = rev.version

    def _on_err(self, s: Sentence, now: float) -> None:
        err = nmea.parse_caerr(s)
        self._s.modem_errors += 1
        self._s.last_error = f"{err.module},{err.number},{err.message}"
        self.events.append(ModemErrorEvent(err.module, err.number, err.message, now))
        if err.module.upper() == "DATA_TIMEOUT":
            if self._tx is not None:
                self._tx_failed_reason = f"DATA_TIMEOUT on frame {err.number}"
            return
        cmd = self._current_cmd
        if cmd is not None:
            if err.module.upper() == "NMEA":
                self._command_failed(cmd, now, f"modem did not understand it ({err.message})")
            elif cmd.expect in ("CACYC", "CATDP"):
                self._command_failed(cmd, now, f"modem error {err.module} {err.message}")

    def _on_cfg(self, s: Sentence, now: float) -> None:
        if len(s.fields) >= 2:
            self.config_values[s.fields[0]] = s.fields[1]
            if s.fields[0] == "info.firmware_version" and s.fields[1]:
                self._s.firmware_version = s.fields[1]

    def _on_mpr(self, s: Sentence, now: float) -> None:
        reply = nmea.parse_campr(s)
        self._s.last_owtt = reply.owtt
        self.events.append(PingResult(reply.src, reply.owtt, now))

    def _on_ignore(self, s: Sentence, now: float) -> None:
        return

    def _deliver(self, frame: ReceivedFrame) -> None:
        self._s.frames_received += 1
        self._received.append(frame)
        self.events.append(frame)

    def _write(self, line: bytes) -> None:
        self._out += line


def _odd_fdp_bug(version: str | None) -> bool:
    """Whether Micromodem-2 firmware ``version`` (``2.0.27087``) needs even-length FDP payloads."""
    if not version:
        return False
    try:
        parts = [int(p) for p in version.strip().lstrip("v").split(".")]
    except ValueError:
        return False
    return len(parts) >= 3 and parts[0] == 2 and parts[1] == 0 and parts[2] < 35490


def _fdp_payload(frames: Sequence[bytes], frame_bytes: int) -> bytes:
    """Frames laid on the modem's frame grid: every frame but the last padded to the frame size,
    so each CoEx frame rides in its own modem frame with its own CRC."""
    parts = [f.ljust(frame_bytes, b"\x00") for f in frames[:-1]]
    parts.append(frames[-1])
    return b"".join(parts)


_HANDLERS: dict[str, Callable[[MicromodemDriver, Sentence, float], None]] = {
    "CYC": MicromodemDriver._on_cyc,
    "DRQ": MicromodemDriver._on_drq,
    "TXF": MicromodemDriver._on_txf,
    "TXP": MicromodemDriver._on_txp,
    "XST": MicromodemDriver._on_xst,
    "RXD": MicromodemDriver._on_rxd,
    "MSG": MicromodemDriver._on_msg,
    "RDP": MicromodemDriver._on_rdp,
    "CST": MicromodemDriver._on_cst,
    "ACK": MicromodemDriver._on_ack,
    "REV": MicromodemDriver._on_rev,
    "ERR": MicromodemDriver._on_err,
    "CFG": MicromodemDriver._on_cfg,
    "MPR": MicromodemDriver._on_mpr,
    "TXD": MicromodemDriver._on_ignore,
    "TDP": MicromodemDriver._on_ignore,
    "RXP": MicromodemDriver._on_ignore,
    "MPC": MicromodemDriver._on_ignore,
    "MPA": MicromodemDriver._on_ignore,
    "TMQ": MicromodemDriver._on_ignore,
    "TMS": MicromodemDriver._on_ignore,
    "CLK": MicromodemDriver._on_ignore,
    "MSC": MicromodemDriver._on_ignore,
}
