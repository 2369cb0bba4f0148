"""Pure codec of the WHOI Micromodem / Micromodem-2 NMEA serial interface.

No ports, no clocks: text in, typed values out, and back. Used by the driver
(:mod:`.driver`), the simulator (:mod:`.simulator`) and the fuzzer (``bench/fuzz_nmea.py``).

* A sentence is ``$`` + 5-letter id (talker ``CC``/``CA``/``SN``/``UP`` + type) + ``,fields`` +
  ``*HH`` + CR LF. The checksum is the XOR of every byte strictly between ``$`` and ``*``,
  written as two uppercase hex digits (:func:`checksum`).
* :func:`parse` accepts a line with or without checksum (both WHOI and Goby hosts do), but a
  present checksum must match (either case of hex digits). Every failure raises
  :class:`NmeaError`, a :class:`~coex_core.errors.DecodeError`; nothing else escapes.
* :class:`LineSplitter` cuts a byte stream into lines, bounding its buffer and counting the
  garbage it throws away.
* Typed parsers (:func:`parse_cacst`, :func:`parse_caxst`, :func:`parse_cardp` ...) follow the field
  orders of the reference note ``micromodem.md`` §1 and raise :class:`NmeaError` on bad fields.
"""

from __future__ import annotations

import base64
import binascii
import datetime as _dt
import functools
import operator
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from coex_core.acoustic import RATES as CORE_RATES
from coex_core.acoustic import RateInfo
from coex_core.errors import DecodeError

__all__ = [
    "MAX_LINE",
    "RATES",
    "FDP_RATES",
    "NmeaError",
    "Sentence",
    "LineSplitter",
    "checksum",
    "parse",
    "format_sentence",
    "hex_field",
    "unhex_field",
    "CycleInit",
    "DataRequest",
    "RxData",
    "Ack",
    "Revision",
    "ModemError",
    "FdpFrame",
    "FdpReceive",
    "ReceiveStats",
    "TransmitStats",
    "PingReply",
    "parse_cacyc",
    "parse_cadrq",
    "parse_carxd",
    "parse_caack",
    "parse_carev",
    "parse_caerr",
    "parse_cardp",
    "parse_cacst",
    "parse_caxst",
    "parse_campr",
    "format_cacst",
    "format_caxst",
    "format_cardp",
    "hhmmss",
]

#: Longest line kept (a rate-5 ``$CARDP`` in hex is about 4.2 kB); longer lines are dropped.
MAX_LINE = 8192


class NmeaError(DecodeError):
    """A line is not a valid Micromodem NMEA sentence (or a field of it is out of range)."""


#: Legacy rates 0-6: bytes per frame and frames per packet (PA ``messageparams.Rates``): the
#: core's one rate table (:data:`coex_core.acoustic.RATES`, which adds the airtime model).
RATES: dict[int, RateInfo] = CORE_RATES

#: FDP data rates of the Micromodem-2 (PA ``FDPDataRates``).
FDP_RATES: dict[int, RateInfo] = {1: RATES[1], 3: RATES[3], 5: RATES[5]}


# ------------------------------------------------------------------------------ line level
def checksum(body: str | bytes) -> str:
    """XOR of every byte of ``body`` (the text between ``$`` and ``*``) as two uppercase hex digits."""
    data = body.encode("ascii") if isinstance(body, str) else body
    return f"{functools.reduce(operator.xor, data, 0):02X}"


@dataclass(frozen=True)
class Sentence:
    """One parsed sentence: ``talker`` (``CA``), ``kind`` (``RXD``) and the raw text fields."""

    talker: str
    kind: str
    fields: tuple[str, ...] = ()

    @property
    def ident(self) -> str:
        """The five-letter id, e.g. ``CARXD``."""
        return self.talker + self.kind

    def field(self, index: int) -> str:
        """Field ``index`` (0-based after the id); :class:`NmeaError` if missing."""
        try:
            return self.fields[index]
        except IndexError:
            raise NmeaError(f"${self.ident}: field {index + 1} missing") from None

    def integer(self, index: int, lo: int | None = None, hi: int | None = None) -> int:
        text = self.field(index)
        try:
            value = int(text, 10)
        except ValueError:
            raise NmeaError(f"${self.ident}: field {index + 1} is not an integer: {text!r}") from None
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise NmeaError(f"${self.ident}: field {index + 1} = {value} out of [{lo}, {hi}]")
        return value

    def number(self, index: int) -> float:
        text = self.field(index)
        try:
            value = float(text)
        except ValueError:
            raise NmeaError(f"${self.ident}: field {index + 1} is not a number: {text!r}") from None
        if value != value or value in (float("inf"), float("-inf")):
            raise NmeaError(f"${self.ident}: field {index + 1} is not finite: {text!r}")
        return value

    def encode(self) -> bytes:
        """The sentence as a line: ``$ID,f1,f2*HH\\r\\n``."""
        return format_sentence(self.ident, self.fields)


