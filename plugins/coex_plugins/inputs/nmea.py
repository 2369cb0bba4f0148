"""The ``nmea`` input: NMEA-0183 sentences from a serial port (any pyserial URL:
``/dev/ttyUSB2``, ``socket://host:port``, ``rfc2217://...``) and / or UDP datagrams (the usual
port is 10110).

=============  ====================================================================
sentence       item
=============  ====================================================================
GGA            Nav lat, lon (no fix: nothing)
RMC            Nav lat, lon, speed (knots -> m/s), extra ``course`` (deg; void: nothing)
HDT            Nav heading (true)
HDG            Nav heading = magnetic + deviation + variation (``variation`` option
               when the sentence has none)
HDM            Nav heading = magnetic + the ``variation`` option
DBT, DPT       depth below the transducer: Nav altitude when ``dbt_is_altitude``
               (a down-looking transducer), else Samples ``depth_below_transducer``
MTW            Samples ``water_temperature`` (deg C)
XDR            Samples, one channel per transducer name
``channels``   ``"SENTENCE.index" = "channel"``: field ``index`` (1 = the first after
               the address) of that sentence (``"VHW.5"``; or with the talker,
               ``"IIVHW.5"``) -> Samples of that channel
=============  ====================================================================

The ``*hh`` checksum is checked (a line without one is refused unless ``require_checksum`` is
false); bad lines are counted (:attr:`NmeaInput.counts`) and skipped. Items are timed when the
line arrives. A port that cannot be opened, or fails, is retried every 5 s.
"""

from __future__ import annotations

import logging
import math
import re
import socket
from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np

from coex import Input, InputContext, Item, Nav, Samples
from coex.options import Option, anything, flag, integer, number, text

from ..options import LogOnce, Problems, need

__all__ = ["NmeaError", "NmeaInput", "checksum", "parse_sentence"]

log = logging.getLogger(__name__)

KNOT = 1852.0 / 3600.0
FOOT = 0.3048
FATHOM = 1.8288
RETRY = 5.0
MAX_LINE = 1024
_CHANNEL_KEY = re.compile(r"^([A-Z0-9]{3,8})\.(\d{1,2})$")


class NmeaError(ValueError):
    """A line that is not a valid NMEA-0183 sentence."""


def checksum(body: str) -> int:
    """The XOR of the characters between ``$``/``!`` and ``*``."""
    value = 0
    for ch in body.encode("ascii", "replace"):
        value ^= ch
    return value


def parse_sentence(line: str, require_checksum: bool = True) -> list[str]:
    """The fields of a sentence, the address first (``["GPGGA", "123519", ...]``)."""
    text = line.strip()
    if text.startswith("\\"):  # NMEA 4 tag block before the sentence
        starts = [i for i in (text.find("$"), text.find("!")) if i >= 0]
        text = text[min(starts):] if starts else ""
    if not text or text[0] not in "$!":
        raise NmeaError("does not start with $ or !")
    star = text.rfind("*")
    if star >= 0:
        body, given = text[1:star], text[star + 1:]
        if len(given) != 2 or not all(c in "0123456789abcdefABCDEF" for c in given):
            raise NmeaError(f"bad checksum field {given!r}")
        if int(given, 16) != checksum(body):
            raise NmeaError(f"checksum {given} is not {checksum(body):02X}")
    elif require_checksum:
        raise NmeaError("no checksum")
    else:
        body = text[1:]
    fields = body.split(",")
    if not re.fullmatch(r"[A-Z0-9]{2,8}", fields[0]):
        raise NmeaError(f"bad address {fields[0]!r}")
    return fields


def _num(fields: list[str], i: int) -> float | None:
    if i >= len(fields) or not fields[i].strip():
        return None
    v = float(fields[i])  # ValueError: a bad line
    return v if math.isfinite(v) else None


def _angle(value: str, hemi: str, degree_digits: int) -> float | None:
    """``ddmm.mmmm`` / ``dddmm.mmmm`` with N/S/E/W -> signed degrees."""
    if not value.strip():
        return None
    head, _, _ = value.partition(".")
    if len(head) < degree_digits + 2 or not head.isdigit():
        raise ValueError(f"bad coordinate {value!r}")
    degrees = int(value[:degree_digits])
    minutes = float(value[degree_digits:])
    if not 0 <= minutes < 60:
        raise ValueError(f"bad minutes in {value!r}")
    sign = {"N": 1, "E": 1, "S": -1, "W": -1}.get(hemi.strip().upper())
    if sign is None:
        raise ValueError(f"bad hemisphere {hemi!r}")
    v = sign * (degrees + minutes / 60.0)
    if abs(v) > (90 if degree_digits == 2 else 180):
        raise ValueError(f"coordinate {value} out of range")
    return v


def _east(value: float | None, hemi: str) -> float:
    """A deviation or variation with its E/W letter, east positive."""
    if value is None:
        return 0.0
    return -value if hemi.strip().upper() == "W" else value


