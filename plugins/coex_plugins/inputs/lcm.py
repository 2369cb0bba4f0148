"""The ``lcm`` input: LCM channels of the vehicle's own middleware.

* ``points_channel``: ``coex.points_t`` -> :class:`~coex.Points` (bathymetry);
* ``nav_channel``: ``coex.nav_t`` -> :class:`~coex.Nav` (status; NaN fields are unknown);
* ``own``: the vehicle's own LCM types, mapped field by field with a tiny path language::

      [[inputs.own]]
      channel = "POSE"
      type = "bot_core.pose_t"
      feeds = "status"
      fields = { x = "pos[1]", y = "pos[0]", depth = "pos[2]", heading = "yaw" }
      scale = { heading = 57.29578 }

      [[inputs.own]]
      channel = "CTD"
      type = "mylcm.ctd_t"
      feeds = "timeseries"
      channels = { temperature = "temp", salinity = "sal" }

  A path is a field name, optionally indexed (``pos[2]``), possibly of a nested type
  (``pose.position.x``), with an optional leading ``-``; ``scale`` multiplies the value of a
  field (or channel) by a factor. ``feeds = "status"`` maps :class:`~coex.Nav` fields (x, y,
  lat, lon, depth, altitude, heading, speed), ``"timeseries"`` maps channel names
  (``channels``), ``"bathymetry"`` maps ``x``, ``y`` and ``z`` to arrays of equal length.
  ``type`` is the Python class lcm-gen generated (``package.module.Class`` or
  ``package.Class``), importable by the daemon. An item's time is the message's ``utime``
  (microseconds; or the field ``time`` names) when it is positive, else the time of reception.

``poll`` handles what is pending without waiting (``handle_timeout(0)`` until nothing is).
A message that does not decode, or a path that does not fit it, is logged once and skipped.
"""

from __future__ import annotations

import importlib
import logging
import math
import os
import re
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

import numpy as np

from coex import ConfigError, Input, InputContext, Item, Nav, Points, Samples

from ..options import LogOnce, Problems, check_lcm_url, check_scale, compile_path, finite, need

__all__ = ["DEFAULT_URL", "LcmInput", "compile_path", "make_nav_t"]

log = logging.getLogger(__name__)

DEFAULT_URL = "udpm://239.255.76.67:7667?ttl=0"
NAV_FIELDS = ("x", "y", "lat", "lon", "depth", "altitude", "heading", "speed")
OWN_KEYS = ("channel", "type", "feeds", "fields", "channels", "scale", "time")
OWN_FEEDS = ("status", "timeseries", "bathymetry")

_TYPE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(?:\.[A-Za-z_][A-Za-z0-9_]*)+$")


def make_nav_t(utime: int = 0, **fields: float) -> Any:
    """A ``coex.nav_t`` with every field NaN (unknown) but those given (lcm-gen's default is 0,
    which would claim the vehicle is at the origin, at the surface, heading north)."""
    from coex.lcm import nav_t

    msg = nav_t()
    msg.utime = int(utime)
    for name in NAV_FIELDS:
        setattr(msg, name, float(fields.pop(name, math.nan)))
    if fields:
        raise TypeError(f"nav_t has no field {', '.join(fields)}")
    return msg


def import_type(spec: str) -> Any:
    """The lcm-gen Python class ``package.module.Class`` or ``package.Class``."""
    module_name, _, attr = spec.rpartition(".")
    try:
        obj = getattr(importlib.import_module(module_name), attr, None)
        if obj is None or isinstance(obj, type(importlib)):
            obj = getattr(importlib.import_module(spec), attr)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"cannot import {spec!r} ({exc})") from exc
    if not callable(getattr(obj, "decode", None)):
        raise ValueError(f"{spec!r} is not an lcm-gen type (no decode)")
    return obj


