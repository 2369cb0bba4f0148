"""USBL fixes from the ship's tracking system: NMEA-0183 sentences over its own serial line or
UDP port (not the acoustic data link), read topside by :class:`UsblInput`.

============  ==============================================================================
sentence      fix
============  ==============================================================================
``TLL``       target latitude / longitude: target number, lat, lon, name, UTC time, status
              (``L`` lost: no fix). A Water Linked Underwater GPS sends ``$RATLL``
``TTM``       tracked target: distance and bearing from the ship (true, or relative to the ship's
              heading from ``HDT``), UTC time; needs the ship's position: a ``GGA`` on the same
              line with ``gga = "ship"``
``GGA``       a position: the vehicle's (``gga = "vehicle"``, the default: a Water Linked
              Underwater GPS sends its fix as ``$GPGGA``) or the ship's (``gga = "ship"``); no
              fix (quality 0): nothing
``PSIMSSB``   Kongsberg HiPAP / HPR / cNODE positions: UTC time, transponder (``B01``), status
              ``A``; coordinates ``U`` + ``E`` (UTM easting, northing in ``utm_zone``, default the
              origin's) or ``C`` + ``N`` (north-up metres east, north of the ship's ``GGA``),
              depth, expected accuracy (m)
============  ==============================================================================

Every fix carries the time of its sentence (``hhmmss.ss`` UTC, on the day of the moment it is read,
or the day before or after when that is nearer) and is projected into the map's local frame at
``node.origin`` through pyproj (:class:`~.frame.LocalFrame`). Checksums are checked with the
project's NMEA code (:mod:`coex_plugins.inputs.nmea`, whose serial / UDP ports, retries and counts
this input shares); ``target`` keeps the fixes of one transponder or target number.
"""

from __future__ import annotations

import math
import time as _time
from collections.abc import Mapping
from typing import Any, ClassVar

from coex import InputContext, Item, Nav
from coex.options import Option, anything, flag, integer, text

from ..inputs.nmea import NmeaInput, _angle, _num, checksum
from ..options import Problems
from .frame import LocalFrame, utm_crs

__all__ = ["UsblInput", "gga_sentence", "psimssb_sentence", "resolve_time", "tll_sentence"]

DAY = 86400.0


def _hhmmss(t: float) -> str:
    tm = _time.gmtime(math.floor(t))
    return f"{tm.tm_hour:02d}{tm.tm_min:02d}{tm.tm_sec + (t - math.floor(t)):05.2f}"


def _lat(lat: float) -> tuple[str, str]:
    a = abs(lat)
    d = int(a)
    return f"{d:02d}{(a - d) * 60.0:09.6f}", "N" if lat >= 0 else "S"


def _lon(lon: float) -> tuple[str, str]:
    a = abs(lon)
    d = int(a)
    return f"{d:03d}{(a - d) * 60.0:09.6f}", "E" if lon >= 0 else "W"


def _sentence(body: str) -> str:
    return f"${body}*{checksum(body):02X}"


def tll_sentence(t: float, target: int, lat: float, lon: float, name: str = "", talker: str = "RA") -> str:
    """A ``$--TLL`` target latitude / longitude sentence of a fix at Unix time ``t``."""
    la, ns = _lat(lat)
    lo, ew = _lon(lon)
    return _sentence(f"{talker}TLL,{int(target):02d},{la},{ns},{lo},{ew},{name},{_hhmmss(t)},T,")


def gga_sentence(t: float, lat: float, lon: float, altitude: float = 0.0, talker: str = "GP") -> str:
    """A ``$--GGA`` position sentence (quality 1) at Unix time ``t``; ``altitude`` above the sea
    (negative: below)."""
    la, ns = _lat(lat)
    lo, ew = _lon(lon)
    return _sentence(f"{talker}GGA,{_hhmmss(t)},{la},{ns},{lo},{ew},1,08,1.0,{altitude:.1f},M,0.0,M,,")


def psimssb_sentence(t: float, transponder: int, x: float, y: float, depth: float, *, coordinates: str = "U",
                     orientation: str = "E", accuracy: float = 0.0) -> str:
    """A Kongsberg ``$PSIMSSB`` position at Unix time ``t``: ``coordinates`` ``U`` (UTM easting,
    northing; ``orientation`` ``E``) or ``C`` (north-up metres east, north of the ship;
    ``orientation`` ``N``)."""
    return _sentence(f"PSIMSSB,{_hhmmss(t)},B{int(transponder):02d},A,,{coordinates},{orientation},M,"
                     f"{x:.2f},{y:.2f},{depth:.1f},{accuracy:.1f},N,,")


