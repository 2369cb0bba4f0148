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

Detectors are sans-I/O like senders: no clock, no file, no socket; time enters as ``now``. They
are saved with the detections sender's state (:mod:`coex_core.state`), so a detector class is
registered with ``@coex.persistent("yourname.Detector")`` and keeps only plain state.
"""

from __future__ import annotations

import abc
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from .errors import ConfigError
from .messages import DetectionSource
from .modality import ModalitySender
from .registry import DETECTOR_GROUP
from .state import persistent

__all__ = ["DETECTOR_GROUP", "Detector", "Finding"]


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


class Detector(abc.ABC):
    """A detector plugin (entry-point group ``coex.detectors``; the name is its entry point's).

    Class attributes: ``modality`` names the modality whose vehicle-side sender holds the data it
    looks at (``"bathymetry"``, ``"imagery"``, a plugin's name); ``source`` says what its
    findings are found in (a :class:`~coex_core.messages.DetectionSource`: the map, images,
    another sensor); ``neighbourhood`` is the radius (m) around a finding whose finest data its
    modality sends next (0: none).

    Contract: ``__init__(config)`` takes a plain mapping (unknown keys: a
    :class:`~coex_core.errors.ConfigError`). :meth:`detect` is called every few seconds (the
    detections sender's ``interval``) with the sender of ``modality`` on this vehicle and
    returns what it finds now; it must be cheap (look at what changed since its last call: the
    call is made while a packet is built), must never raise for data it does not understand
    (return nothing), and never looks at anything but the vehicle's own data."""

    name: ClassVar[str] = "detector"
    modality: ClassVar[str]
    source: ClassVar[DetectionSource] = DetectionSource.OTHER
    neighbourhood: float = 0.0

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        """A detector without options (subclasses take theirs with ``coex.merged_config``)."""
        if config:
            raise ConfigError(f"detector {self.name!r} takes no options, got {', '.join(sorted(config))}")

    @abc.abstractmethod
    def detect(self, data: ModalitySender, now: float) -> list[Finding]:
        """Findings in what ``data`` holds now: new ones, and earlier ones whose measures
        changed (a finding repeated unchanged costs nothing: it is not sent again)."""
