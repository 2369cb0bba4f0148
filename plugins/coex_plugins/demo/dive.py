"""The demo dive: a time-compressed re-enactment of NUI dive 040's nested survey.

Two CoEx nodes (vehicle 2, topside 1), each a channel manager with the built-in modalities, talk
through two simulated WHOI Micromodems (:class:`~coex_transports.micromodem.simulator.ModemNetwork`):
the bytes between each node and its modem are the NMEA sentences of the real driver
(:class:`~coex_transports.micromodem.MicromodemTransport`), so the demo runs the same code path
as a vehicle with real hardware. Rate 5, 6 x 20 s TDMA slots (topside 0 and 3, vehicle 1, 2, 4,
5), configurable frame loss. Everything runs on one simulated clock that jumps from event to
event, so a two-hour dive takes a few minutes at most.

The scenario: descent; a lawnmower multibeam survey at 30 m altitude over a seafloor with ripples
and two car-sized targets the operator does not know about; a camera pass at 3 m altitude over
the candidates the operator found in the 1 m map; ascent. A scripted operator watches the map,
requests the finest level around candidates, then asks for camera images near each target by
time and steps back in time until the target is in frame, as the 2022 operators did.
"""

from __future__ import annotations

import contextlib
import csv
import heapq
import json
import math
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from coex_core.acoustic import AcousticChannel, GilbertElliott
from coex_core.channel import ChannelManager, LinkConfig, Schedule, StreamConfig
from coex_core.channel.events import Received
from coex_core.loopback import SimClock
from coex_core.messages import VehicleMode, VehicleStatus
from coex_core.node import Node
from coex_core.timefmt import to_stamp, unwrap
from coex_plugins.bathymetry import (
    BathymetryModality,
    BathymetryReceiver,
    find_targets,
    write_geotiff,
    write_png,
)
from coex_plugins.bathymetry.sim import Seafloor, Survey, Target, simulate_survey
from coex_plugins.imagery import ImageInput, ImageryModality, ImageryReceiver
from coex_plugins.timeseries import TimeSeriesModality, TimeSeriesReceiver
from coex_plugins.timeseries import synth as ts_synth
from coex_transports._runner import Runner, SimulatedClock, next_wakeup
from coex_transports.micromodem.simulator import ModemNetwork

from .camera import SandTexture, in_frame, render_frame

__all__ = ["DemoConfig", "DemoResult", "run_demo"]

TOPSIDE, VEHICLE = 1, 2
EPOCH = 1_656_633_600.0  # 2022-07-01T00:00:00Z: the dive's clock (simulated)
CYCLE = 120.0
CAMERA_ALTITUDE = 3.0
TRANSIT_ALTITUDE = 10.0
SURVEY_ALTITUDE = 30.0
LINK_STREAM = 6


#: The demo's embedded command key (not a secret: real deployments configure their own).
DEMO_COMMAND_KEY = b"coex-demo-command-key-not-secret"


@dataclass
class DemoConfig:
    """Options of ``coex demo`` (see ``coex demo --help``)."""

    out: Path = Path("coex-demo-out")
    loss: float = 0.3
    seed: int = 1
    images: Path | None = None
    gui: bool = False
    http: str = "127.0.0.1:8080"
    quick: bool = False
    duration: float = 7200.0
    area: float = 256.0
    progress: bool = True
    burst: bool = False
    #: with ``gui``: simulated seconds per wall-clock second, so that a person can act
    speed: float = 20.0
    #: with ``gui``: keep serving the console after the dive until interrupted
    linger: bool = True
    #: shared command key (spec section 10): topside signs every command, the vehicle checks
    #: them; ``None`` turns authentication off
    command_key: bytes | None = DEMO_COMMAND_KEY

    def scaled(self) -> DemoConfig:
        """The short scenario of ``--quick`` (tests): a small area, a short dive."""
        if not self.quick:
            return self
        return DemoConfig(**{**asdict(self), "area": 96.0, "duration": 3000.0, "quick": True})


@dataclass
class Decision:
    t: float
    kind: str
    text: str


@dataclass
class DemoResult:
    out: Path
    metrics: dict[str, Any]
    decisions: list[Decision] = field(default_factory=list)


# ------------------------------------------------------------------------------ scenario


def _targets(area: float, rng: np.random.Generator) -> tuple[Target, ...]:
    """Two car-sized boxes at positions the operator does not know (well inside the area)."""
    margin = 0.2 * area
    out: list[Target] = []
    while len(out) < 2:
        x, y = rng.uniform(margin, area - margin, 2)
        if all(math.hypot(x - t.x, y - t.y) > 0.25 * area for t in out):
            out.append(Target(float(round(x, 1)), float(round(y, 1)), heading=float(rng.uniform(-90, 90))))
    return tuple(out)


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
        # the seafloor on a 1 m grid (with a margin), interpolated for the track's depths
        xs = np.arange(floor.x0 - 64.0, floor.x0 + floor.size + 64.0, 1.0)
        ys = np.arange(floor.y0 - 64.0, floor.y0 + floor.size + 64.0, 1.0)
        self._xs, self._ys = xs, ys
        gx, gy = np.meshgrid(xs, ys)
        self._grid = floor.elevation(gx, gy)
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


