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

Nothing here does I/O or reads a clock: time enters as ``now``. The server adds the locking.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np
import numpy.typing as npt

from coex_core import messages as m
from coex_core.errors import RequestRejected
from coex_core.state import persistent
from coex_core.timefmt import unwrap
from coex_core.wire import encoded_size

from .render import THUMB_SIDE, _picture, elevation_rgb, png_bytes
from .words import _counted, _modality_of, ack_reason, gap_words, hms, region_words

__all__ = [
    "SECTIONS",
    "ConsoleState",
    "png_bytes",
    "elevation_rgb",
]

#: The sections of a snapshot, in the order the page lays them out.
SECTIONS = ("vehicle", "map", "surveys", "images", "series", "other", "link", "queues", "commands",
            "log")

#: Modalities with a panel of their own; the products of any other go to the generic panel.
OWN_PANELS = ("bathymetry", "imagery", "timeseries", "survey", "detections")

#: The states of a survey the page draws (the survey receiver's ``SurveyRecord.state``).
SURVEY_STATES = ("requested", "accepted", "started", "completed", "rejected", "aborted", "given up")
#: The surveys the page lists and draws (the newest).
MAX_SURVEYS = 40
#: How a finished survey reads in the list and on the map when the state alone would hide what
#: happened: (state, reason) -> words. A refusal by the autonomy (autopilot, helm, planner) is
#: not the vehicle's own checks, an autonomy that never answered did not refuse anything, and an
#: abort says who stopped it. Anything else reads as its state ("rejected" by the geofence or a
#: limit, "completed", "given up": no answer from the vehicle over the link).
SURVEY_OUTCOMES = {
    ("rejected", "AUTONOMY_REFUSED"): "refused by autonomy",
    ("rejected", "AUTONOMY_NO_ANSWER"): "no answer from autonomy",
    ("rejected", "NO_AUTONOMY"): "no autonomy",
    ("rejected", "UNAUTHENTICATED"): "not authenticated",
    ("aborted", "SUPERSEDED"): "replaced",
    ("aborted", "AUTONOMY_STOPPED"): "stopped by autonomy",
    ("aborted", "MANUAL_OVERRIDE"): "taken over",
    ("aborted", "AUTONOMY_RESTARTED"): "autonomy restarted",
    ("aborted", "ALL_STOP"): "all-stop",
}
#: Events of one kind (one log key) within this many seconds of the first are counted in one
#: entry of the event log, updated in place, instead of one entry each.
REPEAT_WINDOW = 600.0
#: Counted entries remembered at most (beyond it the oldest start again as a new entry).
MAX_REPEATS = 64
#: A command in these states may still be answered (``pending``: it stands on the vehicle).
OPEN_COMMAND_STATES = ("sent", "pending")

#: The map section shows a level's coverage (the age of its data) in at most this many blocks:
#: every subgrid of a small level, groups of receiver tiles of a big one.
MAP_BLOCKS = 4096
#: The regions of an image the images section lists and the page draws (the newest).
MAX_IMAGE_REGIONS = 12
#: Crops (regions coded on their own) kept for the region lists (the newest).
MAX_CROPS = 64
#: Images the console keeps (the newest by time; the imagery receiver's ``max_images`` default):
#: a dive of several days does not grow the console's memory and saved state with every picture
MAX_IMAGES = 256
#: The largest picture of what is on screen (``/map/<level>/window.png``), in pixels.
MAP_WINDOW_CELLS = 4 * 1024 * 1024


FloatArray = npt.NDArray[np.float64]


def _num(x: float | None, nd: int = 3) -> float | None:
    if x is None:
        return None
    x = float(x)
    return round(x, nd) if math.isfinite(x) else None


# ---------------------------------------------------------------------------- map model


@persistent("console.RoiRequest")
@dataclass
class _RoiRequest:
    """A map region asked from the console: the bathymetry receiver's region object (which
    it sends, retries and closes), and when it was asked."""

    level: int
    x0: int
    y0: int
    w: int
    h: int
    sent: float
    region: Any
    #: the most subgrids the vehicle said it queued for it (0: it never sent anything)
    got: int = 0


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


@persistent("console.Crop")
@dataclass
class _Crop:
    """A crop the imagery receiver holds (a region of an image coded on its own): what it shows
    of its box and the receiver's meta (``parent``, ``box``, ``command_id``, bytes ...)."""

    crop_id: int
    decoded: Any = None
    decoded_version: int = -1
    meta: dict[str, Any] = field(default_factory=dict)
    png: bytes | None = None
    png_version: int = -1


@persistent("console.Command")
@dataclass
class _Command:
    command_id: int
    kind: str
    summary: str
    sent: float
    message: m.Message
    status: str = "sent"
    answered: float | None = None
    roi_key: int | None = None
    #: who sent it: the signed-in operator ("" for a console without sign-in)
    by: str = ""
    #: why the vehicle answered as it did, in words (a rejection's likely cause)
    reason: str = ""


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
                       "_repeats", "max_images"))