_TALKER_OK = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789")


def parse(line: str | bytes) -> Sentence:
    """Parse one line (with or without the CR LF); raise :class:`NmeaError` if it is not a sentence."""
    if isinstance(line, bytes | bytearray):
        try:
            text = bytes(line).decode("ascii")
        except UnicodeDecodeError:
            raise NmeaError("line is not ASCII") from None
    elif isinstance(line, str):
        text = line
    else:
        raise NmeaError(f"a line is str or bytes, not {type(line).__name__}")
    text = text.strip("\r\n")
    if len(text) > MAX_LINE:
        raise NmeaError(f"line of {len(text)} characters is longer than {MAX_LINE}")
    if not text.startswith("$"):
        raise NmeaError("line does not start with '$'")
    if not text.isascii() or not text.isprintable():
        raise NmeaError("line holds non-printable characters")
    body = text[1:]
    star = body.rfind("*")
    if star >= 0:
        given = body[star + 1:]
        body = body[:star]
        if len(given) != 2:
            raise NmeaError(f"checksum {given!r} is not two hex digits")
        if given.upper() != checksum(body):
            raise NmeaError(f"checksum {given} does not match {checksum(body)}")
    if "*" in body or "$" in body:
        raise NmeaError("stray '*' or '$' inside the sentence")
    parts = body.split(",")
    ident = parts[0]
    if len(ident) != 5 or any(c not in _TALKER_OK for c in ident):
        raise NmeaError(f"sentence id {ident!r} is not five upper-case letters")
    return Sentence(ident[:2], ident[2:], tuple(parts[1:]))


def format_sentence(ident: str, fields: Iterable[object] = ()) -> bytes:
    """Build a line ``$IDENT,f1,...*HH\\r\\n``; booleans are written as 0/1, never ``False``."""
    out = []
    for f in fields:
        if isinstance(f, bool):
            out.append("1" if f else "0")
        else:
            text = str(f)
            if any(c in text for c in ",*$\r\n"):
                raise ValueError(f"field {text!r} holds a reserved character")
            out.append(text)
    body = ",".join([ident, *out])
    return f"${body}*{checksum(body)}\r\n".encode("ascii")


def hex_field(data: bytes) -> str:
    """Payload as lowercase hex (what both reference hosts send)."""
    return data.hex()


def unhex_field(text: str, *, ident: str = "?", allow_base64: bool = False) -> bytes:
    """Decode a hex payload field (either case); with ``allow_base64`` fall back to base64."""
    try:
        return bytes.fromhex(text)
    except ValueError:
        if allow_base64:
            try:
                return base64.b64decode(text, validate=True)
            except (binascii.Error, ValueError):
                pass
        raise NmeaError(f"${ident}: payload is not hex: {text[:40]!r}") from None


class LineSplitter:
    """Cut a byte stream into lines at CR or LF, keeping the buffer bounded.

    ``feed(data)`` returns complete non-empty lines (without terminators). Bytes that cannot
    start a sentence (anything before a ``$``) are counted in :attr:`garbage_bytes` and dropped
    (this also strips a Hydroid ``#M<id>`` prefix); a line longer than ``max_line`` is dropped
    and counted in :attr:`overlong`.
    """

    def __init__(self, max_line: int = MAX_LINE) -> None:
        self.max_line = max_line
        self._buf = bytearray()
        self._discarding = False
        self.garbage_bytes = 0
        self.overlong = 0

    def feed(self, data: bytes) -> list[bytes]:
        lines: list[bytes] = []
        for chunk in _split_keep(data):
            if chunk in (b"\r", b"\n"):
                if self._discarding:
                    self._discarding = False
                elif self._buf:
                    lines.append(self._take())
                continue
            if self._discarding:
                continue
            self._buf += chunk
            if len(self._buf) > self.max_line:
                self.overlong += 1
                self._buf.clear()
                self._discarding = True
        return lines

    def _take(self) -> bytes:
        raw = bytes(self._buf)
        self._buf.clear()
        start = raw.find(b"$")
        if start < 0:
            self.garbage_bytes += len(raw)
            return b""
        if start:
            self.garbage_bytes += start
        return raw[start:]

    def pending(self) -> int:
        """Bytes of an unfinished line held in the buffer."""
        return len(self._buf)