# ------------------------------------------------------------------------------ the nodes


def nui_schedule() -> Schedule:
    """6 x 20 s slots, 2 s guard: topside owns slots 0 and 3, the vehicle 1, 2, 4, 5."""
    return Schedule.simple([TOPSIDE, VEHICLE, VEHICLE, TOPSIDE, VEHICLE, VEHICLE], 20.0, 2.0, epoch=EPOCH)


def build_nodes(out: Path, channels: list[dict[str, Any]], command_key: bytes | None = None,
                ) -> tuple[Node, Node, dict[str, Any], dict[str, Any]]:
    sched = nui_schedule()
    vehicle = Node(ChannelManager(VEHICLE, [LinkConfig(0, sched, rate=5, dst=TOPSIDE)],
                                  queue_status_interval=CYCLE, command_key=command_key))
    topside = Node(ChannelManager(TOPSIDE, [LinkConfig(0, sched, rate=5, dst=VEHICLE)],
                                  queue_status_interval=CYCLE, command_key=command_key))
    senders = {
        "bathymetry": BathymetryModality().sender({"send_delay": 20.0}),
        "imagery": ImageryModality().sender({"default_goal": f"layer:{DEFAULT_LAYERS}", "request_goal": f"layer:{CONFIRM_LAYERS}"}),
        "timeseries": TimeSeriesModality().sender({"channels": channels}),
    }
    receivers = {
        "bathymetry": BathymetryModality().receiver(None),
        "imagery": ImageryModality().receiver({"out_dir": str(out / "images")}),
        "timeseries": TimeSeriesModality().receiver(None),
    }
    # NUI 2022 priorities: map subgrids 30, image fragments 30, time series a little less
    vehicle.add_sender(BathymetryModality, senders["bathymetry"], StreamConfig(3, "map", priority=30))
    vehicle.add_sender(ImageryModality, senders["imagery"], StreamConfig(4, "images", priority=30))
    vehicle.add_sender(TimeSeriesModality, senders["timeseries"], StreamConfig(5, "series", priority=20))
    # the vehicle modem's statistics (SNR, bad frames, Doppler) for the console: newest only
    vehicle.manager.add_stream(StreamConfig(LINK_STREAM, "link", priority=40, newest_first=True, max_depth=1))
    topside.add_receiver(BathymetryModality, receivers["bathymetry"])
    topside.add_receiver(ImageryModality, receivers["imagery"])
    topside.add_receiver(TimeSeriesModality, receivers["timeseries"])
    return vehicle, topside, senders, receivers


# ------------------------------------------------------------------------------ operator


@dataclass
class TargetWatch:
    x: float
    y: float
    height: float
    cells: int
    found_at: float
    passed_at: float | None = None
    want: tuple[float, str] | None = None  # the image asked for: (time, "nearest" | "before")
    first_request_at: float | None = None
    request_at: float | None = None
    image_id: int | None = None
    tried: list[int] = field(default_factory=list)
    confirmed_at: float | None = None


#: The operator's test of "a car-sized object in the 1 m map": height and footprint.
MIN_HEIGHT, MAX_HEIGHT = 1.0, 3.0
MIN_CELLS, MAX_CELLS = 3, 20
#: The image goal of a requested image (the vehicle's ``request_goal``): enough to recognise a car.
CONFIRM_LAYERS = 10
#: The vehicle's default set-point for every image (``default_goal``).
DEFAULT_LAYERS = 2


