"""What an input adapter is: something that reads the vehicle's own middleware (a directory, a
file, a bag, LCM, MAVLink, NMEA ...) and gives the daemon *items* to feed the modalities.

An adapter is registered under the entry-point group ``coex.inputs`` (its name is what a
configuration file's ``[[inputs]] type = "..."`` gives), exactly as third parties register
theirs. The daemon builds it with its options (the TOML table without ``type``), calls
:meth:`Input.open`, then :meth:`Input.poll` often (never blocking: return what is there), and
:meth:`Input.close` on shutdown. Items go to the node through the runner, which journals them,
so a restart loses nothing.

Every input counts in :attr:`Input.counts`; its ``skipped`` key (there from the start) is the
number of items it read and could not use: a corrupt image, a message that does not decode, a
garbled line, and the items the daemon could not take from it (:meth:`Input.skip`). The vehicle's
shutdown summary gives it per input.
"""

from __future__ import annotations

import abc
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from coex_core.errors import ConfigError

__all__ = ["FEEDS", "Adapter", "Image", "Input", "InputContext", "Nav", "Points", "Samples", "check_options"]

#: what an input may feed: the bathymetry map, the image sender, time-series channels, the
#: vehicle status
FEEDS = ("bathymetry", "imagery", "timeseries", "status")


@dataclass(frozen=True)
class Points:
    """Soundings: an ``N x 3`` float array (x east, y north, z up; metres, local frame)."""

    time: float
    xyz: np.ndarray


@dataclass(frozen=True)
class Image:
    """A camera image: pixels (``H x W`` or ``H x W x 3`` uint8/uint16) or a file to read, with
    its capture time and position (local metres) when known."""

    time: float
    pixels: np.ndarray | None = None
    path: str | None = None
    x: float | None = None
    y: float | None = None


@dataclass(frozen=True)
class Samples:
    """Time-series samples of one channel (``times`` in seconds since the Unix epoch)."""

    channel: str
    times: np.ndarray
    values: np.ndarray


@dataclass(frozen=True)
class Nav:
    """Where the vehicle is. Any field may be None (unknown); an adapter that knows only some of
    them (depth from a pressure sensor, altitude from a DVL) gives those, and the daemon merges
    them into one vehicle status. ``x``/``y`` metres east/north of the origin; ``lat``/``lon``
    degrees (converted with the configured origin when x/y are not given); depth positive down;
    heading degrees clockwise from north."""

    time: float
    x: float | None = None
    y: float | None = None
    lat: float | None = None
    lon: float | None = None
    depth: float | None = None
    altitude: float | None = None
    heading: float | None = None
    speed: float | None = None
    extra: Mapping[str, float] = field(default_factory=dict)


Item = Points | Image | Samples | Nav


@dataclass(frozen=True)
class InputContext:
    """What every adapter may need from the daemon: the local origin (for lat/lon -> x/y),
    the directory relative paths are taken from, and the clock the daemon runs on."""

    origin_lat: float = 0.0
    origin_lon: float = 0.0
    base_dir: str = "."
    clock: Any = None

    def local(self, lat: float, lon: float) -> tuple[float, float]:
        """Metres east/north of the origin (equirectangular; good to a few cm over a few km)."""
        r = 6378137.0
        x = np.radians(lon - self.origin_lon) * r * np.cos(np.radians(self.origin_lat))
        y = np.radians(lat - self.origin_lat) * r
        return float(x), float(y)

    def geodetic(self, x: float, y: float) -> tuple[float, float]:
        """Latitude and longitude of a local point (the inverse of :meth:`local`)."""
        r = 6378137.0
        lat = self.origin_lat + float(np.degrees(y / r))
        lon = self.origin_lon + float(np.degrees(x / (r * np.cos(np.radians(self.origin_lat)))))
        return lat, lon