def _check_own(p: Problems, who: str, options: Mapping[str, Any]) -> None:
    """Problems of the option ``own``: a list of ``{channel, type, feeds, fields or channels,
    scale}`` tables (the input's own LCM types)."""
    for key, entry in p.option_tables(who, options, "own", OWN_KEYS, hint="[[inputs.own]] or own = [{...}]"):
        for k in ("channel", "type", "feeds"):
            if not isinstance(entry.get(k), str) or not entry[k].strip():
                p.said("own", f"{who}: option '{key}.{k}' is required (a string)")
        if isinstance(entry.get("type"), str) and entry["type"].strip() and not _TYPE.match(entry["type"]):
            p.said("own", f"{who}: option '{key}.type' must be 'package.Class' or "
                            f"'package.module.Class', not {entry['type']!r}")
        feeds = entry.get("feeds")
        if isinstance(feeds, str) and feeds and feeds not in OWN_FEEDS:
            p.said("own", f"{who}: option '{key}.feeds' must be one of "
                            f"{', '.join(map(repr, OWN_FEEDS))}, not {feeds!r}")
            continue
        table = "channels" if feeds == "timeseries" else "fields"
        other = "fields" if table == "channels" else "channels"
        if other in entry:
            p.said("own", f"{who}: option '{key}.{other}' does not apply to feeds = {feeds!r} "
                            f"(use '{key}.{table}')")
        mapping = entry.get(table)
        if not isinstance(mapping, Mapping) or not mapping:
            p.said("own", f"{who}: option '{key}.{table}' is required (a table of "
                            f"{'channel' if table == 'channels' else 'field'} = \"path\")")
            mapping = {}
        wanted: tuple[str, ...] = {"status": NAV_FIELDS, "bathymetry": ("x", "y", "z")}.get(str(feeds), ())
        for field, path in mapping.items():
            if wanted and field not in wanted:
                p.said("own", f"{who}: option '{key}.{table}.{field}': not one of "
                                f"{', '.join(wanted)}")
            try:
                compile_path(path)
            except ValueError as exc:
                p.said("own", f"{who}: option '{key}.{table}.{field}': {exc}")
        if feeds == "bathymetry" and mapping and not all(c in mapping for c in "xyz"):
            p.said("own", f"{who}: option '{key}.fields' needs x, y and z for bathymetry")
        check_scale(p, who, "own", key, entry, mapping, table, "name")
        if "time" in entry:
            try:
                compile_path(entry["time"])
            except ValueError as exc:
                p.said("own", f"{who}: option '{key}.time': {exc}")


class _Own:
    """One compiled ``own`` entry."""

    def __init__(self, index: int, entry: Mapping[str, Any]) -> None:
        self.key = f"own[{index}]"
        self.channel: str = entry["channel"]
        self.type_name: str = entry["type"]
        self.feeds: str = entry["feeds"]
        table = entry["channels"] if self.feeds == "timeseries" else entry["fields"]
        scale = entry.get("scale", {})
        self.getters = {name: (*compile_path(path), float(scale.get(name, 1.0)))
                        for name, path in table.items()}
        self.time = compile_path(entry["time"]) if "time" in entry else None
        self.cls: Any = None

    def resolve(self) -> None:
        """Import the type and check the first field of every path against it."""
        try:
            self.cls = import_type(self.type_name)
        except ValueError as exc:
            raise ConfigError(f"input 'lcm': option '{self.key}.type': {exc}") from exc
        slots = getattr(self.cls, "__slots__", None)
        if slots:
            table = "channels" if self.feeds == "timeseries" else "fields"
            for name, (_, first, _) in self.getters.items():
                if first not in slots:
                    raise ConfigError(f"input 'lcm': option '{self.key}.{table}.{name}': "
                                      f"{self.type_name} has no field {first!r} (fields: {', '.join(slots)})")
            if self.time is not None and self.time[1] not in slots:
                raise ConfigError(f"input 'lcm': option '{self.key}.time': {self.type_name} has no "
                                  f"field {self.time[1]!r}")
            if self.time is None and "utime" in slots:
                self.time = compile_path("utime")


