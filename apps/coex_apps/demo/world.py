"""The simulated world of the demo: the vehicle's track, the two nodes, the schedules and the
sensor feeds."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from coex import Node, Schedule, StreamConfig, to_stamp
from coex.messages import VehicleMode, VehicleStatus
from coex_plugins.bathymetry.sim import Seafloor

from .config import (
    CAMERA,
    EPOCH,
    LINK_STREAM,
    MIN_ALTITUDE,
    TOPSIDE,
    VEHICLE,
)
from .deployment import build, node_mapping, receiver_modalities, sender_modalities
from .operator import CONFIRM_LAYERS
from .scenario import Scenario


@dataclass
class Leg:
    """A straight leg of the vehicle's track at constant depth offset above the seafloor."""

    t0: float
    t1: float
    p0: tuple[float, float]
    p1: tuple[float, float]
    altitude: float
    camera: bool = False

    def at(self, t: float) -> tuple[float, float]:
        f = 0.0 if self.t1 <= self.t0 else min(max((t - self.t0) / (self.t1 - self.t0), 0.0), 1.0)
        return (self.p0[0] + f * (self.p1[0] - self.p0[0]), self.p0[1] + f * (self.p1[1] - self.p0[1]))

    @property
    def heading(self) -> float:
        dx, dy = self.p1[0] - self.p0[0], self.p1[1] - self.p0[1]
        return (math.degrees(math.atan2(dx, dy)) + 360.0) % 360.0 if (dx or dy) else 0.0


class Track:
    """The vehicle's position over time: survey pings first, then planned legs."""

    def __init__(self, floor: Seafloor) -> None:
        self.floor = floor
        # the bare seafloor (the vehicle holds its altitude over the seafloor, not over the
        # objects on it) on a 1 m grid (with a margin), interpolated for the track's depths
        xs = np.arange(floor.x0 - 64.0, floor.x0 + floor.size + 64.0, 1.0)
        ys = np.arange(floor.y0 - 64.0, floor.y0 + floor.size + 64.0, 1.0)
        self._xs, self._ys = xs, ys
        gx, gy = np.meshgrid(xs, ys)
        self._grid = floor.ground(gx, gy)
        self.samples: list[tuple[float, float, float, float]] = []  # t, x, y, altitude
        self.legs: list[Leg] = []

    def add_sample(self, t: float, x: float, y: float, altitude: float) -> None:
        self.samples.append((t, x, y, altitude))

    def position(self, t: float) -> tuple[float, float, float, float, float]:
        """x, y, depth, altitude, heading at time ``t``."""
        for leg in self.legs:
            if leg.t0 <= t <= leg.t1:
                x, y = leg.at(t)
                return (*self._depth(x, y, leg.altitude), leg.heading)
        if self.samples:
            ts = [s[0] for s in self.samples]
            i = int(np.searchsorted(ts, t))
            i = min(max(i, 0), len(self.samples) - 1)
            _, x, y, alt = self.samples[i]
            j = max(i - 1, 0)
            dx, dy = x - self.samples[j][1], y - self.samples[j][2]
            heading = (math.degrees(math.atan2(dx, dy)) + 360.0) % 360.0 if (dx or dy) else 0.0
            return (*self._depth(x, y, alt), heading)
        return (0.0, 0.0, 0.0, 0.0, 0.0)

    def floor_z(self, x: float, y: float) -> float:
        i = float(np.clip(np.interp(y, self._ys, np.arange(len(self._ys))), 0, len(self._ys) - 1.001))
        j = float(np.clip(np.interp(x, self._xs, np.arange(len(self._xs))), 0, len(self._xs) - 1.001))
        i0, j0 = int(i), int(j)
        fi, fj = i - i0, j - j0
        g = self._grid
        return float(g[i0, j0] * (1 - fi) * (1 - fj) + g[i0, j0 + 1] * (1 - fi) * fj
                     + g[i0 + 1, j0] * fi * (1 - fj) + g[i0 + 1, j0 + 1] * fi * fj)

    def _depth(self, x: float, y: float, altitude: float) -> tuple[float, float, float, float]:
        floor_z = self.floor_z(x, y)
        return x, y, max(0.0, -(floor_z + altitude)), altitude