_EOL = re.compile(rb"([\r\n])")


def _split_keep(data: bytes) -> list[bytes]:
    """``data`` cut at CR and LF, keeping each terminator as its own item."""
    return [part for part in _EOL.split(data) if part]


def hhmmss(now: float) -> str:
    """``HHMMSS`` of POSIX time ``now`` (UTC)."""
    t = _dt.datetime.fromtimestamp(now, _dt.UTC)
    return t.strftime("%H%M%S")


def _utc(now: float) -> _dt.datetime:
    return _dt.datetime.fromtimestamp(now, _dt.UTC)


# ---------------------------------------------------------------------------- typed sentences
@dataclass(frozen=True)
class CycleInit:
    """``$CACYC`` / ``$CCCYC``: CMD, SRC, DEST, RATE, ACK, NFRAMES."""

    src: int
    dest: int
    rate: int
    ack: bool
    frames: int


@dataclass(frozen=True)
class DataRequest:
    """``$CADRQ``: HHMMSS, SRC, DEST, ACK, NBYTES, FRAME# (from 1)."""

    src: int
    dest: int
    ack: bool
    nbytes: int
    frame: int


@dataclass(frozen=True)
class RxData:
    """``$CARXD``: SRC, DEST, ACK, FRAME#, HEX."""

    src: int
    dest: int
    ack: bool
    frame: int
    data: bytes


@dataclass(frozen=True)
class Ack:
    """``$CAACK``: SRC (acknowledging node), DEST (us), FRAME#, ACK."""

    src: int
    dest: int
    frame: int
    ack: bool


@dataclass(frozen=True)
class Revision:
    """``$CAREV``: HHMMSS, IDENT (``AUV``, ``INIT`` ...), VERSION."""

    time: str
    ident: str
    version: str


@dataclass(frozen=True)
class ModemError:
    """``$CAERR``: HHMMSS, MODULE, ERRNUM, MESSAGE (``DATA_TIMEOUT`` puts the frame in ERRNUM)."""

    time: str
    module: str
    number: str
    message: str


@dataclass(frozen=True)
class FdpFrame:
    crc_ok: bool
    nbytes: int
    data: bytes


@dataclass(frozen=True)
class FdpReceive:
    """``$CARDP``: SRC, DEST, RATE, ACK, RESERVED, MINIFRAMES, DATAFRAMES (Goby layout)."""

    src: int
    dest: int
    rate: int
    ack: bool
    mini: tuple[FdpFrame, ...]
    data: tuple[FdpFrame, ...]


@dataclass(frozen=True)
class ReceiveStats:
    """``$CACST`` versions 0 (Micromodem-1), 6, 7 and 8 (reference note §1)."""

    version: int
    mode: int
    toa: str
    rate: int
    src: int
    dest: int
    psk_error: int
    packet_type: int
    frames: int
    bad_frames: int
    snr_rss: float
    snr_in: float
    snr_out: float
    snr_sym: float
    mse: float
    dqf: int
    doppler: float
    noise: float
    carrier: int
    bandwidth: int
    extra: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class TransmitStats:
    """``$CAXST`` versions 0 (no VERSION field), 6, 7, 8."""

    version: int
    date: str
    time: str
    mode: int
    rate: int
    src: int
    dest: int
    ack: bool
    frames_expected: int
    frames_sent: int
    packet_type: int
    nbytes: int


@dataclass(frozen=True)
class PingReply:
    """``$CAMPR``: A (pinged node), B (pinger), OWTT seconds."""

    src: int
    dest: int
    owtt: float


def _expect(s: Sentence, kind: str) -> None:
    if s.kind != kind:
        raise NmeaError(f"expected ${s.talker}{kind}, got ${s.ident}")


