"""The console's adapter layer: what topside knows, as JSON, and operator actions as commands.

* :class:`ConsoleState` takes received messages (:meth:`~ConsoleState.apply_message`), receiver
  products (:meth:`~ConsoleState.apply_product`) and node events (:meth:`~ConsoleState.apply_event`)
  and keeps everything the console shows. :meth:`~ConsoleState.snapshot` gives the whole state
  as plain JSON-able data; each section (``vehicle``, ``map``, ``surveys``, ``images``, ``series``,
  ``link``, ``queues``, ``commands``, ``log``) has a version, so :meth:`~ConsoleState.changes` gives only
  the sections that changed since a client last looked (the server pushes those).
* :class:`~.actions.ConsoleActions` (module :mod:`.actions`) turns an operator action into
  wire-format command messages and records every command here, so the page shows "requested"
  until the vehicle answers (``CommandAck``/``MapRoiReply``) or the data arrives. Pictures are
  drawn by :mod:`.render`, words made by :mod:`.words`.

The state is one class; its concerns are in modules of their own, each a part of it:
:mod:`.mapview` (levels, targets, map regions), :mod:`.surveys`, :mod:`.images` (images, regions
of them, crops), :mod:`.linkview` (links, schedules, queues) and :mod:`.commands` (the commands
list, a view of the core tracker's states, :mod:`coex_core.tracker`). Names they define are
importable from here as before.

Nothing here does I/O or reads a clock: time enters as ``now``. The server adds the locking.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from coex import (
    BadFrame,
    CommandResult,
    CommandUnanswered,
    Dropped,
    Event,
    LinkChanged,
    ModalityReceiver,
    Product,
    ProductUpdated,
    Received,
    Rejected,
    RequestRejected,
    persistent,
    unwrap,
)
from coex import messages as m
from coex_core.channel.events import ScheduleSwitched, SenderFailed
from coex_plugins.bathymetry import BathymetryReceiver
from coex_plugins.timeseries import Series

from .commands import OPEN_COMMAND_STATES, CommandsView, _Command
from .images import MAX_CROPS, MAX_IMAGE_REGIONS, ImagesView, _Crop
from .linkview import LinkView
from .mapview import MAP_BLOCKS, MapView, _RoiRequest, map_delta
from .render import THUMB_SIDE, _picture, elevation_rgb, png_bytes
from .surveys import MAX_SURVEYS, SURVEY_OUTCOMES, SURVEY_STATES, SurveysView
from .words import _counted, _modality_of, _num

__all__ = [
    "MAP_BLOCKS",
    "MAX_CROPS",
    "MAX_IMAGE_REGIONS",
    "MAX_SURVEYS",
    "OPEN_COMMAND_STATES",
    "SECTIONS",
    "SURVEY_OUTCOMES",
    "SURVEY_STATES",
    "ConsoleState",
    "map_delta",
    "png_bytes",
    "elevation_rgb",
]

#: The sections of a snapshot, in the order the page lays them out.
SECTIONS = ("vehicle", "map", "surveys", "images", "series", "other", "link", "queues", "commands",
            "log", "navigation")

#: Modalities with a panel of their own; the products of any other go to the generic panel.
OWN_PANELS = ("bathymetry", "imagery", "timeseries", "survey", "detections")

#: Events of one kind (one log key) within this many seconds of the first are counted in one
#: entry of the event log, updated in place, instead of one entry each.
REPEAT_WINDOW = 600.0
#: Counted entries remembered at most (beyond it the oldest start again as a new entry).
MAX_REPEATS = 64

#: Images the console keeps (the newest by time; the imagery receiver's ``max_images`` default):
#: a dive of several days does not grow the console's memory and saved state with every picture
MAX_IMAGES = 256
#: The largest picture of what is on screen (``/map/<level>/window.png``), in pixels.
MAP_WINDOW_CELLS = 4 * 1024 * 1024


FloatArray = npt.NDArray[np.float64]


@persistent("console.Image")
@dataclass
class _Image:
    image_id: int
    t: float | None = None
    goal: tuple[str, int] | None = None
    version: int = 0
    thumb: bytes | None = None
    thumb_version: int = -1
    decoded: Any = None
    decoded_version: int = -1
    decoded_meta: dict[str, Any] = field(default_factory=dict)
    #: the regions the imagery receiver lists for it (its product's ``regions``)
    regions: list[dict[str, Any]] = field(default_factory=list)


#: caches (pictures, summaries) are not state: they are made again when needed
def _upgrade_state(fields: dict[str, Any], saved: int) -> dict[str, Any]:
    """Version 1 (CoEx 0.1 and earlier 0.2 work) may lack what came later: crops, the vehicle's
    altitudes, the camera's field of view, detections, survey products, numbered log entries and
    the surveys already logged."""
    if saved < 2:
        fields.setdefault("crops", {})
        if not isinstance(fields.get("altitudes"), deque):
            fields["altitudes"] = deque(fields.get("altitudes") or (), maxlen=2000)
        fields.setdefault("camera_fov", (60.0, 45.0))
        fields.setdefault("detections", [])
        fields.setdefault("survey_products", {})
        if not isinstance(fields.get("_log_seq"), int):  # saved before entries had numbers
            fields["_log_seq"] = max((int(e.get("id", -1)) for e in fields.get("log", ())), default=-1) + 1
        fields.setdefault("_survey_logged", {})
        fields.setdefault("ended", None)
        fields.setdefault("ended_t", None)
    return fields


@persistent("console.State", version=2, upgrade=_upgrade_state,
            transient=("_region_ids", "_png", "_map_summary", "_targets_cache", "_survey_sig", "_survey_rows",
                       "_repeats", "max_images", "navigation"))
class ConsoleState(MapView, SurveysView, ImagesView, LinkView, CommandsView):
    """Everything the console shows, built from messages, products and events.

    ``stream_names`` names queue streams (id -> name); ``schedules`` gives the TDMA schedule of
    each link (``link -> coex_core.channel.schedule.Schedule`` or anything with ``to_dict()``, or
    a plain dict ``{"version", "epoch", "slots": [{"owner", "duration", "guard", ...}]}``);
    ``node_id`` is topside's node id (its slots are drawn as "ours")."""

    #: the operator whose action is running (set by :meth:`ConsoleActions.dispatch`)
    actor: str = ""
    #: images kept (the newest): :data:`MAX_IMAGES`, or fewer when the imagery receiver shown
    #: keeps fewer (``coex topside`` sets it from the receiver's ``max_images``; not saved)
    max_images: int = MAX_IMAGES
    #: topside's navigation (:class:`coex_plugins.navigation.Navigation`: USBL fixes, the drift
    #: estimate; ``[usbl]`` of the topside file, issue 56), or None; not saved
    navigation: Any = None

    def __init__(
        self,
        *,
        node_id: int = 1,
        vehicle_id: int = 2,
        stream_names: Mapping[int, str] | None = None,
        schedules: Mapping[int, Any] | None = None,
        max_track: int = 5000,
        max_log: int = 200,
        auto_targets: bool = True,
        receivers: Mapping[str, ModalityReceiver] | None = None,
    ) -> None:
        self.node_id = node_id
        self.vehicle_id = vehicle_id
        self.now = 0.0
        self.stream_names = dict(stream_names or {})
        self.versions: dict[str, int] = dict.fromkeys(SECTIONS, 0)
        # vehicle
        self.status: m.VehicleStatus | None = None
        self.status_t: float | None = None
        #: why contact ended for good (the dive is over, the link closed), or None
        self.ended: str | None = None
        self.ended_t: float | None = None
        self.track: deque[tuple[float, float, float, float]] = deque(maxlen=max_track)
        #: modality name -> its topside receiver: a node's (the console shows what they hold
        #: and never decodes anything itself), or, without ``receivers``, the console's own,
        #: made from the registry when a modality's first message arrives (a view of raw
        #: messages: a log replay, a test)
        self.receivers: dict[str, ModalityReceiver] = dict(receivers or {})
        self.own_receivers = receivers is None
        # map (the bathymetry receiver's levels)
        #: per level: (version, summary, coverage span, keys, oldest stamps, image box, step)
        self._map_summary: dict[int, tuple[int, Any, int, Any, Any, list[float], int]] = {}
        self._png: dict[int, tuple[int, bytes]] = {}
        self.targets: list[dict[str, Any]] = []
        #: Flag candidate targets on the finest level (threshold in metres, minimum cells).
        self.auto_targets = auto_targets
        self.target_threshold = 0.8
        self.target_min_cells = 3
        #: At most this many markers, at least this far apart (metres).
        self.max_targets = 8
        self.target_spacing = 6.0
        self._targets_cache: tuple[Any, list[dict[str, Any]]] = (None, [])
        #: the vehicle's detections (the detections receiver's rows): suggestions, shown on the
        #: map apart from the candidates the console or the operator flagged
        self.detections: list[dict[str, Any]] = []
        self.roi: dict[int, _RoiRequest] = {}
        self._region_count = 0
        self._region_sig: tuple[Any, ...] = ()
        self._region_ids: set[int] = set()
        #: A bathymetry receiver whose operator regions (not its automatic gap filling) are
        #: shown even when someone else asked for them (a script, another tool).
        bathymetry = self.receivers.get("bathymetry")
        self.region_source = bathymetry if isinstance(bathymetry, BathymetryReceiver) else None
        self._zrange: tuple[float, float] | None = None
        # surveys: the survey receiver's records (what it asked and what the vehicle answered);
        # products of a survey receiver the console does not hold (rare) are kept here
        self.survey_products: dict[int, dict[str, Any]] = {}
        self._survey_sig: tuple[Any, ...] | None = None
        self._survey_rows: dict[int, tuple[int, dict[str, Any]]] = {}
        # images
        self.images: dict[int, _Image] = {}
        #: the crops of images the receiver holds, by crop id (the newest MAX_CROPS)
        self.crops: dict[int, _Crop] = {}
        self.progress_info: dict[str, Any] | None = None
        self.image_queries: list[dict[str, Any]] = []
        #: (time, altitude) of the vehicle's statuses: where an image's footprint comes from
        self.altitudes: deque[tuple[float, float]] = deque(maxlen=2000)
        #: The camera's field of view in degrees (across, along): image footprints on the map.
        self.camera_fov = (60.0, 45.0)
        # series
        self.series: dict[int, dict[str, Any]] = {}
        self.series_requests: list[dict[str, Any]] = []
        # other modalities: name -> product key -> what the generic panel shows
        self.other: dict[str, dict[str, dict[str, Any]]] = {}
        # link
        self.links: dict[int, dict[str, Any]] = {}
        self.schedules: dict[int, dict[str, Any]] = {}
        for link, sch in (schedules or {}).items():
            self.set_schedule(link, sch)
        self.bad_frames = 0
        # queues
        self.queue_stamp: float | None = None
        self.streams: dict[int, dict[str, Any]] = {}
        # commands and log
        self.commands: dict[int, _Command] = {}
        self.command_order: deque[int] = deque(maxlen=64)
        self._foreign_acks: dict[int, tuple[str, float]] = {}
        self.log: deque[dict[str, Any]] = deque(maxlen=max_log)
        #: the number of the next log entry
        self._log_seq = 0
        #: log key -> its counted entry (one in ``log``), see :meth:`_log`
        self._repeats: dict[str, dict[str, Any]] = {}
        #: survey id -> the history entries already in the event log
        self._survey_logged: dict[int, list[tuple[float, str, str]]] = {}

    def _after_restore(self) -> None:
        """A topside store saves the console with its node (:mod:`coex_core.state`); object
        ids and caches are not state: the regions recorded are the ones the requests in ``roi``
        hold, and the counted log entries go on counting."""
        self._region_ids = {id(r.region) for r in self.roi.values()}
        self._png = {}
        self._map_summary = {}
        self._targets_cache = (None, [])
        self._survey_sig, self._survey_rows = None, {}
        for s in SECTIONS:  # a section added since the console was saved
            self.versions.setdefault(s, 0)
        self._repeats = {}
        for e in self.log:
            if e.get("key") is not None:
                self._repeats[str(e["key"])] = e

    # -------------------------------------------------------------------- bookkeeping
    def _touch(self, *sections: str) -> None:
        for s in sections:
            self.versions[s] += 1

    def _log(self, now: float, text: str, level: str = "info", *, key: str | None = None,
             count: int = 1) -> None:
        """Add ``text`` to the event log at ``now``.

        With a ``key`` (one kind of event: "dropped|2|superseded"), events of that kind are
        counted, not listed: within :data:`REPEAT_WINDOW` of the first, a new one updates that
        entry in place (its total ``count``, its number of events ``n``, its ``last`` time)
        instead of adding one, so a stream dropping a message every few seconds takes one line
        in ten minutes and the list keeps the events that matter. ``{n}`` in ``text`` is
        replaced by the total of the ``count`` s ("stream 2: {n} dropped (superseded)"); without
        it the text says how many times it happened. Memory is bounded: the log is a deque and
        at most :data:`MAX_REPEATS` keys are followed."""
        self._touch("log")
        entry = self._repeats.get(key) if key is not None else None
        if entry is not None and (now - float(entry["t"] or 0.0) > REPEAT_WINDOW or not self.log
                                  or int(entry.get("id", -1)) < int(self.log[0].get("id", -1))):
            del self._repeats[key]  # its window is over, or it left the log: a new entry
            entry = None
        if entry is not None:
            entry["n"] += 1
            entry["count"] += int(count)
            entry["last"] = _num(max(now, float(entry["last"] or now)), 1)
            entry["level"] = "warn" if "warn" in (level, entry["level"]) else level
            entry["text"] = _counted(entry["base"], entry["count"], entry["n"],
                                     float(entry["last"] or now) - float(entry["t"] or now))
            return
        entry = {"id": self._log_seq, "t": _num(now, 1), "level": level,
                 "text": _counted(text, int(count), 1, 0.0)}
        self._log_seq += 1
        if key is not None:
            entry.update(key=key, base=text, n=1, count=int(count), last=_num(now, 1))
            if len(self._repeats) >= MAX_REPEATS:
                del self._repeats[next(iter(self._repeats))]
            self._repeats[key] = entry
        self.log.append(entry)

    def _advance(self, now: float) -> None:
        if now > self.now:
            self.now = float(now)

    # ------------------------------------------------------------------------ inputs
    def apply_message(self, msg: m.Message, now: float, link: int | None = None) -> set[str]:
        """Take one received message (any type; unknown ones are ignored). Returns the sections
        it changed."""
        self._advance(now)
        before = dict(self.versions)
        self._count_rx(msg, now, link)
        handler = _HANDLERS.get(type(msg))
        if handler is not None:
            handler(self, msg, now, link)
        elif self.own_receivers:  # a node's receivers get their messages from the node
            name = _modality_of(msg)
            rx = self._receiver(name) if name is not None else None
            if rx is not None:
                for p in rx.receive(msg, now) or ():
                    self.apply_product(name, p, now)
        return {s for s in SECTIONS if self.versions[s] != before[s]}

    def _receiver(self, name: str | None) -> Any:
        """The receiver of modality ``name``: the node's, or one the console makes (view of raw
        messages) from the registry (None when the modality is not installed)."""
        if name is None:
            return None
        rx = self.receivers.get(name)
        if rx is None and self.own_receivers:
            from coex import load_modality

            try:
                rx = self.receivers[name] = load_modality(name)().receiver()
            except Exception:
                return None
            if isinstance(rx, BathymetryReceiver):
                self.region_source = rx
        return rx

    @property
    def map_receiver(self) -> BathymetryReceiver | None:
        """The bathymetry receiver whose levels the map shows (None before any): with topside's
        navigation applied, seen through it (each subgrid placed by the drift correction at its
        stamp, :class:`coex_plugins.navigation.CorrectedMap`)."""
        rx = self.receivers.get("bathymetry")
        if not isinstance(rx, BathymetryReceiver):
            return None
        nav = self.navigation
        if nav is not None and nav.apply:
            from coex_plugins.navigation import CorrectedMap

            return CorrectedMap(rx, nav, self.vehicle_id)  # type: ignore[return-value]
        return rx

    def apply_messages(self, msgs: Iterable[m.Message], now: float,
                       link: int | None = None) -> set[str]:
        out: set[str] = set()
        for msg in msgs:
            out |= self.apply_message(msg, now, link)
        return out

    def apply_product(self, modality: str, product: Product, now: float) -> set[str]:
        """Take a receiver product (:class:`coex_core.modality.Product`)."""
        self._advance(now)
        before = dict(self.versions)
        kind, data, meta = str(product.kind), product.data, dict(product.meta or {})
        if modality == "survey":
            self._survey_product(product, meta, now)
        elif modality == "detections":
            self._detections_product(data, now)
        elif modality not in OWN_PANELS:
            self._other_product(modality, product, meta)
        elif kind == "series":
            self._series_product(data, meta)
        elif kind == "image":
            self._image_product(product, data, meta, now)
        elif kind == "image-crop":
            self._crop_product(product, data, meta)
        elif kind == "image-progress":
            self.progress_info = {"pending": meta.get("pending"), "current": meta.get("current"),
                                  "unacked_fragments": meta.get("unacked_fragments"),
                                  "next": list(meta.get("next_images") or [])}
            self._touch("images")
        elif "target" in kind:
            self._targets_product(data, meta)
        elif kind == "map-level" and hasattr(data, "shape"):
            self._map_product(data, meta)
        return {s for s in SECTIONS if self.versions[s] != before[s]}

    def apply_event(self, event: Event) -> set[str]:
        """Take a node/channel event (:mod:`coex_core.channel.events`), dispatched on its type
        (the others, and anything not an event, change nothing shown)."""
        if not isinstance(event, Event):
            return set()
        now = float(event.time)
        self._advance(now)
        before = dict(self.versions)
        if isinstance(event, Received):
            self.apply_message(event.message, now, event.link)
        elif isinstance(event, ProductUpdated):
            self.apply_product(str(event.modality), event.product, now)
        elif isinstance(event, CommandResult):
            self._command_result(int(event.command_id), event.status, now, event.command)
        elif isinstance(event, CommandUnanswered):
            self._command_unanswered(int(event.command_id), now, event.command)
        elif isinstance(event, BadFrame):
            self.bad_frames += 1
            lk = self._link(int(event.link))
            lk["local_bad"] = lk.get("local_bad", 0) + 1
            self._touch("link")
            self._log(now, f"bad frame on link {event.link}: {event.reason}", "warn",
                      key=f"bad frame|{event.link}|{event.reason}")
        elif isinstance(event, LinkChanged):
            lk = self._link(int(event.link))
            lk["enabled"], lk["muted"] = bool(event.enabled), bool(event.muted)
            self._touch("link")
            state = "enabled" if event.enabled else "disabled"
            self._log(now, f"link {event.link} {state}{' (muted)' if event.muted else ''}")
        elif isinstance(event, ScheduleSwitched):
            sch = self.schedules.get(int(event.link))
            if sch is not None:
                sch["active_version"] = int(event.version)
            self._touch("link")
            self._log(now, f"link {event.link} runs schedule v{event.version} ({event.reason})")
        elif isinstance(event, Dropped):
            self._log(now, f"stream {event.stream}: {{n}} dropped ({event.reason})", "warn",
                      key=f"dropped|{event.stream}|{event.reason}", count=int(event.count))
        elif isinstance(event, Rejected):
            what = type(event.message).__name__
            self._log(now, f"rejected {what}: {event.reason}", "warn", key=f"rejected|{what}|{event.reason}")
        elif isinstance(event, SenderFailed):
            self._log(now, f"stream {event.stream} sender failed: {event.error}", "warn",
                      key=f"sender failed|{event.stream}|{event.error}")
        return {s for s in SECTIONS if self.versions[s] != before[s]}

    # ---------------------------------------------------------------------- vehicle
    def end_contact(self, now: float, why: str = "the dive is over") -> None:
        """Contact with the vehicle has ended for good (the dive is over, the link closed):
        the page stops saying "live"."""
        self._advance(now)
        self.ended, self.ended_t = str(why), float(now)
        self._touch("vehicle")
        self._log(now, f"contact ended: {why}")

    def _on_status(self, s: m.VehicleStatus, now: float) -> None:
        t = unwrap(s.stamp, now)
        if self.status_t is not None and t < self.status_t:
            return  # an older status arrived late: keep the newest
        from coex_apps.vehicle.faults import fault_changes

        for text, came in fault_changes(self.status.faults if self.status is not None else 0, s.faults):
            self._log(now, text, "warn" if came else "info")  # the vehicle's store, its hearing topside
        self.status, self.status_t = s, t
        if not self.track or self.track[-1][1:3] != (s.x, s.y):
            self.track.append((t, s.x, s.y, s.depth))
        if s.altitude is not None:
            self.altitudes.append((t, float(s.altitude)))
        if self.navigation is not None:
            self.navigation.status(self.vehicle_id, s, now)
            self._touch("navigation", "map")
        self._touch("vehicle")

    # -------------------------------------------------------------------------- map
    def map_window_job(self, level: int, x0: float, y0: float, x1: float, y1: float,
                       step: int = 1, max_pixels: int = MAP_WINDOW_CELLS) -> Callable[[], bytes] | None:
        """What is on screen of a big level, finer than its drawn overview: a job rendering
        ``[x0, x1) x [y0, y1)`` (metres) at ``step`` level cells per pixel as a PNG (north up),
        read from the receiver's tiles now (call it holding the node's lock; the job may run
        without). None if nothing of the level is held; :class:`RequestRejected` if the picture
        would exceed ``max_pixels`` pixels (:data:`MAP_WINDOW_CELLS` unless told)."""
        rx = self.map_receiver
        geometry = rx.geometry(level) if rx is not None else None
        if geometry is None or level not in rx.levels() or step < 1 or not x1 > x0 or not y1 > y0:
            return None
        span = geometry[0] * step
        cells = math.ceil((x1 - x0) / span - 1e-9) * math.ceil((y1 - y0) / span - 1e-9)
        if cells <= 0:
            return None
        if cells > max_pixels:
            raise RequestRejected(f"a map window of {cells} pixels is larger than the {max_pixels} "
                                  "allowed: ask for a smaller area or a larger step")
        z, (_, _, cell) = rx.window(level, x0, y0, x1, y1, max_cells=cells)
        lo, hi = self._zrange or (0.0, 1.0)
        return lambda: png_bytes(elevation_rgb(z, lo, hi, cell))

    def map_png(self, level: int) -> bytes | None:
        """The level as a PNG (colour ramp + hillshade, north up, transparent where empty)."""
        png, job = self.map_png_job(level)
        if job is not None:
            png = job()
        return png

    def map_png_job(self, level: int) -> tuple[bytes | None, Callable[[], bytes] | None]:
        """``(png, None)`` when the picture of the level is current, else ``(None, render)``:
        ``render()`` draws it from a copy of the grid (no need to hold a lock while it runs)
        and keeps it for the next call."""
        rx = self.map_receiver
        if rx is None:
            return None, None
        version = rx.level_version(level)
        cached = self._png.get(level)
        if cached is not None and cached[0] == version:
            return cached[1], None
        grid = self.level_grid(level)
        if grid is None:
            return None, None
        z, _, _, cell = grid
        lo, hi = self._zrange or (0.0, 1.0)

        def render() -> bytes:
            png = png_bytes(elevation_rgb(z, lo, hi, cell))
            if level not in self._png or self._png[level][0] < version:
                self._png[level] = (version, png)
            return png

        return None, render

    # ----------------------------------------------------------------------- images
    def _image(self, image_id: int) -> _Image:
        img = self.images.get(image_id)
        if img is None:
            img = self.images[image_id] = _Image(image_id)
            while len(self.images) > max(self.max_images, 1):  # the oldest go (those without a time first)
                oldest = min((i for i in self.images.values() if i is not img),
                             key=lambda i: (i.t is not None, i.t or 0.0, i.image_id))
                del self.images[oldest.image_id]
        return img

    def crop_png(self, crop_id: int) -> bytes | None:
        """What a crop shows of its box, as a PNG at full size (None before it shows anything)."""
        crop = self.crops.get(crop_id)
        if crop is None or crop.decoded is None:
            return None
        if crop.png is None or crop.png_version != crop.decoded_version:
            crop.png = png_bytes(_picture(np.asarray(crop.decoded), 1 << 16))
            crop.png_version = crop.decoded_version
        return crop.png

    def image_png(self, image_id: int, full: bool = False) -> bytes | None:
        """The newest decoded picture of an image, as a thumbnail PNG (at most
        :data:`THUMB_SIDE` px), or at full size with ``full`` (None before any)."""
        img = self.images.get(image_id)
        if img is None or img.decoded is None:
            return None
        if full:
            return png_bytes(_picture(np.asarray(img.decoded), 1 << 16))
        if img.thumb is None or img.thumb_version != img.decoded_version:
            img.thumb = png_bytes(_picture(np.asarray(img.decoded), THUMB_SIDE))
            img.thumb_version = img.decoded_version
        return img.thumb

    # ------------------------------------------------------------------ time series
    def _series_product(self, data: Any, meta: dict[str, Any]) -> None:
        series = data if isinstance(data, Series) else None
        cid = int(meta.get("channel", series.channel if series is not None else -1))
        if cid < 0:
            return
        s = self.series.setdefault(cid, {"channel": cid})
        for k in ("name", "unit", "lo", "hi", "resolution"):
            if meta.get(k) is not None:
                s[k] = meta[k]
        if series is not None:
            s["times"] = np.asarray(series.times, float)
            s["values"] = np.asarray(series.values, float)
            s["bounds"] = np.asarray(series.bounds, float)
        self._touch("series")

    # ------------------------------------------------------------ other modalities
    def _other_product(self, modality: str, product: Product, meta: dict[str, Any]) -> None:
        """A product of a modality without a panel of its own: the generic panel shows its
        kind, key, version and the receiver's ``view`` of it (else its plain metadata)."""
        view: Any = None
        rx = self.receivers.get(modality)
        if rx is not None:
            try:
                view = rx.view(product)  # declared on ModalityReceiver (default: None)
            except Exception as exc:  # a plugin's view must never stop the console
                view = {"error": f"view failed: {exc}"}
        shown = view if isinstance(view, Mapping) else meta
        fields = {str(k): (_num(v) if isinstance(v, float) else v) for k, v in shown.items()
                  if v is None or isinstance(v, int | float | str | bool)}
        self.other.setdefault(modality, {})[str(product.key)] = {
            "kind": str(product.kind), "key": str(product.key),
            "version": int(product.version), "fields": fields,
            "t": _num(self.now, 1)}
        self._touch("other")

    # -------------------------------------------------------------------- snapshots
    def changes(self, seen: Mapping[str, Any]) -> dict[str, Any]:
        """The sections whose version differs from ``seen`` (section -> version).

        The map section is the big one (every level's blocks). When ``seen`` also holds
        ``"_map"`` (what this client holds of it: :meth:`map_held` of the snapshot it got), the
        map goes as a delta (``"delta": true``): a level whose version did not change is
        ``{"level": n, "same": true}``, a changed one carries its blocks that changed
        (``tiles_changed``) and the ones gone (``tiles_removed``) instead of all ``tiles``;
        ``seen["_map"]`` is updated to what the client holds after this update."""
        out = {s: self.section(s) for s in SECTIONS if seen.get(s) != self.versions[s]}
        held = seen.get("_map")
        if "map" in out and isinstance(held, dict):
            out["map"] = map_delta(out["map"], held)
        return out

    def map_held(self, section: Mapping[str, Any] | None = None) -> dict[int, Any]:
        """What a client that got the map section ``section`` (default: the current one)
        holds of it: per level its version and its blocks (for :meth:`changes`)."""
        held: dict[int, Any] = {}
        map_delta(self._snap_map() if section is None else section, held)
        return held

    def snapshot(self) -> dict[str, Any]:
        """The whole state as JSON-able data (plus ``now`` and section ``versions``)."""
        out = {s: self.section(s) for s in SECTIONS}
        out["now"] = self.now
        out["versions"] = dict(self.versions)
        return out

    def section(self, name: str) -> Any:
        return getattr(self, f"_snap_{name}")()

    def navigation_changed(self) -> None:
        """Topside's navigation took fixes: the section (and the corrected map) changed."""
        self._touch("navigation", "map")

    def _snap_navigation(self) -> dict[str, Any]:
        """USBL fixes, the raw (dead-reckoned) and corrected tracks, the correction's size and
        age (:meth:`coex_plugins.navigation.Navigation.state`); ``{"enabled": false}`` without."""
        nav = self.navigation
        if nav is None:
            return {"enabled": False}
        return {"enabled": True, **nav.state(self.vehicle_id, self.now)}

    def _snap_vehicle(self) -> dict[str, Any]:
        s = self.status
        status = None
        if s is not None:
            status = {"t": self.status_t, "age": _num(self.now - (self.status_t or 0), 1),
                      "x": s.x, "y": s.y, "depth": s.depth, "altitude": s.altitude,
                      "heading": s.heading, "speed": s.speed, "battery": s.battery,
                      "mode": s.mode.name, "faults": s.faults}
        track = list(self.track)
        if len(track) > 1500:  # keep the payload small: every k-th point plus the newest
            k = math.ceil(len(track) / 1500)
            track = [*track[::k], track[-1]]
        ended = self.ended
        return {"status": status, "track": [[_num(t, 1), x, y, d] for t, x, y, d in track],
                "ended": ended, "ended_t": _num(self.ended_t, 1)}

    def _snap_series(self) -> dict[str, Any]:
        chans = []
        for _cid, s in sorted(self.series.items()):
            d: dict[str, Any] = {k: v for k, v in s.items()
                                 if k not in ("times", "values", "bounds")}
            t = s.get("times")
            if t is not None and t.size:
                v, b = s["values"], s["bounds"]
                if t.size > 2000:  # min/max decimation keeps spikes visible
                    k = math.ceil(t.size / 1000)
                    n = (t.size // k) * k
                    tv = t[:n].reshape(-1, k)
                    vv = v[:n].reshape(-1, k)
                    bb = b[:n].reshape(-1, k)
                    imin, imax = vv.argmin(axis=1), vv.argmax(axis=1)
                    rows = np.arange(vv.shape[0])
                    idx = np.sort(np.stack([imin, imax], axis=1), axis=1)
                    t = tv[rows[:, None], idx].ravel()
                    v = vv[rows[:, None], idx].ravel()
                    b = bb.max(axis=1).repeat(2)
                fin = np.isfinite(b)
                d["t"] = np.round(t, 2).tolist()
                d["v"] = np.round(v, 5).tolist()
                d["err"] = np.where(fin, np.round(b, 5), -1.0).tolist()
                d["max_error"] = _num(float(b[fin].max()), 5) if fin.any() else None
                d["samples"] = int(s["times"].size)
            chans.append(d)
        return {"channels": chans, "requests": self.series_requests[-20:]}

    def _snap_other(self) -> dict[str, Any]:
        return {"modalities": [
            {"name": name, "products": sorted(products.values(), key=lambda p: p["key"])[-50:]}
            for name, products in sorted(self.other.items())]}

    def _snap_log(self) -> list[dict[str, Any]]:
        return [{k: v for k, v in e.items() if k not in ("key", "base")} for e in list(self.log)[-60:]]


_HANDLERS: dict[type, Callable[[ConsoleState, Any, float, int | None], None]] = {
    m.VehicleStatus: lambda s, msg, now, link: s._on_status(msg, now),
    m.LinkStatus: lambda s, msg, now, link: s._on_link_status(msg, now),
    m.LinkHealth: lambda s, msg, now, link: s._on_link_health(msg, now),
    m.QueueStatus: lambda s, msg, now, link: s._on_queue_status(msg, now),
    m.CommandAck: lambda s, msg, now, link: s._on_command_ack(msg, now),
}
