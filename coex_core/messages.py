"""CoEx wire messages as frozen dataclasses.

These are the public, construct-free face of the wire format. Field values are the values the
wire carries (already quantised): decoding an encoded message gives back an equal message when
every field is on its grid. Ranges, resolutions and bit widths are specified once, in the
construct definitions of :mod:`coex_core._wire`, and listed in ``spec/wire-format.md``.

Conventions: ``stamp`` fields are whole seconds modulo 2^18 (see :mod:`coex_core.timefmt`); ``x``/``y``
are metres east/north in the survey's local frame; ``level`` 0 is the finest map level.
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass

__all__ = [
    "WITH_COMMAND_ID",
    "command_id",
    "Message",
    "FrameHeader",
    "Frame",
    # core
    "VehicleMode",
    "VehicleStatus",
    "StreamStatus",
    "QueueStatus",
    "QueueConfig",
    "Slot",
    "ScheduleUpdate",
    "LinkControl",
    "SpareConfig",
    "AckStatus",
    "CommandAck",
    "FrameAckEntry",
    "FrameAck",
    "AuthTrailer",
    "LinkHealth",
    "LinkStatus",
    "Opaque",
    # bathymetry
    "MapMetadata",
    "Subgrid",
    "MapRoiRequest",
    "MapRoiReply",
    "SubgridEncoding",
    "SubgridContext",
    "SubgridCells",
    "PredictedSubgrid",
    "SubgridMessage",
    # imagery
    "ImageAnnounce",
    "ImageFragment",
    "ImageAck",
    "ByteRange",
    "GoalKind",
    "ImageGoal",
    "TimeDirection",
    "ImageByTimeRequest",
    "ImageRegionRequest",
    "RegionGoal",
    "ImageCrop",
    "TransferProgress",
    # time series
    "TimeSeriesChannel",
    "Wavelet",
    "TimeSeriesChunk",
    "TimeSeriesPart",
    "TimeSeriesAck",
    "TimeSeriesRequest",
    # surveys
    "SurveyKind",
    "SurveyState",
    "SurveyReason",
    "SurveyPoint",
    "SurveyCommand",
    "SurveyStatus",
    "SURVEY_DETAIL_MAX",
    # detections
    "DetectionSource",
    "Detection",
    # navigation aiding (issue 56)
    "PositionSource",
    "PositionFix",
]


@dataclass(frozen=True, slots=True)
class Message:
    """Base class of every wire message. Do not subclass outside :mod:`coex_core.messages`;
    third-party modalities use :class:`Opaque` with a type id from the third-party range."""


@dataclass(frozen=True, slots=True)
class FrameHeader:
    """The 3-byte header of every frame (plus a CRC-16 when ``crc`` is set).

    ``src``/``dst`` are node ids 0..15 (0 = broadcast as destination); ``seq`` counts
    transmissions modulo 256; ``schedule`` is the TDMA schedule version the sender runs."""

    src: int = 0
    dst: int = 0
    seq: int = 0
    schedule: int = 0
    crc: bool = False


@dataclass(frozen=True, slots=True)
class Frame:
    """A decoded frame: its header and its messages in order."""

    header: FrameHeader
    messages: tuple[Message, ...]


# --------------------------------------------------------------------------------------- core


class VehicleMode(enum.IntEnum):
    UNKNOWN = 0
    IDLE = 1
    SURVEY = 2
    TRANSIT = 3
    HOVER = 4
    SURFACE = 5
    ABORT = 6
    MANUAL = 7


@dataclass(frozen=True, slots=True)
class VehicleStatus(Message):
    """Vehicle safety status: always sent first in a vehicle transmission (strict tier 0)."""

    stamp: int
    x: float
    y: float
    depth: float
    altitude: float | None
    heading: float
    speed: float
    battery: int
    mode: VehicleMode
    faults: int


@dataclass(frozen=True, slots=True)
class StreamStatus:
    """One stream's line in :class:`QueueStatus`."""

    stream: int
    enabled: bool
    tier: int
    priority: int
    depth: int
    queued_bytes: int
    oldest_age: int
    drops: int


@dataclass(frozen=True, slots=True)
class QueueStatus(Message):
    """Per-stream queue state, sent topside regularly."""

    stamp: int
    streams: tuple[StreamStatus, ...]