def dive_schedule(scn: Scenario) -> Schedule:
    """The scenario's TDMA cycle (the NUI 2022 one by default: 6 x 20 s slots, 2 s guard, topside
    slots 0 and 3, vehicle slots 1, 2, 4, 5). In a fleet dive the ``"camera"`` slots are the
    camera vehicle's (:data:`~.config.CAMERA`)."""
    ids = {"topside": TOPSIDE, "vehicle": VEHICLE, "camera": CAMERA}
    owners = [ids[s] for s in scn.slots]
    return Schedule.simple(owners, scn.slot_seconds, scn.guard_seconds, epoch=EPOCH)


def nui_schedule() -> Schedule:
    """6 x 20 s slots, 2 s guard: topside owns slots 0 and 3, the vehicle 1, 2, 4, 5."""
    return dive_schedule(Scenario())


def site_geofence(scn: Scenario) -> dict[str, Any]:
    """The vehicle's geofence for survey commands: the site (``[0, area]`` square) with a margin
    of a quarter of its side (room for a camera line's run-in past the edge), and
    :data:`~coex_apps.demo.config.MIN_ALTITUDE`."""
    m, a = scn.area / 4, scn.area
    return {"polygon": [[-m, -m], [a + m, -m], [a + m, a + m], [-m, a + m]], "min_altitude": MIN_ALTITUDE}


def link_stream() -> StreamConfig:
    """The vehicle modem's statistics (SNR, bad frames, Doppler) for the console: newest only.
    The demo's own stream, beside the deployment's modalities (the daemon has none yet)."""
    return StreamConfig(LINK_STREAM, "link", priority=40, newest_first=True, max_depth=1)


def build_nodes(out: Path, channels: list[dict[str, Any]], command_key: bytes | None = None,
                scenario: Scenario | None = None, *, network: Any, auto_fill: bool = True,
                geofence: dict[str, Any] | None = None,
                ) -> tuple[Node, Node, dict[str, Any], dict[str, Any], dict[int, Any]]:
    """The two nodes of the dive, each built from its deployment configuration
    (:mod:`~coex_apps.demo.deployment`) over its modem on ``network``: the vehicle, topside,
    the vehicle's senders and topside's receivers by modality, and each node's modem by node
    id. ``auto_fill=False`` when the scripted operator asks for the holes of the map itself
    (the receiver's own gap rounds over the whole map would compete with it, and with image
    requests, for the uplink). ``geofence``: the vehicle's limits for survey commands (default
    :func:`site_geofence`)."""
    scn = scenario or Scenario()
    fence = site_geofence(scn) if geofence is None else geofence
    names = ("bathymetry", "imagery", "timeseries", "survey", "detections")
    vehicle, vmodem = build(node_mapping(scn, "vehicle", VEHICLE, TOPSIDE,
                                         sender_modalities(names, channels, fence, CONFIRM_LAYERS),
                                         spare=scn.spare), out, network, command_key)
    vehicle.manager.add_stream(link_stream())
    topside, tmodem = build(node_mapping(scn, "topside", TOPSIDE, VEHICLE, receiver_modalities(out, auto_fill)),
                            out, network, command_key)
    senders = {name: vehicle.sender(name) for name in names}
    receivers = {name: topside.receiver(name) for name in names}
    return vehicle, topside, senders, receivers, {VEHICLE: vmodem, TOPSIDE: tmodem}


@dataclass
class Fleet:
    """The three nodes of a fleet dive (issue 43) on one network: topside, the mapping AUV
    (:data:`~.config.VEHICLE`) and the camera vehicle (:data:`~.config.CAMERA`), each vehicle's
    senders, and topside's receivers: per peer (``Node.add_receiver(..., peer=N)``), so that a
    request or survey command goes to that vehicle alone and only its answers count."""

    mapper: Node
    camera: Node
    topside: Node
    mapper_senders: dict[str, Any]
    camera_senders: dict[str, Any]
    #: topside's receivers by modality: the map, detections and time series are the mapper's,
    #: the images and survey commands the camera vehicle's
    receivers: dict[str, Any]
    #: each node's modem, by node id
    modems: dict[int, Any]


