"""What a vehicle's adapters are: *inputs* that read the vehicle's own middleware (a directory,
a file, a bag, LCM, MAVLink, NMEA, MOOS, ROS ...) and give the daemon *items* to feed the
modalities, and *autonomy outputs* that take accepted surveys to the vehicle's autonomy and
report what happened. The contracts, declared here so that a vehicle team's own adapter and the
conformance kit (``coex_conformance.InputTests``, ``AutonomyTests``) need nothing else; exported
from the :mod:`coex` facade.

An input is registered under the entry-point group ``coex.inputs`` (its name is what a
configuration file's ``[[inputs]] type = "..."`` gives), an autonomy output under
``coex.autonomy``, exactly as the built-ins register theirs. The daemon builds one with its
options (the TOML table without ``type``), calls :meth:`Adapter.open`, then polls it often
(never blocking: return what is there), and :meth:`Adapter.close` on shutdown. Items go to the
node through the runner, which journals them, so a restart loses nothing.
"""

from __future__ import annotations

import abc
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from .config import Problems
from .errors import ConfigError
from .messages import SurveyKind, SurveyReason, SurveyState
from .state import persistent

__all__ = ["FEEDS", "Adapter", "Autonomy", "Image", "Input", "InputContext", "Item", "Nav", "Points", "PositionAid", "Samples",
           "SurveyPlan", "SurveyReport", "adapter_check", "adapter_problems", "check_autonomy_options", "check_options"]

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
    the directory relative paths are taken from, and the clock the daemon runs on (a function
    giving its time now, POSIX seconds, as ``time.time``; None: none given)."""

    origin_lat: float = 0.0
    origin_lon: float = 0.0
    base_dir: str = "."
    clock: Callable[[], float] | None = None

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
    def check(cls, options: Mapping[str, Any]) -> list[str] | Problems:
        """Problems with ``options`` beyond unknown and missing keys (``coex config check``):
        one sentence each, naming the key; or a :class:`~coex_core.config.Problems` that keeps
        each problem's option as its key (its ``option_*`` checks: ``option_int``,
        ``option_bool`` ...). Optional."""
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
    """Unknown and missing keys, then the adapter's own :meth:`Adapter.check`: the sentences of
    :func:`adapter_check`."""
    return adapter_check(cls, options).items


def adapter_check(cls: type[Adapter], options: Mapping[str, Any]) -> Problems:
    """Unknown and missing keys, then the adapter's own :meth:`Adapter.check`, collected in one
    :class:`~coex_core.config.Problems`, each with the option it names."""
    p = Problems()
    for k in options:
        if k not in cls.options and k not in cls.table_keys:
            p.said(str(k), f"unknown option {k!r} for {cls.kind} {cls.name!r} (known: {', '.join(sorted(cls.options))})")
    for k, (default, desc) in cls.options.items():
        if default is ... and k not in options:
            p.said(k, f"{cls.kind} {cls.name!r} needs option {k!r} ({desc})")
    if not p:
        found = cls.check(options)
        if isinstance(found, Problems):
            p.merge(found)
            p.warned.extend(found.warned)
        else:
            p.extend("", found)
    return p


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
        reason once)."""
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

    @property
    def stamp_images(self) -> bool:
        """Whether the daemon gives the images this input yields without a position the
        vehicle's newest position. The default: the input's ``nav`` option, when it has one
        (the directory input's), else False; an input whose ``nav`` means something else (the
        MOOS input's navigation variables) or that says it with another option overrides it."""
        return bool(self.config.get("nav", False))


def check_options(cls: type[Input], options: Mapping[str, Any]) -> list[str]:
    """Unknown and missing keys, then the adapter's own :meth:`Input.check`."""
    return adapter_problems(cls, options)


# ------------------------------------------------------------------ autonomy outputs
@persistent("survey.Plan")
@dataclass(frozen=True)
class SurveyPlan:
    """What the vehicle's autonomy flies: ``waypoints`` (``N x 2``, metres east/north of the
    origin) in order, at ``altitude`` above the seafloor or ``depth`` below the surface (None:
    keep the present one) and ``speed`` (None: the vehicle's own)."""

    survey_id: int
    kind: SurveyKind
    waypoints: tuple[tuple[float, float], ...]
    altitude: float | None = None
    depth: float | None = None
    speed: float | None = None
    #: the command's own shape, for autonomies that have a native lawnmower (MOOS-IvP)
    heading: float | None = None
    length: float | None = None
    width: float | None = None
    spacing: float | None = None
    centre: tuple[float, float] | None = None

    @property
    def path_length(self) -> float:
        w = np.asarray(self.waypoints, float)
        return float(np.hypot(*np.diff(w, axis=0).T).sum()) if len(w) > 1 else 0.0