@dataclass(frozen=True, slots=True)
class QueueConfig(Message):
    """Topside command: change one stream's settings (absent fields are left unchanged) or flush it."""

    command_id: int
    stream: int
    flush: bool
    enabled: bool | None
    priority: int | None
    ttl: int | None
    max_depth: int | None
    newest_first: bool | None


@dataclass(frozen=True, slots=True)
class Slot:
    """One TDMA slot of a :class:`ScheduleUpdate`."""

    owner: int
    duration: float
    guard: float
    min_priority: int


@dataclass(frozen=True, slots=True)
class ScheduleUpdate(Message):
    """Topside command: a new versioned TDMA schedule for one link, active from a cycle boundary."""

    command_id: int
    link: int
    version: int
    activate_cycle: int
    slots: tuple[Slot, ...]


@dataclass(frozen=True, slots=True)
class LinkControl(Message):
    """Topside command: enable or disable one modem link, or mute it."""

    command_id: int
    link: int
    enabled: bool
    mute: bool


@dataclass(frozen=True, slots=True)
class SpareConfig(Message):
    """Topside command: how much of each packet spare traffic may fill, in percent (0: off).
    With ``stream`` absent it sets the share of ``link`` (every link when ``link`` is absent):
    the spare tier and the redundant copies of urgent messages together. With ``stream`` it sets
    that stream's spare share on every link (``link`` must then be absent)."""

    command_id: int
    link: int | None
    stream: int | None
    percent: int


class AckStatus(enum.IntEnum):
    ACCEPTED = 0
    REJECTED = 1
    UNAUTHENTICATED = 2
    UNKNOWN_TARGET = 3
    #: accepted, but what it asks for does not exist yet (an image of a time not captured yet):
    #: the request stands, and a second CommandAck (ACCEPTED when served, REJECTED when it
    #: expires) follows
    PENDING = 4


@dataclass(frozen=True, slots=True)
class CommandAck(Message):
    """Vehicle answer to a topside command (queue, schedule, link, goal)."""

    command_id: int
    status: AckStatus


@dataclass(frozen=True, slots=True)
class FrameAckEntry:
    """One acknowledged transmission of a :class:`FrameAck`: its header ``seq`` and a bitmap of
    the frames received intact (bit i, least significant first, = frame i of the packet)."""

    seq: int
    frames: int


@dataclass(frozen=True, slots=True)
class FrameAck(Message):
    """Receiver's acknowledgement of the frames it received from node ``node`` on link ``link``.

    The sender clears every ack-required message it packed into an acknowledged frame, on every
    link (see ``docs/channel.md``)."""

    node: int
    link: int
    entries: tuple[FrameAckEntry, ...]


@dataclass(frozen=True, slots=True)
class AuthTrailer(Message):
    """Command authentication: a monotonic counter and a truncated HMAC-SHA256 tag (8 bytes)
    over the frame bytes before this trailer. It is the last message of its frame."""

    counter: int
    tag: bytes


@dataclass(frozen=True, slots=True)
class LinkStatus(Message):
    """Modem link statistics for the console (from the modem's receive statistics)."""

    stamp: int
    link: int
    frames: int
    bad_frames: int
    snr: float | None
    doppler: float | None


@dataclass(frozen=True, slots=True)
class LinkHealth(Message):
    """Vehicle report: the outages of one of its modems (the device or stream gone and back),
    sent when a modem goes down (on another link) or comes back, and with the status now and
    then while it has had any."""

    stamp: int
    link: int
    up: bool
    outages: int
    down_total: int
    last_down: int


@dataclass(frozen=True, slots=True)
class Opaque(Message):
    """A message of a type id in a third-party range: the body is the plugin's own bytes.

    A receiver without the plugin can skip it because third-party bodies always carry a length."""

    type_id: int
    body: bytes


# -------------------------------------------------------------------------------- bathymetry


@dataclass(frozen=True, slots=True)
class MapMetadata(Message):
    """The map's geometry and progress; lets topside lay out levels before subgrids arrive."""

    stamp: int
    resolution: float
    vertical_resolution: float
    subgrid_side: int
    levels: int
    origin_lat: float
    origin_lon: float
    x_min: int
    y_min: int
    x_max: int
    y_max: int
    pending: int
    #: thousands of soundings the vehicle's map has dropped (a budget exhausted), rounded up
    dropped_k: int = 0