def build_fleet(out: Path, channels: list[dict[str, Any]], command_key: bytes | None, scn: Scenario, *,
                network: Any, auto_fill: bool = True, geofence: dict[str, Any] | None = None) -> Fleet:
    """The nodes of a fleet dive (see :class:`Fleet`) over their modems on ``network``. The
    mapper carries the multibeam, its detector, the sensor channels and a survey sender of its
    own (it could be retargeted; the demo never does, and a command for the camera vehicle must
    never reach it); the camera vehicle carries the camera and the survey sender its autonomy
    flies. Each node is built from its deployment configuration
    (:mod:`~coex_apps.demo.deployment`); topside's ``[[vehicles]]`` say which modalities each
    vehicle carries, so its per-vehicle receivers are the map, time series, detections and
    survey answers of the mapper and the images and survey answers of the camera vehicle. Its
    link broadcasts (``dst`` 0, docs/channel.md); its per-peer receivers address their requests
    to their vehicle."""
    fence = site_geofence(scn) if geofence is None else geofence
    carried = {VEHICLE: ("bathymetry", "timeseries", "detections", "survey"), CAMERA: ("imagery", "survey")}
    mapper, mapper_modem = build(node_mapping(scn, "vehicle", VEHICLE, TOPSIDE, sender_modalities(
        ("bathymetry", "timeseries", "survey", "detections"), channels, fence, CONFIRM_LAYERS), spare=scn.spare),
        out, network, command_key)
    mapper.manager.add_stream(link_stream())
    topside, topside_modem = build(node_mapping(scn, "topside", TOPSIDE, VEHICLE, receiver_modalities(
        out, auto_fill, ("bathymetry", "timeseries", "detections", "survey", "imagery")), vehicles=carried),
        out, network, command_key)
    camera, camera_modem = build(node_mapping(scn, "vehicle", CAMERA, TOPSIDE, sender_modalities(
        ("imagery", "survey"), channels, fence, CONFIRM_LAYERS), spare=scn.spare), out, network, command_key)
    receivers = {
        "bathymetry": topside.receiver("bathymetry", VEHICLE),
        "timeseries": topside.receiver("timeseries", VEHICLE),
        "detections": topside.receiver("detections", VEHICLE),
        "imagery": topside.receiver("imagery", CAMERA),
        "survey": topside.receiver("survey", CAMERA),
        # the mapper's answers to survey commands (it is never sent one: what would come is shown)
        "mapper_survey": topside.receiver("survey", VEHICLE),
    }
    return Fleet(mapper, camera, topside,
                 {name: mapper.sender(name) for name in ("bathymetry", "timeseries", "survey", "detections")},
                 {name: camera.sender(name) for name in ("imagery", "survey")}, receivers,
                 {VEHICLE: mapper_modem, TOPSIDE: topside_modem, CAMERA: camera_modem})


def rng_for(seed: int, salt: int) -> np.random.Generator:
    return np.random.default_rng([seed, salt])


def vehicle_status(track: Track, t: float) -> VehicleStatus:
    x, y, depth, alt, heading = track.position(t)
    return VehicleStatus(to_stamp(t), round(x, 1), round(y, 1), round(min(depth, 6000.0), 1),
                         round(min(alt, 500.0), 1), round(heading % 359.9, 1), 0.5,
                         max(0, 100 - int((t - EPOCH) / 120)), VehicleMode.SURVEY, 0)


def image_files(path: Path | None) -> list[Path]:
    if path is None:
        return []
    files = sorted(p for p in Path(path).iterdir() if p.suffix.lower() in (".tif", ".tiff", ".png", ".jpg"))
    if not files:
        raise FileNotFoundError(f"no images (.tif, .tiff, .png, .jpg) in {path}")
    return files


