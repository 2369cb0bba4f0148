"""Onboard detectors: the plugin point (entry-point group ``coex.detectors``) through which a
vehicle looks at its own data as it grows and points at what matters.

A :class:`Detector` looks at what one modality's sender holds on the vehicle (the bathymetry
sender's full-resolution map, the imagery sender's frames, a third-party modality's data) and
returns :class:`Finding` objects: where something stands out, how well it matches what the
vehicle was told to look for (``score``, which ranks findings) and what it measured of it. The
``detections`` modality (``coex_plugins.detections``) runs the detectors a vehicle is configured
with, sends their findings topside as :class:`~coex_core.messages.Detection` messages (highest
score first) and asks the detector's modality to send its finest data around each one next
(:meth:`~coex_core.modality.ModalitySender.focus`). A detection is a suggestion: topside shows
it, and the operator decides.

What a detector looks at is declared, typed: a modality's sender offers detectors one view of
what it holds (:meth:`~coex_core.modality.ModalitySender.detector_view`), and a detector
declares the type of view it takes (``view``, its generic parameter): the bathymetry sender's
map is a :class:`MapView`, the imagery sender's frames an :class:`ImageFrames` (of
:class:`ImageFrame`), a third-party modality's whatever class it documents. The detections
modality hands a detector only a view of its declared type.

Detectors are sans-I/O like senders: no clock, no file, no socket; time enters as ``now``. They
are saved with the detections sender's state (:mod:`coex_core.state`), so a detector class is
registered with ``@coex.persistent("yourname.Detector")`` and keeps only plain state.
"""

from __future__ import annotations

import abc
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Generic, Protocol, TypeVar, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from .errors import ConfigError
from .messages import DetectionSource
from .registry import DETECTOR_GROUP
from .state import persistent

__all__ = ["DETECTOR_GROUP", "Detector", "Finding", "ImageFrame", "ImageFrames", "MapView"]

#: the view of its modality's data a detector takes
V = TypeVar("V")


@runtime_checkable
class MapView(Protocol):
    """The vehicle's own full-resolution bathymetry map, as the ``bathymetry`` modality's sender
    offers it to detectors: square tiles of ``tile`` cells a side, cells ``resolution`` metres
    (level 0), each tile with a version that grows whenever soundings change it."""

    @property
    def tile(self) -> int:
        """Cells a tile has a side (level 0)."""

    @property
    def resolution(self) -> float:
        """Metres a cell has a side (level 0)."""

    @property
    def tiles(self) -> Sequence[tuple[int, int]]:
        """The keys ``(tx, ty)`` of the tiles held (tile ``(tx, ty)`` starts at
        ``(tx * tile * resolution, ty * tile * resolution)`` metres)."""

    def tile_version(self, key: tuple[int, int]) -> int:
        """The version of a tile (-1: not held)."""

    def window(self, x0: float, y0: float, x1: float,
               y1: float) -> tuple[NDArray[np.float64], NDArray[np.float64], float, float]:
        """The level-0 cells of ``[x0, x1) x [y0, y1)`` (metres), snapped outwards to cells:
        ``(mean, updated, wx0, wy0)``: mean elevation (NaN where empty), the time of the last
        sounding (``-inf`` where empty), row 0 south, and the window's south-west corner."""


class ImageFrame(Protocol):
    """One camera frame the vehicle holds (:class:`ImageFrames`)."""

    @property
    def image_id(self) -> int:
        """The frame's image id (what a :class:`Finding`'s ``image_id`` names)."""

    @property
    def time(self) -> float:
        """Capture time (absolute seconds, like ``now``)."""

    @property
    def x(self) -> float | None:
        """Metres east of the origin where it was taken (None: unknown)."""

    @property
    def y(self) -> float | None:
        """Metres north of the origin (None: unknown)."""

    @property
    def image(self) -> Any:
        """The pixels as coded (an array: grey, or colour in the last axis)."""


@runtime_checkable
class ImageFrames(Protocol):
    """The camera frames the vehicle holds, as the ``imagery`` modality's sender offers them to
    detectors."""

    def frames(self, since: float = ...) -> Sequence[ImageFrame]:
        """The frames captured after ``since``, in capture order."""


