"""The scripted topside operator of ``coex demo`` (``--operator script``): what the 2022
operators did by hand, deciding only from what reached topside.

* **The map.** Every half TDMA cycle it looks for bumps on a coarse level and asks for the 1 m
  level around them; in the 1 m map it measures each bump (height above the local background,
  footprint, length, width and orientation from the cells' second moments) and scores how
  target-like it is (:func:`target_likeness`: an object of the sizes sought, :data:`TARGET_SIZES`,
  2 to 8 m long by default; a spike or a wide hummock scores low). A bump of the map alone that
  the map as it is now no longer shows (a low bump of a partly received map, gone when the rest
  of its ground arrived) gets no camera line unless it shows again. Candidates are visited in
  that order while camera time remains: the operator sends the vehicle one survey command per
  candidate (a camera line across its long axis, high enough for a frame to hold it:
  :func:`camera_altitude`, queued behind the lines already sent), over the acoustic link like
  every other command; the vehicle's answers (accepted, rejected with its reason, started,
  completed) come back.
* **The images.** Once the vehicle has passed over a candidate (the vehicle's reports of the
  line, else the closest approach along the track topside received, then the announced frame
  taken nearest the candidate), it asks for that image. Its eye (:mod:`coex_apps.demo.eye`)
  looks at the image as received, with nothing but the image, its announced position and time,
  the vehicle's altitude and the camera's field of view: a target (a car, a container, a hull,
  debris, or a straight-edged object of no known kind) near the candidate confirms it; an
  object too unclear to tell makes it ask for that object's region at a higher quality; an
  object cut by the frame's top or bottom edge, or sand, makes it step to the previous or next
  image; an object cut by the frame's left or right side (the line passed beside it) makes it
  send one more camera line, through where the eye's sighting puts the object (or, when six
  images showed no target and the received track passed more than 1.5 m from the candidate,
  through the candidate again: :meth:`Operator._reaim`, once per candidate); a natural object
  (a rock, a mound of living things), or too many tries, makes it move on.

It imports nothing of the simulation's truth or its labelled renderer (``tests/test_demo_eye.py``).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from coex import Node, RequestRejected, unwrap
from coex.messages import SurveyCommand, VehicleStatus
from coex.messages import command_id as command_id_of
from coex_plugins.bathymetry import BathymetryReceiver, find_targets
from coex_plugins.bathymetry.relief import FLAT, SIZES, Bump, bumps, measure_bump, range_likeness
from coex_plugins.detections import DetectionsReceiver
from coex_plugins.imagery import ImageryReceiver
from coex_plugins.survey import SurveyReceiver

from .eye import TARGET_KINDS, Eye, Sight, metres_per_pixel
from .specs import (
    CAMERA_ASPECT,
    CAMERA_HFOV_DEG,
    CAMERA_PERIOD,
    CAMERA_SPEED,
    TRANSIT_ALTITUDE,
    TRANSIT_SPEED,
)

__all__ = ["CameraLine", "CandidateView", "Operator", "camera_altitude", "map_bumps", "measure", "target_likeness"]

#: the sizes of the targets sought (length, width, height ranges, m): the vehicle's relief
#: detector's default (2 to 8 m long), set for the mission, not for the scene
TARGET_SIZES = SIZES
#: candidates scoring below this are not worth camera time
MIN_SCORE = 0.05
#: a bump of the received 1 m map is the same candidate as one within this distance (m); a
#: candidate of the map alone with no bump of the map as it is now within it is gone (not worth
#: camera time until it shows again: :meth:`Operator.watch_map`)
GONE_RADIUS = 4.0
#: a bump of the received 1 m map peaks this high above its background (m), on a foot of at
#: least :data:`BUMP_MIN_CELLS` cells standing :data:`BUMP_FOOT` m above it
#: (:func:`~coex_plugins.bathymetry.relief.bumps`; the grid despiked first). A debris patch of 2
#: to 3 m has a main piece of 1 to 1.5 m: averaged into the 1 m cells it stands 0.5 to 0.9 m in
#: one cell, often with no neighbour 0.4 m up (issue 50: 0.7 m on a foot of two cells missed 32
#: of 60 development patches); the sand's ripples and the soundings' noise make one-cell bumps of
#: up to about 0.4 m (0.45 m: 6 bumps with no object in 30 development maps, 0.4 m: 31, 0.5 m:
#: 4). Values chosen on the development maps of ``bench/map_targets.py`` (seeds 1000-1029), as
#: ``docs/demo.md`` says.
BUMP_THRESHOLD = 0.5
BUMP_FOOT = 0.4
BUMP_MIN_CELLS = 1
#: layers of a requested image the vehicle sends first (its ``request_goal``: with the default
#: quality marks 20 / 25 / 30 / 35 dB, layer 3 is where the frame first reaches 30 dB), and the
#: most the operator asks for, in the region of the frame where something too blurry to tell
#: lies (layer 4: 35 dB)
CONFIRM_LAYERS = 3
MORE_LAYERS = 4
#: the operator never confirms a car from a preview: an image needs this many quality layers
#: (30 dB) before what it shows counts
MIN_CONFIRM_LAYERS = 3
#: pixels added around an unclear object's outline when the operator asks for its region
REGION_MARGIN = 24
#: images the operator looks at for one candidate before moving on
MAX_LOOKS = 6
#: an image is "at" a candidate when taken within this distance of it (m)
NEAR = 6.0
#: an object the eye sees is the candidate's when it lies within this distance of it (m)
SIGHT_RADIUS = 5.0
#: gaps in the 1 m map are asked for in tiles of this size (m), a few tiles per look, each tile
#: again after GAP_RETRY seconds at the earliest
GAP_TILE = 64.0
GAP_TILES_PER_LOOK = 2
GAP_RETRY = 600.0
#: region requests the operator keeps open at once (the uplink also carries image requests),
#: during the survey and during the camera pass
MAX_OPEN_MAP_REQUESTS = 12
MAX_OPEN_MAP_REQUESTS_CAMERA = 3
#: an image request the vehicle has not answered after this many TDMA cycles is asked again
ANSWER_CYCLES = 3
#: the highest camera line (m): below the altitude the vehicle transits at, so that a status
#: from a camera line is told from one in transit
MAX_CAMERA_ALTITUDE = TRANSIT_ALTITUDE - 1.0
#: metres added to an object's length across a camera line: where the line passes (a metre
#: either side) and the object's orientation measured in the 1 m map (15 degrees)
LINE_MARGIN = 2.5
#: the camera lines' speed (m/s): slower than the vehicle's usual camera speed, so that frames
#: are 1.8 m apart and one of them holds an object up to 6 m along the line whole
LINE_SPEED = 0.3
#: a camera line reaches this far (m) either side of its candidate
LINE_HALF = 15.0
#: a camera line is sent only when topside expects the vehicle to be done with the lines already
#: sent within this many seconds (s; two TDMA cycles: the command's tries on a lossy uplink):
#: each line is put into the vehicle's frame by the drift predicted for when it is flown, and that
#: prediction is only as good as its horizon is short (issue 56; ``bench/navigation_lines.py``)
LINE_AHEAD = 240.0
#: every camera line is flown at the altitude that holds the largest object sought (length,
#: width; :data:`TARGET_SIZES`) in a frame (:func:`camera_altitude`)
LINE_ALTITUDE_FOR = (TARGET_SIZES[0][1], TARGET_SIZES[1][1])
#: camera lines re-aimed per candidate at most: when the eye sees the candidate's object cut by
#: the frame's left or right side (the line passed beside it), or the received track shows the
#: line passed more than :data:`REAIM_OFF` metres from it and no image showed a target
MAX_REAIMS = 1
REAIM_OFF = 1.5


@dataclass
class CandidateView:
    """A bump in the received 1 m map as the operator measured it, or a detection the vehicle
    sent (until the operator can measure it in the received map)."""

    x: float
    y: float
    height: float
    cells: int
    length: float
    width: float
    score: float
    found_at: float
    flatness: float = FLAT
    #: orientation of its long axis (degrees clockwise from north, 0-180)
    orientation: float = 0.0
    #: the vehicle's detection of it (its id) and when that first reached topside
    detection: int | None = None
    detected_at: float | None = None
    #: the operator measured it in the received 1 m map (not only the vehicle's measures)
    measured: bool = True
    #: when the received 1 m map last stopped showing it (a bump of the map alone, no camera line
    #: sent yet): not worth camera time while the map does not show it (:meth:`Operator.watch_map`)
    gone_at: float | None = None
    #: the camera pass over it: a survey command sent for it (and not refused), then what the
    #: operator made of the images
    planned: bool = False
    #: the survey id of its camera line
    survey_id: int | None = None
    #: why the vehicle will not fly its camera line (refused, or replaced by someone else's)
    refused: str | None = None
    passed_at: float | None = None
    #: a look from another line's pass came to a dead end (nothing earlier to step back to):
    #: only a pass after this time counts (its own camera line's)
    wait_after: float | None = None
    #: where its latest camera line was re-aimed (from the eye's sighting of it cut by the
    #: frame's side, or its own position when the received track passed off it), the re-aimed
    #: lines sent, and a re-aim asked for that the next camera round sends
    aim: tuple[float, float] | None = None
    reaims: int = 0
    reaim_want: tuple[float, float] | None = None
    want: tuple[float, str] | None = None  # (time, "nearest" | "before" | "after")
    want_goal: int | None = None  # image id of a pending request for more layers
    want_region: int | None = None  # command id of that request when it asked for a region
    request_at: float | None = None
    command_id: int | None = None  # of the latest request
    first_request_at: float | None = None
    #: bytes held of the image answering the latest request, and when they last grew
    progress: tuple[int, float] = (0, -math.inf)
    looked: list[int] = field(default_factory=list)
    looked_times: dict[int, float] = field(default_factory=dict)
    image_id: int | None = None
    confirmed_at: float | None = None
    #: what the eye made of it: a target kind (:data:`~coex_apps.demo.eye.TARGET_KINDS`: car,
    #: container, hull, debris, object), "natural" or "given up"
    verdict: str = ""
    verdict_image: int | None = None
    #: the eye's box (full-size pixels) round the object it confirmed, and what it measured
    evidence_box: tuple[int, int, int, int] | None = None
    evidence_sight: dict[str, Any] | None = None
    #: the image as received when the operator confirmed a car (for the referee), its capture
    #: time, position and received bytes
    evidence: Any = field(default=None, repr=False)
    evidence_time: float | None = None
    evidence_xy: tuple[float, float] | None = None
    evidence_bytes: int | None = None

    @property
    def done(self) -> bool:
        return bool(self.verdict)

    @property
    def point(self) -> tuple[float, float]:
        """Where its camera line aims: the re-aimed point, else the candidate."""
        return self.aim if self.aim is not None else (self.x, self.y)

    def distance(self, x: float, y: float) -> float:
        """Distance (m) from (x, y) to the candidate or to where its line was re-aimed."""
        d = math.hypot(x - self.x, y - self.y)
        return d if self.aim is None else min(d, math.hypot(x - self.aim[0], y - self.aim[1]))

    @property
    def confirmed(self) -> bool:
        """The eye saw a target here (its verdict is a target kind)."""
        return self.verdict in TARGET_KINDS


@dataclass
class CameraLine:
    """A camera line the operator sent (a LINE survey over a candidate), and what topside heard
    of it: the stamps of the vehicle's reports."""

    survey_id: int
    candidate: CandidateView
    start: tuple[float, float]
    end: tuple[float, float]
    speed: float
    sent_at: float
    #: the line's heading (degrees clockwise from north) and altitude (m)
    heading: float = 0.0
    altitude: float = 5.0
    state: str = "requested"
    #: the vehicle's stamps: set off for the line (STARTED 0), reached its start (STARTED 1), done
    set_off: float | None = None
    at_start: float | None = None
    completed: float | None = None

    @property
    def length(self) -> float:
        return math.hypot(self.end[0] - self.start[0], self.end[1] - self.start[1])

    @property
    def open(self) -> bool:
        """Still to be flown or being flown (as far as topside knows)."""
        return self.state in ("requested", "accepted", "started")

    def reported_pass(self) -> float | None:
        """When the camera passed the candidate, from the vehicle's reports: the line's start
        reached, plus half the line at its speed (or the line done, less that)."""
        half = self.length / 2 / self.speed
        if self.at_start is not None:
            return self.at_start + half
        if self.completed is not None:
            return self.completed - half
        return None