def load_image(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


class SurveyedCells:
    """The referee's count of the site's surveyed cells, in the frame the map is sent in (issue 54).

    The vehicle maps in its believed frame (issue 56): a sounding of the site, truly at ``(x,
    y)``, lands in the vehicle's map where the vehicle places it. :meth:`add` marks, at
    ``resolution`` (the map's level-0 cell), every cell where the vehicle placed a valid (not
    wild) sounding whose true position is inside the site ``[x0, x0 + size) x [y0, y0 + size)``; :meth:`fraction`
    is the share of those cells (at a level's cell size) that a received level holds. So the
    completeness of the map on the link is judged on what the survey gave the vehicle to send,
    in the frame it was sent in, and not on where topside's navigation correction puts it
    (that is ``map_error_m``'s business): with perfect navigation (``drift = 0``) the surveyed
    cells are the site's cells the survey sounded, the whole site for the demo's lawnmower."""

    def __init__(self, floor: Seafloor, resolution: float = 1.0, margin: float | None = None) -> None:
        self.floor = floor
        self.resolution = float(resolution)
        # the believed frame is the site moved by the dead-reckoning error: room for the site's
        # side of it all round (the cells placed beyond are counted as not held)
        margin = float(floor.size if margin is None else margin)
        self.step = 8 * self.resolution  # the grid's corner on whole cells of levels 0 to 3
        self.x0 = math.floor((floor.x0 - margin) / self.step) * self.step
        self.y0 = math.floor((floor.y0 - margin) / self.step) * self.step
        n = math.ceil((floor.size + 2 * margin) / self.step) * 8
        self.mask = np.zeros((n, n), dtype=bool)
        #: soundings of the site placed beyond the grid (a drift larger than the margin)
        self.beyond = 0

    def add(self, true_xy: np.ndarray, placed_xy: np.ndarray, valid: np.ndarray | None = None) -> None:
        """Soundings truly at ``true_xy`` (N x 2) that the vehicle placed at ``placed_xy``;
        ``valid`` (N booleans, default all) marks those that measured the seafloor: the
        simulation's wild soundings (``Survey.outlier``, metres off, which the vehicle's outlier
        screen is there to refuse) survey nothing, so a cell whose only soundings were wild is
        not a surveyed cell (issue 54)."""
        f = self.floor
        t = np.asarray(true_xy, dtype=float)[:, :2]
        site = (t[:, 0] >= f.x0) & (t[:, 0] < f.x0 + f.size) & (t[:, 1] >= f.y0) & (t[:, 1] < f.y0 + f.size)
        if valid is not None:
            site &= np.asarray(valid, dtype=bool)
        p = np.asarray(placed_xy, dtype=float)[site, :2]
        col = np.floor((p[:, 0] - self.x0) / self.resolution).astype(np.int64)
        row = np.floor((p[:, 1] - self.y0) / self.resolution).astype(np.int64)
        n = self.mask.shape[0]
        ok = (col >= 0) & (row >= 0) & (col < n) & (row < n)
        self.beyond += int(np.count_nonzero(~ok))
        self.mask[row[ok], col[ok]] = True

    def cells(self, cell: float) -> np.ndarray:
        """The surveyed cells at cell size ``cell`` (a power of two of the resolution, at most
        8 of them): a boolean grid from ``(x0, y0)``, row 0 south."""
        k = max(1, round(cell / self.resolution))
        n = self.mask.shape[0] // k
        return np.asarray(self.mask[:n * k, :n * k].reshape(n, k, n, k).any(axis=(1, 3)))

    def fraction(self, grid: np.ndarray, cell: float, origin: tuple[float, float]) -> float:
        """Share of the surveyed cells at ``cell`` that ``grid`` (row 0 south, south-west corner
        ``origin``, NaN where empty) holds; 0 when nothing was surveyed yet."""
        want = self.cells(cell)
        rows, cols = np.nonzero(want)
        if not len(rows):
            return 0.0
        g = np.asarray(grid, dtype=float)
        c = np.floor((self.x0 + (cols + 0.5) * cell - origin[0]) / cell).astype(np.int64)
        r = np.floor((self.y0 + (rows + 0.5) * cell - origin[1]) / cell).astype(np.int64)
        ok = (c >= 0) & (r >= 0) & (c < g.shape[1]) & (r < g.shape[0])
        held = np.count_nonzero(np.isfinite(g[r[ok], c[ok]]))
        return float(held / len(rows))


def area_fraction(grid: np.ndarray, cell: float, origin: tuple[float, float], floor: Seafloor) -> float:
    """Fraction of the survey area's cells that the topside grid holds."""
    ny, nx = grid.shape
    xs = origin[0] + (np.arange(nx) + 0.5) * cell
    ys = origin[1] + (np.arange(ny) + 0.5) * cell
    cx = (xs >= floor.x0) & (xs <= floor.x0 + floor.size)
    cy = (ys >= floor.y0) & (ys <= floor.y0 + floor.size)
    sub = grid[np.ix_(cy, cx)]
    total = (floor.size / cell) ** 2
    return float(min(1.0, np.count_nonzero(np.isfinite(sub)) / max(total, 1.0)))


def schedule_series(at: Callable[[float, Callable[[float], None]], None], sender: Any, series: Any,
                     t0: float, end: float) -> None:
    """Feed the synthetic sensor channels to the vehicle in 60 s batches."""
    step = 60.0
    t = t0 + step
    while t <= end:
        def feed(now: float, lo: float = t - step, hi: float = t) -> None:
            batch = {}
            for s in series:
                m = (s.times >= lo) & (s.times < hi)
                if m.any():
                    batch[s.name] = (s.times[m], s.values[m])
            if batch:
                sender.ingest(batch, now)
        at(t, feed)
        t += step