def _flag(s: Sentence, i: int) -> bool:
    return s.integer(i, 0, 1) == 1


def parse_cacyc(s: Sentence) -> CycleInit:
    _expect(s, "CYC")
    return CycleInit(s.integer(1, 0, 255), s.integer(2, 0, 255), s.integer(3, 0, 6), _flag(s, 4), s.integer(5, 0, 64))


def parse_cadrq(s: Sentence) -> DataRequest:
    _expect(s, "DRQ")
    return DataRequest(s.integer(1, 0, 255), s.integer(2, 0, 255), _flag(s, 3), s.integer(4, 0, 4096), s.integer(5, 1, 64))


def parse_carxd(s: Sentence) -> RxData:
    _expect(s, "RXD")
    return RxData(s.integer(0, 0, 255), s.integer(1, 0, 255), _flag(s, 2), s.integer(3, 1, 64),
                  unhex_field(s.field(4), ident=s.ident))


def parse_caack(s: Sentence) -> Ack:
    _expect(s, "ACK")
    return Ack(s.integer(0, 0, 255), s.integer(1, 0, 255), s.integer(2, 0, 64), _flag(s, 3))


def parse_carev(s: Sentence) -> Revision:
    _expect(s, "REV")
    return Revision(s.field(0), s.field(1), s.field(2) if len(s.fields) > 2 else "")


def parse_caerr(s: Sentence) -> ModemError:
    _expect(s, "ERR")
    f = list(s.fields) + [""] * 4
    return ModemError(f[0], f[1], f[2], ",".join(s.fields[3:]))


def parse_campr(s: Sentence) -> PingReply:
    _expect(s, "MPR")
    return PingReply(s.integer(0, 0, 255), s.integer(1, 0, 255), abs(s.number(2)))


def _fdp_frames(s: Sentence, text: str, base64data: bool) -> tuple[FdpFrame, ...]:
    if not text:
        return ()
    parts = text.split(";")
    if len(parts) % 3:
        raise NmeaError(f"${s.ident}: frame list is not crc;nbytes;data triples")
    out = []
    for i in range(0, len(parts), 3):
        crc, nbytes, payload = parts[i:i + 3]
        if crc not in ("0", "1") or not nbytes.isdigit() or len(nbytes) > 5 or int(nbytes) > 4096:
            raise NmeaError(f"${s.ident}: bad frame triple {crc!r};{nbytes!r}")
        if base64data:
            try:
                data = base64.b64decode(payload, validate=True)
            except (binascii.Error, ValueError):
                raise NmeaError(f"${s.ident}: frame payload is not base64") from None
        else:
            data = unhex_field(payload, ident=s.ident)
        out.append(FdpFrame(crc == "1", int(nbytes), data))
    return tuple(out)


def parse_cardp(s: Sentence, *, base64data: bool = False) -> FdpReceive:
    """Goby's 7-field layout; each list is ``crc_ok;nbytes;data`` triples joined by ``;``."""
    _expect(s, "RDP")
    if len(s.fields) != 7:
        raise NmeaError(f"$CARDP has {len(s.fields)} fields, expected 7")
    return FdpReceive(s.integer(0, 0, 255), s.integer(1, 0, 255), s.integer(2, 0, 15), _flag(s, 3),
                      _fdp_frames(s, s.field(5), base64data), _fdp_frames(s, s.field(6), base64data))