class NmeaInput(Input):
    """NMEA-0183 over serial and / or UDP (see the module docstring)."""

    name = "nmea"
    feeds: ClassVar[tuple[str, ...]] = ("status", "timeseries")
    options: ClassVar[Mapping[str, Option]] = {
        "serial": text("", "pyserial port or URL: /dev/ttyUSB2, socket://host:port ..."),
        "baud": integer(4800, "baud rate of the serial port", unit="baud", lo=1, hi=10_000_000),
        "udp": text("", "host:port to receive datagrams on, e.g. 0.0.0.0:10110"),
        "require_checksum": flag(True, "refuse lines without a *hh checksum"),
        "dbt_is_altitude": flag(True, "DBT / DPT depth below the transducer is the vehicle's altitude "
                                      "(a down-looking transducer)"),
        "variation": number(0.0, "magnetic variation in degrees, east positive, for HDM (and HDG "
                                 "without one)", unit="deg", lo=-180, hi=180),
        "channels": anything({}, "more time series: \"SENTENCE.field_index\" = \"channel\""),
    }

    @classmethod
    def check(cls, options: Mapping[str, Any]) -> Problems:
        p, who = Problems(), f"input {cls.name!r}"
        p.option_host_port(who, options, "udp")
        if not options.get("serial") and not options.get("udp"):
            p.said("", f"{who} needs the option 'serial' or 'udp' (or both)")
        channels = options.get("channels", {})
        if not isinstance(channels, Mapping):
            p.said("channels", f"{who}: option 'channels' must be a table of \"SENTENCE.index\" = \"channel\"")
            channels = {}
        for key, channel in channels.items():
            if not _CHANNEL_KEY.match(str(key)) or int(str(key).rpartition(".")[2]) == 0:
                p.said(f"channels.{key}", f"{who}: option 'channels.{key}': the key must be a sentence "
                                          "and a field index from 1, like \"VHW.5\" or \"IIVHW.5\"")
            if not isinstance(channel, str) or not channel.strip():
                p.said(f"channels.{key}", f"{who}: option 'channels.{key}' must be a channel name")
        return p

    @classmethod
    def paths(cls, options: Mapping[str, Any]) -> list[tuple[str, str, str]]:
        port = options.get("serial")
        return [("serial", port, "device")] if isinstance(port, str) and port.startswith("/") else []

    def __init__(self, options: Mapping[str, Any], context: InputContext) -> None:
        super().__init__(options, context)
        self.channels: dict[str, tuple[int, str]] = {}
        for key, channel in self.config.get("channels", {}).items():
            sentence, _, index = str(key).rpartition(".")
            self.channels[sentence] = (int(index), channel)
        self._serial: Any = None
        self._udp: socket.socket | None = None
        self._retry_at = {"serial": -math.inf, "udp": -math.inf}
        self._buffers = {"serial": b"", "udp": b""}
        self._problem = LogOnce(log)
        #: lines read, used, with a bad checksum, otherwise bad, of an unknown sentence; and, as
        #: every input, ``skipped``: the lines with a bad checksum or otherwise bad
        self.counts.update(lines=0, used=0, bad_checksum=0, bad=0, unknown=0)

    # ----------------------------------------------------------------- ports
    def open(self) -> None:
        self._open_ports(-math.inf)

    def _open_ports(self, now: float) -> None:
        if self.config["serial"] and self._serial is None and now >= self._retry_at["serial"]:
            serial = need("serial", "nmea")
            try:
                self._serial = serial.serial_for_url(self.config["serial"], baudrate=self.config["baud"],
                                                     timeout=0)
                log.info("input nmea: %s open", self.config["serial"])
            except Exception as exc:  # not plugged in yet: try again
                self._retry_at["serial"] = now + RETRY
                self._problem(f"open-serial:{type(exc).__name__}", "input nmea: cannot open %r (%s); "
                              "retrying every %.0f s", self.config["serial"], exc, RETRY)
        if self.config["udp"] and self._udp is None and now >= self._retry_at["udp"]:
            host, _, port = self.config["udp"].rpartition(":")
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                if hasattr(socket, "SO_REUSEPORT"):  # several listeners of one broadcast port
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
                sock.bind((host, int(port)))
                sock.setblocking(False)
                self._udp = sock
            except OSError as exc:
                sock.close()
                self._retry_at["udp"] = now + RETRY
                self._problem(f"open-udp:{exc.errno}", "input nmea: cannot receive on udp %s (%s); "
                              "retrying every %.0f s", self.config["udp"], exc, RETRY)

    def _read(self, now: float) -> dict[str, bytes]:
        data = {"serial": b"", "udp": b""}
        if self._serial is not None:
            try:
                data["serial"] = bytes(self._serial.read(65536))
            except Exception as exc:  # unplugged: reopen later
                self._problem(f"read-serial:{type(exc).__name__}", "input nmea: %s failed (%s)",
                              self.config["serial"], exc)
                self._close_serial()
                self._retry_at["serial"] = now + RETRY
        if self._udp is not None:
            chunks = []
            for _ in range(1000):
                try:
                    chunk, _addr = self._udp.recvfrom(65536)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError as exc:
                    self._problem(f"read-udp:{exc.errno}", "input nmea: udp %s: %s", self.config["udp"], exc)
                    break
                # a datagram holds whole sentences: end it as a line
                chunks.append(chunk if chunk.endswith(b"\n") else chunk + b"\n")
            data["udp"] = b"".join(chunks)
        return data

    def _close_serial(self) -> None:
        if self._serial is not None:
            try:
                self._serial.close()
            except Exception:  # closing must not fail
                pass
            self._serial = None

    def close(self) -> None:
        self._close_serial()
        if self._udp is not None:
            self._udp.close()
            self._udp = None

    # ----------------------------------------------------------------- the loop
    def poll(self, now: float) -> list[Item]:
        self._open_ports(now)
        items: list[Item] = []
        samples: dict[str, list[float]] = {}
        for source, data in self._read(now).items():
            buf = self._buffers[source] + data
            *lines, rest = buf.split(b"\n")
            if len(rest) > MAX_LINE:  # no newline in sight: noise
                self.counts["bad"] += 1
                self.skip()
                rest = b""
            self._buffers[source] = rest
            for raw in lines:
                line = raw.decode("ascii", "replace").strip()
                if not line:
                    continue
                self.counts["lines"] += 1
                self._line(line, now, items, samples)
        for channel, values in samples.items():
            items.append(Samples(channel, np.full(len(values), float(now)), np.asarray(values, np.float64)))
        return items

    def _line(self, line: str, now: float, items: list[Item], samples: dict[str, list[float]]) -> None:
        try:
            fields = parse_sentence(line, self.config["require_checksum"])
        except NmeaError as exc:
            key = "bad_checksum" if "checksum" in str(exc) else "bad"
            self.counts[key] += 1
            self.skip()
            self._problem(key, "input nmea: line skipped (%s): %r", exc, line[:100])
            return
        address = fields[0]
        kind = address[2:] if len(address) == 5 else address
        try:
            used = self._sentence(kind, fields, now, items, samples)
            extra = self.channels.get(address) or self.channels.get(kind)
            if extra is not None:
                value = _num(fields, extra[0])
                if value is not None:
                    samples.setdefault(extra[1], []).append(value)
                used = True
        except (ValueError, IndexError) as exc:
            self.counts["bad"] += 1
            self.skip()
            self._problem(f"bad:{kind}", "input nmea: %s skipped (%s): %r", kind, exc, line[:100])
            return
        self.counts["used" if used else "unknown"] += 1

    def _sentence(self, kind: str, f: list[str], now: float, items: list[Item],
                  samples: dict[str, list[float]]) -> bool:
        """Turn one known sentence into items; False when the sentence is not one of them."""
        if kind == "GGA":
            quality = f[6].strip() if len(f) > 6 else ""
            if quality in ("", "0"):
                return True  # no fix
            lat, lon = _angle(f[2], f[3], 2), _angle(f[4], f[5], 3)
            if lat is not None and lon is not None:
                items.append(Nav(now, lat=lat, lon=lon))
        elif kind == "RMC":
            if f[2].strip().upper() != "A":
                return True  # void
            lat, lon = _angle(f[3], f[4], 2), _angle(f[5], f[6], 3)
            knots, course = _num(f, 7), _num(f, 8)
            items.append(Nav(now, lat=lat, lon=lon, speed=None if knots is None else knots * KNOT,
                             extra={} if course is None else {"course": course % 360.0}))
        elif kind in ("HDT", "HDM", "HDG"):
            heading = _num(f, 1)
            if heading is None:
                return True
            if kind == "HDM":
                heading += float(self.config["variation"])
            elif kind == "HDG":
                heading += _east(_num(f, 2), f[3] if len(f) > 3 else "")
                variation = _num(f, 4)
                heading += (_east(variation, f[5] if len(f) > 5 else "") if variation is not None
                            else float(self.config["variation"]))
            items.append(Nav(now, heading=heading % 360.0))
        elif kind in ("DBT", "DPT"):
            if kind == "DBT":
                metres, feet, fathoms = _num(f, 3), _num(f, 1), _num(f, 5)
                depth = (metres if metres is not None else feet * FOOT if feet is not None
                         else fathoms * FATHOM if fathoms is not None else None)
            else:
                depth = _num(f, 1)
            if depth is None or depth < 0:
                return True
            if self.config["dbt_is_altitude"]:
                items.append(Nav(now, altitude=depth))
            else:
                samples.setdefault("depth_below_transducer", []).append(depth)
        elif kind == "MTW":
            temp = _num(f, 1)
            if temp is not None:
                samples.setdefault("water_temperature", []).append(temp)
        elif kind == "XDR":
            for i in range(1, len(f) - 3, 4):
                value, name = _num(f, i + 1), f[i + 3].strip()
                if value is not None and name:
                    samples.setdefault(name, []).append(value)
        else:
            return False
        return True