class SubgridEncoding(enum.IntEnum):
    """How a :class:`Subgrid` codes its cells (``q`` = elevation / vertical_resolution, an integer).

    * ``OFFSET``: ``q = z_base + v``, every ``v`` in ``width`` bits (``width`` 0: all equal ``z_base``).
    * ``DELTA``: present cells in serpentine order (row 0 west to east, row 1 east to west, ...);
      ``q[k] = q[k-1] + unzigzag(v[k])`` with ``q[-1] = z_base``; ``v`` Rice-coded with parameter
      ``width``.
    * ``PLANE``: ``q(i, j) = z_base + ((slope_x * j + slope_y * i + 4) >> 3) + unzigzag(v)``
      (slopes in 1/8 units per cell, arithmetic shift), ``v`` Rice-coded with parameter ``width``.
    * ``GRADIENT`` (complete subgrids only, ``mask`` None): ``r = unzigzag(v)`` in row-major order
      is the second difference of ``q - z_base`` (predictor west + south - south-west, zero
      outside the block), so ``q = z_base + cumsum(cumsum(r, rows), columns)``; Rice-coded with
      parameter ``width``.

    ``unzigzag(v) = v >> 1 if v is even else -((v + 1) >> 1)``. Every encoding uses only the
    subgrid's own bits: a subgrid never depends on another message."""

    OFFSET = 0
    DELTA = 1
    PLANE = 2
    GRADIENT = 3


@dataclass(frozen=True, slots=True)
class Subgrid(Message):
    """A square block of ``side x side`` cells at one level, decodable on its own.

    Cell (i, j) (row i northwards, column j eastwards) covers x in
    ``[(ix*side + j) * r, (ix*side + j + 1) * r)`` and y in ``[(iy*side + i) * r, (iy*side + i + 1) * r)``
    with ``r = resolution * 2**level``. ``mask`` has one bit per cell in row-major order (most
    significant bit = cell (0, 0)), 1 = present; ``None`` means every cell is present. ``values``
    holds one code per present cell, interpreted as ``encoding`` says (:class:`SubgridEncoding`);
    ``slope_x``/``slope_y`` are set for ``PLANE`` only (None otherwise). Elevations are
    ``q * vertical_resolution`` metres (positive up). ``coex_plugins.bathymetry.decode_subgrid``
    turns a subgrid into an array.
    """

    level: int
    ix: int
    iy: int
    stamp: int
    resolution: float
    vertical_resolution: float
    side: int
    encoding: SubgridEncoding
    z_base: int
    width: int
    mask: int | None
    values: tuple[int, ...]
    slope_x: int | None = None
    slope_y: int | None = None


class SubgridContext(enum.IntEnum):
    """What a :class:`PredictedSubgrid` is predicted from (``spec/payloads.md`` section 1.6).

    * ``NONE``: its own ``z_base``: it decodes on its own, like a :class:`Subgrid`.
    * ``PARENT``: the cells of its parent subgrid (the level above, ``(ix >> 1, iy >> 1)``) as
      the receiver holds them; ``check`` is a CRC-8 of the parent's cells the prediction reads,
      so a receiver that holds other cells there knows it cannot decode the subgrid (yet)."""

    NONE = 0
    PARENT = 1


@dataclass(frozen=True, slots=True)
class SubgridCells:
    """The arithmetic-coded part of a :class:`PredictedSubgrid`: ``mask`` (one bit per cell,
    row-major, most significant bit = cell (0, 0), 1 = present; ``None``: every cell present)
    and the residual of each present cell in row-major order (signed integers, vertical units)."""

    mask: int | None
    residuals: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class PredictedSubgrid(Message):
    """A square block of ``side x side`` cells at one level, predicted from what topside already
    holds (its parent subgrid, ``context`` PARENT) or from its own base (``NONE``), the residuals
    arithmetic-coded. Cells and geometry as :class:`Subgrid`; elevations (vertical units) are
    rebuilt by ``coex_core.predicted.decode_predicted_units`` from the message and, for PARENT,
    the parent's cells. ``predictor`` (0..3) picks the prediction of the context's table and
    ``shift`` (0..3) how many low bits of each residual are sent raw. ``resolution``,
    ``vertical_resolution`` and ``z_base`` are sent with ``NONE`` only (``PARENT``: the parent's
    geometry; ``None`` here); ``check`` with ``PARENT`` only."""

    level: int
    ix: int
    iy: int
    stamp: int
    side: int
    context: SubgridContext
    predictor: int
    shift: int
    cells: SubgridCells
    check: int | None = None
    resolution: float | None = None
    vertical_resolution: float | None = None
    z_base: int | None = None


