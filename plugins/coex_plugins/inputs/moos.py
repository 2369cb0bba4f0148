"""The ``moos`` input: variables of a MOOS community (``docs/moos.md``).

A :class:`~coex_transports.moos.MoosClient` (pure Python, no libMOOS) registers for:

* the navigation variables (``NAV_X``, ``NAV_Y``, ``NAV_DEPTH``, ``NAV_ALTITUDE``,
  ``NAV_HEADING``, ``NAV_SPEED``, ``NAV_LAT``, ``NAV_LONG``; each renamed or switched off with
  ``nav = { x = "USM_X", lat = "" }``) -> one :class:`~coex.Nav` per poll holding the newest
  value of each (x, y metres east/north of the origin, which must be the mission's
  ``LatOrigin``/``LongOrigin``; depth positive down; heading degrees clockwise from north, as
  MOOS-IvP has them; ``lat``/``lon`` are used only when x/y are not given);
* ``channels`` (``{ MOOS_VAR = "channel" }``): numeric variables -> :class:`~coex.Samples`;
* ``image_var``: a string variable whose value is an image file path (or
  ``file=PATH,x=..,y=..,time=..``) -> :class:`~coex.Image` (the daemon reads the file);
* ``points_var``: a string variable naming a ``.npy`` / ``.csv`` point file ->
  :class:`~coex.Points`.

Items are timed with the writer's MOOS time turned back into Unix seconds: MOOS time is warped
(``MOOSTimeWarp``: a MOOS clock reads the Unix time times the warp), so the option
``time_warp`` must be the community's warp (pCoex takes it from the mission file). ``poll``
only takes what the client's thread received (never blocks); the client reconnects by itself,
so MOOSDB may start after CoEx, stop and come back. A value of the wrong type or an unreadable
file is logged once and skipped.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from coex import Image, Input, InputContext, Item, Nav, Points, Samples
from coex.options import Option, anything, flag, text

from ..options import LogOnce, Problems, moos_client, time_warp

__all__ = ["NAV_DEFAULTS", "MoosInput", "parse_server"]

log = logging.getLogger(__name__)

#: Nav field -> the MOOS variable read by default (pNodeReporter's inputs)
NAV_DEFAULTS: dict[str, str] = {
    "x": "NAV_X", "y": "NAV_Y", "depth": "NAV_DEPTH", "altitude": "NAV_ALTITUDE",
    "heading": "NAV_HEADING", "speed": "NAV_SPEED", "lat": "NAV_LAT", "lon": "NAV_LONG",
}


def parse_server(value: Any) -> tuple[str, int]:
    """``"host:port"`` -> ``(host, port)``; ValueError if it is not one."""
    if isinstance(value, str):
        host, sep, port = value.rpartition(":")
        if sep and host and port.isdigit() and 0 < int(port) <= 65535:
            return host, int(port)
    raise ValueError(f"'host:port' (e.g. 'localhost:9000'), not {value!r}")


def _var_ok(v: Any) -> bool:
    return isinstance(v, str) and not any(c.isspace() for c in v)


class MoosInput(Input):
    """MOOS variables (see the module docstring)."""

    name = "moos"
    feeds = ("status", "timeseries", "imagery", "bathymetry")
    options: ClassVar[Mapping[str, Option]] = {
        "server": text("localhost:9000", "the MOOSDB, host:port (pCoex: the mission's ServerHost:ServerPort)"),
        "name": text("pCoex_in", "MOOS client name (unique on the MOOSDB)"),
        "nav": anything({}, "navigation variables: { x = 'NAV_X', y = ..., depth, altitude, heading, speed, lat, "
                            "lon }; '' switches one off"),
        "channels": anything({}, "numeric MOOS variable -> time-series channel name"),
        "image_var": text("", "string variable whose value is an image file path"),
        "points_var": text("", "string variable whose value is a .npy / .csv point file"),
        "nav_images": flag(True, "images without a position get the newest vehicle position"),
        "time_warp": time_warp("the community's MOOSTimeWarp (pCoex: the mission's); MOOS times / warp = Unix times"),
    }

    @classmethod
    def check(cls, options: Mapping[str, Any]) -> Problems:
        p, who = Problems(), f"input {cls.name!r}"
        if "server" in options:
            try:
                parse_server(options["server"])
            except ValueError as exc:
                p.said("server", f"input 'moos': option 'server' must be {exc}")
        p.option_str(who, options, "name", nonempty=True)
        nav = options.get("nav", {})
        if not isinstance(nav, Mapping):
            p.said("nav", f"input 'moos': option 'nav' must be a table like {{ x = \"USM_X\" }}, not {nav!r}")
        else:
            for k, v in nav.items():
                if k not in NAV_DEFAULTS:
                    p.said(f"nav.{k}", f"input 'moos': nav.{k} is not a navigation field "
                                       f"(known: {', '.join(NAV_DEFAULTS)})")
                elif not _var_ok(v):
                    p.said(f"nav.{k}", f"input 'moos': nav.{k} must be a MOOS variable name (or ''), not {v!r}")
        channels = options.get("channels", {})
        if not isinstance(channels, Mapping):
            p.said("channels", f"input 'moos': option 'channels' must be a table {{ MOOS_VAR = \"channel\" }}, "
                               f"not {channels!r}")
        else:
            for k, v in channels.items():
                if not _var_ok(k) or not k:
                    p.said("channels", f"input 'moos': channels: {k!r} is not a MOOS variable name")
                if not isinstance(v, str) or not v:
                    p.said(f"channels.{k}", f"input 'moos': channels.{k} must be a channel name, not {v!r}")
        for key in ("image_var", "points_var"):
            if isinstance(options.get(key), str) and not _var_ok(options[key]):
                p.said(key, f"input 'moos': option {key!r} must be a MOOS variable name, not {options[key]!r}")
        return p

    def __init__(self, options: Mapping[str, Any], context: InputContext, client: Any = None) -> None:
        super().__init__(options, context)
        self.host, self.port = parse_server(self.config["server"])
        nav = {**NAV_DEFAULTS, **dict(self.config["nav"])}
        #: MOOS variable -> Nav field
        self.nav_vars = {var: field for field, var in nav.items() if var}
        self.channels: dict[str, str] = dict(self.config["channels"])
        self.image_var: str = self.config["image_var"]
        self.points_var: str = self.config["points_var"]
        self.client = client
        self._problem = LogOnce(log)
        self.counts.update(nav=0, samples=0, images=0, points=0)  # and skipped, as every input

    @property
    def stamp_images(self) -> bool:
        """Whether the daemon gives images without a position the newest vehicle position."""
        return bool(self.config["nav_images"])

    @property
    def variables(self) -> list[str]:
        out = [*self.nav_vars, *self.channels]
        out += [v for v in (self.image_var, self.points_var) if v]
        return list(dict.fromkeys(out))

    def open(self) -> None:
        self.client = moos_client(self.client, self.host, self.port, self.config["name"], self.variables,
                                  float(self.config["time_warp"]))

    def close(self) -> None:
        if self.client is not None:
            self.client.close()
            self.client = None

    def poll(self, now: float) -> list[Item]:
        if self.client is None:
            return []
        nav: dict[str, float] = {}
        nav_time: float | None = None
        samples: dict[str, tuple[list[float], list[float]]] = {}
        items: list[Item] = []
        warp = float(self.config["time_warp"])
        for m in self.client.fetch():
            # the writer's MOOS time, unwarped; a value without a plausible time is timed now
            t = m.time / warp if isinstance(m.time, float) and math.isfinite(m.time) else now
            t = t if t > 1e8 else now
            if m.key in self.nav_vars or m.key in self.channels:
                if not m.is_double:
                    self._skip(f"type:{m.key}", "input moos: %s is a %s, not a number: skipped", m.key,
                               "string" if m.is_string else "binary value")
                    continue
                v = float(m.value)  # type: ignore[arg-type]
                if not math.isfinite(v):
                    self._skip(f"nan:{m.key}", "input moos: %s = %s skipped", m.key, v)
                    continue
                if m.key in self.nav_vars:
                    nav[self.nav_vars[m.key]] = v
                    nav_time = t if nav_time is None else max(nav_time, t)
                if m.key in self.channels:
                    ts, vs = samples.setdefault(self.channels[m.key], ([], []))
                    ts.append(t)
                    vs.append(v)
            if m.key == self.image_var and self.image_var:
                item = self._image(m, t)
                if item is not None:
                    items.append(item)
            if m.key == self.points_var and self.points_var:
                pts = self._points(m, t)
                if pts is not None:
                    items.append(pts)
        for channel, (ts, vs) in samples.items():
            order = np.argsort(np.asarray(ts), kind="stable")
            items.append(Samples(channel, np.asarray(ts, float)[order], np.asarray(vs, float)[order]))
            self.counts["samples"] += len(ts)
        if nav:
            g = nav.get
            items.insert(0, Nav(nav_time if nav_time is not None else now, x=g("x"), y=g("y"), lat=g("lat"),
                                lon=g("lon"), depth=g("depth"), altitude=g("altitude"), heading=g("heading"),
                                speed=g("speed")))
            self.counts["nav"] += 1
        return items

    # ------------------------------------------------------------------ helpers
    def _skip(self, key: str, message: str, *args: Any) -> None:
        self.skip()
        self._problem(key, message, *args)

    def _path(self, text: str) -> Path:
        p = Path(text.strip()).expanduser()
        return p if p.is_absolute() else Path(self.context.base_dir) / p

    def _text(self, m: Any) -> str | None:
        if m.is_double:
            self._skip(f"type:{m.key}", "input moos: %s is a number, not a file name: skipped", m.key)
            return None
        value = m.value.decode("utf-8", "replace") if isinstance(m.value, bytes) else str(m.value)
        if not value.strip():
            self._skip(f"empty:{m.key}", "input moos: %s is empty: skipped", m.key)
            return None
        return value

    def _image(self, m: Any, t: float) -> Image | None:
        value = self._text(m)
        if value is None:
            return None
        fields = _fields(value)
        path = self._path(fields.get("file", value if "file" not in fields else ""))
        if not path.is_file():
            self._skip(f"missing:{path}", "input moos: image %s (from %s) does not exist: skipped", path, m.key)
            return None
        x, y = _num(fields.get("x")), _num(fields.get("y"))
        lat, lon = _num(fields.get("lat")), _num(fields.get("lon"))
        if (x is None or y is None) and lat is not None and lon is not None:
            x, y = self.context.local(lat, lon)
        when = _num(fields.get("time"))
        self.counts["images"] += 1
        return Image(when if when is not None else t, None, str(path), x, y)

    def _points(self, m: Any, t: float) -> Points | None:
        value = self._text(m)
        if value is None:
            return None
        path = self._path(value)
        try:
            from coex_plugins.bathymetry.points import iter_points

            from .points import finite_rows

            chunks = [xyz for _, xyz in iter_points(path)]
            xyz = finite_rows(np.concatenate(chunks) if chunks else np.zeros((0, 3)))
        except Exception as exc:  # a missing or damaged file never stops the vehicle
            self._skip(f"points:{path}", "input moos: point file %s (from %s) not read: %s", path, m.key, exc)
            return None
        if not len(xyz):
            self._skip(f"nopoints:{path}", "input moos: point file %s holds no finite point: skipped", path)
            return None
        self.counts["points"] += 1
        return Points(t, xyz)


def _fields(value: str) -> dict[str, str]:
    """``file=/a.png,x=1,y=2`` -> fields; a plain path -> {}."""
    if "=" not in value:
        return {}
    out: dict[str, str] = {}
    for part in value.split(","):
        k, sep, v = part.partition("=")
        if sep:
            out[k.strip().lower()] = v.strip()
    return out if "file" in out else {}


def _num(v: str | None) -> float | None:
    if v is None:
        return None
    try:
        f = float(v)
    except ValueError:
        return None
    return f if math.isfinite(f) else None