class Operator:
    """The scripted topside operator (what the 2022 operators did by hand).

    It knows the survey box (it planned the survey), never the targets: it finds candidates in
    what topside received, asks for 1 m data around them, shortlists car-sized ones, and asks for
    images by time, stepping back until the target is in frame."""

    def __init__(self, topside: Node, receivers: dict[str, Any], box: tuple[float, float, float, float],
                 log: Callable[[float, str, str], None]) -> None:
        self.topside = topside
        self.bathy: BathymetryReceiver = receivers["bathymetry"]
        self.imagery: ImageryReceiver = receivers["imagery"]
        self.series: TimeSeriesReceiver = receivers["timeseries"]
        self.box = box
        self.log = log
        self.track: list[tuple[float, float, float, float]] = []  # t, x, y, heading (received)
        self.coarse_requested: list[tuple[float, float]] = []
        self.targets: list[TargetWatch] = []
        self.camera_phase = False

    def inside(self, x: float, y: float, margin: float = 3.0) -> bool:
        x0, y0, x1, y1 = self.box
        return x0 + margin <= x <= x1 - margin and y0 + margin <= y <= y1 - margin

    # what topside hears
    def on_status(self, s: VehicleStatus, now: float) -> None:
        # the status's own time (its stamp), not when it arrived: it may have waited for a slot
        if s.altitude is not None and s.altitude <= CAMERA_ALTITUDE + 2.0:  # on a camera transect
            self.track.append((unwrap(s.stamp, now), s.x, s.y, s.heading))

    def level_grid(self, level: int) -> tuple[np.ndarray, float, tuple[float, float]] | None:
        try:
            p = self.bathy.level_product(level)
        except Exception:
            return None
        if p.data is None:
            return None
        meta = dict(p.meta)
        return np.asarray(p.data, dtype=float), float(meta["cell_size"]), (float(meta["x0"]), float(meta["y0"]))

    def candidates(self, level: int, threshold: float, **kw: Any) -> list[Any]:
        g = self.level_grid(level)
        if g is None:
            return []
        grid, cell, (x0, y0) = g
        return [c for c in find_targets(grid, cell=cell, x0=x0, y0=y0, threshold=threshold, **kw)
                if self.inside(c.x, c.y)]

    def shortlist(self, n: int = 2) -> list[TargetWatch]:
        return sorted(self.targets, key=lambda t: -t.height)[:n]

    def watch_map(self, now: float) -> None:
        """Every half cycle: look for bumps on a coarse level and ask for 1 m data around them;
        shortlist car-sized objects in the 1 m map."""
        for level in (2, 1):
            cands = self.candidates(level, 0.3, min_cells=1)
            if self.level_grid(level) is None:
                continue
            for c in cands:
                if any(math.hypot(c.x - x, c.y - y) < 12.0 for x, y in self.coarse_requested):
                    continue
                self.coarse_requested.append((c.x, c.y))
                self.bathy.request_area(0, c.x - 12.0, c.y - 12.0, c.x + 12.0, c.y + 12.0)
                self.log(now, "ROI request", f"level 0 (1 m) around ({c.x:.0f}, {c.y:.0f}): a "
                         f"{c.height:.1f} m bump at level {level} ({2 ** level} m cells)")
            break
        for c in self.candidates(0, MIN_HEIGHT, min_cells=MIN_CELLS, max_area=float(MAX_CELLS)):
            if not (MIN_HEIGHT <= c.height <= MAX_HEIGHT and MIN_CELLS <= c.cells <= MAX_CELLS):
                continue
            if any(math.hypot(c.x - t.x, c.y - t.y) < 6.0 for t in self.targets):
                continue
            self.targets.append(TargetWatch(c.x, c.y, c.height, c.cells, now))
            self.log(now, "target at 1 m", f"car-sized object at ({c.x:.1f}, {c.y:.1f}): {c.height:.1f} m "
                     f"high, {c.cells} cells in the 1 m map")

    # camera pass
    def watch_images(self, now: float) -> None:
        if not self.camera_phase or not self.track:
            return
        _, x_now, y_now, _ = self.track[-1]
        for tw in self.shortlist():
            if tw.confirmed_at is not None:
                continue
            if tw.passed_at is None:
                d, t_close = _closest_approach(self.track, tw.x, tw.y)
                if d < 6.0 and math.hypot(x_now - tw.x, y_now - tw.y) > 10.0:
                    tw.passed_at = t_close
                    self._ask(tw, t_close, "nearest", now)
                continue
            meta = self._answer(tw)
            if meta is None:
                continue
            tw.image_id = int(meta["image_id"])
            if not self._shows(tw, float(meta["x"]), float(meta["y"])):
                if tw.image_id not in tw.tried:
                    tw.tried.append(tw.image_id)
                    self.log(now, "image request", f"image {tw.image_id} does not show the target at "
                             f"({tw.x:.0f}, {tw.y:.0f}): stepping back in time")
                    self._ask(tw, float(meta["time"]), "before", now)
                continue
            if int(meta.get("layers_complete", 0)) >= CONFIRM_LAYERS or meta.get("complete"):
                tw.confirmed_at = now
                dt = now - (tw.request_at or now)
                self.log(now, "confirming image", f"image {tw.image_id} shows the target at "
                         f"({tw.x:.0f}, {tw.y:.0f}): {meta['bytes_used']} B, {dt:.0f} s after its request")

    def _answer(self, tw: TargetWatch) -> dict[str, Any] | None:
        """The image the vehicle serves for the operator's latest request, by the rule the vehicle
        applies (nearest to the time, or the newest before it), once topside has heard the
        announcements it needs to tell (images are announced in capture order)."""
        if tw.want is None:
            return None
        t, direction = tw.want
        metas = [dict(p.meta) for p in self.imagery.products()
                 if p.kind == "image" and p.meta.get("x") is not None and p.meta.get("time") is not None]
        if direction == "before":
            older = [m for m in metas if float(m["time"]) < t]
            return max(older, key=lambda m: float(m["time"]), default=None)
        if not any(float(m["time"]) >= t for m in metas):
            return None  # the images after that time are not announced yet: wait
        # ties go to the earlier image, as on the vehicle
        return min(metas, key=lambda m: (abs(float(m["time"]) - t), float(m["time"])), default=None)

    def _shows(self, tw: TargetWatch, x: float, y: float) -> bool:
        box = Target(tw.x, tw.y, 3.0, 3.0, 1.0, 0.0)  # the operator knows roughly where, not how it lies
        return in_frame(box, x, y, CAMERA_ALTITUDE, 0.0, fraction=0.15)

    def _ask(self, tw: TargetWatch, t: float, direction: str, now: float) -> None:
        t = float(math.floor(t))  # the wire carries whole seconds
        msg = self.imagery.request_by_time(t, direction, now)
        tw.want = (t, direction)
        tw.request_at = now
        if tw.first_request_at is None:
            tw.first_request_at = now
        self.log(now, "image request", f"image {direction} dive time {t - EPOCH:.0f} s, for the target at "
                 f"({tw.x:.0f}, {tw.y:.0f}) [command {msg.command_id}]")