class LcmInput(Input):
    """LCM subscriptions (see the module docstring)."""

    name = "lcm"
    feeds = ("bathymetry", "status", "timeseries")
    options: ClassVar[Mapping[str, tuple[Any, str]]] = {
        "url": ("", "LCM provider URL; empty: $LCM_DEFAULT_URL, else " + DEFAULT_URL),
        "points_channel": ("", "channel of coex.points_t soundings"),
        "nav_channel": ("", "channel of coex.nav_t vehicle positions"),
        "own": ([], "the vehicle's own types: a list of {channel, type, feeds, fields | channels, "
                    "scale, time} tables"),
    }

    @classmethod
    def check(cls, options: Mapping[str, Any]) -> Problems:
        p, who = Problems(), f"input {cls.name!r}"
        for key in ("url", "points_channel", "nav_channel"):
            p.option_str(who, options, key)
        check_lcm_url(p, who, options)
        if "own" in options:
            _check_own(p, who, options)
        if not (options.get("points_channel") or options.get("nav_channel") or options.get("own")):
            p.said("", f"{who} needs at least one of the options 'points_channel', 'nav_channel', 'own'")
        return p

    def __init__(self, options: Mapping[str, Any], context: InputContext) -> None:
        super().__init__(options, context)
        self.url: str = self.config["url"] or os.environ.get("LCM_DEFAULT_URL") or DEFAULT_URL
        self.own = [_Own(i, e) for i, e in enumerate(self.config["own"])]
        self._lc: Any = None
        self._subs: list[Any] = []
        self._now = 0.0
        self._items: list[Item] = []
        self._samples: dict[str, list[tuple[float, float]]] = {}
        self._problem = LogOnce(log)
        #: messages turned into items (and, as every input, ``skipped``: messages skipped)
        self.counts.update(messages=0)

    def open(self) -> None:
        if self._lc is not None:
            return
        lcm = need("lcm", "lcm")
        from coex.lcm import nav_t, points_t

        for own in self.own:
            own.resolve()
        try:
            lc = lcm.LCM(self.url)
        except Exception as exc:
            raise ConfigError(f"input 'lcm': option 'url': cannot open {self.url!r} ({exc})") from exc
        subs = []
        if self.config["points_channel"]:
            subs.append(lc.subscribe(re.escape(self.config["points_channel"]),
                                     self._handler(points_t, self._points)))
        if self.config["nav_channel"]:
            subs.append(lc.subscribe(re.escape(self.config["nav_channel"]), self._handler(nav_t, self._nav)))
        for own in self.own:
            subs.append(lc.subscribe(re.escape(own.channel), self._handler(own.cls, self._own(own))))
        self._lc, self._subs = lc, subs

    def _handler(self, cls: Any, convert: Callable[[Any], None]) -> Callable[[str, bytes], None]:
        def handle(channel: str, data: bytes) -> None:
            try:
                convert(cls.decode(data))
                self.counts["messages"] += 1
            except Exception as exc:  # a foreign or damaged message: skip it
                self.skip()
                self._problem(f"{channel}:{type(exc).__name__}",
                              "input lcm: a message on %s skipped (%s: %s)", channel, type(exc).__name__, exc)
        return handle

    def _time(self, utime: Any) -> float:
        try:
            u = float(utime)
        except (TypeError, ValueError):
            return self._now
        return u * 1e-6 if math.isfinite(u) and u > 0 else self._now

    # ------------------------------------------------------------- message types
    def _points(self, msg: Any) -> None:
        n = int(msg.n)
        xyz = np.column_stack([np.asarray(msg.x, np.float64), np.asarray(msg.y, np.float64),
                               np.asarray(msg.z, np.float64)]) if n else np.zeros((0, 3))
        if xyz.shape != (n, 3):
            raise ValueError(f"points_t with n = {n} but arrays of {xyz.shape[0]}")
        xyz = xyz[np.isfinite(xyz).all(axis=1)]
        if len(xyz):
            self._items.append(Points(self._time(msg.utime), xyz))

    def _nav(self, msg: Any) -> None:
        self._items.append(Nav(self._time(msg.utime), **{f: finite(getattr(msg, f)) for f in NAV_FIELDS}))

    def _own(self, own: _Own) -> Callable[[Any], None]:
        def convert(msg: Any) -> None:
            t = self._time(own.time[0](msg)) if own.time is not None else self._now
            values = {name: (get(msg), factor) for name, (get, _, factor) in own.getters.items()}
            if own.feeds == "bathymetry":
                cols = [np.asarray(values[c][0], np.float64).ravel() * values[c][1] for c in "xyz"]
                if not len({len(c) for c in cols}) == 1:
                    raise ValueError(f"x, y, z of {len(cols[0])}, {len(cols[1])}, {len(cols[2])} values")
                xyz = np.column_stack(cols)
                xyz = xyz[np.isfinite(xyz).all(axis=1)]
                if len(xyz):
                    self._items.append(Points(t, xyz))
                return
            scaled: dict[str, float | None] = {}
            for name, (v, factor) in values.items():
                if isinstance(v, list | tuple | np.ndarray | bytes):
                    raise ValueError(f"{own.key}: {name!r} is {len(v)} values (index it: name[i])")
                f = finite(v)
                scaled[name] = None if f is None else f * factor
            if own.feeds == "status":
                self._items.append(Nav(t, **scaled))
            else:
                for channel, v in scaled.items():
                    if v is not None:
                        self._samples.setdefault(channel, []).append((t, v))
        return convert

    # ------------------------------------------------------------- the loop
    def poll(self, now: float, limit: int = 10000) -> list[Item]:
        """Everything pending (at most ``limit`` messages; the rest at the next call)."""
        if self._lc is None:
            self.open()
        self._now = now
        for _ in range(limit):
            try:
                if self._lc.handle_timeout(0) <= 0:
                    break
            except Exception as exc:  # the socket failed: try again at the next poll
                self._problem(f"handle:{type(exc).__name__}", "input lcm: %s: %s", self.url, exc)
                break
        items, self._items = self._items, []
        for channel, pairs in self._samples.items():
            arr = np.asarray(pairs, np.float64)
            arr = arr[np.argsort(arr[:, 0], kind="stable")]  # in time order, whatever the arrival
            items.append(Samples(channel, arr[:, 0].copy(), arr[:, 1].copy()))
        self._samples = {}
        return items

    def close(self) -> None:
        if self._lc is not None:
            for sub in self._subs:
                try:
                    self._lc.unsubscribe(sub)
                except Exception:  # closing must not fail
                    pass
            self._lc, self._subs = None, []