#: Either form of a subgrid on the wire: ``isinstance(m, SubgridMessage)`` (a receiver, a filter
#: of what a sender filled) takes both.
SubgridMessage = Subgrid | PredictedSubgrid


@dataclass(frozen=True, slots=True)
class MapRoiRequest(Message):
    """Topside request for a region at one level, with the implicit ack of what topside holds.

    The region is the subgrid-index rectangle ``[x0, x0+w) x [y0, y0+h)`` at ``level``.
    Without ``fill_gaps``, ``held`` has one entry per subgrid of the region in row-major order
    (at most 64): the newest stamp topside holds for it, or ``None`` when it holds nothing; the
    vehicle re-sends the subgrids it has newer data for or that topside lacks. With ``fill_gaps``
    (gap filling, regions up to 16 x 16) ``held`` is empty and ``have`` is a bitmap of ``w*h`` bits
    (row-major, most significant bit first, 1 = topside holds that subgrid); the vehicle sends
    only what topside lacks.
    """

    request_id: int
    level: int
    x0: int
    y0: int
    w: int
    h: int
    fill_gaps: bool
    held: tuple[int | None, ...]
    have: int | None = None


@dataclass(frozen=True, slots=True)
class MapRoiReply(Message):
    """Vehicle answer to a :class:`MapRoiRequest`: ``queued`` subgrids will follow (0: nothing
    newer). Lets topside tell "lost" from "nothing to send" and time its retry. ``waiting``
    subgrids of the region hold no data yet: the request then *stands* on the vehicle (until it
    expires) and they follow as soon as they are surveyed (0: the request does not stand)."""

    request_id: int
    level: int
    queued: int
    waiting: int = 0


# ----------------------------------------------------------------------------------- imagery


@dataclass(frozen=True, slots=True)
class ImageAnnounce(Message):
    """A new image exists on the vehicle."""

    image_id: int
    stamp: int
    x: float | None
    y: float | None
    width: int
    height: int
    grey: bool
    total_bytes: int
    params: int


@dataclass(frozen=True, slots=True)
class ImageFragment(Message):
    """Bytes ``[offset, offset + len(data))`` of an image's codestream body.

    ``packets`` lists the offsets, relative to ``offset`` and increasing, at which a packet
    starts inside ``data`` (0 when ``data`` starts a packet; an offset equal to ``len(data)``
    says the next packet starts right after ``data``), and ``packet`` is then the index (in
    codestream order) of the JPEG 2000 packet that holds ``data[0]``. A fragment inside one
    packet has no marks and no ``packet`` (None): on the wire it is two bytes shorter.
    With the marks the receiver decodes whole packets only and repairs around a lost fragment."""

    image_id: int
    offset: int
    packet: int | None
    packets: tuple[int, ...]
    data: bytes


@dataclass(frozen=True, slots=True)
class ByteRange:
    """Bytes ``[start, end)`` of a codestream body."""

    start: int
    end: int


@dataclass(frozen=True, slots=True)
class ImageAck(Message):
    """Selective ack: topside holds bytes ``[0, contiguous)`` and each ``[start, end)`` range."""

    image_id: int
    contiguous: int
    ranges: tuple[ByteRange, ...]


class GoalKind(enum.IntEnum):
    SKIP = 0
    FRACTION = 1
    LAYER = 2
    FULL = 3


@dataclass(frozen=True, slots=True)
class ImageGoal(Message):
    """Topside command: transfer an image up to a goal (fraction in 1/100, layer, or full)."""

    command_id: int
    image_id: int
    kind: GoalKind
    value: int