@persistent("survey.Report")
@dataclass(frozen=True)
class SurveyReport:
    """What the vehicle's autonomy says about a survey (the survey sender's input):
    ``state`` STARTED (``index``: the waypoint it heads for), COMPLETED, ABORTED (``reason``:
    AUTONOMY_STOPPED, MANUAL_OVERRIDE, AUTONOMY_RESTARTED, ALL_STOP) or REJECTED (``reason``
    AUTONOMY_REFUSED: the autopilot or helm did not take it, ``value`` its code, ``detail`` its
    words; AUTONOMY_NO_ANSWER: it never answered, ``value`` the tries made). ``detail`` goes
    topside cut to :data:`~coex_core.messages.SURVEY_DETAIL_MAX` bytes."""

    survey_id: int
    state: SurveyState
    time: float
    reason: SurveyReason = SurveyReason.NONE
    index: int | None = None
    value: float | None = None
    detail: str | None = None



@persistent("survey.PositionAid")
@dataclass(frozen=True)
class PositionAid:
    """Where topside says the vehicle truly was (a ``PositionFix`` command, spec type 15), for
    an autonomy whose navigation accepts aiding: ``time`` (Unix seconds), ``x``/``y`` local metres
    east/north of the origin, ``sigma`` the 1-sigma horizontal error (m), ``depth`` (None:
    unknown), ``source`` ``"usbl"``, ``"estimate"`` or ``"other"``."""

    time: float
    x: float
    y: float
    sigma: float
    depth: float | None = None
    source: str = "usbl"


class Autonomy(Adapter, abc.ABC):
    """An autonomy output: the bridge from accepted survey commands to the vehicle's own autonomy
    (a MAVLink autopilot's mission, an LCM planner, the MOOS-IvP helm, ROS, or just a log).

    The daemon gives it each survey the vehicle accepted as a ``SurveyPlan`` (:meth:`submit`; a
    new plan replaces the one being flown), polls it for what happened (:meth:`poll`:
    ``SurveyReport`` items: started with the waypoint it heads for, completed, refused, no
    answer, stopped), and closes it on shutdown. Never blocking: an output that runs a protocol
    (the MAVLink mission upload) advances it in :meth:`poll`, and takes time only from ``now``."""

    kind: ClassVar[str] = "autonomy"

    @abc.abstractmethod
    def submit(self, plan: Any, now: float) -> None:
        """Fly ``plan`` (a SurveyPlan) instead of whatever is flown now."""

    @abc.abstractmethod
    def poll(self, now: float) -> list[Any]:
        """SurveyReports since the last call (never blocks)."""

    def resume(self, plan: Any, now: float) -> bool:
        """After the daemon restarted: ``plan`` is the survey it had submitted before (the vehicle
        may still be flying it). Follow its progress again **without** submitting it anew
        (which would start it over); True when the output can. Optional: the default, False,
        makes the daemon log that the survey's progress is no longer followed."""
        return False

    def aid(self, fix: Any, now: float) -> bool:
        """Give the vehicle's navigation a position fix (a :class:`PositionAid`): the MAVLink
        output sends it as ``GPS_INPUT``, the MOOS output posts it for the vehicle's navigation,
        the ROS output publishes a ``PoseWithCovarianceStamped`` (``docs/autonomy.md``). True when
        the output passed it on. Optional: the default, False, is an autonomy that takes no
        aiding (the daemon logs it once)."""
        return False

    def position(self, now: float) -> tuple[float, float] | None:
        """Where the vehicle is (local metres), for an output that knows (a simulated vehicle);
        the daemon uses it for the vehicle status when no input gives navigation. Optional:
        the default, None, is "not known"."""
        return None

    # ------------------------------------------------------------------ the survey lifecycle
    # (the daemon drives it for every output: coex_plugins.autonomy.lifecycle, docs/autonomy.md)
    def end(self, survey_id: int, now: float) -> None:
        """Survey ``survey_id`` ended (completed, refused, no answer, aborted, or the daemon
        found it ended after a restart): take it back from the vehicle's autonomy, so that
        nothing that starts or restarts later is handed it again. An output that leaves
        something behind (a latched topic, a variable the database keeps, a mission stored on
        the autopilot) replaces it with its ended form; an output that was following the survey
        stops. Called again when a late answer shows the autonomy still flies it, and after a
        restart of the daemon; so it must be harmless twice. Optional: the default does
        nothing (an output that leaves nothing behind)."""
        return None

    def heard(self, now: float) -> float | None:
        """When the vehicle's autonomy last showed it is alive (``now``'s clock): its heartbeat,
        the helm's postings, its planner's answers or presence. While a survey flies, the daemon
        aborts it (``AUTONOMY_SILENT``) when this is older than :meth:`silence` seconds. None:
        this output cannot tell (no liveness watch), the default."""
        return None

    def silence(self) -> float:
        """Seconds without a sign of life (:meth:`heard`) while a survey flies before it is
        aborted, ``AUTONOMY_SILENT``; 0: not watched. The default: the option ``silence`` when
        the output declares one, else 0."""
        v = self.config.get("silence", 0.0)
        return float(v) if isinstance(v, int | float) and not isinstance(v, bool) and v > 0 else 0.0

    def silent_detail(self) -> str:
        """What was not heard when the autonomy fell silent, in a few words (the report's
        ``detail``: ``no HEARTBEAT from 1/1``); "" for none, the default."""
        return ""


def check_autonomy_options(cls: type[Autonomy], options: Mapping[str, Any]) -> list[str]:
    """Unknown and missing keys, then the output's own :meth:`Autonomy.check`."""
    return adapter_problems(cls, options)