def parse_cacst(s: Sentence) -> ReceiveStats:
    """Versions 6, 7 (30+ fields) and 8 (34 fields); a first field below 6 is the Micromodem-1
    layout (no VERSION field, 29 fields)."""
    _expect(s, "CST")
    first = s.integer(0, 0)
    if first >= 6:
        version, o = first, 1
        if len(s.fields) < 30:
            raise NmeaError(f"$CACST version {version} has {len(s.fields)} fields, expected >= 30")
    else:
        version, o = 0, 0
        if len(s.fields) < 29:
            raise NmeaError(f"$CACST (Micromodem-1) has {len(s.fields)} fields, expected 29")
    mode = s.integer(o, 0, 9)
    toa = s.field(o + 1)
    extra: dict[str, int] = {}
    if version >= 8 and len(s.fields) >= 34:
        for i, name in enumerate(("seq", "data_rate", "data_frames", "bad_data_frames")):
            extra[name] = s.integer(30 + i)
    return ReceiveStats(
        version=version, mode=mode, toa=toa,
        rate=s.integer(o + 12, 0, 15), src=s.integer(o + 13, 0, 255), dest=s.integer(o + 14, 0, 255),
        psk_error=s.integer(o + 15, 0, 99), packet_type=s.integer(o + 16, -1, 99),
        frames=s.integer(o + 17, 0, 255), bad_frames=s.integer(o + 18, 0, 255),
        snr_rss=s.number(o + 19), snr_in=s.number(o + 20), snr_out=s.number(o + 21),
        snr_sym=s.number(o + 22), mse=s.number(o + 23), dqf=int(s.number(o + 24)),
        doppler=s.number(o + 25), noise=s.number(o + 26), carrier=s.integer(o + 27), bandwidth=s.integer(o + 28),
        extra=extra,
    )


def parse_caxst(s: Sentence) -> TransmitStats:
    """Versions 6-8 (VERSION first) and the Micromodem-1 layout (first field a ``YYYYMMDD`` date)."""
    _expect(s, "XST")
    first = s.integer(0, 0)
    if first > 19700000:
        version, o = 0, 0
    else:
        version, o = first, 1
    if len(s.fields) < o + 15:
        raise NmeaError(f"$CAXST has {len(s.fields)} fields, expected >= {o + 15}")
    return TransmitStats(
        version=version, date=s.field(o), time=s.field(o + 1), mode=s.integer(o + 3, 0, 99),
        rate=s.integer(o + 7, 0, 15), src=s.integer(o + 8, 0, 255), dest=s.integer(o + 9, 0, 255),
        ack=s.integer(o + 10, 0, 1) == 1, frames_expected=s.integer(o + 11, 0, 255),
        frames_sent=s.integer(o + 12, 0, 255), packet_type=s.integer(o + 13, -1, 99), nbytes=s.integer(o + 14, 0),
    )


# ----------------------------------------------------------------- sentences a modem writes
def format_cacst(
    now: float, *, mode: int, rate: int, src: int, dest: int, psk_error: int, packet_type: int,
    frames: int, bad_frames: int, snr_in: float, snr_out: float, doppler: float, noise: int = 70,
    carrier: int = 10000, bandwidth: int = 2000, mse: float = -10.0,
) -> bytes:
    """A version-6 ``$CACST`` (30 fields), which both reference hosts parse."""
    t = _utc(now)
    toa = t.strftime("%Y%m%d%H%M%S") + f".{t.microsecond:06d}"
    fields: list[object] = [
        6, mode, toa, 3, 120, 10, 100, 150, 0, 0, 0, 0, 0, rate, src, dest, psk_error, packet_type,
        frames, bad_frames, round(snr_in + 160), f"{snr_in:.2f}", f"{snr_out:.2f}",
        f"{snr_out:.2f}", f"{mse:.2f}", 100 if bad_frames == 0 else 60, f"{doppler:.2f}", noise,
        carrier, bandwidth,
    ]
    return format_sentence("CACST", fields)


def format_caxst(
    now: float, *, mode: int, rate: int, src: int, dest: int, ack: bool, frames_expected: int,
    frames_sent: int, packet_type: int, nbytes: int, carrier: int = 10000, bandwidth: int = 2000,
) -> bytes:
    """A version-6 ``$CAXST`` (16 fields)."""
    t = _utc(now)
    fields: list[object] = [
        6, t.strftime("%Y%m%d"), t.strftime("%H%M%S") + f".{t.microsecond // 100:04d}", 3, mode, 0,
        bandwidth, carrier, rate, src, dest, ack, frames_expected, frames_sent, packet_type, nbytes,
    ]
    return format_sentence("CAXST", fields)


def format_cardp(src: int, dest: int, rate: int, ack: bool, mini: Sequence[FdpFrame],
                 data: Sequence[FdpFrame]) -> bytes:
    def join(frames: Sequence[FdpFrame]) -> str:
        return ";".join(f"{int(f.crc_ok)};{f.nbytes};{f.data.hex()}" for f in frames)

    return format_sentence("CARDP", [src, dest, rate, ack, 0, join(mini), join(data)])
