"""The ``detections`` modality: the robot points at what matters.

On the vehicle, :class:`DetectionsSender` runs the onboard detectors it is configured with
(entry-point group ``coex.detectors``, :mod:`coex_core.detect`; the built-in ``relief``
detector looks for relief anomalies in the vehicle's own full-resolution map) every
``interval`` seconds on what the vehicle holds, and sends each finding topside as a
:class:`~coex_core.messages.Detection` (type 14, about 16 bytes), highest score first. A
detection is sent once, again when its measures change (more data came in) and again when the
channel reports it lost. For each new finding that scores at least ``focus_score`` it asks the
detector's modality to send its finest data around it next
(:meth:`~coex_core.modality.ModalitySender.focus`: the 1 m subgrids around a relief anomaly,
as a region request from topside would have them, without the round trip). Findings made
outside CoEx (a vehicle's own detector process) come in through :meth:`DetectionsSender.ingest`.

Topside, :class:`DetectionsReceiver` keeps every detection (per id, the one with the newest
stamp) with when it first arrived, and offers them as one ``detections`` product. They are
suggestions: the console shows them on the map as such, and the operator decides.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

from coex import (
    CoexError,
    ConfigError,
    Detector,
    Finding,
    Modality,
    ModalityReceiver,
    ModalitySender,
    PluginLoadError,
    PluginNotFound,
    Product,
    RequestRejected,
    merged_config,
    persistent,
    to_stamp,
    unwrap,
)
from coex.messages import Detection, DetectionSource, Message
from coex.wire import encoded_size

__all__ = ["DetectionsModality", "DetectionsReceiver", "DetectionsSender", "SENDER_DEFAULTS",
           "detection_message"]

log = logging.getLogger(__name__)

SENDER_DEFAULTS: dict[str, Any] = {
    #: the detectors to run: each ``{"type": NAME, ...its options}`` (NAME in ``coex.detectors``)
    "detectors": [{"type": "relief"}],
    #: seconds between two runs of the detectors
    "interval": 10.0,
    #: findings scoring below this are kept on the vehicle, not sent
    "min_score": 0.05,
    #: findings scoring at least this have their neighbourhood sent next (``focus``)
    "focus_score": 0.2,
    #: a finding of the same detector within this many metres of a detection updates it
    "merge_radius": 4.0,
    #: a detection is sent again when its score changes by this much, or it moves this far (m)
    "resend_score": 0.1,
    "resend_distance": 1.0,
    #: detections kept (the lowest scores go first)
    "max_detections": 256,
}
RECEIVER_DEFAULTS: dict[str, Any] = {
    #: detections kept topside (the oldest go first)
    "max_detections": 1024,
}
#: a finding from outside (:meth:`DetectionsSender.ingest`) is numbered as this detector
EXTERNAL = -1


class InvalidFinding(CoexError, ValueError):
    """What was given to :meth:`DetectionsSender.ingest` is not a finding."""


def _clamp(v: float | None, lo: float, hi: float, res: float) -> float | None:
    if v is None or not math.isfinite(v):
        return None
    return round(min(max(float(v), lo), hi) / res) * res


def detection_message(detection_id: int, source: DetectionSource, f: Finding) -> Detection:
    """The wire form of a finding: every measure rounded into its field's range (the long axis
    first: a width above the length swaps them)."""
    length, width = f.length, f.width
    if length is not None and width is not None and width > length:
        length, width = width, length
    orient = None if f.orientation is None or not math.isfinite(f.orientation) else float(round(f.orientation) % 180)
    foot = None if f.footprint is None or not math.isfinite(f.footprint) else int(min(max(round(f.footprint), 0), 1022))
    length = _clamp(length, 0.0, 50.8, 0.2)
    width = _clamp(width, 0.0, 50.8, 0.2)
    if length is not None and width is not None and width > length:
        width = length
    return Detection(
        detection_id % 1024, source, to_stamp(f.time),
        round(min(max(f.x, -50000.0), 50000.0), 1), round(min(max(f.y, -50000.0), 50000.0), 1),
        round(min(max(float(f.score), 0.0), 1.0), 2),
        None if f.height is None else round(min(max(float(f.height), 0.0), 25.4), 1),
        None if length is None else round(length, 1), None if width is None else round(width, 1),
        orient, foot, f.image_id if source == DetectionSource.IMAGE and f.image_id is not None else None)


def _upgrade_det(fields: dict[str, Any], saved: int) -> dict[str, Any]:
    """Version 1 was saved before the neighbourhood was asked for again on newer data (no
    ``focused``): an older detection loads as never focused (its neighbourhood is asked for
    with its next finding). Version 2 always has it."""
    return {"focused": -math.inf, **fields}


@persistent("detections.Det", version=2, upgrade=_upgrade_det)
class _Det:
    """A detection on the vehicle: the newest finding, what of it was last sent, its fate."""

    __slots__ = ("acked", "detection_id", "detector", "finding", "first", "focused", "message", "sent", "source")

    def __init__(self, detection_id: int, detector: int, source: DetectionSource, finding: Finding,
                 now: float) -> None:
        self.detection_id, self.detector, self.source = detection_id, detector, source
        self.finding = finding
        self.first = now
        #: the finding last sent (None: never, or lost), the message it went as, and whether a
        #: frame that carried it was acknowledged
        self.sent: Finding | None = None
        self.message: Detection | None = None
        self.acked = False
        #: the time of the newest data its neighbourhood was asked for with (-inf: never)
        self.focused = -math.inf

    def due(self, resend_score: float, resend_distance: float) -> bool:
        s, f = self.sent, self.finding
        if s is None:
            return True
        return (abs(f.score - s.score) >= resend_score or math.hypot(f.x - s.x, f.y - s.y) >= resend_distance
                or _changed(s.height, f.height, 0.2) or _changed(s.length, f.length, 0.5)
                or _changed(s.width, f.width, 0.5))


def _changed(a: float | None, b: float | None, tol: float) -> bool:
    if a is None or b is None:
        return (a is None) != (b is None)
    return abs(a - b) >= tol


def _build_detector(spec: Any, where: str) -> Detector[Any]:
    if isinstance(spec, Detector):
        return spec
    if isinstance(spec, str):
        spec = {"type": spec}
    if not isinstance(spec, Mapping) or not isinstance(spec.get("type"), str):
        raise ConfigError(f"{where}: a detector is {{\"type\": NAME, ...options}}, got {spec!r}")
    from coex import load_detector

    try:
        cls = load_detector(spec["type"])
    except (PluginNotFound, PluginLoadError) as exc:
        raise ConfigError(f"{where}: {exc}") from exc
    if not (isinstance(cls, type) and issubclass(cls, Detector)):
        raise ConfigError(f"{where}: coex.detectors {spec['type']!r} is not a Detector")
    return cls({k: v for k, v in spec.items() if k != "type"})


@persistent("detections.Sender")
class DetectionsSender(ModalitySender):
    """The vehicle side (see the module docstring). Options: :data:`SENDER_DEFAULTS`."""

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        cfg = merged_config(config, SENDER_DEFAULTS, "detections sender")
        specs = cfg["detectors"]
        if not isinstance(specs, list | tuple):
            raise ConfigError("detections sender: detectors must be a list")
        self.detectors: list[Detector[Any]] = [_build_detector(d, f"detections sender: detectors[{i}]")
                                               for i, d in enumerate(specs)]
        try:
            self.interval = float(cfg["interval"])
            self.min_score = float(cfg["min_score"])
            self.focus_score = float(cfg["focus_score"])
            self.merge_radius = float(cfg["merge_radius"])
            self.resend_score = float(cfg["resend_score"])
            self.resend_distance = float(cfg["resend_distance"])
            self.max_detections = int(cfg["max_detections"])
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"detections sender: {exc}") from exc
        if self.interval <= 0 or self.merge_radius < 0 or self.max_detections < 1:
            raise ConfigError("detections sender: interval > 0, merge_radius >= 0 and max_detections >= 1")
        if not 0.0 <= self.min_score <= 1.0:
            raise ConfigError("detections sender: min_score in [0, 1]")
        self.detections: dict[int, _Det] = {}
        self._next_id = 0
        self._last_run = -math.inf
        #: findings each detector made (counts, for the daemon's summary)
        self.found = 0
        #: neighbourhoods asked of the detectors' modalities (messages queued for them)
        self.focused = 0
        #: bytes of Detection messages handed to the link (each version, each re-send)
        self.bytes_sent = 0
        #: detectors whose modality is not on this node, or offers no view of their type
        #: (logged once each)
        self._absent: set[int] = set()

    # ------------------------------------------------------------------ findings
    def ingest(self, data: Any, now: float) -> None:
        """Findings made outside CoEx (a :class:`~coex_core.detect.Finding` or a list of them):
        sent like a detector's (source OTHER unless the finding says otherwise)."""
        items = [data] if isinstance(data, Finding) else list(data) if isinstance(data, list | tuple) else None
        if items is None or not all(isinstance(f, Finding) for f in items):
            raise InvalidFinding(f"the detections sender takes Findings, not {type(data).__name__}")
        for f in items:
            if not (math.isfinite(f.x) and math.isfinite(f.y) and math.isfinite(f.score)):
                raise InvalidFinding("a finding needs a finite position and score")
        for f in items:
            self._take(EXTERNAL, f.source if f.source is not None else DetectionSource.OTHER, f, None, now)

    def run(self, now: float) -> int:
        """Run every detector once on what the vehicle holds now; returns how many findings
        they made."""
        self._last_run = now
        n = 0
        for i, d in enumerate(self.detectors):
            data = self._view(i, d)
            if data is None:
                continue
            try:
                found = d.detect(data, now)
            except Exception as exc:  # a detector's failure never stops the link
                log.warning("detector %s failed: %s: %s", d.name, type(exc).__name__, exc)
                continue
            for f in found:
                if isinstance(f, Finding) and math.isfinite(f.x) and math.isfinite(f.y) and math.isfinite(f.score):
                    self._take(i, f.source if f.source is not None else d.source, f, d, now)
                    n += 1
        self.found += n
        return n

    def _view(self, i: int, d: Detector[Any]) -> object | None:
        """The view of ``d.modality``'s data ``d`` takes (its declared ``view``), or None (the
        modality is not on this node, or offers no such view: logged once)."""
        sender = self.peer(d.modality)
        view = None if sender is None else sender.detector_view()
        if view is not None and isinstance(view, d.view):
            return view
        if i not in self._absent:
            self._absent.add(i)
            if sender is None:
                log.warning("detector %s looks at modality %r, which this node does not send",
                            d.name, d.modality)
            else:
                log.warning("detector %s takes a %s of modality %r, whose sender offers %s", d.name,
                            d.view.__name__, d.modality, "none" if view is None else type(view).__name__)
        return None

    def _take(self, detector: int, source: DetectionSource, f: Finding, d: Detector[Any] | None,
              now: float) -> None:
        same = None
        for det in self.detections.values():
            if det.detector != detector:
                continue
            if (f.key is not None and det.finding.key == f.key) or (
                    f.key is None and math.hypot(det.finding.x - f.x, det.finding.y - f.y) <= self.merge_radius):
                same = det
                break
        if same is None:
            same = _Det(self._next_id, detector, source, f, now)
            self._next_id = (self._next_id + 1) % 1024
            while self._next_id in self.detections and len(self.detections) < 1024:
                self._next_id = (self._next_id + 1) % 1024
            self.detections[same.detection_id] = same
            self._forget()
        else:
            same.finding = f
        # the neighbourhood, again whenever the finding rests on newer data (a later swath over
        # it): the modality sends only what changed since it went
        if (d is not None and f.score >= self.focus_score and d.neighbourhood > 0
                and f.time > same.focused):
            sender = self.peer(d.modality)
            if sender is not None:
                same.focused = f.time
                try:
                    self.focused += int(sender.focus(f.x, f.y, d.neighbourhood, now))
                except Exception as exc:  # the neighbourhood is a bonus: never fatal
                    log.warning("focus on %s failed: %s: %s", d.modality, type(exc).__name__, exc)

    def _forget(self) -> None:
        while len(self.detections) > self.max_detections:
            worst = min(self.detections.values(), key=lambda d: (d.finding.score, d.first))
            del self.detections[worst.detection_id]

    # ------------------------------------------------------------------ sending
    def _due(self) -> list[_Det]:
        due = [d for d in self.detections.values() if d.finding.score >= self.min_score
               and d.due(self.resend_score, self.resend_distance)]
        due.sort(key=lambda d: (-d.finding.score, d.first))
        return due

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        if now - self._last_run >= self.interval:
            self.run(now)
        out: list[Message] = []
        left = int(max_bytes)
        for d in self._due():
            msg = detection_message(d.detection_id, d.source, d.finding)
            size = encoded_size(msg)
            if size > left:
                continue
            out.append(msg)
            left -= size
            d.sent, d.message, d.acked = d.finding, msg, False
            self.bytes_sent += size
        return out

    def handle(self, message: Message, now: float) -> list[Message]:
        raise RequestRejected(f"the detections sender takes no requests ({type(message).__name__})")

    def acked(self, message: Message, now: float) -> None:
        if isinstance(message, Detection):
            d = self.detections.get(message.detection_id)
            if d is not None and d.message == message:
                d.acked = True

    def lost(self, message: Message, now: float) -> None:
        """A detection whose frames were all lost goes again (if it is still the newest)."""
        if isinstance(message, Detection):
            d = self.detections.get(message.detection_id)
            if d is not None and d.message == message and not d.acked:
                d.sent = None

    def pending_bytes(self) -> int:
        return 16 * len(self._due())

    def summary(self) -> dict[str, Any]:
        """Counts for a daemon's log line: detections held, sent, acknowledged, neighbourhoods."""
        return {"detections": len(self.detections),
                "sent": sum(1 for d in self.detections.values() if d.message is not None),
                "acknowledged": sum(1 for d in self.detections.values() if d.acked),
                "found": self.found, "focused": self.focused, "bytes_sent": self.bytes_sent}