def _seconds_of_day(value: str) -> float | None:
    v = value.strip()
    if not v:
        return None
    if len(v) < 6 or not v[:6].isdigit():
        raise ValueError(f"bad time {value!r}")
    h, m, s = int(v[:2]), int(v[2:4]), float(v[4:])
    if h > 23 or m > 59 or not 0 <= s < 61:
        raise ValueError(f"bad time {value!r}")
    return h * 3600.0 + m * 60.0 + s


def resolve_time(seconds_of_day: float, now: float) -> float:
    """The Unix time of a UTC time of day: on the day of ``now``, or the day before or after
    when that is nearer (a fix stamped 23:59:59 read at 00:00:01)."""
    day = math.floor(now / DAY) * DAY
    candidates = [day - DAY + seconds_of_day, day + seconds_of_day, day + DAY + seconds_of_day]
    return min(candidates, key=lambda c: abs(c - now))


class UsblInput(NmeaInput):
    """The ship's USBL tracking system (see the module docstring): :meth:`poll` gives one
    :class:`~coex_core.adapters.Nav` per fix, with ``time`` the fix's own, ``x``/``y`` in the local
    frame, ``lat``/``lon``, ``depth`` when the sentence says it, and ``extra``: ``target`` (the
    target number or transponder) and ``accuracy`` (m, when said)."""

    name = "usbl"
    feeds: ClassVar[tuple[str, ...]] = ()
    options: ClassVar[Mapping[str, Option]] = {
        "serial": text("", "pyserial port or URL of the tracking system's output: /dev/ttyUSB3, socket://host:port ..."),
        "baud": integer(4800, "baud rate of the serial port", unit="baud", lo=1, hi=10_000_000),
        "udp": text("", "host:port to receive its datagrams on, e.g. 0.0.0.0:10111"),
        "require_checksum": flag(True, "refuse lines without a *hh checksum"),
        "target": anything("", "keep only this target or transponder (TLL / TTM target number, PSIMSSB "
                               "transponder: 2, \"B02\"); empty: every fix"),
        "gga": text("vehicle", "what a GGA on this line is: \"vehicle\" (a USBL that sends the vehicle's "
                               "position as GGA) or \"ship\" (the ship's GPS, for TTM and relative PSIMSSB)",
                    choices=("vehicle", "ship")),
        "utm_zone": text("", "the UTM zone of PSIMSSB UTM coordinates, like \"31N\" (default: the origin's)"),
    }

    @classmethod
    def check(cls, options: Mapping[str, Any]) -> Problems:
        p, who = Problems(), f"input {cls.name!r}"
        p.option_host_port(who, options, "udp")
        if not options.get("serial") and not options.get("udp"):
            p.said("", f"{who} needs the option 'serial' or 'udp' (or both)")
        target = options.get("target", "")
        if not isinstance(target, str | int) or isinstance(target, bool):
            p.said("target", f"{who}: option 'target' must be a target number or a transponder like \"B02\"")
        zone = options.get("utm_zone", "")
        if zone:
            try:
                utm_crs(str(zone))
            except ValueError as exc:
                p.said("utm_zone", f"{who}: option 'utm_zone': {exc}")
        return p

    def __init__(self, options: Mapping[str, Any], context: InputContext) -> None:
        super().__init__(options, context)
        self.frame = LocalFrame(context.origin_lat, context.origin_lon, str(self.config["utm_zone"]) or None)
        self._target = _target_key(self.config["target"])
        #: the ship's newest position (local x, y) and heading, from GGA / HDT with gga = "ship"
        self.ship: tuple[float, float] | None = None
        self.ship_heading: float | None = None
        #: fixes given, lost or void targets, fixes of other targets
        self.counts.update(fixes=0, void=0, other_target=0)

    def udp_address(self) -> tuple[str, int] | None:
        """The address the UDP port is bound to once open (a ``udp`` of port 0 gets a free one)."""
        if self._udp is None:
            return None
        host, port = self._udp.getsockname()[:2]
        return str(host), int(port)

    def _fix(self, items: list[Item], t_day: float | None, now: float, x: float, y: float, target: str,
             depth: float | None = None, accuracy: float | None = None) -> None:
        if self._target and _target_key(target) != self._target:
            self.counts["other_target"] += 1
            return
        t = now if t_day is None else resolve_time(t_day, now)
        lat, lon = self.frame.geodetic(x, y)
        extra: dict[str, float] = {}
        digits = "".join(ch for ch in target if ch.isdigit())
        if digits:
            extra["target"] = float(int(digits))
        if accuracy:
            extra["accuracy"] = accuracy
        items.append(Nav(t, x=x, y=y, lat=lat, lon=lon, depth=depth, extra=extra))
        self.counts["fixes"] += 1

    def _sentence(self, kind: str, f: list[str], now: float, items: list[Item],
                  samples: dict[str, list[float]]) -> bool:
        """One sentence of the tracking system into fixes (False: not one this input reads)."""
        if kind == "TLL":
            status = f[8].strip().upper() if len(f) > 8 else ""
            lat, lon = _angle(f[2], f[3], 2), _angle(f[4], f[5], 3)
            if status == "L" or lat is None or lon is None:
                self.counts["void"] += 1
                return True
            x, y = self.frame.local(lat, lon)
            self._fix(items, _seconds_of_day(f[7]) if len(f) > 7 else None, now, x, y, f[1])
        elif kind == "GGA":
            quality = f[6].strip() if len(f) > 6 else ""
            lat, lon = _angle(f[2], f[3], 2), _angle(f[4], f[5], 3)
            if quality in ("", "0") or lat is None or lon is None:
                self.counts["void"] += 1
                return True
            x, y = self.frame.local(lat, lon)
            if self.config["gga"] == "ship":
                self.ship = (x, y)
                return True
            alt = _num(f, 9)
            self._fix(items, _seconds_of_day(f[1]), now, x, y, "", depth=None if alt is None else max(-alt, 0.0))
        elif kind == "HDT":
            heading = _num(f, 1)
            if heading is not None:
                self.ship_heading = heading % 360.0
        elif kind == "TTM":
            distance, bearing = _num(f, 2), _num(f, 3)
            status = f[12].strip().upper() if len(f) > 12 else ""
            if distance is None or bearing is None or status == "L" or self.ship is None:
                self.counts["void"] += 1
                return True
            if (f[4].strip().upper() if len(f) > 4 else "T") == "R":
                if self.ship_heading is None:
                    self.counts["void"] += 1
                    return True
                bearing += self.ship_heading
            unit = f[10].strip().upper() if len(f) > 10 else "N"
            metres = distance * {"K": 1000.0, "N": 1852.0, "S": 1609.344}.get(unit, 1852.0)
            b = math.radians(bearing)
            x, y = self.ship[0] + metres * math.sin(b), self.ship[1] + metres * math.cos(b)
            self._fix(items, _seconds_of_day(f[14]) if len(f) > 14 else None, now, x, y, f[1])
        elif kind == "PSIMSSB":
            if len(f) < 12 or f[3].strip().upper() != "A":
                self.counts["void"] += 1
                return True
            coords, orient = f[5].strip().upper(), f[6].strip().upper()
            east, north = _num(f, 8), _num(f, 9)
            below, accuracy = _num(f, 10), _num(f, 11)
            if east is None or north is None:
                self.counts["void"] += 1
                return True
            if coords == "U":
                x, y = self.frame.from_utm(east, north)
            elif coords == "C" and orient == "N" and self.ship is not None:
                x, y = self.ship[0] + east, self.ship[1] + north
            else:
                raise ValueError(f"PSIMSSB coordinates {coords}{orient} are not read (U+E, or C+N with the "
                                 "ship's GGA)")
            self._fix(items, _seconds_of_day(f[1]), now, x, y, f[2], depth=below, accuracy=accuracy)
        else:
            return False
        return True


def _target_key(target: Any) -> str:
    """``2``, ``"02"``, ``"B02"`` -> ``"2"``; empty -> ``""``."""
    digits = "".join(ch for ch in str(target) if ch.isdigit())
    return str(int(digits)) if digits else str(target).strip()