class TimeDirection(enum.IntEnum):
    NEAREST = 0
    BEFORE = 1
    AFTER = 2


@dataclass(frozen=True, slots=True)
class ImageByTimeRequest(Message):
    """Topside request: the image nearest ``stamp``, or the one before / after it."""

    command_id: int
    stamp: int
    direction: TimeDirection


class RegionGoal(enum.IntEnum):
    """How far an image region is to be brought: quality in 0.1 dB PSNR inside the region,
    a number of quality layers, or a budget of body bytes."""

    QUALITY = 0
    LAYER = 1
    BYTES = 2


@dataclass(frozen=True, slots=True)
class ImageRegionRequest(Message):
    """Topside command: bring the rectangle ``[x0, x1) x [y0, y1)`` (pixels of the image as
    announced) of image ``image_id`` to a goal, by sending the JPEG 2000 packets of the precincts
    that cover it (those topside holds are not sent again)."""

    command_id: int
    image_id: int
    x0: int
    y0: int
    x1: int
    y1: int
    kind: RegionGoal
    value: int


@dataclass(frozen=True, slots=True)
class ImageCrop(Message):
    """A region of an image coded on its own: a small JPEG 2000 codestream of the rectangle
    ``[x0, x1) x [y0, y1)`` of image ``parent``, sent in ``ImageFragment``s and acked by
    ``ImageAck``s under its own ``image_id`` like any image. It answers the region request
    ``command_id``. It codes the difference between the rectangle and what topside holds of
    it: the parent decoded from its first ``base`` packets (spec/payloads.md 3.7); ``cover``
    is the number of the parent's quality layers the whole crop is at least as good as inside
    the rectangle."""

    image_id: int
    parent: int
    command_id: int
    x0: int
    y0: int
    x1: int
    y1: int
    total_bytes: int
    params: int
    base: int
    cover: int


@dataclass(frozen=True, slots=True)
class TransferProgress(Message):
    """What the image sender is doing: pending count, current image, next images, unacked bytes."""

    stamp: int
    pending: int
    current: int | None
    unacked_fragments: int
    next_images: tuple[int, ...]


# ------------------------------------------------------------------------------- time series


@dataclass(frozen=True, slots=True)
class TimeSeriesChannel(Message):
    """Registration of a time-series channel: name, unit, range and resolution."""

    channel: int
    name: str
    unit: str
    lo: float
    hi: float
    resolution: float


class Wavelet(enum.IntEnum):
    """The wavelet of a time-series block (PyWavelets names: haar, bior2.2, bior4.4, db4)."""

    HAAR = 0
    BIOR22 = 1
    BIOR44 = 2
    DB4 = 3


@dataclass(frozen=True, slots=True)
class TimeSeriesChunk(Message):
    """A self-contained piece of one refinement pass of one block of a channel.

    A block is ``count`` samples on the regular grid ``t_i = start + offset + i * period``.
    Pass ``level`` 0 is the coarse overview (approximation plus the largest details); pass
    ``p > 0`` codes the residual left by passes ``0..p-1``. The chunk holds the quantised
    wavelet coefficients ``[first, end)`` of the pass (flat order: approximation first, then
    details coarse to fine), or all of them when ``first``/``end`` are ``None``; a coefficient
    is ``q * step_value(step)``. A ``samples`` pass holds residual sample values instead of
    wavelet coefficients (indices are sample indices). ``error`` codes the maximum absolute error of the block once
    passes ``0..level`` are all held (see ``docs/timeseries.md`` for the codes and ``data``)."""

    channel: int
    start: int
    offset: float
    period: float
    count: int
    wavelet: Wavelet
    level: int
    samples: bool
    step: int
    error: int
    first: int | None
    end: int | None
    data: bytes


@dataclass(frozen=True, slots=True)
class TimeSeriesPart:
    """Names one chunk: its block (``start``, ``offset``), pass ``level`` and ``first``
    coefficient (0 for a chunk that holds the whole pass)."""

    start: int
    offset: float
    level: int
    first: int


@dataclass(frozen=True, slots=True)
class TimeSeriesAck(Message):
    """Topside ack: the channel's registration (``registered``) and chunks it now holds."""

    channel: int
    registered: bool
    parts: tuple[TimeSeriesPart, ...]