def camera_altitude(length: float, width: float, lowest: float) -> float:
    """The altitude (m) of a camera line over an object ``length`` x ``width`` metres, flown
    across its long axis: high enough that one frame holds the object across the line (its
    length and :data:`LINE_MARGIN` for the line's and the map's errors) and along it (its width,
    the distance between two frames, :data:`LINE_SPEED` x :data:`CAMERA_PERIOD`, and a metre),
    so that some frame shows its whole outline; at least ``lowest`` (the scenario's camera
    altitude) and at most :data:`MAX_CAMERA_ALTITUDE`. The operator flies every line at the
    altitude for the largest object sought (:data:`LINE_ALTITUDE_FOR`): the 1 m map measures a
    rounded or tapering object (a hull, a small car) shorter than it is."""
    span = 2.0 * math.tan(math.radians(CAMERA_HFOV_DEG) / 2.0)
    across = (length + LINE_MARGIN) / span
    along = (width + LINE_SPEED * CAMERA_PERIOD + 1.0) / (span * CAMERA_ASPECT)
    return round(min(max(across, along, lowest), MAX_CAMERA_ALTITUDE), 1)


def target_likeness(height: float, length: float, width: float, flatness: float = FLAT,
                    sizes: tuple[tuple[float, float], tuple[float, float], tuple[float, float]] = TARGET_SIZES) -> float:
    """How target-like a bump is, in [0, 1]: 1 for a bump of the sizes sought (``sizes``:
    length, width, height ranges), falling off outside them with the spreads a 1 m map allows,
    and lower for a rounded top (:func:`~coex_plugins.bathymetry.relief.range_likeness`)."""
    return range_likeness(height, length, width, flatness, sizes)


def measure(grid: np.ndarray, cell: float, x0: float, y0: float, cand: Any, now: float = 0.0,
            ) -> CandidateView | None:
    """Measure a :func:`find_targets` candidate in the 1 m grid
    (:func:`~coex_plugins.bathymetry.relief.measure_bump`) and score how target-like it is."""
    b = measure_bump(grid, cell, x0, y0, cand.peak_x, cand.peak_y, cand.height)
    return None if b is None else _view(b, now)


def _view(b: Bump, now: float) -> CandidateView:
    return CandidateView(round(b.x, 1), round(b.y, 1), round(b.height, 2), b.cells, round(b.length, 1),
                         round(b.width, 1), round(target_likeness(b.height, b.length, b.width, b.flatness), 3), now,
                         flatness=round(b.flatness, 2), orientation=round(b.orientation, 1))