@persistent("core.Finding")
@dataclass(frozen=True)
class Finding:
    """Something a detector found. ``x``, ``y``: metres east and north of the origin;
    ``score`` in [0, 1] (higher first); ``time``: of the newest data it was found in (absolute
    seconds, like ``now``). The measures are optional: ``height`` above the local background
    (m), ``length`` and ``width`` of its footprint (m, ``length`` >= ``width``: the long axis),
    ``orientation`` of the long axis (degrees clockwise from north, 0..180), ``footprint`` (m²),
    ``image_id`` (the frame an image detector found it in). ``key``: the detector's own name for
    the object, when it can tell that a finding is one it reported before (findings without a
    key are matched by position). ``source``: what it was found in, when not the detector's."""

    x: float
    y: float
    score: float
    time: float
    height: float | None = None
    length: float | None = None
    width: float | None = None
    orientation: float | None = None
    footprint: float | None = None
    image_id: int | None = None
    key: str | None = None
    #: what it was found in, when not its detector's ``source`` (findings ingested from
    #: outside, e.g. a vehicle's own detector process)
    source: DetectionSource | None = None


class Detector(abc.ABC, Generic[V]):
    """A detector plugin (entry-point group ``coex.detectors``; the name is its entry point's),
    generic in the view of its modality's data it takes (``Detector[MapView]``).

    Class attributes: ``modality`` names the modality whose vehicle-side sender holds the data it
    looks at (``"bathymetry"``, ``"imagery"``, a plugin's name); ``view`` is the type of view of
    that data it takes (what the sender's
    :meth:`~coex_core.modality.ModalitySender.detector_view` gives: :class:`MapView`,
    :class:`ImageFrames`, a plugin's class), a class or a runtime-checkable protocol, the same as
    the generic parameter; ``source`` says what its findings are found in (a
    :class:`~coex_core.messages.DetectionSource`: the map, images, another sensor);
    ``neighbourhood`` is the radius (m) around a finding whose finest data its modality sends
    next (0: none). A class that implements :meth:`detect` without declaring ``modality`` and
    ``view`` is a ``TypeError`` when it is defined.

    Contract: ``__init__(config)`` takes a plain mapping (unknown keys: a
    :class:`~coex_core.errors.ConfigError`). :meth:`detect` is called every few seconds (the
    detections sender's ``interval``) with the view of ``modality``'s data on this vehicle (only
    when the modality's sender offers one of type ``view``) and returns what it finds now; it
    must be cheap (look at what changed since its last call: the call is made while a packet is
    built), must never raise for data it does not understand (return nothing), and never looks
    at anything but the vehicle's own data."""

    name: ClassVar[str] = "detector"
    modality: ClassVar[str]
    view: ClassVar[type[Any]]
    source: ClassVar[DetectionSource] = DetectionSource.OTHER
    neighbourhood: float = 0.0

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if getattr(cls.detect, "__isabstractmethod__", False):
            return  # an abstract detector: its concrete subclasses declare them
        declared = {k for c in cls.__mro__ for k in vars(c)}
        missing = [a for a in ("modality", "view") if a not in declared]
        if missing:
            raise TypeError(f"detector {cls.__name__} declares no {' and no '.join(missing)} "
                            "(the modality whose data it looks at, the type of its view)")
        if not isinstance(cls.view, type):
            raise TypeError(f"detector {cls.__name__}: view is a class or a runtime-checkable protocol, "
                            f"not {cls.view!r}")
        try:
            isinstance(None, cls.view)
        except TypeError as exc:  # a protocol without @runtime_checkable
            raise TypeError(f"detector {cls.__name__}: its view {cls.view.__name__} cannot be checked "
                            f"({exc})") from None

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        """A detector without options (subclasses take theirs with ``coex.merged_config``)."""
        if config:
            raise ConfigError(f"detector {self.name!r} takes no options, got {', '.join(sorted(config))}")

    @abc.abstractmethod
    def detect(self, data: V, now: float) -> list[Finding]:
        """Findings in ``data`` (the view of its modality's data) now: new ones, and earlier
        ones whose measures changed (a finding repeated unchanged costs nothing: it is not sent
        again)."""