@dataclass(frozen=True, slots=True)
class TimeSeriesRequest(Message):
    """Topside request: refine every block of a channel that overlaps the window
    ``[start, end]`` (stamps) until its maximum absolute error is at most ``max_error``."""

    command_id: int
    channel: int
    start: int
    end: int
    max_error: float


# ------------------------------------------------------------------------------- surveys
class SurveyKind(enum.IntEnum):
    """What a :class:`SurveyCommand` asks the vehicle to fly."""

    #: go to the point (``x``, ``y``) and hold there
    GOTO = 0
    #: one straight line from (``x``, ``y``) along ``heading`` for ``length`` metres
    LINE = 1
    #: a lawnmower centred on (``x``, ``y``): rows ``length`` long along ``heading``, ``spacing``
    #: apart, across ``width`` (the first row on the port side of ``heading``)
    LAWNMOWER = 2
    #: the waypoints (``x``, ``y``) then ``points``, in order
    WAYPOINTS = 3


class SurveyState(enum.IntEnum):
    """Where a survey command is (:class:`SurveyStatus`)."""

    #: it passed the vehicle's checks and went to its autonomy
    ACCEPTED = 0
    #: refused (``reason`` says why); the vehicle does nothing
    REJECTED = 1
    #: the vehicle is flying it (``index``: the waypoint it is heading for)
    STARTED = 2
    #: flown to its end
    COMPLETED = 3
    #: stopped before its end (``reason``: replaced by a newer survey, or the autonomy failed)
    ABORTED = 4


class SurveyReason(enum.IntEnum):
    """Why a survey was rejected or aborted."""

    NONE = 0
    #: a waypoint or a leg lies outside the vehicle's geofence (``index``: the first such point;
    #: ``value``: how far outside, metres)
    OUTSIDE_GEOFENCE = 1
    #: the altitude asked is below the vehicle's minimum (``value``: the minimum, metres)
    ALTITUDE_LIMIT = 2
    #: the depth asked is beyond the vehicle's maximum (``value``: the maximum, metres)
    DEPTH_LIMIT = 3
    #: the path is longer than the vehicle's limit (``value``: the limit, metres)
    TOO_LONG = 4
    #: the command cannot be flown as given (a field it needs is missing or zero)
    INVALID = 5
    #: the vehicle's autonomy refused it (a mission upload was not accepted)
    AUTONOMY_REFUSED = 6
    #: a newer survey replaced it
    SUPERSEDED = 7
    #: the vehicle has no autonomy that takes survey commands
    NO_AUTONOMY = 8
    #: the autonomy stopped it (a fault, a mode change, an operator on the vehicle)
    AUTONOMY_STOPPED = 9
    #: the speed asked is above the vehicle's maximum (``value``: the maximum, m/s)
    SPEED_LIMIT = 10
    #: the vehicle's autonomy never answered (an autopilot that is down or not listening;
    #: ``value``: the tries made before giving up)
    AUTONOMY_NO_ANSWER = 11
    #: someone or something on the vehicle took control (MOOS_MANUAL_OVERRIDE, a pilot's mode change)
    MANUAL_OVERRIDE = 12
    #: the vehicle's autonomy restarted and lost the survey (a helm restart mid-survey)
    AUTONOMY_RESTARTED = 13
    #: the autonomy stopped all motion (the IvP helm's all-stop; ``detail``: its reason)
    ALL_STOP = 14
    #: the vehicle's autonomy fell silent while it flew the survey (no heartbeat, no helm
    #: posting, its planner gone) for longer than the vehicle's bound (``value``: the seconds of
    #: silence; ``detail``: what was not heard)
    AUTONOMY_SILENT = 15


@dataclass(frozen=True, slots=True)
class SurveyPoint:
    """A waypoint of a :class:`SurveyCommand` (metres east/north of the origin)."""

    x: float
    y: float


