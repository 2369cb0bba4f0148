"""The console's declared state: every attribute the parts of
:class:`~coex_apps.console.state.ConsoleState` share, with its type, made in one place
(:meth:`ConsoleModel.__init__`), and the bookkeeping they all use (section versions, the event
log, the console's clock).

The parts of the state (:mod:`.mapview`, :mod:`.surveys`, :mod:`.images`, :mod:`.linkview`,
:mod:`.commands`) are subclasses of :class:`ConsoleModel`: what each reads and writes is
declared here, so a type checker reads every part against one declaration. A part that needs
another part's behaviour says so by subclassing it (the commands list shows what became of a
map region, a survey and an image: :class:`~.commands.CommandsView` is a map, surveys and images
view). Nothing here does I/O or reads a clock.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from coex import ModalityReceiver
from coex import messages as m
from coex_plugins.bathymetry import BathymetryReceiver
from coex_plugins.survey import SurveyProduct

from .records import _Command, _Crop, _Image, _RoiRequest
from .words import _counted, _num

if TYPE_CHECKING:
    from coex_plugins.navigation import Navigation

__all__ = ["MAX_IMAGES", "MAX_REPEATS", "OPEN_COMMAND_STATES", "REPEAT_WINDOW", "SECTIONS", "ConsoleModel", "MapSummary"]

#: The sections of a snapshot, in the order the page lays them out.
SECTIONS = ("vehicle", "map", "surveys", "images", "series", "other", "link", "queues", "commands",
            "log", "navigation")

#: A command in these states may still be answered (``pending``: it stands on the vehicle).
OPEN_COMMAND_STATES = ("sent", "pending")

#: Events of one kind (one log key) within this many seconds of the first are counted in one
#: entry of the event log, updated in place, instead of one entry each.
REPEAT_WINDOW = 600.0
#: Counted entries remembered at most (beyond it the oldest start again as a new entry).
MAX_REPEATS = 64

#: Images the console keeps (the newest by time; the imagery receiver's ``max_images`` default):
#: a dive of several days does not grow the console's memory and saved state with every picture
MAX_IMAGES = 256

#: A level's drawn summary, cached per level version: (version, the receiver's summary, coverage
#: span, block keys, their oldest stamps, the picture's box [x0, y0, x1, y1], its step)
MapSummary = tuple[int, Any, int, Any, Any, list[float], int]


class ConsoleModel:
    """What the console knows: every attribute of the state, declared and typed (see the
    module docstring). ``stream_names`` names queue streams (id -> name); ``node_id`` is
    topside's node id; ``receivers`` the node's topside receivers (None: the console makes its
    own from the registry, a view of raw messages)."""

    #: the operator whose action is running (set by :meth:`ConsoleActions.dispatch`)
    actor: str = ""
    #: images kept (the newest): :data:`MAX_IMAGES`, or fewer when the imagery receiver shown
    #: keeps fewer (``coex topside`` sets it from the receiver's ``max_images``; not saved)
    max_images: int = MAX_IMAGES
    #: topside's navigation (:class:`coex_plugins.navigation.Navigation`: USBL fixes, the drift
    #: estimate; ``[usbl]`` of the topside file, issue 56), or None; not saved
    navigation: Navigation | None = None

    def __init__(
        self,
        *,
        node_id: int = 1,
        vehicle_id: int = 2,
        stream_names: Mapping[int, str] | None = None,
        max_track: int = 5000,
        max_log: int = 200,
        auto_targets: bool = True,
        receivers: Mapping[str, ModalityReceiver] | None = None,
    ) -> None:
        self.node_id: int = node_id
        self.vehicle_id: int = vehicle_id
        #: the newest time the console heard of (time enters as ``now``)
        self.now: float = 0.0
        self.stream_names: dict[int, str] = dict(stream_names or {})
        self.versions: dict[str, int] = dict.fromkeys(SECTIONS, 0)
        self._init_vehicle(max_track, receivers)
        self._init_map(auto_targets)
        self._init_products()
        self._init_link_and_log(max_log)

    def _init_vehicle(self, max_track: int, receivers: Mapping[str, ModalityReceiver] | None) -> None:
        """The vehicle's state: its status, the end of contact, its track, the receivers shown."""
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
        self.own_receivers: bool = receivers is None

    def _init_map(self, auto_targets: bool) -> None:
        """The map: the levels' drawn summaries, candidate targets, detections, regions asked."""
        #: per level: its drawn summary (:data:`MapSummary`)
        self._map_summary: dict[int, MapSummary] = {}
        #: per level: (version, its picture as a PNG)
        self._png: dict[int, tuple[int, bytes]] = {}
        self.targets: list[dict[str, Any]] = []
        #: Flag candidate targets on the finest level (threshold in metres, minimum cells).
        self.auto_targets: bool = auto_targets
        self.target_threshold: float = 0.8
        self.target_min_cells: int = 3
        #: At most this many markers, at least this far apart (metres).
        self.max_targets: int = 8
        self.target_spacing: float = 6.0
        #: ((level, version) looked at, or None; the candidates found there)
        self._targets_cache: tuple[tuple[int, int] | None, list[dict[str, Any]]] = (None, [])
        #: the vehicle's detections (the detections receiver's rows): suggestions, shown on the
        #: map apart from the candidates the console or the operator flagged
        self.detections: list[dict[str, Any]] = []
        #: map regions asked (key: minus their number)
        self.roi: dict[int, _RoiRequest] = {}
        self._region_count: int = 0
        self._region_sig: tuple[Any, ...] = ()
        self._region_ids: set[int] = set()
        #: A bathymetry receiver whose operator regions (not its automatic gap filling) are
        #: shown even when someone else asked for them (a script, another tool).
        bathymetry = self.receivers.get("bathymetry")
        self.region_source: BathymetryReceiver | None = (
            bathymetry if isinstance(bathymetry, BathymetryReceiver) else None)
        #: the depth range of the colour scale (lowest, highest), None before any level
        self._zrange: tuple[float, float] | None = None

    def _init_products(self) -> None:
        """Surveys, images and crops, time series and other modalities' products."""
        # surveys: the survey receiver's records (what it asked and what the vehicle answered);
        # products of a survey receiver the console does not hold (rare) are kept here
        self.survey_products: dict[int, SurveyProduct] = {}
        #: (survey id, record version, state) of every record last looked at (None: look again)
        self._survey_sig: tuple[tuple[int, int, str], ...] | None = None
        #: survey id -> (record version, its product)
        self._survey_rows: dict[int, tuple[int, SurveyProduct]] = {}
        #: survey id -> the history entries already in the event log
        self._survey_logged: dict[int, list[tuple[float, str, str]]] = {}
        # images
        self.images: dict[int, _Image] = {}
        #: the crops of images the receiver holds, by crop id (the newest MAX_CROPS)
        self.crops: dict[int, _Crop] = {}
        self.progress_info: dict[str, Any] | None = None
        self.image_queries: list[dict[str, Any]] = []
        #: (time, altitude) of the vehicle's statuses: where an image's footprint comes from
        self.altitudes: deque[tuple[float, float]] = deque(maxlen=2000)
        #: The camera's field of view in degrees (across, along): image footprints on the map.
        self.camera_fov: tuple[float, float] = (60.0, 45.0)
        # series: channel -> what the series panel shows (times, values, bounds as arrays)
        self.series: dict[int, dict[str, Any]] = {}
        self.series_requests: list[dict[str, Any]] = []
        # other modalities: name -> product key -> what the generic panel shows
        self.other: dict[str, dict[str, dict[str, Any]]] = {}

    def _init_link_and_log(self, max_log: int) -> None:
        """The links and their schedules, the queues, the commands and the event log."""
        # link
        self.links: dict[int, dict[str, Any]] = {}
        self.schedules: dict[int, dict[str, Any]] = {}
        self.bad_frames: int = 0
        # queues
        self.queue_stamp: float | None = None
        self.streams: dict[int, dict[str, Any]] = {}
        # commands and log
        self.commands: dict[int, _Command] = {}
        self.command_order: deque[int] = deque(maxlen=64)
        #: command id -> (the answer, when) of answers to commands not sent from here
        self._foreign_acks: dict[int, tuple[str, float]] = {}
        self.log: deque[dict[str, Any]] = deque(maxlen=max_log)
        #: the number of the next log entry
        self._log_seq: int = 0
        #: log key -> its counted entry (one in ``log``), see :meth:`_log`
        self._repeats: dict[str, dict[str, Any]] = {}

    # -------------------------------------------------------------------- bookkeeping
    def _touch(self, *sections: str) -> None:
        for s in sections:
            self.versions[s] += 1

    def _advance(self, now: float) -> None:
        if now > self.now:
            self.now = float(now)

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
        if key is not None and entry is not None and (
                now - float(entry["t"] or 0.0) > REPEAT_WINDOW or not self.log
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