class ConsoleState:
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
        receivers: Mapping[str, Any] | None = None,
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
        self.receivers: dict[str, Any] = dict(receivers or {})
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
        self.region_source: Any = self.receivers.get("bathymetry")
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
            from coex_core.registry import load_modality

            try:
                rx = self.receivers[name] = load_modality(name)().receiver()
            except Exception:
                return None
            if name == "bathymetry":
                self.region_source = rx
        return rx

    @property
    def map_receiver(self) -> Any:
        """The bathymetry receiver whose levels the map shows (None before any)."""
        return self.receivers.get("bathymetry")

    def apply_messages(self, msgs: Iterable[m.Message], now: float,
                       link: int | None = None) -> set[str]:
        out: set[str] = set()
        for msg in msgs:
            out |= self.apply_message(msg, now, link)
        return out

    def apply_product(self, modality: str, product: Any, now: float) -> set[str]:
        """Take a receiver product (:class:`coex_core.modality.Product`)."""
        self._advance(now)
        before = dict(self.versions)
        kind = str(getattr(product, "kind", ""))
        data = getattr(product, "data", None)
        meta = dict(getattr(product, "meta", {}) or {})
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

    def apply_event(self, event: Any) -> set[str]:
        """Take a node/channel event (:mod:`coex_core.channel.events`), duck-typed by name."""
        name = type(event).__name__
        now = float(getattr(event, "time", self.now))
        self._advance(now)
        before = dict(self.versions)
        if name == "Received":
            self.apply_message(event.message, now, getattr(event, "link", None))
        elif name == "ProductUpdated":
            self.apply_product(str(event.modality), event.product, now)
        elif name == "CommandResult":
            self._command_result(int(event.command_id), event.status, now,
                                 getattr(event, "command", None))
        elif name == "BadFrame":
            self.bad_frames += 1
            lk = self._link(int(event.link))
            lk["local_bad"] = lk.get("local_bad", 0) + 1
            self._touch("link")
            self._log(now, f"bad frame on link {event.link}: {event.reason}", "warn",
                      key=f"bad frame|{event.link}|{event.reason}")
        elif name == "LinkChanged":
            lk = self._link(int(event.link))
            lk["enabled"], lk["muted"] = bool(event.enabled), bool(event.muted)
            self._touch("link")
            state = "enabled" if event.enabled else "disabled"
            self._log(now, f"link {event.link} {state}{' (muted)' if event.muted else ''}")
        elif name == "ScheduleSwitched":
            sch = self.schedules.get(int(event.link))
            if sch is not None:
                sch["active_version"] = int(event.version)
            self._touch("link")
            self._log(now, f"link {event.link} runs schedule v{event.version} ({event.reason})")
        elif name == "Dropped":
            self._log(now, f"stream {event.stream}: {{n}} dropped ({event.reason})", "warn",
                      key=f"dropped|{event.stream}|{event.reason}", count=int(getattr(event, "count", 1)))
        elif name == "Rejected":
            what = type(event.message).__name__
            self._log(now, f"rejected {what}: {event.reason}", "warn", key=f"rejected|{what}|{event.reason}")
        elif name == "SenderFailed":
            self._log(now, f"stream {event.stream} sender failed: {event.error}", "warn",
                      key=f"sender failed|{event.stream}|{event.error}")
        return {s for s in SECTIONS if self.versions[s] != before[s]}

    def set_schedule(self, link: int, schedule: Any) -> None:
        """Record the TDMA schedule a link runs (for the timeline)."""
        d = schedule.to_dict() if hasattr(schedule, "to_dict") else dict(schedule)
        slots = [dict(s) for s in d.get("slots", [])]
        self.schedules[int(link)] = {
            "link": int(link), "version": int(d.get("version", 0)),
            "active_version": int(d.get("version", 0)),
            "epoch": float(d.get("epoch", 0.0)), "first_cycle": int(d.get("first_cycle", 0)),
            "cycle": float(sum(float(s["duration"]) for s in slots)),
            "slots": [{"owner": int(s["owner"]), "duration": float(s["duration"]),
                       "guard": float(s.get("guard", 0.0)),
                       "min_priority": int(s.get("min_priority", 0))} for s in slots],
            "proposed": None,
        }
        self._link(int(link))
        self._touch("link")

    def add_targets(self, targets: Iterable[Mapping[str, Any]]) -> None:
        """Add candidate targets (``x``, ``y`` and optionally ``height``, ``level``, ``score``)."""
        for t in targets:
            self.targets.append({k: (_num(v) if isinstance(v, float) else v) for k, v in t.items()})
        self._touch("map")

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
        self.status, self.status_t = s, t
        if not self.track or self.track[-1][1:3] != (s.x, s.y):
            self.track.append((t, s.x, s.y, s.depth))
        if s.altitude is not None:
            self.altitudes.append((t, float(s.altitude)))
        self._touch("vehicle")

    # -------------------------------------------------------------------------- map
    def _map_product(self, data: Any, meta: Mapping[str, Any]) -> None:
        """A level of the bathymetry receiver changed: its depth range widens the colour scale
        (the receiver's ``zmin``/``zmax`` when it says them: a big level is not scanned)."""
        if meta.get("zmin") is not None and meta.get("zmax") is not None:
            lo, hi = float(meta["zmin"]), float(meta["zmax"])
            zr = self._zrange or (lo, hi)
            self._zrange = (min(zr[0], lo), max(zr[1], hi))
            self._touch("map")
            return
        z = np.asarray(data, float)
        finite = z[np.isfinite(z)]
        if finite.size:
            lo, hi = float(finite.min()), float(finite.max())
            zr = self._zrange or (lo, hi)
            self._zrange = (min(zr[0], lo), max(zr[1], hi))
        self._touch("map")

    def held_stamps(self, level: int, x0: int, y0: int, w: int, h: int) -> list[int | None]:
        """Per subgrid of the region, row-major (rows = y): the stamp topside holds, or None."""
        rx = self.map_receiver
        if rx is None:
            return [None] * (w * h)
        return list(rx.region_stamps(level, x0, y0, w, h))

    def level_grid(self, level: int) -> tuple[FloatArray, float, float, float] | None:
        """A copy of the receiver's drawn level: ``(z, x0, y0, cell)`` with row 0 = south, or
        None if nothing of it is held. A big level is a decimated overview (``cell`` is then a
        multiple of the level's: at most the receiver's ``max_mosaic_cells``)."""
        rx = self.map_receiver
        if rx is None or level not in rx.levels():
            return None
        p = rx.level_product(level)
        z = np.array(p.data, dtype=float)
        if not np.isfinite(z).any():
            return None
        return z, float(p.meta["x0"]), float(p.meta["y0"]), float(p.meta["cell_size"])

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

    def _image_product(self, product: Any, data: Any, meta: dict[str, Any], now: float) -> None:
        iid = meta.get("image_id")
        if iid is None:
            try:
                iid = int(str(getattr(product, "key", "")).rsplit("-", 1)[-1])
            except ValueError:
                return
        img = self._image(int(iid))
        if data is not None and hasattr(data, "shape"):
            img.decoded = data
            img.decoded_version = int(getattr(product, "version", img.decoded_version + 1))
        img.decoded_meta = {k: v for k, v in meta.items()
                            if v is None or isinstance(v, int | float | str | bool)}
        if isinstance(meta.get("regions"), list | tuple):
            img.regions = [dict(r) for r in meta["regions"] if isinstance(r, Mapping)]
        if img.t is None and isinstance(meta.get("time"), int | float):
            img.t = float(meta["time"])
        img.version += 1
        self._touch("images")

    def _crop_product(self, product: Any, data: Any, meta: dict[str, Any]) -> None:
        """A crop's product: what it shows of its box (drawn in the region list of its image)."""
        try:
            cid = int(meta["image_id"])
        except (KeyError, TypeError, ValueError):
            return
        crop = self.crops.pop(cid, None) or _Crop(cid)
        self.crops[cid] = crop  # the newest last
        if data is not None and hasattr(data, "shape"):
            crop.decoded = data
            crop.decoded_version = int(getattr(product, "version", crop.decoded_version + 1))
        crop.meta = {k: (list(v) if isinstance(v, list | tuple) else v) for k, v in meta.items()
                     if v is None or isinstance(v, int | float | str | bool | list | tuple)}
        while len(self.crops) > MAX_CROPS:
            del self.crops[next(iter(self.crops))]
        self._touch("images")

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

    def by_time_answer(self, msg: m.ImageByTimeRequest, now: float) -> _Image | None:
        """The image that answered an accepted by-time request: the one the vehicle's rule
        picks (nearest, newest before, oldest after the time) among the images topside knows."""
        t = unwrap(msg.stamp, now)
        known = [i for i in self.images.values() if i.t is not None]
        if msg.direction == m.TimeDirection.BEFORE:
            known = [i for i in known if cast(float, i.t) < t - 0.5]
            return max(known, key=lambda i: cast(float, i.t), default=None)
        if msg.direction == m.TimeDirection.AFTER:
            known = [i for i in known if cast(float, i.t) > t + 0.5]
            return min(known, key=lambda i: cast(float, i.t), default=None)
        return min(known, key=lambda i: abs(cast(float, i.t) - t), default=None)

    # ------------------------------------------------------------------ time series
    def _series_product(self, data: Any, meta: dict[str, Any]) -> None:
        cid = int(meta.get("channel", getattr(data, "channel", -1)))
        if cid < 0:
            return
        s = self.series.setdefault(cid, {"channel": cid})
        for k in ("name", "unit", "lo", "hi", "resolution"):
            if meta.get(k) is not None:
                s[k] = meta[k]
        if data is not None and hasattr(data, "times"):
            s["times"] = np.asarray(data.times, float)
            s["values"] = np.asarray(data.values, float)
            s["bounds"] = np.asarray(data.bounds, float)
        self._touch("series")

    def _detections_product(self, data: Any, now: float) -> None:
        """The detections receiver's rows: what the vehicle's detectors suggest (new ones are
        logged once)."""
        known = {int(d["id"]) for d in self.detections}
        rows = []
        for r in data if isinstance(data, list | tuple) else ():
            if not isinstance(r, Mapping) or r.get("x") is None or r.get("y") is None:
                continue
            rows.append({k: (_num(v, 2) if isinstance(v, float) else v) for k, v in r.items()
                         if k in ("id", "source", "x", "y", "score", "height", "length", "width", "orientation",
                                  "footprint", "image_id", "time", "first_at")})
            if int(r["id"]) not in known:
                size = "" if r.get("length") is None else f", {r['length']:.1f} x {r['width']:.1f} m"
                high = "" if r.get("height") is None else f", {r['height']:.1f} m high"
                self._log(now, f"the vehicle suggests a detection at ({r['x']:.0f}, {r['y']:.0f}){high}{size}, "
                          f"score {r['score']:.2f} (detection {r['id']}, in its {r.get('source', 'data')})")
        self.detections = rows
        self._touch("map")

    def _targets_product(self, data: Any, meta: dict[str, Any]) -> None:
        rows = data if isinstance(data, list | tuple) else meta.get("targets", [])
        out = []
        for t in rows:
            d = t if isinstance(t, Mapping) else getattr(t, "__dict__", {})
            if "x" in d and "y" in d:
                out.append({k: (_num(v) if isinstance(v, float) else v) for k, v in d.items()
                            if isinstance(v, int | float | str | bool)})
        self.targets = out
        self._touch("map")

    # ---------------------------------------------------------------------- surveys
    @property
    def survey_receiver(self) -> Any:
        """The survey receiver (``coex_plugins.survey.SurveyReceiver``) that sends the operator's
        survey requests and follows them (None: this console cannot ask for surveys)."""
        return self.receivers.get("survey")

    def _survey_product(self, product: Any, meta: dict[str, Any], now: float) -> None:
        """A survey changed state (the survey receiver's product): shown in the surveys
        section, and in the event log with its reason in words."""
        try:
            sid = int(meta.get("survey_id", getattr(product, "key", "")))
        except (TypeError, ValueError):
            return
        if self.survey_receiver is None:  # nobody holds the records: keep what we were told
            self.survey_products[sid] = dict(meta)
        self._log_survey(sid, meta, now)
        self._survey_sig = None  # shown again at once
        self._touch("surveys", "commands")

    def _log_survey(self, sid: int, meta: Mapping[str, Any], now: float) -> None:
        """One event-log line per state the survey receiver added to the survey's history (the
        present state, or an older one that arrived late), at its time. The history is the
        receiver's, in the vehicle's time order; nothing is re-sorted here. The present state
        reads as its outcome ("survey 3 no answer from autonomy: ...")."""
        history = [(float(h[0]), str(h[1]), str(h[2] or "")) for h in meta.get("history") or ()]
        if not history:  # a receiver without a history: the present state
            history = [(float(meta.get("time") or now), str(meta.get("state", "")), str(meta.get("text") or ""))]
        present = (str(meta.get("state", "")), str(meta.get("text") or ""))
        seen = self._survey_logged.get(sid)
        if seen is None:  # first heard of: its present state (its request was logged when sent)
            new = [h for h in history if (h[1], h[2]) == present][-1:]
        else:
            new = [h for h in history if h not in seen]
        self._survey_logged[sid] = history
        while len(self._survey_logged) > 2 * MAX_SURVEYS:
            del self._survey_logged[next(iter(self._survey_logged))]
        for t, state, text in new:
            label = SURVEY_OUTCOMES.get((state, str(meta.get("reason"))), state) if (state, text) == present else state
            bad = state in ("rejected", "aborted", "given up")
            self._log(t, f"survey {sid} {label}" + (f": {text}" if text else ""), "warn" if bad else "info")

    def refresh_surveys(self) -> bool:
        """Look at the survey receiver's records (a request made by someone else, a survey given
        up for want of an answer): True, and the surveys section changed, if they did."""
        rx = self.survey_receiver
        records = getattr(rx, "surveys", None)
        if not isinstance(records, Mapping):
            return False
        sig = tuple((int(k), int(getattr(r, "version", 0)), str(getattr(r, "state", "")))
                    for k, r in list(records.items()))
        if sig == self._survey_sig:
            return False
        self._survey_sig = sig
        self._touch("surveys", "commands")
        return True

    def _survey_metas(self) -> dict[int, dict[str, Any]]:
        """survey id -> the survey receiver's product metadata (cached per record version)."""
        rx = self.survey_receiver
        records = getattr(rx, "surveys", None)
        if not isinstance(records, Mapping):
            return dict(self.survey_products)
        out: dict[int, dict[str, Any]] = {}
        rows: dict[int, tuple[int, dict[str, Any]]] = {}
        stale = [k for k, r in records.items()
                 if self._survey_rows.get(int(k), (None,))[0] != getattr(r, "version", 0)]
        fresh = ({int(p.key): dict(p.meta) for p in rx.products() if str(p.key).isdigit()}
                 if stale else {})
        for k, r in records.items():
            k = int(k)
            version = int(getattr(r, "version", 0))
            cached = self._survey_rows.get(k)
            meta = fresh.get(k) if cached is None or cached[0] != version else cached[1]
            if meta is None:
                continue
            rows[k] = (version, meta)
            out[k] = meta
        self._survey_rows = rows
        return out

    def _snap_surveys(self) -> dict[str, Any]:
        """Every survey asked (the newest :data:`MAX_SURVEYS`): its path (``waypoints``, metres
        east/north), its state and, for a rejection or an abort, the reason in words."""
        items = []
        for sid, meta in self._survey_metas().items():
            history = [[_num(float(t), 1), str(st), str(tx)] for t, st, tx in meta.get("history") or ()]
            requested = history[0][0] if history else _num(meta.get("time"), 1)
            wps = [[_num(float(a), 2), _num(float(b), 2)] for a, b in meta.get("waypoints") or ()]
            state, reason = meta.get("state"), meta.get("reason")
            row = {"survey_id": sid, "kind": meta.get("kind"), "state": state,
                   "outcome": SURVEY_OUTCOMES.get((str(state), str(reason)), state),
                   "text": meta.get("text") or "", "reason": reason,
                   "index": meta.get("index"), "time": _num(meta.get("time"), 1),
                   "requested": requested, "history": history, "waypoints": wps}
            for k in ("heading", "length", "width", "spacing", "altitude", "depth", "speed"):
                v = meta.get(k)
                row[k] = _num(float(v), 2) if isinstance(v, int | float) else None
            row["append"] = bool(meta.get("append", False))
            items.append(row)
        items.sort(key=lambda r: (r["requested"] or 0.0, r["survey_id"]))
        # whether the page may ask for surveys (a node's survey receiver sends them)
        available = self.survey_receiver is not None and not self.own_receivers
        return {"items": items[-MAX_SURVEYS:], "available": available,
                "states": list(SURVEY_STATES)}

    # ------------------------------------------------------------ other modalities
    def _other_product(self, modality: str, product: Any, meta: dict[str, Any]) -> None:
        """A product of a modality without a panel of its own: the generic panel shows its
        kind, key, version and the receiver's ``view`` of it (else its plain metadata)."""
        view: Any = None
        show = getattr(self.receivers.get(modality), "view", None)
        if callable(show):
            try:
                view = show(product)
            except Exception as exc:  # a plugin's view must never stop the console
                view = {"error": f"view failed: {exc}"}
        shown = view if isinstance(view, Mapping) else meta
        fields = {str(k): (_num(v) if isinstance(v, float) else v) for k, v in shown.items()
                  if v is None or isinstance(v, int | float | str | bool)}
        self.other.setdefault(modality, {})[str(getattr(product, "key", ""))] = {
            "kind": str(getattr(product, "kind", "")), "key": str(getattr(product, "key", "")),
            "version": int(getattr(product, "version", 0)), "fields": fields,
            "t": _num(self.now, 1)}
        self._touch("other")

    # -------------------------------------------------------------------------- link
    def _link(self, link: int) -> dict[str, Any]:
        lk = self.links.get(link)
        if lk is None:
            lk = self.links[link] = {"link": link, "enabled": True, "muted": False,
                                     "packets": 0, "frames": 0, "bad_frames": 0, "snr": None,
                                     "doppler": None, "last": None, "history": deque(maxlen=240)}
        return lk

    def _count_rx(self, msg: m.Message, now: float, link: int | None) -> None:
        """Throughput: the bytes of the messages received, per TDMA cycle of the link (60 s
        without a schedule). Not a change of its own: the bins go out with the link section's
        next change (the modem's report of the packet, topside's frame counters)."""
        try:
            size = encoded_size(msg)
        except Exception:  # a message the codec cannot build (a test double): not counted
            return
        if link is None:
            link = min(self.links, default=0)
        lk = self._link(int(link))
        sch = self.schedules.get(int(link))
        cycle = float(sch["cycle"]) if sch and sch.get("cycle", 0) > 0 else 60.0
        epoch = float(sch["epoch"]) if sch else 0.0
        start = epoch + math.floor((now - epoch) / cycle) * cycle
        bins = lk.get("_rx")
        if not isinstance(bins, deque):
            bins = lk["_rx"] = deque(maxlen=240)
        if bins and abs(bins[-1][0] - start) < 1e-6:
            bins[-1][1] += size
        else:
            bins.append([start, size, cycle])
        lk["rx_bytes"] = int(lk.get("rx_bytes", 0)) + size

    def _on_link_status(self, s: m.LinkStatus, now: float) -> None:
        lk = self._link(s.link)
        t = unwrap(s.stamp, now)
        lk["packets"] += 1
        lk["frames"] += s.frames
        lk["bad_frames"] += s.bad_frames
        lk["snr"], lk["doppler"], lk["last"] = s.snr, s.doppler, t
        lk["history"].append((t, s.snr, s.frames, s.bad_frames))
        self._touch("link")

    def _on_link_health(self, h: m.LinkHealth, now: float) -> None:
        """The vehicle's report of one of its modems' outages (gone and back)."""
        from coex_transports.recovery import describe_seconds

        lk = self._link(h.link)
        t = unwrap(h.stamp, now)
        prev = lk.get("vehicle_modem")
        if prev is not None and prev["t"] > t:
            return  # an older report arriving late
        lk["vehicle_modem"] = {"t": _num(t, 1), "up": h.up, "outages": h.outages, "down_total": h.down_total,
                               "last_down": h.last_down}
        if h.up:
            text = (f"vehicle modem {h.link} was down {describe_seconds(h.last_down)} (outage {h.outages}; "
                    f"{describe_seconds(h.down_total)} down in all)")
        else:
            text = f"vehicle modem {h.link} is down (outage {h.outages}, reported over another link)"
        self._log(now, text, "warn")
        self._touch("link")

    def set_own_modem(self, link: int, up: bool, outages: int, down_total: float, last_down: float,
                      last_error: str, now: float) -> None:
        """Topside's own modem on ``link``: up or being reopened, its outages so far."""
        from coex_transports.recovery import describe_seconds

        lk = self._link(link)
        new = {"up": up, "outages": outages, "down_total": _num(down_total, 0), "last_down": _num(last_down, 0),
               "last_error": last_error if not up else ""}
        old = lk.get("topside_modem")
        if old is not None and (old["up"], old["outages"]) == (up, outages):
            if not up:  # the outage grows: shown, not logged
                lk["topside_modem"] = new
            return
        lk["topside_modem"] = new
        if outages and (old is not None or not up):
            self._log(now, f"topside modem {link}: " + (
                f"back after {describe_seconds(last_down)} (outage {outages})" if up else
                f"{last_error}; reopening it"), "warn")
        self._touch("link")

    # ------------------------------------------------------------------------ queues
    def _on_queue_status(self, q: m.QueueStatus, now: float) -> None:
        self.queue_stamp = unwrap(q.stamp, now)
        for st in q.streams:
            row = self.streams.setdefault(st.stream, {"stream": st.stream, "drops_total": 0})
            row.update(enabled=st.enabled, tier=st.tier, priority=st.priority, depth=st.depth,
                       queued_bytes=st.queued_bytes, oldest_age=st.oldest_age, drops=st.drops)
            row["drops_total"] += st.drops
        self._touch("queues")

    # ---------------------------------------------------------------------- commands
    def record_command(self, msg: m.Message, now: float, summary: str = "") -> None:
        """Remember a command the operator sent (shown as pending until answered)."""
        self._advance(now)
        cid = getattr(msg, "command_id", getattr(msg, "request_id", None))
        if cid is None:
            return
        kind = type(msg).__name__
        key = self._new_command_key()
        self.commands[key] = _Command(int(cid), kind, summary or kind, now, msg, by=self.actor)
        self.command_order.append(key)
        self._prune_commands()
        if isinstance(msg, m.ImageGoal):
            self._image(msg.image_id).goal = (msg.kind.name, msg.value)
            self._touch("images")
        elif isinstance(msg, m.ImageRegionRequest):
            self._touch("images")
        elif isinstance(msg, m.ImageByTimeRequest):
            self.image_queries.append({"command_id": msg.command_id, "stamp": msg.stamp,
                                       "direction": msg.direction.name, "sent": _num(now, 1)})
            self._touch("images")
        elif isinstance(msg, m.TimeSeriesRequest):
            self.series_requests.append({"command_id": msg.command_id, "channel": msg.channel,
                                         "start": unwrap(msg.start, now),
                                         "end": unwrap(msg.end, now),
                                         "max_error": msg.max_error, "sent": _num(now, 1)})
            self._touch("series")
        elif isinstance(msg, m.ScheduleUpdate):
            sch = self.schedules.get(msg.link)
            if sch is not None:
                sch["proposed"] = {"version": msg.version, "activate_cycle": msg.activate_cycle,
                                   "command_id": msg.command_id, "status": "sent",
                                   "slots": [{"owner": s.owner, "duration": s.duration,
                                              "guard": s.guard, "min_priority": s.min_priority}
                                             for s in msg.slots]}
                self._touch("link")
        self._touch("commands")
        self._log(now, f"{self.actor + ' ' if self.actor else ''}sent {summary or kind}")

    def _new_command_key(self) -> int:
        """A key no other command of this console has (command ids wrap at 256 and are reused:
        a command is never looked up by its id alone)."""
        return max(self.commands, default=0) + 1

    def _prune_commands(self) -> None:
        """Forget commands that fell out of the list (``command_order`` keeps the newest 64)."""
        keep = set(self.command_order)
        for key in [k for k in self.commands if k not in keep]:
            del self.commands[key]

    def _find_command(self, command_id: int, message: m.Message | None = None) -> int | None:
        """The key of the newest command with ``command_id`` (and, when given, that message)."""
        for key in reversed(self.command_order):
            c = self.commands.get(key)
            if c is None or c.roi_key is not None or c.command_id != command_id:
                continue
            if message is None or c.message == message:
                return key
        return None

    def replace_command(self, built: m.Message, sent: m.Message, now: float) -> None:
        """The node sent ``sent`` for the command recorded as ``built`` (another command id)."""
        key = self._find_command(int(getattr(built, "command_id", -1)), built)
        if key is None:
            return
        old = self.commands[key]
        old.message, old.command_id = sent, int(getattr(sent, "command_id", 0))
        if isinstance(sent, m.ScheduleUpdate):
            sch = self.schedules.get(sent.link)
            if sch is not None and sch.get("proposed"):
                sch["proposed"]["command_id"] = sent.command_id
                sch["proposed"]["activate_cycle"] = sent.activate_cycle
        self._touch("commands", "link")

    def record_regions(self, regions: Sequence[Any], now: float, summary: str) -> None:
        """Remember map regions a bathymetry receiver will request (and retry) for us."""
        self._advance(now)
        for r in regions:
            if id(r) in self._region_ids:
                continue
            self._region_ids.add(id(r))
            self._region_count += 1
            key = -self._region_count
            self.roi[key] = _RoiRequest(r.level, r.x0, r.y0, r.w, r.h, now, r)
            text = f"{summary}: {region_words(self, r)}"
            ckey = self._new_command_key()
            self.commands[ckey] = _Command(-1, "MapRoiRequest", text, now,
                                           m.MapRoiRequest(0, r.level, r.x0, r.y0, r.w, r.h,
                                                           True, (), 0),
                                           status="queued", roi_key=key, by=self.actor)
            self.command_order.append(ckey)
            self._prune_commands()
            self._log(now, f"{self.actor + ' ' if self.actor else ''}requested {text}")
        self._touch("map", "commands")

    def _command_result(self, command_id: int, status: Any, now: float,
                        command: m.Message | None = None) -> None:
        """The vehicle's answer to a command. The node gives the command it answers the first
        time (``command``); a repeated answer (the vehicle answers every re-send) comes without
        it and changes nothing, nor does an answer to a command already answered: ids wrap at
        256, so an old answer must never land on a newer command that reuses the id."""
        name = status.name if hasattr(status, "name") else str(status)
        new = name.lower()
        key = self._find_command(command_id, command)
        if key is None and command is None:
            last = self._foreign_acks.get(command_id)
            if last is None or last[0] != name or now - last[1] > 600:
                self._log(now, f"vehicle answered command {command_id}: {new} "
                               "(not sent from this console)")
            self._foreign_acks[command_id] = (name, now)
            return
        if key is None:
            # a command the topside node sent for someone else (a script, a receiver)
            key = self._new_command_key()
            self.commands[key] = _Command(command_id, type(command).__name__,
                                          f"{type(command).__name__} (by the node)", now,
                                          cast(m.Message, command))
            self.command_order.append(key)
            self._prune_commands()
        cmd = self.commands[key]
        if cmd.status == new:
            return  # the same answer again (a re-send answered): nothing new
        if cmd.status not in OPEN_COMMAND_STATES:
            return  # already answered for good: a late or repeated answer changes nothing
        was_pending = cmd.status == "pending"
        cmd.status, cmd.answered = new, now
        cmd.reason = ack_reason(cmd.message, name, was_pending)
        if isinstance(cmd.message, m.ScheduleUpdate):
            sch = self.schedules.get(cmd.message.link)
            if sch is not None and sch.get("proposed"):
                sch["proposed"]["status"] = new
            self._touch("link")
        if isinstance(cmd.message, m.ImageByTimeRequest | m.ImageGoal | m.ImageRegionRequest):
            self._touch("images")
        self._touch("commands")
        if isinstance(cmd.message, m.SurveyCommand):
            return  # the survey receiver's product says it, with the reason (_survey_product)
        self._log(now, f"{cmd.summary}: {new}" + (f" ({cmd.reason})" if cmd.reason else ""),
                  "info" if name in ("ACCEPTED", "PENDING") else "warn")

    def _on_command_ack(self, a: m.CommandAck, now: float) -> None:
        self._command_result(a.command_id, a.status, now)

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

    def _snap_map(self) -> dict[str, Any]:
        rx = self.map_receiver
        levels = []
        for level in sorted(rx.levels(), reverse=True) if rx is not None else ():
            geometry = rx.geometry(level)
            if geometry is None:
                continue
            c, side = geometry
            version = rx.level_version(level)
            cached = self._map_summary.get(level)
            if cached is None or cached[0] != version:
                # from the receiver's running summary and its coverage in at most MAP_BLOCKS
                # blocks (every subgrid of a small level): a big level is never read whole
                summary = rx.level_summary(level)
                span, keys, ts = rx.coverage(level, MAP_BLOCKS)
                p = rx.level_product(level)
                pc = float(p.meta["cell_size"])
                px0, py0 = float(p.meta["x0"]), float(p.meta["y0"])
                image = [px0, py0, px0 + p.data.shape[1] * pc, py0 + p.data.shape[0] * pc]
                cached = (version, summary, span, keys, ts, image, int(p.meta.get("step", 1)))
                self._map_summary[level] = cached
            _, summary, span, keys, ts, image, step = cached
            if summary is None or not summary["subgrids"] or summary["extent"] is None:
                continue
            ix0, iy0, ix1, iy1 = summary["extent"]
            cells = int(summary["cells"])
            # gaps: blocks of tile_span x tile_span subgrids inside the extent with no data
            bx = math.ceil(ix1 / span) - math.floor(ix0 / span)
            by = math.ceil(iy1 / span) - math.floor(iy0 / span)
            empty = max(0, bx * by - len(keys))
            block_m = span * side * c
            levels.append({
                "level": level, "cell": c, "side": side, "subgrids": int(summary["subgrids"]),
                "cells": cells, "coverage_m2": cells * c * c,
                "fill_pct": round(100.0 * cells / max(1, (ix1 - ix0) * (iy1 - iy0) * side * side)),
                "gaps": empty, "gap_block_m": block_m,
                "gap_note": gap_words(empty, block_m, int(summary["subgrids"]) * side * side,
                                      cells),
                "x0": float(ix0 * side * c), "y0": float(iy0 * side * c),
                "x1": float(ix1 * side * c), "y1": float(iy1 * side * c),
                "newest_age": _num(self.now - float(summary["newest"]), 1),
                "oldest_age": _num(self.now - float(summary["oldest"]), 1),
                # absolute times (s): the page takes the ages from its clock, so that a level
                # that did not change is the same in every update (and need not be resent)
                "newest": _num(float(summary["newest"]), 1),
                "oldest": _num(float(summary["oldest"]), 1),
                "version": version, "png": f"/map/{level}.png?v={version}",
                # where the picture goes (the receiver's drawn array, which may be larger than
                # what is held, and coarser: ``step`` level cells per pixel)
                "image": image, "step": step,
                # per block of tile_span x tile_span subgrids: the time of its oldest data
                "tile_span": span,
                "tiles": np.column_stack([keys, np.round(ts)]).astype(np.int64).tolist(),
            })
        meta = rx.metadata if rx is not None else None
        zr = self._zrange
        return {
            "meta": None if meta is None else {
                "resolution": meta.resolution, "vertical_resolution": meta.vertical_resolution,
                "subgrid_side": meta.subgrid_side, "levels": meta.levels,
                "origin_lat": meta.origin_lat, "origin_lon": meta.origin_lon,
                "pending": meta.pending},
            "levels": levels, "zrange": None if zr is None else [zr[0], zr[1]],
            "targets": list(self.targets) + self._auto_targets(),
            "detections": list(self.detections),
            "requests": [self._snap_roi(r) for r in sorted(self.roi.values(),
                                                          key=lambda r: r.sent)][-40:],
        }

    def _auto_targets(self) -> list[dict[str, Any]]:
        """Candidate targets flagged on the finest level held at 2 m or better (cells standing
        out from their surroundings, the bathymetry plugin's ``find_targets``), if it is drawn
        whole (a level too big for that is a decimated overview: no car stands out in it)."""
        rx = self.map_receiver
        if not self.auto_targets or rx is None:
            return []
        fine = [lv for lv in rx.levels() if (rx.geometry(lv) or (99.0, 0))[0] <= 2.0
                and rx.level_product(lv).meta.get("step", 1) == 1]
        if not fine:
            return []
        level = min(fine)
        summary = rx.level_summary(level)
        version, count = rx.level_version(level), int(summary["subgrids"]) if summary else 0
        last = self._targets_cache[0]
        # a big map changes with every subgrid: look again once 5% more of it has come in
        stale = (last is None or last[0] != level or version < last[1]
                 or version - last[1] >= max(1, count // 20))
        if stale:
            from coex_plugins.bathymetry import find_targets

            grid = self.level_grid(level)
            found: list[dict[str, Any]] = []
            if grid is not None:
                z, x0, y0, cell = grid
                cands = find_targets(z, cell=cell, x0=x0, y0=y0, threshold=self.target_threshold,
                                     min_cells=self.target_min_cells)
                for c in sorted(cands, key=lambda c: -c.height):
                    if len(found) >= self.max_targets:
                        break
                    if any(math.hypot(c.x - f["x"], c.y - f["y"]) < self.target_spacing
                           for f in found):
                        continue  # one marker per object
                    found.append({"x": _num(c.x, 1), "y": _num(c.y, 1),
                                  "height": _num(c.height, 2), "cells": int(c.cells),
                                  "level": level, "auto": True})
            self._targets_cache = ((level, version), found)
        return list(self._targets_cache[1])

    def subgrid_metres(self, level: int) -> float:
        """The side of a subgrid of ``level`` in metres."""
        rx = self.map_receiver
        geometry = rx.geometry(level) if rx is not None else None
        meta = rx.metadata if rx is not None else None
        if geometry is not None:
            return float(geometry[0] * geometry[1])
        if meta is not None:
            return float(meta.resolution * 2 ** level * meta.subgrid_side)
        return 8.0 * 2 ** level

    def _snap_roi(self, r: _RoiRequest) -> dict[str, Any]:
        """A region request as the bathymetry receiver sends and retries it: ``waiting`` (not
        sent yet), ``sent``, ``queued`` (the vehicle queued ``queued`` subgrids for it; asked
        again until it has nothing newer), ``waiting for survey`` (the request stands on the
        vehicle for ``awaiting_survey`` subgrids not surveyed yet) or ``nothing newer`` (done)."""
        rx = self.map_receiver
        geometry = rx.geometry(r.level) if rx is not None else None
        meta = rx.metadata if rx is not None else None
        if geometry is not None:
            span = geometry[0] * geometry[1]
        elif meta is not None:
            span = meta.resolution * 2 ** r.level * meta.subgrid_side
        else:
            span = 8.0 * 2 ** r.level
        region = r.region
        rid = region.request_id if region.request_id is not None else -1
        queued = getattr(region, "queued", None)
        waiting = getattr(region, "waiting", 0)
        got = max(int(getattr(r, "got", 0) or 0), int(queued or 0))
        r.got = got
        # ``status``: the request as the receiver sends it; ``state``: what it means for the
        # operator (requested, in flight, waiting for data, filled, nothing to send)
        if region.done:
            status = "nothing newer"
            state = "filled" if got else "nothing to send"
        elif queued:
            status, state = "queued", "in flight"
        elif waiting:
            status, state = "waiting for survey", "waiting for data"
        elif region.sends:
            status, state = "sent", "requested"
        else:
            status, state = "waiting", "requested"
        text = {"requested": "asked" + (f" ({region.sends}x)" if region.sends > 1 else "")
                             if region.sends else "waiting for a topside slot",
                "in flight": f"{queued} subgrid{'s' if queued != 1 else ''} on the way",
                "waiting for data": f"{waiting} subgrid{'s' if waiting != 1 else ''} not surveyed yet",
                "filled": f"filled ({got} subgrid{'s' if got != 1 else ''})",
                "nothing to send": "nothing to send: topside had it all"}[state]
        return {"request_id": rid, "level": r.level, "x0": r.x0, "y0": r.y0,
                "w": r.w, "h": r.h, "status": status, "state": state, "text": text,
                "got": got, "queued": queued, "awaiting_survey": waiting,
                "sent": _num(r.sent, 1),
                "rect": [r.x0 * span, r.y0 * span, (r.x0 + r.w) * span, (r.y0 + r.h) * span]}

    def _snap_images(self) -> dict[str, Any]:
        items = []
        for img in sorted(self.images.values(), key=lambda i: (i.t or 0, i.image_id)):
            info = img.decoded_meta
            total = info.get("total_bytes")
            got = int(info.get("held_bytes", 0) or 0)
            items.append({
                "image_id": img.image_id, "t": _num(img.t, 1),
                "stamp": info.get("stamp"), "x": info.get("x"), "y": info.get("y"),
                "width": info.get("width"), "height": info.get("height"),
                "total_bytes": total, "bytes_received": got,
                "fraction": _num(got / total, 3) if total else None,
                "goal": None if img.goal is None else {"kind": img.goal[0], "value": img.goal[1]},
                "thumb": (f"/image/{img.image_id}.png?v={img.decoded_version}"
                          if img.decoded is not None else None),
                "full": (f"/image/{img.image_id}.png?full=1&v={img.decoded_version}"
                         if img.decoded is not None else None),
                "layers": info.get("layers"), "layers_complete": info.get("layers_complete"),
                "packets": info.get("packets"), "packets_used": info.get("packets_used"),
                "bytes_used": info.get("bytes_used"), "complete": info.get("complete"),
                "footprint": self._footprint(img),
                "precincts": info.get("precincts"),
                "regions": self._image_regions(img),
                "meta": img.decoded_meta,
            })
        return {"items": items, "queries": self.image_queries[-10:],
                "progress": self.progress_info}

    def _image_regions(self, img: _Image) -> list[dict[str, Any]]:
        """The regions asked of an image (the newest :data:`MAX_IMAGE_REGIONS`): the ones this
        console sent, with their command's state (and the rejection's reason), and the ones the
        imagery receiver lists (asked through it: by this console on a node, or by a script),
        with the quality layers complete inside each. ``box`` is ``[x0, y0, x1, y1]`` (image
        pixels, x1 and y1 exclusive); ``state`` is ``requested``, ``waiting``, ``accepted`` or
        ``rejected``; ``value`` is in dB for a quality goal."""
        known = {(int(r.get("command_id", -1)), tuple(int(v) for v in r.get("box", ()))): r
                 for r in getattr(img, "regions", ()) or ()}
        layers = img.decoded_meta.get("layers")
        out: list[dict[str, Any]] = []
        for key in self.command_order:
            c = self.commands.get(key)
            msg = c.message if c is not None else None
            if c is None or not isinstance(msg, m.ImageRegionRequest) or msg.image_id != img.image_id:
                continue
            box = (msg.x0, msg.y0, msg.x1, msg.y1)
            rx_row = known.pop((msg.command_id, box), None)
            state = {"sent": "requested", "queued": "requested", "pending": "waiting",
                     "accepted": "accepted"}.get(c.status, "rejected")
            if c.status in OPEN_COMMAND_STATES and rx_row is not None \
                    and rx_row.get("state") in ("accepted", "rejected", "waiting"):
                state = str(rx_row["state"])  # the receiver heard the answer first
            out.append({"command_id": msg.command_id, "box": list(box),
                        "kind": m.RegionGoal(msg.kind).name.lower(),
                        "value": msg.value / 10 if msg.kind == m.RegionGoal.QUALITY else msg.value,
                        "state": state,
                        "reason": (getattr(c, "reason", "") or ack_reason(msg, "REJECTED"))
                        if state == "rejected" else "",
                        "time": _num(c.sent, 1), "by": getattr(c, "by", ""),
                        "layers_complete": None if rx_row is None else rx_row.get("layers_complete"),
                        "layers": layers, **self._served(rx_row)})
        for (cid, box), r in known.items():  # asked through the receiver by someone else
            state = str(r.get("state", "requested"))
            out.append({"command_id": cid, "box": list(box), "kind": str(r.get("kind", "quality")),
                        "value": r.get("value"), "state": state,
                        "reason": "refused by the vehicle" if state == "rejected" else "",
                        "time": _num(r.get("time"), 1), "by": "",
                        "layers_complete": r.get("layers_complete"), "layers": layers, **self._served(r)})
        out.sort(key=lambda r: r["time"] or 0.0)
        return out[-MAX_IMAGE_REGIONS:]

    def _served(self, rx_row: Mapping[str, Any] | None) -> dict[str, Any]:
        """How the vehicle serves a region, from the receiver's row: ``served`` (``crop`` or
        ``packets``; None while unknown), ``bytes`` that arrived for it, and ``crop``: the crop
        (its image id, size, body bytes held and in all, complete, shown over the image, and
        ``png``, the picture of what it shows) or None."""
        if rx_row is None:
            return {"served": None, "bytes": None, "crop": None}
        crop = rx_row.get("crop")
        out: dict[str, Any] = {"served": rx_row.get("served"), "bytes": rx_row.get("bytes"), "crop": None}
        if isinstance(crop, Mapping):
            cid = int(crop.get("image_id", -1))
            held = self.crops.get(cid)
            out["crop"] = {k: crop.get(k) for k in ("image_id", "width", "height", "total_bytes", "held_bytes",
                                                    "complete", "shown")}
            out["crop"]["png"] = (f"/crop/{cid}.png?v={held.decoded_version}"
                                  if held is not None and held.decoded is not None else None)
        return out

    def _footprint(self, img: _Image) -> list[float] | None:
        """The seafloor an image covers, ``[width, height]`` in metres: the camera's field of
        view (:attr:`camera_fov`, degrees across and along) at the altitude the vehicle reported
        nearest the image's time. None without a position or an altitude."""
        info = img.decoded_meta
        if info.get("x") is None or img.t is None:
            return None
        alt = None
        best = math.inf
        for t, a in self.altitudes:
            if abs(t - img.t) < best and a is not None:
                best, alt = abs(t - img.t), a
        if alt is None or best > 300:
            return None
        fx, fy = self.camera_fov
        return [_num(2 * alt * math.tan(math.radians(fx) / 2), 2),
                _num(2 * alt * math.tan(math.radians(fy) / 2), 2)]

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

    def _snap_link(self) -> dict[str, Any]:
        links = []
        for lk in sorted(self.links.values(), key=lambda x: x["link"]):
            d = {k: v for k, v in lk.items() if k != "history" and not k.startswith("_")}
            d["history"] = [[_num(t, 1), snr, f, b] for t, snr, f, b in lk["history"]]
            # bytes received per cycle: [cycle start, bytes, cycle length] (the open cycle last)
            d["throughput"] = [[_num(t, 1), int(n), _num(c, 1)]
                               for t, n, c in lk.get("_rx") or ()]
            d["age"] = _num(self.now - lk["last"], 1) if lk["last"] is not None else None
            links.append(d)
        schedules = [{k: v for k, v in self.schedules[link].items() if not k.startswith("_")}
                     for link in sorted(self.schedules)]
        return {"links": links, "schedules": schedules,
                "node_id": self.node_id, "vehicle_id": self.vehicle_id,
                "bad_frames": self.bad_frames}

    def _snap_queues(self) -> dict[str, Any]:
        rows = []
        for sid, row in sorted(self.streams.items()):
            d = dict(row)
            d["name"] = self.stream_names.get(sid, f"stream {sid}")
            rows.append(d)
        return {"t": self.queue_stamp,
                "age": _num(self.now - self.queue_stamp, 1) if self.queue_stamp else None,
                "streams": rows}

    def _snap_commands(self) -> list[dict[str, Any]]:
        out = []
        surveys: dict[int, dict[str, Any]] | None = None
        for key in reversed(self.command_order):
            c = self.commands[key]
            status, reason = c.status, getattr(c, "reason", "")
            if c.roi_key is not None and c.roi_key in self.roi:
                roi = self._snap_roi(self.roi[c.roi_key])
                status, reason = roi["state"], roi["text"]
            elif isinstance(c.message, m.SurveyCommand):  # the survey's own state
                if surveys is None:
                    surveys = self._survey_metas()
                meta = surveys.get(int(c.message.survey_id))
                if meta is not None:
                    status = str(meta.get("state") or status)
                    if status in ("rejected", "aborted", "given up") and meta.get("text"):
                        reason = str(meta["text"])
            answer, img = "", None
            if isinstance(c.message, m.ImageByTimeRequest) and status == "accepted":
                img = self.by_time_answer(c.message, c.sent)
                answer = (f"answered by image #{img.image_id} taken {hms(img.t)}"
                          if img is not None else "answered: the image is on its way")
            out.append({"command_id": c.command_id, "kind": c.kind, "summary": c.summary,
                        "answer": answer, "image_id": None if img is None else img.image_id,
                        "sent": _num(c.sent, 1), "status": status,
                        "answered": _num(c.answered, 1), "by": getattr(c, "by", ""),
                        "reason": reason})
        return out

    def _snap_log(self) -> list[dict[str, Any]]:
        return [{k: v for k, v in e.items() if k not in ("key", "base")} for e in list(self.log)[-60:]]


def map_delta(full: Mapping[str, Any], held: dict[int, Any]) -> dict[str, Any]:
    """The map section ``full`` as a delta against what a client holds (``held``: level ->
    (version, {(ix, iy): t}, tile_span), updated to what it holds after it): see
    :meth:`ConsoleState.changes`."""
    levels = []
    present = set()
    for lv in full["levels"]:
        n = int(lv["level"])
        present.add(n)
        tiles = {(int(a), int(b)): int(t) for a, b, t in lv["tiles"]}
        had = held.get(n)
        if had is None or had[2] != lv["tile_span"]:
            levels.append(lv)
        elif had[0] == lv["version"]:
            levels.append({"level": n, "same": True})
        else:
            old = had[1]
            part = {k: v for k, v in lv.items() if k != "tiles"}
            part["tiles_changed"] = [[a, b, t] for (a, b), t in tiles.items() if old.get((a, b)) != t]
            part["tiles_removed"] = [[a, b] for (a, b) in old if (a, b) not in tiles]
            levels.append(part)
        held[n] = (lv["version"], tiles, lv["tile_span"])
    for n in [n for n in held if n not in present]:
        del held[n]
    return {**full, "levels": levels, "delta": True}


_HANDLERS: dict[type, Callable[[ConsoleState, Any, float, int | None], None]] = {
    m.VehicleStatus: lambda s, msg, now, link: s._on_status(msg, now),
    m.LinkStatus: lambda s, msg, now, link: s._on_link_status(msg, now),
    m.LinkHealth: lambda s, msg, now, link: s._on_link_health(msg, now),
    m.QueueStatus: lambda s, msg, now, link: s._on_queue_status(msg, now),
    m.CommandAck: lambda s, msg, now, link: s._on_command_ack(msg, now),
}