@dataclass(frozen=True, slots=True)
class SurveyCommand(Message):
    """Topside command: survey somewhere (see :class:`SurveyKind`). The vehicle answers with a
    :class:`CommandAck` and reports the survey's state in :class:`SurveyStatus` messages.
    ``altitude`` (above the seafloor) or ``depth`` (below the surface) sets how high it flies
    (neither: as it is); ``append`` queues it after the surveys already accepted instead of
    replacing them."""

    command_id: int
    survey_id: int
    kind: SurveyKind
    x: float
    y: float
    heading: float | None = None
    length: float | None = None
    width: float | None = None
    spacing: float | None = None
    altitude: float | None = None
    depth: float | None = None
    speed: float | None = None
    append: bool = False
    points: tuple[SurveyPoint, ...] = ()


@dataclass(frozen=True, slots=True)
class SurveyStatus(Message):
    """Vehicle report: the state of one survey (the newest state only; re-sent until acked).
    ``detail`` is the autonomy's own words for a refusal or a stop (a helm's bad parameters, an
    autopilot's result name), at most :data:`SURVEY_DETAIL_MAX` bytes of UTF-8."""

    survey_id: int
    state: SurveyState
    reason: SurveyReason
    stamp: int
    index: int | None = None
    value: float | None = None
    detail: str | None = None


#: Longest ``SurveyStatus.detail``, bytes of UTF-8.
SURVEY_DETAIL_MAX = 48


# ----------------------------------------------------------------------------- detections
class DetectionSource(enum.IntEnum):
    """What a :class:`Detection` was found in, on the vehicle."""

    #: the vehicle's own map (a relief anomaly of its full-resolution bathymetry)
    MAP = 0
    #: the vehicle's own camera frames (``image_id`` names the frame)
    IMAGE = 1
    #: another of the vehicle's sensors
    OTHER = 2


@dataclass(frozen=True, slots=True)
class Detection(Message):
    """Vehicle report: something a detector on the vehicle found in its own data, a suggestion
    for the operator (not a confirmation). ``detection_id`` is the vehicle's (wrapping at 1024);
    a detection sent again with the same id and a newer ``stamp`` replaces the older one (more
    data came in). ``score`` (0..1) ranks detections: how well it matches what the detector
    looks for. The measures of what stands out are optional (a detector gives those it has):
    ``height`` above the local background (m), ``length`` and ``width`` of its footprint (m,
    ``length`` the long axis), ``orientation`` of the long axis (degrees clockwise from north,
    0..179: an axis, not a heading), ``footprint`` (its area, m²); ``image_id`` is the frame an
    image detection was found in."""

    detection_id: int
    source: DetectionSource
    stamp: int
    x: float
    y: float
    score: float
    height: float | None = None
    length: float | None = None
    width: float | None = None
    orientation: float | None = None
    footprint: int | None = None
    image_id: int | None = None


class PositionSource(enum.IntEnum):
    """Where a :class:`PositionFix` comes from."""

    #: one fix of the ship's USBL, as measured
    USBL = 0
    #: topside's estimate (the USBL fixes fused with the vehicle's own track, docs/navigation.md)
    ESTIMATE = 1
    #: another positioning system (LBL, a surface fix)
    OTHER = 2


@dataclass(frozen=True, slots=True)
class PositionFix(Message):
    """Topside command: where the vehicle truly was at ``stamp`` (metres east/north of the
    origin, ``depth`` optional), with its 1-sigma horizontal uncertainty ``sigma`` (m). A vehicle
    that accepts aiding gives it to its navigation (which resets or fuses its estimate); it answers
    with a :class:`CommandAck` (REJECTED: it does not take aiding)."""

    command_id: int
    source: PositionSource
    stamp: int
    x: float
    y: float
    sigma: float
    depth: float | None = None


def _with_command_id() -> frozenset[type[Message]]:
    out = set()
    for cls in list(globals().values()):
        if isinstance(cls, type) and issubclass(cls, Message) and dataclasses.is_dataclass(cls) \
                and any(f.name == "command_id" for f in dataclasses.fields(cls)):
            out.add(cls)
    return frozenset(out)


#: the message types that declare a ``command_id`` field: commands, requests answered with a
#: ``CommandAck``, the answers themselves
WITH_COMMAND_ID: frozenset[type[Message]] = _with_command_id()


def command_id(message: object) -> int | None:
    """The command id ``message`` carries, or None for a message whose type declares none
    (:data:`WITH_COMMAND_ID`)."""
    return int(message.command_id) if type(message) in WITH_COMMAND_ID else None  # type: ignore[attr-defined]