@persistent("detections.Receiver")
class DetectionsReceiver(ModalityReceiver):
    """The topside side: every detection received, per id the newest (by stamp), with when it
    first and last arrived; one ``detections`` product (data: the detections as dicts, highest
    score first)."""

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        cfg = merged_config(config, RECEIVER_DEFAULTS, "detections receiver")
        self.max_detections = int(cfg["max_detections"])
        self.detections: dict[int, dict[str, Any]] = {}
        self.version = 0

    def receive(self, message: Message, now: float) -> list[Product]:
        if not isinstance(message, Detection):
            return []
        t = float(unwrap(message.stamp, now))
        old = self.detections.get(message.detection_id)
        if old is not None and (t <= old["time"] or old["message"] == message):
            return []
        row = {"id": message.detection_id, "source": message.source.name.lower(), "time": t,
               "x": message.x, "y": message.y, "score": message.score, "height": message.height,
               "length": message.length, "width": message.width, "orientation": message.orientation,
               "footprint": message.footprint, "image_id": message.image_id,
               "first_at": now if old is None else old["first_at"], "updated_at": now,
               "bytes": encoded_size(message) + (0 if old is None else int(old["bytes"])),
               "message": message}
        self.detections[message.detection_id] = row
        while len(self.detections) > self.max_detections:
            del self.detections[min(self.detections, key=lambda k: self.detections[k]["first_at"])]
        self.version += 1
        return [self._product()]

    def rows(self) -> list[dict[str, Any]]:
        """Every detection held, highest score first (without its message)."""
        rows = [{k: v for k, v in r.items() if k != "message"} for r in self.detections.values()]
        rows.sort(key=lambda r: (-r["score"], r["first_at"]))
        return rows

    def _product(self) -> Product:
        rows = self.rows()
        return Product("detections", "detections", self.version, rows, {"count": len(rows)})

    def poll(self, now: float) -> list[Message]:
        return []

    def products(self) -> list[Product]:
        return [self._product()] if self.detections else []

    def view(self, product: Product) -> Mapping[str, Any] | None:
        rows = list(product.data or [])
        best = rows[0] if rows else None
        return {"detections": len(rows),
                "best": None if best is None else f"({best['x']:.0f}, {best['y']:.0f}) score {best['score']:.2f}"}


class DetectionsModality(Modality):
    """Onboard detections: :class:`DetectionsSender` on the vehicle, :class:`DetectionsReceiver`
    topside; one message type, :class:`~coex_core.messages.Detection`."""

    name: ClassVar[str] = "detections"
    version: ClassVar[str] = "1.0.0"
    messages: ClassVar[tuple[type[Message], ...]] = (Detection,)

    def sender(self, config: Mapping[str, Any] | None = None) -> DetectionsSender:
        return DetectionsSender(config)

    def receiver(self, config: Mapping[str, Any] | None = None) -> DetectionsReceiver:
        return DetectionsReceiver(config)


def findings_of(items: Sequence[Any]) -> list[Finding]:
    """Findings from plain mappings (an input adapter's JSON: ``x``, ``y``, ``score``, ``time``
    and the optional measures)."""
    out = []
    for it in items:
        try:
            out.append(it if isinstance(it, Finding) else Finding(**dict(it)))
        except TypeError as exc:
            raise InvalidFinding(f"not a finding: {it!r} ({exc})") from exc
    return out