class Adapter:
    """What inputs and autonomy outputs share: a name, declared options checked by name, the
    merged ``config`` and the daemon's :class:`InputContext`."""

    #: the entry-point name
    name: ClassVar[str] = ""
    #: its options: name -> (default, one-line description); ``...`` as default = required
    options: ClassVar[Mapping[str, tuple[Any, str]]] = {}
    #: what the configuration says of it ("input", "autonomy"), and table keys that are not options
    kind: ClassVar[str] = "adapter"
    table_keys: ClassVar[tuple[str, ...]] = ("type",)

    def __init__(self, options: Mapping[str, Any], context: InputContext) -> None:
        problems = adapter_problems(type(self), options)
        if problems:
            raise ConfigError("; ".join(problems))
        self.config: dict[str, Any] = {k: v[0] for k, v in self.options.items() if v[0] is not ...}
        self.config.update(options)
        self.context = context

    @classmethod
    def check(cls, options: Mapping[str, Any]) -> list[str]:
        """Problems with ``options`` beyond unknown and missing keys (``coex config check``):
        one sentence each, naming the key. Optional."""
        return []

    @classmethod
    def paths(cls, options: Mapping[str, Any]) -> list[tuple[str, str, str]]:
        """The local files, folders and devices the adapter will open, as ``(option, path,
        kind)`` with kind ``"file"``, ``"folder"``, ``"file or folder"`` (taken from the
        configuration's directory when relative) or ``"device"`` (as given). ``coex config
        check`` warns, naming the option, about any that is not there now (it may be by the time
        the adapter opens it; a device may be plugged in later). Optional: the default is none."""
        return []

    def open(self) -> None:
        """Start (open files, sockets, subscriptions; connect)."""

    def close(self) -> None:
        """Stop and release everything."""


def adapter_problems(cls: type[Adapter], options: Mapping[str, Any]) -> list[str]:
    """Unknown and missing keys, then the adapter's own :meth:`Adapter.check`."""
    problems = [f"unknown option {k!r} for {cls.kind} {cls.name!r} (known: {', '.join(sorted(cls.options))})"
                for k in options if k not in cls.options and k not in cls.table_keys]
    problems += [f"{cls.kind} {cls.name!r} needs option {k!r} ({desc})"
                 for k, (default, desc) in cls.options.items() if default is ... and k not in options]
    if not problems:
        problems += cls.check(options)
    return problems


class Input(Adapter, abc.ABC):
    """An input adapter (see the module docstring)."""

    #: what it can feed (a subset of :data:`FEEDS`)
    feeds: ClassVar[tuple[str, ...]] = ()
    kind: ClassVar[str] = "input"
    table_keys: ClassVar[tuple[str, ...]] = ("type", "feeds")

    def __init__(self, options: Mapping[str, Any], context: InputContext) -> None:
        super().__init__(options, context)
        #: what this input counted, by name. Every input has ``skipped``: the items it read and
        #: could not use (a corrupt file, a message that does not decode, a garbled line), by
        #: itself or by the daemon (:meth:`skip`); an adapter adds its own keys with
        #: ``self.counts.update(...)`` (never replace the dict).
        self.counts: dict[str, int] = {"skipped": 0}

    def skip(self, n: int = 1) -> None:
        """Count ``n`` items read and not used: call it wherever an item is dropped (log the
        reason once, e.g. with :class:`~coex_plugins.vehicle.options.LogOnce`)."""
        self.counts["skipped"] = self.counts.get("skipped", 0) + int(n)

    @property
    def skipped(self) -> int:
        """The items skipped so far (``counts["skipped"]``)."""
        return int(self.counts.get("skipped", 0))

    @abc.abstractmethod
    def poll(self, now: float) -> list[Item]:
        """What arrived since the last call (never blocks)."""

    def next_event(self, now: float) -> float | None:
        """When this input next has something (a replayed bag's next message), or None: the
        daemon polls it at its own pace."""
        return None


def check_options(cls: type[Input], options: Mapping[str, Any]) -> list[str]:
    """Unknown and missing keys, then the adapter's own :meth:`Input.check`."""
    return adapter_problems(cls, options)