def map_bumps(bathy: Any, now: float = 0.0) -> list[CandidateView]:
    """Every bump of a bathymetry receiver's 1 m level, measured and scored: a peak
    :data:`BUMP_THRESHOLD` m above its background (one cell is enough: a small debris patch's
    main piece) on a foot of :data:`BUMP_MIN_CELLS` cells or more :data:`BUMP_FOOT` m above it
    (:func:`~coex_plugins.bathymetry.relief.bumps`, the grid despiked first: a wild sounding on a
    car would make it a one-cell spike, and one on sand a bump). With a corrected
    map (a view that can ``place`` what is measured in the level as ``received``:
    :class:`~coex_plugins.navigation.CorrectedMap`), each bump is measured in the level as
    received and its centre placed by the map's correction: the corrected level is resampled by
    fractions of a cell, which spreads a one- or two-cell peak over its neighbours and lowers it."""
    place = getattr(bathy, "place", None)
    received = getattr(bathy, "received", None)
    source = received if place is not None and received is not None else bathy
    if 0 not in source.levels():
        return []
    p = source.level_product(0)
    if p.data is None:
        return []
    meta = dict(p.meta)
    grid, cell = np.asarray(p.data, dtype=float), float(meta["cell_size"])
    x0, y0 = float(meta["x0"]), float(meta["y0"])
    found = [b for _c, b in bumps(grid, cell=cell, x0=x0, y0=y0, threshold=BUMP_THRESHOLD,
                                  min_cells=BUMP_MIN_CELLS, max_area=40.0, foot=BUMP_FOOT)]
    if found and place is not None and source is not bathy:
        xy = np.asarray(place(0, [b.x for b in found], [b.y for b in found]), dtype=np.float64)
        found = [replace(b, x=float(x), y=float(y)) for b, (x, y) in zip(found, xy, strict=True)]
    return [_view(b, now) for b in found]