# ------------------------------------------------------------------------------ the run


def _rng(seed: int, salt: int) -> np.random.Generator:
    return np.random.default_rng([seed, salt])


def _status(track: Track, t: float) -> VehicleStatus:
    x, y, depth, alt, heading = track.position(t)
    return VehicleStatus(to_stamp(t), round(x, 1), round(y, 1), round(min(depth, 6000.0), 1),
                         round(min(alt, 500.0), 1), round(heading % 359.9, 1), 0.5,
                         max(0, 100 - int((t - EPOCH) / 120)), VehicleMode.SURVEY, 0)


def _image_files(path: Path | None) -> list[Path]:
    if path is None:
        return []
    files = sorted(p for p in Path(path).iterdir() if p.suffix.lower() in (".tif", ".tiff", ".png", ".jpg"))
    if not files:
        raise FileNotFoundError(f"no images (.tif, .tiff, .png, .jpg) in {path}")
    return files


def _load_image(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


class _Progress:
    def __init__(self, total: float, enabled: bool) -> None:
        self.total = total
        self.enabled = enabled and sys.stderr.isatty()
        self.last = -1

    def update(self, t: float) -> None:
        if not self.enabled:
            return
        pct = int(100 * min(max(t / self.total, 0.0), 1.0))
        if pct != self.last:
            self.last = pct
            bar = "#" * (pct // 4) + "-" * (25 - pct // 4)
            sys.stderr.write(f"\r[{bar}] {pct:3d}%  dive time {t:6.0f} s")
            sys.stderr.flush()

    def close(self) -> None:
        if self.enabled:
            sys.stderr.write("\n")


def run_demo(config: DemoConfig, *, on_decision: Callable[[Decision], None] | None = None) -> DemoResult:
    cfg = config.scaled()
    out = Path(cfg.out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "map").mkdir(exist_ok=True)
    wall0 = time.perf_counter()
    decisions: list[Decision] = []

    def log(now: float, kind: str, text: str) -> None:
        d = Decision(round(now - EPOCH, 1), kind, text)
        decisions.append(d)
        if on_decision is not None:
            on_decision(d)

    # the world
    floor = Seafloor(size=cfg.area, depth=500.0, targets=_targets(cfg.area, _rng(cfg.seed, 1)), seed=cfg.seed)
    texture = SandTexture(seed=cfg.seed)
    track = Track(floor)
    descent = 300.0 if not cfg.quick else 120.0
    survey: Survey = simulate_survey(floor, altitude=SURVEY_ALTITUDE, speed=1.0 if not cfg.quick else 1.5,
                                     ping_rate=2.0, beams=256, t0=EPOCH + descent,
                                     turn_time=60.0 if not cfg.quick else 20.0, seed=cfg.seed + 1)
    survey_end = float(survey.times[-1]) if len(survey) else EPOCH + descent

    # the link: two simulated Micromodems on one acoustic channel, the real driver on each side
    clock = SimClock(EPOCH)
    burst = _burst(cfg.loss) if cfg.burst else None
    channel = AcousticChannel(loss=0.0 if burst else cfg.loss, burst=burst, seed=cfg.seed)
    # each node's driver talks NMEA to its simulated modem through a real pseudo-terminal pair
    net = ModemNetwork({TOPSIDE: (cfg.area / 2, -200.0, 0.0), VEHICLE: (0.0, 0.0, 500.0)},
                       channel=channel, clock=clock, ptys=True)
    end = EPOCH + cfg.duration
    series = ts_synth.dataset(duration=max(cfg.duration, 1200.0), period=1.0, seed=cfg.seed, t0=EPOCH)
    vehicle, topside, senders, receivers = build_nodes(out, [s.channel() for s in series], cfg.command_key)
    link_log = (out / "link.jsonl").open("w")
    runners = {
        VEHICLE: Runner(vehicle, {0: net.transport(VEHICLE, rate=5, dest=TOPSIDE)}, SimulatedClock(sim=clock),
                        link_log=link_log),
        TOPSIDE: Runner(topside, {0: net.transport(TOPSIDE, rate=5, dest=VEHICLE)}, SimulatedClock(sim=clock),
                        link_log=link_log),
    }
    operator = Operator(topside, receivers, (floor.x0, floor.y0, floor.x0 + floor.size, floor.y0 + floor.size), log)

    # timed events (simulated): sensor data, status, operator
    events: list[tuple[float, int, Callable[[float], None]]] = []
    counter = iter(range(10**9))

    def at(t: float, fn: Callable[[float], None]) -> None:
        heapq.heappush(events, (t, next(counter), fn))

    for t, xyz in survey.pings(batch=20):
        track.add_sample(float(t), float(np.mean(xyz[:, 0])), float(np.mean(xyz[:, 1])), SURVEY_ALTITUDE)
        at(float(t), lambda now, xyz=xyz: senders["bathymetry"].ingest(xyz, now))
    track.samples.sort()
    track.legs.append(Leg(EPOCH, EPOCH + descent, (0.0, 0.0), (0.0, 0.0), SURVEY_ALTITUDE))

    _schedule_series(at, senders["timeseries"], series, EPOCH, end)

    t_status = EPOCH
    while t_status < end:
        at(t_status, lambda now: vehicle.push_status(_status(track, now), now))
        t_status += 10.0

    vehicle_modem = runners[VEHICLE].transports[0]

    def push_link_status(now: float) -> None:
        status = vehicle_modem.link_status()
        if status is not None:
            vehicle.manager.push(LINK_STREAM, status, now)

    def every_cycle(now: float) -> None:
        operator.watch_map(now)
        operator.watch_images(now)
        metrics_tick(now)

    coverage: dict[int, list[tuple[float, float]]] = {}
    visible_at: dict[int, float] = {}

    def metrics_tick(now: float) -> None:
        push_link_status(now)
        for level in range(0, 4):
            g = operator.level_grid(level)
            frac = 0.0
            if g is not None:
                grid = g[0]
                frac = _area_fraction(grid, g[1], g[2], floor)
            coverage.setdefault(level, []).append((round(now - EPOCH, 1), round(frac, 4)))
        g0 = operator.level_grid(0)
        if g0 is not None:
            cands = operator.candidates(0, MIN_HEIGHT, min_cells=MIN_CELLS, max_area=float(MAX_CELLS))
            for i, tgt in enumerate(floor.targets):
                if i not in visible_at and any(math.hypot(c.x - tgt.x, c.y - tgt.y) < 3.5 for c in cands):
                    visible_at[i] = now

    t_op = EPOCH + CYCLE / 2
    while t_op < end:
        at(t_op, every_cycle)
        t_op += CYCLE / 2

    # the camera pass is planned when the survey ends, from the targets the operator found
    plan_at = survey_end + 30.0
    camera_times: list[float] = []

    def plan_camera(now: float) -> None:
        operator.camera_phase = True
        found = operator.shortlist()
        if not found:
            log(now, "camera pass", "no target confirmed at 1 m: camera transect through the centre")
            points = [(cfg.area / 2, cfg.area / 2)]
        else:
            points = [(tw.x, tw.y) for tw in found]
            log(now, "camera pass", "vehicle retargeted over " + ", ".join(f"({x:.0f}, {y:.0f})" for x, y in points))
        t = now
        pos = track.position(now)[:2]
        half = 30.0 if not cfg.quick else 15.0
        for x, y in points:
            start = (x + 1.0, y - half)
            dist = math.hypot(start[0] - pos[0], start[1] - pos[1])
            track.legs.append(Leg(t, t + dist / 1.0, pos, start, TRANSIT_ALTITUDE))
            t += dist / 1.0
            track.legs.append(Leg(t, t + 2 * half / 0.5, start, (x + 1.0, y + half), CAMERA_ALTITUDE, camera=True))
            t += 2 * half / 0.5
            pos = (x + 1.0, y + half)
        track.legs.append(Leg(t, end, pos, pos, 50.0))
        period = 6.0
        tc = now + period
        while tc < t:
            camera_times.append(tc)
            at(tc, take_picture)
            tc += period

    image_files = _image_files(cfg.images)
    shot = iter(range(10**9))
    taken: list[float] = []

    def take_picture(now: float) -> None:
        if not any(leg.camera and leg.t0 <= now <= leg.t1 for leg in track.legs):
            return  # the camera runs on the transects only
        x, y, depth, _alt, heading = track.position(now)
        k = next(shot)
        taken.append(now)
        if image_files:
            img = _load_image(image_files[k % len(image_files)])
        else:
            z = -(depth)
            img = render_frame(floor.elevation, x, y, z, heading, targets=floor.targets, texture=texture,
                               rng=_rng(cfg.seed, 100 + k))
        senders["imagery"].ingest(ImageInput(img, time=now, x=round(x, 1), y=round(y, 1)), now)

    at(plan_at, plan_camera)
    server = _start_gui(cfg, topside) if cfg.gui else None
    lock = server.hub.lock if server is not None else contextlib.nullcontext()
    wall_start, sim_start = time.monotonic(), clock.now

    # the loop: one simulated clock for the modems, the drivers, both nodes and the scenario
    progress = _Progress(cfg.duration, cfg.progress)
    steps = 0
    while clock.now < end:
        t = next_wakeup(clock.now, end, events[0][0] if events else None,
                        [net.next_event(), *(r.node.next_event(clock.now) for r in runners.values())],
                        started=bool(steps))
        if server is not None:  # pace the dive so that a person at the console can act
            t = min(t, clock.now + 1.0)
            ahead = (t - sim_start) / cfg.speed - (time.monotonic() - wall_start)
            if ahead > 0:
                time.sleep(ahead)
        with lock:
            net.run_until(t)
            while events and events[0][0] <= clock.now:
                _, _, fn = heapq.heappop(events)
                fn(clock.now)
            for r in runners.values():
                r.step()
            net.step()
            for ev in topside.events():
                _observe(ev, operator, clock.now)
            vehicle.events()
        steps += 1
        progress.update(clock.now - EPOCH)
    progress.close()
    link_log.close()
    ptys = net.pty_paths()
    net.close()
    if server is not None and cfg.linger:
        print(f"coex demo: the dive is over; the console stays at {server.url} (Ctrl+C to stop)",
              file=sys.stderr)
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            pass
    if server is not None:
        server.close()

    # outputs
    wall = time.perf_counter() - wall0
    metrics = _finish(out, cfg, floor, survey_end, operator, receivers, coverage, visible_at, decisions, wall,
                      runners, taken)
    metrics["modems"] = {"nmea_over": {str(k): v for k, v in ptys.items()}, "rate": 5,
                         "tdma": "6 x 20 s, guard 2 s; topside slots 0, 3; vehicle slots 1, 2, 4, 5"}
    metrics["authentication"] = {
        "enabled": cfg.command_key is not None,
        "signed_frames": topside.manager.stats["signed"],
        "rejected_frames": vehicle.stats["unauthenticated"],
    }
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return DemoResult(out, metrics, decisions)


def _closest_approach(track: list[tuple[float, float, float, float]], x: float, y: float) -> tuple[float, float]:
    """Distance and time of the track's closest approach to (x, y), between its points too
    (statuses arrive tens of metres apart on a slow link)."""
    best = (math.inf, 0.0)
    for (t0, x0, y0, _), (t1, x1, y1, _) in zip(track, track[1:] or track):
        dx, dy = x1 - x0, y1 - y0
        seg = dx * dx + dy * dy
        f = 0.0 if seg == 0 or t1 - t0 > 120.0 else min(max(((x - x0) * dx + (y - y0) * dy) / seg, 0.0), 1.0)
        px, py = x0 + f * dx, y0 + f * dy
        d = math.hypot(px - x, py - y)
        if d < best[0]:
            best = (d, t0 + f * (t1 - t0))
    return best


def _area_fraction(grid: np.ndarray, cell: float, origin: tuple[float, float], floor: Seafloor) -> float:
    """Fraction of the survey area's cells that the topside grid holds."""
    ny, nx = grid.shape
    xs = origin[0] + (np.arange(nx) + 0.5) * cell
    ys = origin[1] + (np.arange(ny) + 0.5) * cell
    cx = (xs >= floor.x0) & (xs <= floor.x0 + floor.size)
    cy = (ys >= floor.y0) & (ys <= floor.y0 + floor.size)
    sub = grid[np.ix_(cy, cx)]
    total = (floor.size / cell) ** 2
    return float(min(1.0, np.count_nonzero(np.isfinite(sub)) / max(total, 1.0)))


def _burst(loss: float, mean_burst: float = 4.0) -> GilbertElliott:
    """Bursty loss with the given mean rate and mean burst length (frames): a bad state losing
    everything, a good state losing nothing."""
    p_bg = 1.0 / mean_burst
    p_gb = loss * p_bg / max(1.0 - loss, 1e-6)
    return GilbertElliott(p_good_bad=min(p_gb, 1.0), p_bad_good=p_bg, loss_good=0.0, loss_bad=1.0)


def _observe(ev: Any, operator: Operator, now: float) -> None:
    if isinstance(ev, Received) and isinstance(ev.message, VehicleStatus):
        operator.on_status(ev.message, now)



def _schedule_series(at: Callable[[float, Callable[[float], None]], None], sender: Any, series: Any,
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


def _start_gui(cfg: DemoConfig, topside: Node) -> Any:
    from coex_plugins.console import serve

    host, _, port = cfg.http.rpartition(":")
    server = serve(topside, host or "127.0.0.1", int(port),
                   stream_names={3: "map", 4: "images", 5: "series", LINK_STREAM: "link"})
    print(f"coex demo: web console at {server.url} (the dive runs at {cfg.speed:g}x)", file=sys.stderr)
    return server


# ------------------------------------------------------------------------------ outputs


def _finish(out: Path, cfg: DemoConfig, floor: Seafloor, survey_end: float, operator: Operator,
            receivers: dict[str, Any], coverage: dict[int, list[tuple[float, float]]],
            visible_at: dict[int, float], decisions: list[Decision], wall: float,
            runners: dict[int, Runner], camera_times: list[float]) -> dict[str, Any]:
    from .report import line_chart, timeline_chart, write_report

    bathy: BathymetryReceiver = receivers["bathymetry"]
    origin = (floor.x0, floor.y0)
    map_files: list[str] = []
    for level in range(0, 6):
        try:
            p = bathy.level_product(level)
        except Exception:
            continue
        if p.data is None or not np.isfinite(np.asarray(p.data, float)).any():
            continue
        meta = dict(p.meta)
        cell, x0, y0 = float(meta["cell_size"]), float(meta["x0"]), float(meta["y0"])
        grid = np.asarray(p.data, float)
        write_geotiff(out / "map" / f"level_{level}.tif", grid, x0=x0, y0=y0, cell=cell,
                      origin_lat=float(meta.get("origin_lat", 0.0)), origin_lon=float(meta.get("origin_lon", 0.0)))
        write_png(out / "map" / f"level_{level}.png", grid, cell=cell)
        map_files.append(f"map/level_{level}.png")
    # ground truth at 1 m
    xs = np.arange(0.5, floor.size, 1.0) + floor.x0
    ys = np.arange(0.5, floor.size, 1.0) + floor.y0
    gx, gy = np.meshgrid(xs, ys)
    truth = floor.elevation(gx, gy)
    write_geotiff(out / "truth.tif", truth, x0=origin[0], y0=origin[1], cell=1.0)  # row 0 = south
    (out / "truth.json").write_text(json.dumps({
        "seafloor": {"size_m": floor.size, "depth_m": floor.depth, "seed": floor.seed, "cell_m": 1.0},
        "targets": [asdict(t) for t in floor.targets],
    }, indent=2))
    # time series
    ts: TimeSeriesReceiver = receivers["timeseries"]
    ts.to_csv(out / "timeseries.csv")
    # images
    img: ImageryReceiver = receivers["imagery"]
    image_meta = [dict(p.meta) for p in img.products() if p.kind == "image"]
    image_files = sorted(str(p.relative_to(out)) for p in (out / "images").glob("*.png"))

    # link use
    link = _link_summary(out / "link.jsonl")
    targets = []
    for i, t in enumerate(floor.targets):
        seen = visible_at.get(i)
        targets.append({"x": t.x, "y": t.y, "visible_at_1m_s": None if seen is None else round(seen - EPOCH, 1),
                        "before_survey_end": seen is not None and seen <= survey_end})
    confirmations = []
    for tw in operator.shortlist():
        if tw.request_at is None:
            confirmations.append({"x": round(tw.x, 1), "y": round(tw.y, 1), "first_request_at_s": None,
                                  "requested_at_s": None, "confirmed_at_s": None, "seconds": None,
                                  "tdma_cycles": None, "image_id": None, "stepped_back": 0})
            continue
        dt = None if tw.confirmed_at is None else tw.confirmed_at - tw.request_at
        first = tw.first_request_at or tw.request_at
        confirmations.append({"x": round(tw.x, 1), "y": round(tw.y, 1),
                              "first_request_at_s": round(first - EPOCH, 1),
                              "requested_at_s": round(tw.request_at - EPOCH, 1),
                              "confirmed_at_s": None if tw.confirmed_at is None else round(tw.confirmed_at - EPOCH, 1),
                              "seconds": None if dt is None else round(dt, 1),
                              "tdma_cycles": None if dt is None else round(dt / CYCLE, 2),
                              "image_id": tw.image_id, "stepped_back": len(tw.tried)})
    both_visible = len(targets) == 2 and all(t["before_survey_end"] for t in targets)
    images_ok = bool(confirmations) and all(
        c["tdma_cycles"] is not None and c["tdma_cycles"] <= 2.0 for c in confirmations)
    metrics: dict[str, Any] = {
        # the key itself never goes into the outputs
        "config": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(cfg).items()
                   if k != "command_key"},
        "wall_seconds": round(wall, 1),
        "dive_seconds": cfg.duration,
        "survey_end_s": round(survey_end - EPOCH, 1),
        "targets": targets,
        "confirming_images": confirmations,
        "images_received": len(image_meta),
        "images_captured": len(camera_times),
        "link": link,
        "map_coverage": {str(k): v[-1][1] if v else 0.0 for k, v in coverage.items()},
        "bad_frames": {"topside": runners[TOPSIDE].node.stats.get("bad_frames", 0),
                       "vehicle": runners[VEHICLE].node.stats.get("bad_frames", 0)},
        "goals": {
            "both targets identifiable topside at 1 m before the survey ends": {
                "met": both_visible,
                "detail": "; ".join(
                    f"target {i + 1} at ({t['x']:.0f}, {t['y']:.0f}): "
                    + (f"visible at {t['visible_at_1m_s']:.0f} s" if t["visible_at_1m_s"] is not None else "not visible")
                    for i, t in enumerate(targets)) + f"; survey ended at {survey_end - EPOCH:.0f} s",
            },
            "a confirming image within two TDMA cycles of its request": {
                "met": images_ok,
                "detail": "; ".join(f"{c['tdma_cycles']} cycles" if c["tdma_cycles"] is not None
                                    else "not confirmed" for c in confirmations) or "no image requested",
            },
        },
    }
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    charts = [
        line_chart({f"level {k} ({2**k} m)": v for k, v in sorted(coverage.items())},
                   title="Map filling in over time (fraction of the survey area held topside)",
                   xlabel="dive time (s)", ylabel="fraction",
                   markers=[(survey_end - EPOCH, "survey ends")] + [
                       (v - EPOCH, f"target {i + 1} visible at 1 m") for i, v in visible_at.items()]),
        line_chart({"capacity": link["capacity_series"], "used": link["used_series"],
                    "delivered": link["delivered_series"]},
                   title="Link use against capacity (cumulative bytes, vehicle to topside)",
                   xlabel="dive time (s)", ylabel="bytes"),
        timeline_chart([{"t": d.t, "kind": d.kind, "text": d.text} for d in decisions], t_end=cfg.duration),
    ]
    write_report(out, metrics, charts, [asdict(d) for d in decisions],
                 {"Map levels": map_files, "Received images": image_files[:60]})
    for k in ("capacity_series", "used_series", "delivered_series"):
        link.pop(k, None)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    with (out / "decisions.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["dive_time_s", "kind", "text"])
        for d in decisions:
            w.writerow([d.t, d.kind, d.text])
    return metrics


def _link_summary(path: Path) -> dict[str, Any]:
    cap = used = delivered = 0
    cap_s: list[tuple[float, float]] = []
    used_s: list[tuple[float, float]] = []
    del_s: list[tuple[float, float]] = []
    sent = lost = 0
    for line in path.read_text().splitlines():
        try:
            rec = json.loads(line)
        except ValueError:
            continue
        if rec.get("src") != VEHICLE:
            continue
        t = float(rec.get("time", 0.0)) - EPOCH
        if rec.get("cause") == "sent":
            cap += int(rec.get("capacity_bytes") or 0)
            used += int(rec.get("used_bytes") or 0)
            sent += 1
            cap_s.append((round(t, 1), cap))
            used_s.append((round(t, 1), used))
        elif rec.get("delivered") is not None:
            d = rec.get("delivered")
            n = sum(1 for x in d if x) if isinstance(d, list) else int(d)
            delivered += int(rec.get("used_bytes") or 0) if n else 0
            lost += int(rec.get("lost") or 0) if not isinstance(rec.get("lost"), list) else len(rec["lost"])
            del_s.append((round(t, 1), delivered))
    return {"packets_sent": sent, "capacity_bytes": cap, "used_bytes": used,
            "fill": round(used / cap, 4) if cap else None, "capacity_series": cap_s, "used_series": used_s,
            "delivered_series": del_s}


def iter_decisions(result: DemoResult) -> Iterator[str]:
    for d in result.decisions:
        yield f"{d.t:7.0f} s  {d.kind:<16} {d.text}"