class Operator:
    """The scripted operator (see the module docstring). It knows the survey box (it planned the
    survey), the camera altitude it plans with and the camera's field of view, never the
    targets."""

    def __init__(self, topside: Node, receivers: dict[str, Any], box: tuple[float, float, float, float],
                 log: Callable[..., None], *, camera_altitude: float, cycle: float = 120.0, eye: Eye | None = None,
                 active: bool = True) -> None:
        self.topside = topside
        self.bathy: BathymetryReceiver = receivers["bathymetry"]
        #: the vehicle's detections (suggestions; absent: a vehicle without detectors)
        self.detections: DetectionsReceiver | None = receivers.get("detections")
        self.imagery: ImageryReceiver = receivers["imagery"]
        self.survey: SurveyReceiver = receivers["survey"]
        self.box = box
        self.log = log
        self.camera_altitude = camera_altitude
        self.cycle = cycle
        self.eye = eye or Eye()
        #: ``False`` (``--operator none``): the operator watches nothing and asks for nothing
        self.active = active
        self.track: list[tuple[float, float, float, float]] = []  # t, x, y, heading (received)
        #: t, altitude of every status received from a camera line
        self.altitudes: list[tuple[float, float]] = []
        #: every sight of the eye: image id -> what it saw there (for the report)
        self.sights: dict[int, list[dict[str, Any]]] = {}
        self.coarse_requested: list[tuple[float, float]] = []
        self.candidates: list[CandidateView] = []
        self.camera_phase = False
        #: the region requests made (image id, pixel box, command id, time, candidate)
        self.regions: list[dict[str, Any]] = []
        self.position: tuple[float, float] | None = None  # the newest reported position
        self.positions: list[tuple[float, float, float]] = []  # t, x, y of every status received
        #: the camera lines sent, by survey id
        self.lines: dict[int, CameraLine] = {}
        #: per gap tile: when last asked, how often, what was held then, requests that brought nothing
        self._gap_asked: dict[tuple[float, float], tuple[float, int, float, int]] = {}
        self._overview = [3, 2, 1]

    def inside(self, x: float, y: float, margin: float = 3.0) -> bool:
        x0, y0, x1, y1 = self.box
        return x0 + margin <= x <= x1 - margin and y0 + margin <= y <= y1 - margin

    # ------------------------------------------------------------------ what topside hears
    def on_status(self, s: VehicleStatus, now: float) -> None:
        # the status's own time (its stamp), not when it arrived: it may have waited for a slot
        self.position = (s.x, s.y)
        self.positions.append((unwrap(s.stamp, now), s.x, s.y))
        if s.altitude is not None and s.altitude <= MAX_CAMERA_ALTITUDE + 0.5:  # on a camera line
            self.track.append((unwrap(s.stamp, now), s.x, s.y, s.heading))
            self.altitudes.append((unwrap(s.stamp, now), float(s.altitude)))

    def level_grid(self, level: int) -> tuple[np.ndarray, float, tuple[float, float]] | None:
        """The received level ``level`` (cells, cell size, south-west corner), or None while
        no subgrid of it has arrived. Any other failure to read it is raised, not hidden."""
        if level not in self.bathy.levels():
            return None
        p = self.bathy.level_product(level)
        if p.data is None:
            return None
        meta = dict(p.meta)
        return np.asarray(p.data, dtype=float), float(meta["cell_size"]), (float(meta["x0"]), float(meta["y0"]))

    def bumps(self, level: int, threshold: float, **kw: Any) -> list[Any]:
        g = self.level_grid(level)
        if g is None:
            return []
        grid, cell, (x0, y0) = g
        return [c for c in find_targets(grid, cell=cell, x0=x0, y0=y0, threshold=threshold, **kw)
                if self.inside(c.x, c.y)]

    def measured(self, now: float) -> list[CandidateView]:
        """Every bump of the received 1 m map inside the survey box, measured and scored
        (:func:`map_bumps`; nothing remembered)."""
        return [v for v in map_bumps(self.bathy, now) if self.inside(v.x, v.y)]

    def ranked(self) -> list[CandidateView]:
        """Candidates worth camera time, most car-like first: scoring :data:`MIN_SCORE` or more,
        and shown by the received map as it is now (not :attr:`CandidateView.gone_at`)."""
        return sorted((c for c in self.candidates if c.score >= MIN_SCORE and c.gone_at is None),
                      key=lambda c: -c.score)

    def watch_map(self, now: float, views: list[CandidateView] | None = None) -> None:
        """Ask for 1 m data around coarse bumps; measure and rank the bumps of the 1 m map
        (``views``: :meth:`measured` at ``now``, if the caller has it already)."""
        if not self.active:
            return
        self.watch_detections(now)
        slow = self.slow_link()
        suggested = [(c.x, c.y) for c in self.candidates if c.detection is not None]
        for level in (2, 1):
            if self.level_grid(level) is None:
                continue
            for c in self.bumps(level, 0.3, min_cells=1):
                if any(math.hypot(c.x - x, c.y - y) < 12.0 for x, y in self.coarse_requested):
                    continue
                if slow and any(math.hypot(c.x - x, c.y - y) < 16.0 for x, y in suggested):
                    continue  # a slow link: the vehicle sends the 1 m map around its detections itself
                if self._map_requests_open() >= self._map_limit():
                    break  # the uplink is shared with image requests: a few map requests at a time
                self.coarse_requested.append((c.x, c.y))
                self.bathy.request_area(0, c.x - 12.0, c.y - 12.0, c.x + 12.0, c.y + 12.0)
                self.log(now, "ROI request", f"level 0 (1 m) around ({c.x:.0f}, {c.y:.0f}): a "
                         f"{c.height:.1f} m bump at level {level} ({2 ** level} m cells)")
            break
        if not slow:  # on a slow link the vehicle sends the rest of the 1 m map as spare work
            self._ask_for_gaps(now)
        while self.camera_phase and self._overview and self._map_requests_open() < self._map_limit():
            # the survey is over: complete the coarse levels of the box too (the overview maps),
            # a level at a time while the uplink has room
            level = self._overview.pop(0)
            x0, y0, x1, y1 = self.box
            with contextlib.suppress(RequestRejected):
                self.bathy.request_area(level, x0, y0, x1 - 1e-3, y1 - 1e-3)
            self.log(now, "ROI request", f"level {level} ({2 ** level} m) over the whole survey box: the "
                     "overview map")
        views = self.measured(now) if views is None else views
        for v in views:
            old = next((c for c in self.candidates if math.hypot(c.x - v.x, c.y - v.y) < GONE_RADIUS), None)
            if old is None:
                self.candidates.append(v)
                if v.score >= MIN_SCORE:
                    self.log(now, "candidate at 1 m", self._describe(v))
            elif not old.planned:  # more data came in: measure again; once flagged, stay flagged
                if old.gone_at is not None:
                    old.gone_at = None
                    if max(v.score, old.score) >= MIN_SCORE:
                        self.log(now, "candidate at 1 m", "the received map shows a bump again at " + self._describe(v))
                was = old.score
                old.x, old.y, old.height, old.cells = v.x, v.y, v.height, v.cells
                old.length, old.width, old.orientation = v.length, v.width, v.orientation
                # a detection keeps the vehicle's score (measured on its whole map) unless the
                # received map shows it more car-like
                old.score = max(v.score, was)
                old.flatness, old.measured = v.flatness, True
                if was < MIN_SCORE <= v.score:
                    self.log(now, "candidate at 1 m", self._describe(old))
        self._forget_gone(now, views)

    def _forget_gone(self, now: float, views: list[CandidateView]) -> None:
        """A bump of the received 1 m map alone (no detection of the vehicle's), no camera line
        sent for it yet, that the map as it is now no longer shows (no bump within
        :data:`GONE_RADIUS`) is not worth camera time until it shows again: a low bump of a
        partly received map (the edge of what is held, one pass's soundings over ground two
        passes cover) often goes when the rest of its neighbourhood arrives."""
        for c in self.candidates:
            if c.detection is not None or not c.measured or c.planned or c.done or c.gone_at is not None:
                continue
            if any(math.hypot(c.x - v.x, c.y - v.y) < GONE_RADIUS for v in views):
                continue
            c.gone_at = now
            if c.score >= MIN_SCORE:
                self.log(now, "candidate gone", f"the received 1 m map no longer shows a bump at ({c.x:.1f}, "
                         f"{c.y:.1f}) (car-likeness {c.score:.2f} when it did): no camera time unless it shows again")

    def slow_link(self) -> bool:
        """Whether the vehicle's link is slow, as topside can tell: what the vehicle's slots
        carry less the loss of its frames measured here, below the channel's low threshold."""
        mgr = self.topside.manager
        return bool(mgr.peer_throughput(self.vehicle_id) < mgr.low_throughput)

    def watch_detections(self, now: float) -> None:
        """The vehicle's detections are suggestions: each becomes a candidate (or marks the
        candidate already there), ranked by the vehicle's score until the operator can measure
        the bump in the received 1 m map (the vehicle sends the map around each detection)."""
        if self.detections is None:
            return
        for row in self.detections.rows():
            x, y = float(row["x"]), float(row["y"])
            if not self.inside(x, y):
                continue  # the operator planned the survey: nothing is sought outside it
            old = next((c for c in self.candidates if c.detection == row["id"]), None) or next(
                (c for c in self.candidates if c.detection is None and math.hypot(c.x - x, c.y - y) < 4.0), None)
            if old is None:
                cv = CandidateView(x, y, float(row["height"] or 0.0), int(row["footprint"] or 0),
                                   float(row["length"] or 0.0), float(row["width"] or 0.0), float(row["score"]),
                                   now, orientation=float(row["orientation"] or 0.0), detection=int(row["id"]),
                                   detected_at=float(row["first_at"]), measured=False)
                self.candidates.append(cv)
                if cv.score >= MIN_SCORE:
                    self.log(now, "detection", f"the vehicle suggests ({x:.1f}, {y:.1f}): {row['height']} m high, "
                             f"{row['length']} x {row['width']} m, oriented {row['orientation']} deg, score "
                             f"{row['score']:.2f} [detection {row['id']}]")
                continue
            if old.detection is None:
                old.detection, old.detected_at = int(row["id"]), float(row["first_at"])
            elif not old.measured and not old.planned:  # the vehicle measured it again
                old.x, old.y, old.score = x, y, float(row["score"])
                old.height, old.length = float(row["height"] or 0.0), float(row["length"] or 0.0)
                old.width = float(row["width"] or 0.0)
                old.orientation = float(row["orientation"] or 0.0)

    #: the vehicle's node id (for what topside can tell of its link)
    vehicle_id: int = 2

    def _ask_for_gaps(self, now: float) -> None:
        """Holes in the 1 m map where the coarse map shows the ground was surveyed: ask for the
        1 m subgrids there that are missing or newer than topside's (a region request lists the
        stamps topside holds), a few tiles at a time, tiles never asked first; a tile again after :data:`GAP_RETRY` seconds, and no more
        once two requests brought nothing (the vehicle has no more there)."""
        fine = self.level_grid(0)
        if fine is None:
            return
        grid, cell, (gx0, gy0) = fine
        coarse = [g for g in (self.level_grid(k) for k in (1, 2, 3)) if g is not None]
        x0, y0, x1, y1 = self.box
        wanted = []
        for ty in np.arange(y0, y1, GAP_TILE):
            for tx in np.arange(x0, x1, GAP_TILE):
                key = (float(tx), float(ty))
                asked_at, n, held_then, stale = self._gap_asked.get(key, (-np.inf, 0, -1.0, 0))
                if now < asked_at + GAP_RETRY or stale >= 2:
                    continue
                # the whole box once the survey is over (the operator planned it); before, where
                # a coarse level shows the swaths have passed
                surveyed = 1.0 if self.camera_phase else max(
                    (_fraction(g, c, gx, gy, tx, ty, GAP_TILE) for g, c, (gx, gy) in coarse), default=0.0)
                held = _fraction(grid, cell, gx0, gy0, tx, ty, GAP_TILE)
                if surveyed < 0.3 or held >= 0.98 * surveyed:
                    continue
                stale = stale + 1 if n and held <= held_then + 0.005 else 0
                if stale >= 2:
                    self._gap_asked[key] = (asked_at, n, held, stale)
                    continue
                wanted.append((n, held, key, surveyed, stale))
        room = max(0, min(GAP_TILES_PER_LOOK, self._map_limit() - self._map_requests_open()))
        for n, held, (tx, ty), surveyed, stale in sorted(wanted)[:room]:
            self._gap_asked[(tx, ty)] = (now, n + 1, held, stale)
            x1t, y1t = min(tx + GAP_TILE, x1) - 1e-3, min(ty + GAP_TILE, y1) - 1e-3
            # a region request with topside's stamps, not a gap request: a hole is often in a
            # subgrid topside holds in an older, partly surveyed version
            self.bathy.request_area(0, tx, ty, x1t, y1t)
            self.log(now, "gap request", f"level 0 (1 m) gaps in {GAP_TILE:.0f} m x {GAP_TILE:.0f} m at "
                     f"({tx:.0f}, {ty:.0f}): {held:.0%} held where {surveyed:.0%} was surveyed")

    def _map_limit(self) -> int:
        """Map requests the operator keeps open at once: fewer once images are being asked for
        (they share the uplink's control queue with the image requests)."""
        return MAX_OPEN_MAP_REQUESTS_CAMERA if self.camera_phase else MAX_OPEN_MAP_REQUESTS

    def _map_requests_open(self) -> int:
        """Region requests of the operator's still open (not yet answered "nothing more")."""
        return sum(1 for r in self.bathy.active_regions() if not r.auto)

    @staticmethod
    def _describe(v: CandidateView) -> str:
        return (f"({v.x:.1f}, {v.y:.1f}): {v.height:.1f} m high, {v.length:.1f} x {v.width:.1f} m "
                f"({v.cells} cells), top {v.flatness:.0%} flat, car-likeness {v.score:.2f}")

    # ------------------------------------------------------------------ the camera pass
    def camera_round(self, now: float, *, end: float, reserve: float, half: float, first: bool = False,
                     free_at: float | None = None) -> None:
        """Send the vehicle over the candidates not yet sent, most target-like first, while camera
        time remains: one survey command per candidate, a camera line of ``2 * half`` metres (at
        most twice :data:`LINE_HALF`) across the candidate's long axis (as the map measured it)
        through it, at the altitude that holds the largest object sought in a frame
        (:func:`camera_altitude`, :data:`LINE_ALTITUDE_FOR`) and :data:`LINE_SPEED`, queued behind the
        lines already sent (``append``: commands that cross the link out of order cannot undo
        each other; the vehicle holds with an empty queue, so the first starts at once). Camera
        time is counted from topside's estimate of when the vehicle is done with its queue, and
        not before ``free_at`` (when the vehicle's own survey ends: the operator planned it)."""
        if not self.active:
            return
        for sid, line in self.lines.items():  # no answer after every try: the receiver gave it up
            rec = self.survey.surveys.get(sid)
            if rec is not None and rec.state == "given up" and line.state != "given up":
                self.on_survey({"survey_id": sid, "state": rec.state, "time": rec.time, "text": rec.text}, now)
        t, pos = self._queue_end(now)
        t = max(t, free_at or t)
        sent = 0
        half = min(half, LINE_HALF)
        altitude = camera_altitude(*LINE_ALTITUDE_FOR, self.camera_altitude)
        t, pos = self._send_reaims(now, t, pos, end - reserve, half, altitude)
        for cv in self.ranked():
            if cv.planned or cv.refused is not None:
                continue
            if t - now > LINE_AHEAD:
                break  # the vehicle has lines enough: the next is aimed nearer its time
            heading = (cv.orientation + 90.0) % 180.0
            h = math.radians(heading)
            start = (cv.x - half * math.sin(h), cv.y - half * math.cos(h))
            dist = math.hypot(start[0] - pos[0], start[1] - pos[1])
            if t + dist / TRANSIT_SPEED + 2 * half / LINE_SPEED > end - reserve:
                break  # no camera time left for the next in rank order
            try:
                cmd = self.survey.request("line", round(start[0], 1), round(start[1], 1), now, heading=round(heading, 1),
                                          length=2 * half, altitude=altitude, speed=LINE_SPEED, append=True)
            except RequestRejected as exc:
                cv.refused = f"cannot be sent: {exc}"
                self.log(now, "survey command", f"a camera line over ({cv.x:.0f}, {cv.y:.0f}) {cv.refused}")
                continue
            line = self._line(cmd, cv, now)
            cv.planned, cv.survey_id = True, cmd.survey_id
            t += dist / TRANSIT_SPEED + 2 * half / LINE_SPEED
            pos = line.end
            sent += 1
            self.log(now, "survey command", f"survey {cmd.survey_id} sent: a {2 * half:.0f} m camera line over "
                     f"({cv.x:.0f}, {cv.y:.0f}) [target-likeness {cv.score:.2f}, {cv.length:.1f} x {cv.width:.1f} m], "
                     f"heading {line.heading:.0f} deg at {line.altitude:g} m and {LINE_SPEED:g} m/s, queued after "
                     f"{len(self._open_lines()) - 1} line(s) [command {cmd.command_id}]")
        if first and not sent:
            self.log(now, "camera pass", "no target-like candidate in the 1 m map yet: the vehicle holds")

    def _send_reaims(self, now: float, t: float, pos: tuple[float, float], until: float, half: float,
                     altitude: float) -> tuple[float, tuple[float, float]]:
        """Send the camera lines re-aimed since the last round (:meth:`_reaim`), queued like the
        others, each through its new point at its first line's heading, while camera time
        remains; one that no longer fits is dropped (its candidate's images are looked at on)."""
        for cv in self.ranked():
            if cv.reaim_want is None or cv.done:
                continue
            if t - now > LINE_AHEAD:
                break  # sent at a later round, nearer its time (:data:`LINE_AHEAD`)
            aim, cv.reaim_want = cv.reaim_want, None
            old = self.lines.get(cv.survey_id) if cv.survey_id is not None else None
            heading = old.heading if old is not None else (cv.orientation + 90.0) % 180.0
            h = math.radians(heading)
            start = (aim[0] - half * math.sin(h), aim[1] - half * math.cos(h))
            dist = math.hypot(start[0] - pos[0], start[1] - pos[1])
            if t + dist / TRANSIT_SPEED + 2 * half / LINE_SPEED > until:
                self.log(now, "camera pass", f"no camera time left to re-aim the line over ({cv.x:.0f}, {cv.y:.0f})")
                continue
            try:
                cmd = self.survey.request("line", round(start[0], 1), round(start[1], 1), now, heading=round(heading, 1),
                                          length=2 * half, altitude=altitude, speed=LINE_SPEED, append=True)
            except RequestRejected as exc:
                self.log(now, "survey command", f"a re-aimed camera line over ({aim[0]:.0f}, {aim[1]:.0f}) "
                         f"cannot be sent: {exc}")
                continue
            line = self._line(cmd, cv, now)
            # only this line's pass counts from now on; its images are looked at afresh
            cv.wait_after = max([now, *cv.looked_times.values()])
            cv.aim, cv.survey_id, cv.passed_at = aim, cmd.survey_id, None
            cv.want = cv.want_goal = cv.want_region = None
            cv.looked, cv.looked_times = [], {}
            t += dist / TRANSIT_SPEED + 2 * half / LINE_SPEED
            pos = line.end
            self.log(now, "survey command", f"survey {cmd.survey_id} sent: the camera line over ({cv.x:.0f}, "
                     f"{cv.y:.0f}) re-aimed at ({aim[0]:.1f}, {aim[1]:.1f}), heading {line.heading:.0f} deg at "
                     f"{line.altitude:g} m and {LINE_SPEED:g} m/s [command {cmd.command_id}]")
        return t, pos

    def _reaim(self, cv: CandidateView, aim: tuple[float, float], why: str, now: float) -> bool:
        """Ask the next camera round for one more line over ``cv``, through ``aim`` (at most
        :data:`MAX_REAIMS` per candidate); False when none is left."""
        if cv.reaims >= MAX_REAIMS:
            return False
        cv.reaims += 1
        cv.reaim_want = aim
        self.log(now, "re-aim", f"the candidate at ({cv.x:.0f}, {cv.y:.0f}): {why}: one more camera line, "
                 f"through ({aim[0]:.1f}, {aim[1]:.1f})")
        return True

    @staticmethod
    def _side_cut_aim(cv: CandidateView, mine: list[Sight], meta: dict[str, Any], mpp: float,
                      heading: float) -> tuple[float, float] | None:
        """Where an object the frame cuts at its left or right side lies, from what the eye saw:
        its inner edge plus half its length (the longer of the map's measure and the part seen,
        at most the largest sought) toward the cut side, across the line; None when no object
        near ``cv`` is cut at one side only."""
        sides = [s for s in mine if len({"left", "right"} & set(s.cut)) == 1]
        if not sides:
            return None
        s = max(sides, key=lambda s: s.area_m2)
        length = min(max(cv.length, s.length_m), TARGET_SIZES[0][1])
        width, height = int(meta["width"]), int(meta["height"])
        if "right" in s.cut:
            right = (s.box[0] - width / 2) * mpp + length / 2
        else:
            right = (s.box[2] - width / 2) * mpp - length / 2
        ahead = (height / 2 - s.centre[1]) * mpp
        h = math.radians(heading)
        return (round(float(meta["x"]) + right * math.cos(h) + ahead * math.sin(h), 1),
                round(float(meta["y"]) - right * math.sin(h) + ahead * math.cos(h), 1))

    def _line(self, cmd: SurveyCommand, cv: CandidateView, now: float) -> CameraLine:
        x, y, length = float(cmd.x), float(cmd.y), float(cmd.length or 0.0)
        heading = float(cmd.heading or 0.0)
        h = math.radians(heading)
        line = CameraLine(int(cmd.survey_id), cv, (x, y), (x + length * math.sin(h), y + length * math.cos(h)),
                          float(cmd.speed or CAMERA_SPEED), now, heading=heading,
                          altitude=float(cmd.altitude or self.camera_altitude))
        self.lines[line.survey_id] = line
        return line

    def _open_lines(self) -> list[CameraLine]:
        return [ln for _, ln in sorted(self.lines.items()) if ln.open]

    def _position_before(self, t: float) -> tuple[float, float] | None:
        """The newest reported position stamped no later than ``t``."""
        before = [p for p in self.positions if p[0] <= t]
        if not before:
            return None
        _, x, y = max(before, key=lambda p: p[0])
        return x, y

    def _position_at(self, t: float) -> tuple[float, float] | None:
        if not self.positions:
            return None
        _, x, y = min(self.positions, key=lambda p: abs(p[0] - t))
        return x, y

    def _queue_end(self, now: float) -> tuple[float, tuple[float, float]]:
        """When and where topside expects the vehicle to be done with the lines it sent, from the
        vehicle's reports; a new command reaches the vehicle a quarter cycle from now at best
        (topside's slots)."""
        x0, y0, x1, y1 = self.box
        pos = self.position or ((x0 + x1) / 2, (y0 + y1) / 2)
        t = now + self.cycle / 4
        for line in self._open_lines():
            fly = line.length / line.speed
            if line.at_start is not None:
                done = line.at_start + fly
            elif line.set_off is not None:
                start = self._position_at(line.set_off) or pos
                done = line.set_off + math.hypot(line.start[0] - start[0], line.start[1] - start[1]) / TRANSIT_SPEED + fly
            else:
                done = t + math.hypot(line.start[0] - pos[0], line.start[1] - pos[1]) / TRANSIT_SPEED + fly
            t, pos = max(done, now + self.cycle / 4), line.end
        return t, pos

    def on_survey(self, meta: dict[str, Any], now: float) -> None:
        """A survey's state as it reached topside (the survey receiver's product): log it, and for
        the operator's camera lines note the vehicle's stamps, or why it will not fly one."""
        sid = int(meta["survey_id"])
        state, stamp, text = str(meta.get("state")), float(meta.get("time") or now), str(meta.get("text") or "")
        index = meta.get("index")
        line = self.lines.get(sid)
        when = f" (at {stamp - self.epoch:.0f} s)" if abs(stamp - now) >= 1.0 else ""
        what = {"accepted": "accepted by the vehicle", "started": "started" + (f": {text}" if text else ""),
                "completed": "completed", "rejected": "rejected", "aborted": "aborted",
                "given up": "given up"}.get(state, state)
        if state in ("rejected", "aborted", "given up") and text:
            what += f": {text}"
        if line is not None:
            what += f", the camera line over ({line.candidate.x:.0f}, {line.candidate.y:.0f})"
        self.log(now, "survey state", f"survey {sid} {what}{when}", "system" if line is None else "script")
        if line is None:
            return
        line.state = state
        cv = line.candidate
        if state == "started":
            if index == 0 and line.set_off is None:
                line.set_off = stamp
            elif index == 1:
                line.at_start = stamp
        elif state == "completed":
            line.completed = stamp
        elif state in ("rejected", "aborted") and cv.passed_at is None and cv.survey_id == sid:
            # the vehicle will not fly it: no camera time for this candidate (never asked again:
            # the answer would be the same, and a replaced line was someone else's decision)
            if not text.startswith("refused by the vehicle"):  # its reason follows
                cv.planned, cv.refused = False, text or state
            else:
                cv.planned, cv.refused = False, cv.refused or "refused by the vehicle"
        elif state == "given up" and cv.survey_id == sid:
            cv.planned, cv.survey_id = False, None  # never reached the vehicle: sent again next round

    def _pass_time(self, cv: CandidateView, now: float) -> float | None:
        """When the camera passed ``cv`` (:meth:`_pass_estimate`), then the capture time of the
        announced image taken nearest ``cv`` within two cycles of that estimate (every image is
        announced with where it was taken), if one lies within :data:`NEAR` of it."""
        t = self._pass_estimate(cv, now)
        if t is None:
            return t
        px, py = cv.point
        near = [(math.hypot(float(p.meta["x"]) - px, float(p.meta["y"]) - py), float(p.meta["time"]))
                for p in self.imagery.products()
                if p.kind == "image" and p.meta.get("x") is not None and p.meta.get("time") is not None
                and abs(float(p.meta["time"]) - t) <= 2 * self.cycle]
        best = min((d_t for d_t in near if d_t[0] <= NEAR), default=None)
        return t if best is None else best[1]

    def _pass_estimate(self, cv: CandidateView, now: float) -> float | None:
        """When the camera passed ``cv``, from what reached topside, once it is past: the
        vehicle's report of reaching the line's start (or of finishing it: exact stamps), once
        the next frame after the pass is taken; else the closest approach of the received track
        on a camera line (the vehicle more than 10 m beyond); else, on a lossy link where all
        are late, from when it set off for this line (from where its last status before that put
        it, or the end of the line it had just finished), a cycle on. Never from another line's
        reports: the vehicle flies the lines in the order their commands reached it, which loss
        can make unlike the order sent. One rule for every dive, one vehicle or a fleet."""
        line = self.lines.get(cv.survey_id) if cv.survey_id is not None else None
        reported = line.reported_pass() if line is not None else None
        if reported is not None:  # the image nearest that time exists once the next frame is taken
            return reported if now >= reported + CAMERA_PERIOD else None
        px, py = cv.point
        x_now, y_now = self.position or (self.track[-1][1:3] if self.track else (px, py))
        if self.track:
            d, t_close = closest_approach(self.track, px, py)
            if d < NEAR and math.hypot(x_now - px, y_now - py) > 10.0:
                return t_close
        if line is None:
            return None
        half = line.length / 2 / line.speed
        est = None
        if line.set_off is not None:
            start = self._position_before(line.set_off) or self._position_at(line.set_off)
            before = [ln for ln in self.lines.values()
                      if ln.completed is not None and abs(ln.completed - line.set_off) <= 1.0]
            if before:
                start = before[0].end
            if start is not None:
                est = line.set_off + math.hypot(line.start[0] - start[0], line.start[1] - start[1]) / TRANSIT_SPEED + half
        return est if est is not None and now > est + self.cycle else None

    def watch_images(self, now: float) -> None:
        """Ask for the image of each candidate the camera has passed, and look at what came."""
        if not self.active:
            return
        for cv in self.ranked():
            if not cv.planned or cv.done or cv.reaim_want is not None:
                continue  # (a re-aimed line asked for: the next camera round sends it)
            if cv.passed_at is None:
                t_pass = self._pass_time(cv, now)
                if t_pass is not None and (cv.wait_after is None or t_pass > cv.wait_after):
                    cv.passed_at = t_pass
                    self._ask(cv, t_pass, "nearest", now)
                continue
            self._look(cv, now)

    def frame_geometry(self, cv: CandidateView, meta: dict[str, Any]) -> tuple[float, float]:
        """The seafloor size of a full-size pixel (m) of an announced image, and the heading it
        was taken at (degrees), from what topside knows: the altitude of the vehicle's status
        nearest its capture time (within a cycle), else the altitude of the camera line flown
        for ``cv``; the line's heading (else the received track's); the camera's field of view."""
        t = float(meta["time"])
        line = self.lines.get(cv.survey_id) if cv.survey_id is not None else None
        near = min(self.altitudes, key=lambda a: abs(a[0] - t), default=None)
        if near is not None and abs(near[0] - t) <= self.cycle / 2:
            altitude = near[1]
        else:
            altitude = line.altitude if line is not None else self.camera_altitude
        heading = line.heading if line is not None else (
            min(self.track, key=lambda p: abs(p[0] - t))[3] if self.track else 0.0)
        return metres_per_pixel(altitude, int(meta["width"]), CAMERA_HFOV_DEG), heading

    @staticmethod
    def ground(sight: Sight, meta: dict[str, Any], mpp: float, heading: float) -> tuple[float, float]:
        """Where on the seafloor the centre of ``sight`` lies: the frame's announced position
        plus the sight's offset from the frame's centre (right and ahead), turned by the
        heading."""
        right = (sight.centre[0] - int(meta["width"]) / 2) * mpp
        ahead = (int(meta["height"]) / 2 - sight.centre[1]) * mpp
        h = math.radians(heading)
        return (float(meta["x"]) + right * math.cos(h) + ahead * math.sin(h),
                float(meta["y"]) - right * math.sin(h) + ahead * math.cos(h))

    def _look(self, cv: CandidateView, now: float) -> None:
        """Look at the image answering a candidate's request: confirm it, call it natural, ask for
        a sharper look at an unclear object, re-aim a line that passed beside it, give up, or
        step on along the line."""
        meta = self._answer(cv)
        if self._unanswered(cv, meta, now):
            return
        assert meta is not None
        image_id = int(meta["image_id"])
        cv.image_id = image_id
        img = self.imagery.image(image_id)
        here = cv.distance(float(meta["x"]), float(meta["y"])) <= NEAR
        settled = self._arrived(cv, meta)
        layers = int(meta.get("layers_complete", 0))
        preview = layers < MIN_CONFIRM_LAYERS and not meta.get("complete")
        # the best image of it the operator will get: the sharper look asked for has arrived
        final = settled and (cv.want_goal == image_id or bool(meta.get("complete")) or layers >= MORE_LAYERS)
        sights: list[Sight] = []
        mine: list[Sight] = []
        mpp, heading = self.frame_geometry(cv, meta)
        if img is not None and (settled or not preview):  # a preview is a smudge: not worth a look
            sights = self.eye.look(img, mpp, settled=final)
            self.sights[image_id] = [s.as_dict() for s in sights]
            mine = [s for s in sights if cv.distance(*self.ground(s, meta, mpp, heading)) <= SIGHT_RADIUS]
        kinds = {s.kind for s in mine}
        targets = [s for s in mine if s.target]
        if here and targets and not preview:
            self._confirm(cv, targets[0], img, meta, now)
            return
        if not settled:
            return  # the vehicle is still sending the layers asked for: look again later
        if image_id not in cv.looked:
            cv.looked.append(image_id)
            cv.looked_times[image_id] = float(meta["time"])
        if here and kinds == {"natural"}:
            cv.verdict, cv.verdict_image = "natural", image_id
            self.log(now, "not a target", f"image {image_id} shows something natural at ({cv.x:.0f}, {cv.y:.0f}) "
                     f"[{self._seen(mine)}]: moving on")
            return
        if "unclear" in kinds and cv.want_goal != image_id and layers < MORE_LAYERS:
            self._ask_sharper(cv, mine, meta, now)
            return
        aim = self._side_cut_aim(cv, mine, meta, mpp, heading)
        if aim is not None and self._reaim(cv, aim, f"image {image_id} cuts it at its side "
                                           f"[{self._seen(mine)}]: the line passed beside it", now):
            return
        if len(cv.looked) >= MAX_LOOKS:
            off, _ = closest_approach(self.track, *cv.point) if self.track else (0.0, 0.0)
            if off > REAIM_OFF and self._reaim(cv, cv.point, f"no target in {len(cv.looked)} images and the "
                                               f"received track passed {off:.1f} m from it", now):
                return
            cv.verdict = "given up"
            self.log(now, "given up", f"no target in {len(cv.looked)} images near ({cv.x:.0f}, {cv.y:.0f}): "
                     "moving on")
            return
        self._step_on(cv, mine, meta, now)

    def _unanswered(self, cv: CandidateView, meta: dict[str, Any] | None, now: float) -> bool:
        """Whether the candidate's request has no image to look at yet (none announced, or one
        stuck with no answer for ``ANSWER_CYCLES`` cycles); a stuck request is asked again."""
        pending = {command_id_of(m) for m in self.imagery.pending_requests()}
        if meta is not None and int(meta.get("bytes_used", 0)) > cv.progress[0]:
            cv.progress = (int(meta["bytes_used"]), now)  # the answer is coming: not stuck
        since = max(cv.request_at or now, cv.progress[1])
        stuck = (cv.request_at is not None and now - since > ANSWER_CYCLES * self.cycle
                 and cv.command_id not in pending)  # still being retried by the receiver: wait
        if not (meta is None or (stuck and not self._arrived(cv, meta))):
            return False
        if stuck and cv.want is not None:  # no answer: the request may never have reached the vehicle
            t, direction = cv.want
            self.log(now, "image request", f"no answer for {now - (cv.request_at or now):.0f} s: asking again")
            if cv.want_goal is not None and meta is not None:
                cv.request_at = now
                cv.want_region = None
                cv.command_id = self.imagery.request_goal(cv.want_goal, "layer", MORE_LAYERS, now).command_id
            else:
                self._ask(cv, t, direction, now)
        return True

    def _confirm(self, cv: CandidateView, best: Sight, img: Any, meta: dict[str, Any], now: float) -> None:
        """The eye saw a target in a received image at the candidate: the operator's verdict,
        with the image kept as its evidence."""
        image_id = int(meta["image_id"])
        cv.verdict, cv.verdict_image, cv.confirmed_at = best.kind, image_id, now
        cv.evidence = None if img is None else np.array(img, copy=True)
        cv.evidence_time = float(meta["time"])
        cv.evidence_xy = (float(meta["x"]), float(meta["y"]))
        cv.evidence_bytes = int(meta["bytes_used"])
        cv.evidence_box, cv.evidence_sight = best.box, best.as_dict()
        dt = now - (cv.request_at or now)
        self.log(now, "confirming image", f"image {image_id} shows a {best.kind} at ({cv.x:.0f}, {cv.y:.0f}) "
                 f"[{best.describe()}]: {meta['bytes_used']} B, {dt:.0f} s after its request")

    def _ask_sharper(self, cv: CandidateView, mine: list[Sight], meta: dict[str, Any], now: float) -> None:
        """An object too unclear to tell: ask for more layers of the region it is in (the whole
        image when the eye draws no box)."""
        image_id = int(meta["image_id"])
        cv.want_goal = image_id
        cv.request_at = now
        box = self._region_of([s for s in mine if s.kind == "unclear"], meta)
        if box is not None:
            # look where it matters: only the part of the frame with the unclear object
            reg = self.imagery.request_region(image_id, box, "layer", MORE_LAYERS, now)
            cv.command_id = cv.want_region = reg.command_id
            self.regions.append({"image_id": image_id, "box": list(box), "command_id": reg.command_id,
                                 "time": now, "candidate": (cv.x, cv.y)})
            self.log(now, "image region", f"image {image_id} shows something at ({cv.x:.0f}, {cv.y:.0f}) "
                     f"too unclear to tell [{self._seen(mine)}]: asking for {MORE_LAYERS} layers of "
                     f"its region x {box[0]}..{box[2]}, y {box[1]}..{box[3]} px "
                     f"[command {reg.command_id}]")
            return
        cv.want_region = None
        msg = self.imagery.request_goal(image_id, "layer", MORE_LAYERS, now)
        cv.command_id = msg.command_id
        self.log(now, "image goal", f"image {image_id} shows something at ({cv.x:.0f}, {cv.y:.0f}) "
                 f"too unclear to tell [{self._seen(mine)}]: asking for {MORE_LAYERS} layers "
                 f"[command {msg.command_id}]")

    def _step_on(self, cv: CandidateView, mine: list[Sight], meta: dict[str, Any], now: float) -> None:
        """No verdict from this image: ask for the next one along the line, toward the side where
        the frame cut the object (or toward the candidate), never an image already seen."""
        image_id = int(meta["image_id"])
        # an object the frame cuts: the rest of it is ahead (the frame's top) or behind
        cut = {c for s in mine for c in s.cut}
        if "top" in cut and "bottom" not in cut:
            direction, why = "after", "runs off the frame ahead"
        elif "bottom" in cut and "top" not in cut:
            direction, why = "before", "runs off the frame behind"
        else:
            direction, why = self._towards(cv, meta), "shows no target"
        # step on from the furthest image already seen that way: never the same image twice
        times = cv.looked_times.values()
        start = min(times) if direction == "before" else max(times)
        if direction == "before" and not any(
                p.kind == "image" and p.meta.get("time") is not None and float(p.meta["time"]) < start
                for p in self.imagery.products()):  # images are announced in capture order: none earlier
            line = self.lines.get(cv.survey_id) if cv.survey_id is not None else None
            if line is not None and line.completed is None and cv.wait_after is None:
                # seen from another line's pass: wait for its own camera line
                cv.passed_at, cv.want, cv.want_goal, cv.wait_after = None, None, None, max(times)
                self.log(now, "image request", f"image {image_id} {why} at ({cv.x:.0f}, {cv.y:.0f}) "
                         f"[{self._seen(mine)}]: no earlier image; waiting for its own camera line")
                return
            direction, start = "after", max(times)  # nothing behind: look ahead instead
        self.log(now, "image request", f"image {image_id} {why} at ({cv.x:.0f}, {cv.y:.0f}) "
                 f"[{self._seen(mine)}]: stepping {'back' if direction == 'before' else 'forward'} in time")
        self._ask(cv, start, direction, now)

    @staticmethod
    def _seen(sights: list[Sight]) -> str:
        if not sights:
            return "sand only"
        return "; ".join(s.describe() for s in sights)

    @staticmethod
    def _region_of(sights: list[Sight], meta: dict[str, Any]) -> tuple[int, int, int, int] | None:
        """The pixel box around the eye's unclear objects of a frame (their boxes, plus
        :data:`REGION_MARGIN`), or None when the image cannot be asked for by region (coded
        without precincts) or the box would be most of the frame."""
        if not meta.get("precincts") or not sights:
            return None
        width, height = int(meta["width"]), int(meta["height"])
        x0 = max(0, min(s.box[0] for s in sights) - REGION_MARGIN)
        y0 = max(0, min(s.box[1] for s in sights) - REGION_MARGIN)
        x1 = min(width, max(s.box[2] for s in sights) + REGION_MARGIN)
        y1 = min(height, max(s.box[3] for s in sights) + REGION_MARGIN)
        if (x1 - x0) * (y1 - y0) > 0.6 * width * height:
            return None
        return (x0, y0, x1, y1)

    @staticmethod
    def _arrived(cv: CandidateView, meta: dict[str, Any]) -> bool:
        """Whether the layers asked for of this image (or of its region) are all topside."""
        if cv.want_goal == int(meta["image_id"]) and cv.want_region is not None:
            for reg in meta.get("regions", ()):
                if reg["command_id"] == cv.want_region:
                    if reg["state"] == "rejected":
                        return True  # nothing more will come: judge what is there
                    return bool(meta.get("complete")) or int(reg.get("layers_complete", 0)) >= MORE_LAYERS
        want = MORE_LAYERS if cv.want_goal == int(meta["image_id"]) else CONFIRM_LAYERS
        return bool(meta.get("complete")) or int(meta.get("layers_complete", 0)) >= want

    def _towards(self, cv: CandidateView, meta: dict[str, Any]) -> str:
        """``"before"`` when the candidate lies behind the frame along the vehicle's heading."""
        t = float(meta["time"])
        heading = 0.0
        if self.track:
            heading = min(self.track, key=lambda p: abs(p[0] - t))[3]
        h = math.radians(heading)
        px, py = cv.point
        ahead = (px - float(meta["x"])) * math.sin(h) + (py - float(meta["y"])) * math.cos(h)
        return "after" if ahead > 0 else "before"

    def _answer(self, cv: CandidateView) -> dict[str, Any] | None:
        """The image the vehicle serves for the operator's latest request, by the rule the vehicle
        applies (nearest to the time, or the newest before / oldest after it), once topside has
        heard the announcements it needs to tell (images are announced in capture order)."""
        if cv.want is None:
            return None
        t, direction = cv.want
        metas = [dict(p.meta) for p in self.imagery.products()
                 if p.kind == "image" and p.meta.get("x") is not None and p.meta.get("time") is not None]
        if cv.want_goal is not None:
            for m in metas:
                if int(m["image_id"]) == cv.want_goal:
                    return m
        later = [m for m in metas if float(m["time"]) > t]
        if direction == "before":
            older = [m for m in metas if float(m["time"]) < t]
            return max(older, key=lambda m: float(m["time"]), default=None)
        if direction == "after":
            return min(later, key=lambda m: float(m["time"]), default=None)
        if not any(float(m["time"]) >= t for m in metas):
            return None  # the images after that time are not announced yet: wait
        # ties go to the earlier image, as on the vehicle
        return min(metas, key=lambda m: (abs(float(m["time"]) - t), float(m["time"])), default=None)

    def _ask(self, cv: CandidateView, t: float, direction: str, now: float) -> None:
        t = float(math.floor(t)) if direction != "after" else float(math.ceil(t))  # whole seconds
        msg = self.imagery.request_by_time(t, direction, now)
        cv.command_id = msg.command_id
        cv.want = (t, direction)
        cv.want_goal = None
        cv.request_at = now
        cv.progress = (0, -math.inf)
        if cv.first_request_at is None:
            cv.first_request_at = now
        self.log(now, "image request", f"image {direction} dive time {t - self.epoch:.0f} s, for the candidate "
                 f"at ({cv.x:.0f}, {cv.y:.0f}) [command {msg.command_id}]")

    #: the dive's epoch, for dive times in the log (set by the demo)
    epoch: float = 0.0


def _fraction(grid: np.ndarray, cell: float, x0: float, y0: float, tx: float, ty: float, size: float) -> float:
    """Fraction of the square [tx, tx + size) x [ty, ty + size) that a level grid holds."""
    ny, nx = grid.shape
    c0, c1 = max(int((tx - x0) / cell), 0), min(math.ceil((tx + size - x0) / cell), nx)
    r0, r1 = max(int((ty - y0) / cell), 0), min(math.ceil((ty + size - y0) / cell), ny)
    if c1 <= c0 or r1 <= r0:
        return 0.0
    expected = max((size / cell) ** 2, 1.0)
    return float(np.count_nonzero(np.isfinite(grid[r0:r1, c0:c1])) / expected)


def closest_approach(track: list[tuple[float, float, float, float]], x: float, y: float) -> tuple[float, float]:
    """Distance and time of the track's closest approach to (x, y), between its points too
    (statuses arrive tens of metres apart on a slow link)."""
    best = (math.inf, 0.0)
    for (t0, x0, y0, _), (t1, x1, y1, _) in zip(track, track[1:] or track):
        dx, dy = x1 - x0, y1 - y0
        seg = dx * dx + dy * dy
        # between two statuses of one transect (not across a transit between transects)
        f = 0.0 if seg == 0 or seg > 80.0**2 or t1 - t0 > 400.0 else min(
            max(((x - x0) * dx + (y - y0) * dy) / seg, 0.0), 1.0)
        px, py = x0 + f * dx, y0 + f * dy
        d = math.hypot(px - x, py - y)
        if d < best[0]:
            best = (d, t0 + f * (t1 - t0))
    return best
