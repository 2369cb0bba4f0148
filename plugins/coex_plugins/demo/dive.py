"""The demo dive: a time-compressed re-enactment of NUI dive 040's nested survey.

Two CoEx nodes (vehicle 2, topside 1), each a channel manager with the built-in modalities, talk
through two simulated WHOI Micromodems (:class:`~coex_transports.micromodem.simulator.ModemNetwork`):
the bytes between each node and its modem are the NMEA sentences of the real driver
(:class:`~coex_transports.micromodem.MicromodemTransport`), so the demo runs the same code path
as a vehicle with real hardware. The scenario (:mod:`coex_plugins.demo.scenario`: a preset or a
TOML file) sets the site, the survey, the modem rate, the TDMA slots, the loss model and where
the ship is. Everything runs on one simulated clock that jumps from event to event, so a
two-hour dive takes well under a minute.

The dive: descent; a lawnmower multibeam survey over a seafloor with ripples, cars (the targets)
and possibly car-sized boulders (decoys) that the operator does not know about; camera transects
at low altitude over the candidates the operator ranked in the received 1 m map, most car-like
first, while camera time remains; then the vehicle holds until the end of the dive. The scripted
operator (:mod:`coex_plugins.demo.operator`) decides only from what reached topside. The goals
are judged against the simulation's truth (:mod:`coex_plugins.demo.truth`), never against the
operator's belief.
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

from coex import Runner, SimulatedClock
from coex_core.acoustic import AcousticChannel
from coex_core.channel import ChannelManager, LinkConfig, Schedule, StreamConfig
from coex_core.channel.events import Received
from coex_core.errors import ConfigError
from coex_core.loopback import SimClock
from coex_core.messages import VehicleMode, VehicleStatus
from coex_core.node import Node
from coex_core.timefmt import to_stamp
from coex_plugins.bathymetry import (
    BathymetryModality,
    BathymetryReceiver,
    write_geotiff,
    write_png,
)
from coex_plugins.bathymetry.sim import Seafloor, Survey, Target, simulate_survey
from coex_plugins.imagery import ImageInput, ImageryModality, ImageryReceiver
from coex_plugins.timeseries import TimeSeriesModality, TimeSeriesReceiver
from coex_plugins.timeseries import synth as ts_synth
from coex_transports.micromodem.simulator import ModemNetwork
from coex_transports.runner import next_wakeup

from .camera import CameraModel, SandTexture, render_labelled
from .operator import CONFIRM_LAYERS, MIN_SCORE, CandidateView, Operator
from .scenario import Scenario, preset
from .truth import FrameTruth, frame_truth, judge

__all__ = ["DemoConfig", "DemoResult", "run_demo"]

TOPSIDE, VEHICLE = 1, 2
EPOCH = 1_656_633_600.0  # 2022-07-01T00:00:00Z: the dive's clock (simulated)
TRANSIT_ALTITUDE = 10.0
HOLD_ALTITUDE = 50.0
LINK_STREAM = 6
#: seconds between camera frames on a transect
CAMERA_PERIOD = 6.0
#: the vehicle's default set-point for every image (``default_goal``)
DEFAULT_LAYERS = 2
#: a target is identifiable at 1 m when a car-like candidate of the received 1 m map lies this
#: close to it (m)
IDENTIFY_RADIUS = 3.5
OPERATORS = ("script", "none")


#: The demo's embedded command key (not a secret: real deployments configure their own).
DEMO_COMMAND_KEY = b"coex-demo-command-key-not-secret"


@dataclass
class DemoConfig:
    """Options of ``coex demo`` (see ``coex demo --help``)."""

    out: Path = Path("coex-demo-out")
    #: frame loss; ``None`` keeps the scenario's loss model (``--loss``)
    loss: float | None = None
    seed: int = 1
    images: Path | None = None
    gui: bool = False
    http: str = "127.0.0.1:8080"
    quick: bool = False
    progress: bool = True
    #: bursty (Gilbert-Elliott) loss at ``loss`` (or the scenario's rate) instead of independent
    burst: bool = False
    #: with ``gui``: simulated seconds per wall-clock second, so that a person can act
    speed: float = 20.0
    #: with ``gui``: keep serving the console after the dive until interrupted
    linger: bool = True
    #: shared command key (spec section 10): topside signs every command, the vehicle checks
    #: them; ``None`` turns authentication off
    command_key: bytes | None = DEMO_COMMAND_KEY
    #: the dive (``--scenario FILE`` / ``--preset NAME``); ``None`` is preset ``default``
    scenario: Scenario | None = None
    #: ``"script"`` or ``"none"``; ``None``: the script, unless a person has the console (``gui``)
    operator: str | None = None

    def resolved(self) -> tuple[Scenario, str]:
        """The scenario with ``--quick``, ``--loss`` and ``--burst`` applied, and the operator."""
        scn = self.scenario or preset("default")
        scn = scn.with_loss(self.loss, self.burst)
        if self.quick:
            scn = scn.quick()
        op = self.operator or ("none" if self.gui else "script")
        if op not in OPERATORS:
            raise ConfigError(f"operator must be one of {', '.join(OPERATORS)}, got {op!r}")
        return scn, op


@dataclass
class Decision:
    t: float
    kind: str
    text: str
    #: ``"script"`` (the scripted operator), ``"person"`` (an action in the console) or ``"system"``
    who: str = "script"


@dataclass
class DemoResult:
    out: Path
    metrics: dict[str, Any]
    decisions: list[Decision] = field(default_factory=list)


# ------------------------------------------------------------------------------ scenario


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


def dive_schedule(scn: Scenario) -> Schedule:
    """The scenario's TDMA cycle (the NUI 2022 one by default: 6 x 20 s slots, 2 s guard, topside
    slots 0 and 3, vehicle slots 1, 2, 4, 5)."""
    owners = [TOPSIDE if s == "topside" else VEHICLE for s in scn.slots]
    return Schedule.simple(owners, scn.slot_seconds, scn.guard_seconds, epoch=EPOCH)


def nui_schedule() -> Schedule:
    """6 x 20 s slots, 2 s guard: topside owns slots 0 and 3, the vehicle 1, 2, 4, 5."""
    return dive_schedule(Scenario())


def build_nodes(out: Path, channels: list[dict[str, Any]], command_key: bytes | None = None,
                scenario: Scenario | None = None, *, auto_fill: bool = True,
                ) -> tuple[Node, Node, dict[str, Any], dict[str, Any]]:
    """The two nodes of the dive. ``auto_fill=False`` when the scripted operator asks for the
    holes of the map itself (the receiver's own gap rounds over the whole map would compete with
    it, and with image requests, for the uplink)."""
    scn = scenario or Scenario()
    sched = dive_schedule(scn)
    cycle = scn.cycle
    vehicle = Node(ChannelManager(VEHICLE, [LinkConfig(0, sched, rate=scn.modem_rate, dst=TOPSIDE)],
                                  queue_status_interval=cycle, command_key=command_key))
    topside = Node(ChannelManager(TOPSIDE, [LinkConfig(0, sched, rate=scn.modem_rate, dst=VEHICLE)],
                                  queue_status_interval=cycle, command_key=command_key))
    senders = {
        "bathymetry": BathymetryModality().sender({"send_delay": 20.0}),
        "imagery": ImageryModality().sender({"default_goal": f"layer:{DEFAULT_LAYERS}",
                                             "request_goal": f"layer:{CONFIRM_LAYERS}"}),
        "timeseries": TimeSeriesModality().sender({"channels": channels}),
    }
    receivers = {
        "bathymetry": BathymetryModality().receiver({"auto_fill": auto_fill}),
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
    scn, operator_mode = config.resolved()
    cfg = config
    out = Path(cfg.out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "map").mkdir(exist_ok=True)
    wall0 = time.perf_counter()
    decisions: list[Decision] = []

    def log(now: float, kind: str, text: str, who: str = "script") -> None:
        d = Decision(round(now - EPOCH, 1), kind, text, who)
        decisions.append(d)
        if on_decision is not None:
            on_decision(d)

    # the world: cars (the targets) and boulders (decoys) at positions the operator does not know
    placed_targets, placed_decoys = scn.place(cfg.seed)
    cars, rocks = placed_targets, placed_decoys
    floor = Seafloor(size=scn.area, depth=scn.water_depth, relief=scn.relief,
                     ripple_amplitude=scn.ripple_amplitude, targets=cars + rocks, seed=cfg.seed)
    texture = SandTexture(seed=cfg.seed)
    camera = CameraModel()
    track = Track(floor)
    descent = 300.0 if not cfg.quick else 120.0
    survey: Survey = simulate_survey(floor, altitude=scn.survey_altitude, line_spacing=scn.line_spacing or None,
                                     speed=scn.survey_speed,
                                     ping_rate=2.0, beams=256, t0=EPOCH + descent,
                                     turn_time=60.0 if not cfg.quick else 20.0, seed=cfg.seed + 1)
    survey_end = float(survey.times[-1]) if len(survey) else EPOCH + descent
    end = EPOCH + scn.duration

    # the link: two simulated Micromodems on one acoustic channel, the real driver on each side
    clock = SimClock(EPOCH)
    channel = AcousticChannel(loss=scn.loss.independent(), burst=scn.loss.burst(),
                              range_loss=scn.loss.range_loss(), seed=cfg.seed)
    # each node's driver talks NMEA to its simulated modem through a real pseudo-terminal pair
    net = ModemNetwork({TOPSIDE: (scn.ship[0], scn.ship[1], 0.0), VEHICLE: (0.0, 0.0, 0.0)},
                       channel=channel, clock=clock, ptys=True)
    series = ts_synth.dataset(duration=max(scn.duration, 1200.0), period=1.0, seed=cfg.seed, t0=EPOCH)
    vehicle, topside, senders, receivers = build_nodes(out, [s.channel() for s in series], cfg.command_key, scn,
                                                       auto_fill=operator_mode != "script")
    link_log = (out / "link.jsonl").open("w")
    runners = {
        VEHICLE: Runner(vehicle, {0: net.transport(VEHICLE, rate=scn.modem_rate, dest=TOPSIDE)},
                        SimulatedClock(sim=clock), link_log=link_log),
        TOPSIDE: Runner(topside, {0: net.transport(TOPSIDE, rate=scn.modem_rate, dest=VEHICLE)},
                        SimulatedClock(sim=clock), link_log=link_log),
    }

    # what the camera saw, for the operator's eye and the referee (frames showing an object only)
    frames: dict[float, FrameTruth] = {}

    def frame_at(t: float) -> FrameTruth | None:
        best = min(frames, key=lambda ft: abs(ft - t), default=None)
        return frames[best] if best is not None and abs(best - t) <= 1.0 else None

    operator = Operator(topside, receivers, (floor.x0, floor.y0, floor.x0 + floor.size, floor.y0 + floor.size),
                        log, frames=frame_at, camera_altitude=scn.camera_altitude, cycle=scn.cycle,
                        active=operator_mode == "script")
    operator.epoch = EPOCH
    received_track: list[tuple[float, float]] = []

    # timed events (simulated): sensor data, status, operator
    events: list[tuple[float, int, Callable[[float], None]]] = []
    counter = iter(range(10**9))

    def at(t: float, fn: Callable[[float], None]) -> None:
        heapq.heappush(events, (t, next(counter), fn))

    for t, xyz in survey.pings(batch=20):
        track.add_sample(float(t), float(np.mean(xyz[:, 0])), float(np.mean(xyz[:, 1])), scn.survey_altitude)
        at(float(t), lambda now, xyz=xyz: senders["bathymetry"].ingest(xyz, now))
    track.samples.sort()
    track.legs.append(Leg(EPOCH, EPOCH + descent, (0.0, 0.0), (0.0, 0.0), scn.survey_altitude))

    _schedule_series(at, senders["timeseries"], series, EPOCH, end)

    def push_status(now: float) -> None:
        status = _status(track, now)
        channel.set_position(VEHICLE, (status.x, status.y, status.depth or 0.0))  # range-dependent loss
        vehicle.push_status(status, now)

    t_status = EPOCH
    while t_status < end:
        at(t_status, push_status)
        t_status += 10.0

    vehicle_modem = runners[VEHICLE].transports[0]

    def push_link_status(now: float) -> None:
        status = vehicle_modem.link_status()
        if status is not None:
            vehicle.manager.push(LINK_STREAM, status, now)

    coverage: dict[int, list[tuple[float, float]]] = {}
    visible_at: dict[int, float] = {}

    def every_half_cycle(now: float) -> None:
        views = operator.measured(now)
        operator.watch_map(now, views)
        operator.watch_images(now)
        push_link_status(now)
        for level in range(0, 4):
            g = operator.level_grid(level)
            frac = 0.0 if g is None else _area_fraction(g[0], g[1], g[2], floor)
            coverage.setdefault(level, []).append((round(now - EPOCH, 1), round(frac, 4)))
        # judged against the truth: a car-like bump of the received 1 m map where a car is
        for i, tgt in enumerate(cars):
            if i not in visible_at and any(v.score >= MIN_SCORE and math.hypot(v.x - tgt.x, v.y - tgt.y)
                                           <= IDENTIFY_RADIUS for v in views):
                visible_at[i] = now

    t_op = EPOCH + scn.cycle / 2
    while t_op < end:
        at(t_op, every_half_cycle)
        t_op += scn.cycle / 2

    # the camera pass, planned when the survey ends: transects over the candidates in rank order
    # while camera time remains; when they are done, the next candidates found meanwhile
    half = 30.0 if not cfg.quick else 15.0
    reserve = 2 * scn.cycle  # the last frames need time to come up before the dive ends
    holds: list[Leg] = []

    def transect(t: float, pos: tuple[float, float], x: float, y: float) -> tuple[float, tuple[float, float]]:
        start = (x, y - half)
        dist = math.hypot(start[0] - pos[0], start[1] - pos[1])
        track.legs.append(Leg(t, t + dist / 1.0, pos, start, TRANSIT_ALTITUDE))
        t += dist / 1.0
        track.legs.append(Leg(t, t + 2 * half / 0.5, start, (x, y + half), scn.camera_altitude, camera=True))
        return t + 2 * half / 0.5, (x, y + half)

    def plan_camera(now: float, first: bool = False) -> None:
        operator.camera_phase = True
        pos = track.position(now)[:2]
        t = now
        planned: list[CandidateView] = []
        if operator.active:
            for _rank, cv in enumerate(operator.ranked(), 1):
                if cv.planned:
                    continue
                dist = math.hypot(cv.x - pos[0], cv.y - half - pos[1])
                if t + dist + 4 * half > end - reserve:
                    break  # no camera time left for the next in rank order
                t, pos = transect(t, pos, cv.x, cv.y)
                cv.planned = True
                cv.pass_planned = t - 2 * half / 0.5 + half / 0.5  # the middle of its transect
                planned.append(cv)
            if planned:
                log(now, "camera pass", "vehicle retargeted over " + ", ".join(
                    f"({c.x:.0f}, {c.y:.0f}) [car-likeness {c.score:.2f}]" for c in planned))
            elif first:
                log(now, "camera pass", "no car-like candidate in the 1 m map yet: the vehicle holds")
        elif first:
            t, pos = transect(t, pos, scn.area / 2, scn.area / 2)
            log(now, "camera pass", "no operator script: one camera transect through the centre of the site",
                "system")
        if planned or first:
            if holds:
                holds[-1].t1 = now
            hold = Leg(t, end, pos, pos, HOLD_ALTITUDE)
            holds.append(hold)
            track.legs.append(hold)
        if operator.active and t < end - reserve:
            at(max(t, now + scn.cycle), plan_camera)

    at(survey_end + 30.0, lambda now: plan_camera(now, first=True))

    image_files = _image_files(cfg.images)
    shot = iter(range(10**9))
    taken: list[float] = []
    hfov = math.tan(math.radians(camera.hfov_deg) / 2)

    def take_picture(now: float) -> None:
        if not any(leg.camera and leg.t0 <= now <= leg.t1 for leg in track.legs):
            return  # the camera runs on the transects only
        x, y, depth, alt, heading = track.position(now)
        k = next(shot)
        taken.append(now)
        rendered, labels = render_labelled(floor.ground, x, y, -depth, heading, targets=cars, rocks=rocks,
                                           texture=texture, camera=camera, rng=_rng(cfg.seed, 100 + k))
        img = rendered
        if image_files:  # a real dive image, with the simulated objects where the camera sees them
            real = _load_image(image_files[k % len(image_files)])
            if real.shape == rendered.shape:
                img = np.where(labels[..., None] > 0, rendered, real)
            else:
                img, labels = real, np.zeros(real.shape[:2], np.uint8)
        areas, pixel = {}, {}
        for i, o in enumerate(cars + rocks, 1):
            dome = o.shape == "dome"
            areas[i] = o.length * o.width * (math.pi / 4 if dome else 1.0)
            top = max(alt - o.height * (0.67 if dome else 1.0), 0.3)
            pixel[i] = (2 * top * hfov / camera.width) ** 2
        ft = frame_truth(now, x, y, heading, img, labels, len(cars), areas, pixel)
        if ft is not None:
            frames[now] = ft
        senders["imagery"].ingest(ImageInput(img, time=now, x=round(x, 1), y=round(y, 1)), now)

    tc = survey_end + 30.0 + CAMERA_PERIOD
    while tc < end:
        at(tc, take_picture)
        tc += CAMERA_PERIOD

    server = _start_gui(cfg, topside, log) if cfg.gui else None
    lock = server.hub.lock if server is not None else contextlib.nullcontext()
    wall_start, sim_start = time.monotonic(), clock.now

    # the loop: one simulated clock for the modems, the drivers, both nodes and the scenario
    progress = _Progress(scn.duration, cfg.progress)
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
                if isinstance(ev, Received) and isinstance(ev.message, VehicleStatus):
                    operator.on_status(ev.message, clock.now)
                    received_track.append((ev.message.x, ev.message.y))
            vehicle.events()
            for rec in channel.log():  # what arrived, per packet and receiver: delivered or lost frames
                link_log.write(json.dumps(rec, sort_keys=True, separators=(",", ":")) + "\n")
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
    world = _World(scn, floor, cars, rocks, survey_end, frames, received_track, taken, operator_mode)
    metrics = _finish(out, cfg, world, operator, receivers, coverage, visible_at, decisions, wall, runners)
    metrics["modems"] = {"nmea_over": {str(k): v for k, v in ptys.items()}, "rate": scn.modem_rate,
                         "tdma": f"{len(scn.slots)} x {scn.slot_seconds:g} s, guard {scn.guard_seconds:g} s; "
                                 f"topside slots {', '.join(str(i) for i, s in enumerate(scn.slots) if s == 'topside')}; "
                                 f"vehicle slots {', '.join(str(i) for i, s in enumerate(scn.slots) if s == 'vehicle')}"}
    metrics["authentication"] = {
        "enabled": cfg.command_key is not None,
        "signed_frames": topside.manager.stats["signed"],
        "rejected_frames": vehicle.stats["unauthenticated"],
    }
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return DemoResult(out, metrics, decisions)


@dataclass
class _World:
    """What the simulation knows, handed to the judging."""

    scenario: Scenario
    floor: Seafloor
    cars: tuple[Target, ...]
    rocks: tuple[Target, ...]
    survey_end: float
    frames: dict[float, FrameTruth]
    received_track: list[tuple[float, float]]
    camera_times: list[float]
    operator: str


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


def _start_gui(cfg: DemoConfig, topside: Node, log: Callable[..., None]) -> Any:
    from coex_plugins.console import serve

    host, _, port = cfg.http.rpartition(":")
    server = serve(topside, host or "127.0.0.1", int(port),
                   stream_names={3: "map", 4: "images", 5: "series", LINK_STREAM: "link"})
    hub = server.hub
    act = hub.act

    def logged(action: str, args: dict[str, Any]) -> list[Any]:
        """What a person does in the console goes into the decision list too."""
        now = hub.clock()
        try:
            sent = act(action, args)
        except Exception as exc:
            log(now, "console action", f"{action} {json.dumps(args, default=str)} refused: {exc}", "person")
            raise
        log(now, "console action", f"{action} {json.dumps(args, default=str)}", "person")
        return sent

    hub.act = logged
    print(f"coex demo: web console at {server.url} (the dive runs at {cfg.speed:g}x)", file=sys.stderr)
    return server


# ------------------------------------------------------------------------------ outputs


def _judge(world: _World, operator: Operator, bytes_of: Callable[[int], int | None],
           cycle: float) -> tuple[list[dict[str, Any] | None], list[dict[str, Any]]]:
    """Every confirmation the operator made, judged against the truth: per true target the first
    confirmation by a received image that shows it, and the confirmations that show no target."""
    per_target: list[dict[str, Any] | None] = [None] * len(world.cars)
    false: list[dict[str, Any]] = []
    confirmed = sorted((c for c in operator.candidates if c.verdict == "car"), key=lambda c: c.confirmed_at or 0.0)
    for c in confirmed:
        truth = world.frames.get(c.evidence_time) if c.evidence_time is not None else None
        shown = judge(c.evidence, truth) if (c.evidence is not None and truth is not None) else []
        hit = [k for kind, k in shown if kind == "target"]
        assert c.confirmed_at is not None and c.verdict_image is not None
        record = {"image_id": c.verdict_image,
                  "image_time_s": None if c.evidence_time is None else round(c.evidence_time - EPOCH, 1),
                  "image_x": c.evidence_xy[0] if c.evidence_xy else None,
                  "image_y": c.evidence_xy[1] if c.evidence_xy else None,
                  "confirmed_at_s": round(c.confirmed_at - EPOCH, 1),
                  "bytes": c.evidence_bytes,
                  "requested_at_s": None if c.request_at is None else round(c.request_at - EPOCH, 1),
                  "first_requested_at_s": None if c.first_request_at is None else round(c.first_request_at - EPOCH, 1),
                  "tdma_cycles": None if c.request_at is None else round((c.confirmed_at - c.request_at) / cycle, 2),
                  "tdma_cycles_from_first_request": None if c.first_request_at is None
                  else round((c.confirmed_at - c.first_request_at) / cycle, 2),
                  "candidate": {"x": c.x, "y": c.y}}
        if hit:
            for k in hit:
                if per_target[k] is None:
                    per_target[k] = record
        else:
            others = [f"decoy {k + 1} (a boulder)" for kind, k in shown if kind == "decoy"]
            false.append({"x": c.x, "y": c.y, "image_id": c.verdict_image,
                          "confirmed_at_s": record["confirmed_at_s"],
                          "shows": ", ".join(others) or "no target (sand, or too little of one, or too blurry)"})
    return per_target, false


def _why_not(i: int, world: _World, operator: Operator, visible: float | None) -> str:
    """Why target ``i`` was not confirmed, from the truth."""
    car = world.cars[i]
    near = [c for c in operator.candidates if math.hypot(c.x - car.x, c.y - car.y) <= IDENTIFY_RADIUS]
    shown = sorted(ft.time for ft in world.frames.values() if ft.visible.get(i + 1, 0.0) >= 0.15)
    if shown:
        return (f"photographed ({len(shown)} frames from {shown[0] - EPOCH:.0f} s), but no received image of it "
                "was confirmed")
    if visible is None:
        return "never photographed: never identifiable in the received 1 m map"
    if world.operator == "none":
        return "never photographed: never visited with the camera (no operator retargeted the vehicle)"
    if not any(c.planned for c in near):
        return ("never photographed: identifiable at 1 m but never visited with the camera (ranked too low, "
                "or no camera time left)")
    return "never photographed: visited, but no camera frame showed enough of it"


def _finish(out: Path, cfg: DemoConfig, world: _World, operator: Operator, receivers: dict[str, Any],
            coverage: dict[int, list[tuple[float, float]]], visible_at: dict[int, float],
            decisions: list[Decision], wall: float, runners: dict[int, Runner]) -> dict[str, Any]:
    from .report import line_chart, map_figure, timeline_chart, write_report

    scn, floor = world.scenario, world.floor
    bathy: BathymetryReceiver = receivers["bathymetry"]
    names = {("target", i): f"target {i + 1}" for i in range(len(world.cars))}
    names.update({("decoy", k): f"decoy {k + 1} (rock)" for k in range(len(world.rocks))})
    ranked = operator.ranked()
    rank_of = {id(c): r for r, c in enumerate(ranked, 1)}

    def truth_near(x: float, y: float) -> str:
        for key, objs in (("target", world.cars), ("decoy", world.rocks)):
            for k, o in enumerate(objs):
                if math.hypot(o.x - x, o.y - y) <= IDENTIFY_RADIUS:
                    return names[(key, k)]
        return "none"

    candidates = [{"x": c.x, "y": c.y, "height": c.height, "cells": c.cells, "length": c.length, "width": c.width,
                   "score": c.score, "rank": rank_of.get(id(c)), "visited": c.planned, "verdict": c.verdict or None,
                   "truth": truth_near(c.x, c.y)}
                  for c in sorted(operator.candidates, key=lambda c: -c.score) if c.score >= MIN_SCORE]
    map_svgs: list[str] = []
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
        if level <= 3:
            # the survey box (and a margin), not the whole quadtree
            sub, sx0, sy0 = _crop(grid, cell, x0, y0, floor.x0 - 8, floor.y0 - 8, floor.x0 + floor.size + 8,
                                  floor.y0 + floor.size + 8)
            map_svgs.append(map_figure(
                sub, cell=cell, x0=sx0, y0=sy0,
                title=f"Level {level}: {cell:g} m cells, as received topside",
                track=world.received_track,
                targets=[{"x": t.x, "y": t.y, "label": f"target {i + 1}"} for i, t in enumerate(world.cars)],
                decoys=[{"x": t.x, "y": t.y, "label": f"decoy {i + 1} (rock)"} for i, t in enumerate(world.rocks)],
                candidates=[{"x": c["x"], "y": c["y"], "label": f"#{c['rank']}", "visited": c["visited"]}
                            for c in candidates if c["rank"] is not None] if level == 0 else []))
    # ground truth at 1 m
    xs = np.arange(0.5, floor.size, 1.0) + floor.x0
    ys = np.arange(0.5, floor.size, 1.0) + floor.y0
    gx, gy = np.meshgrid(xs, ys)
    write_geotiff(out / "truth.tif", floor.elevation(gx, gy), x0=floor.x0, y0=floor.y0, cell=1.0)  # row 0 = south
    (out / "truth.json").write_text(json.dumps({
        "seafloor": {"size_m": floor.size, "depth_m": floor.depth, "seed": floor.seed, "cell_m": 1.0},
        "targets": [{"name": f"target {i + 1}", "kind": "car", **_obj(t)} for i, t in enumerate(world.cars)],
        "decoys": [{"name": f"decoy {i + 1}", "kind": "rock", **_obj(t)} for i, t in enumerate(world.rocks)],
    }, indent=2))
    # time series
    ts: TimeSeriesReceiver = receivers["timeseries"]
    ts.to_csv(out / "timeseries.csv")
    # images
    img: ImageryReceiver = receivers["imagery"]
    metas = {int(p.meta["image_id"]): dict(p.meta) for p in img.products() if p.kind == "image"}

    def bytes_of(image_id: int) -> int | None:
        m = metas.get(image_id)
        return None if m is None else int(m["bytes_used"])

    per_target, false = _judge(world, operator, bytes_of, scn.cycle)
    link = _link_summary(out / "link.jsonl")
    targets = []
    for i, t in enumerate(world.cars):
        seen = visible_at.get(i)
        conf = per_target[i]
        targets.append({"name": f"target {i + 1}", "x": t.x, "y": t.y, "heading": t.heading,
                        "identifiable_at_1m_s": None if seen is None else round(seen - EPOCH, 1),
                        "before_survey_end": seen is not None and seen <= world.survey_end,
                        "confirmation": conf,
                        "why_not": None if conf is not None else _why_not(i, world, operator, seen)})
    confirming = {c["image_id"]: t["name"] for t in targets if (c := t["confirmation"]) is not None}
    requested = {i for c in operator.candidates for i in c.looked + ([c.image_id] if c.image_id is not None else [])}
    images = [{"file": f"images/image_{i:04d}.png", "image_id": i, "time_s": round(float(m["time"]) - EPOCH, 1),
               "x": m.get("x"), "y": m.get("y"), "bytes": int(m["bytes_used"]), "layers": int(m["layers_complete"]),
               "confirms": confirming.get(i), "requested": i in requested}
              for i, m in sorted(metas.items(), key=lambda kv: float(kv[1]["time"]))
              if (out / "images" / f"image_{i:04d}.png").exists()]

    all_identifiable = all(t["before_survey_end"] for t in targets)
    all_confirmed = all(t["confirmation"] is not None for t in targets)
    success = all_confirmed and not false
    cycles = [t["confirmation"]["tdma_cycles"] for t in targets if t["confirmation"] is not None]
    fast = success and all(c is not None and c <= 2.0 for c in cycles)
    none_text = "no targets in this scenario" if not targets else ""
    goals = {
        "every target identifiable topside at 1 m before the survey ends": {
            "met": all_identifiable,
            "detail": "; ".join(
                f"{t['name']} at ({t['x']:.0f}, {t['y']:.0f}): "
                + (f"identifiable at {t['identifiable_at_1m_s']:.0f} s" if t["identifiable_at_1m_s"] is not None
                   else "never identifiable") for t in targets) or none_text
            + f"; survey ended at {world.survey_end - EPOCH:.0f} s",
        },
        "every target confirmed by a received image that shows it, and nothing else confirmed": {
            "met": success,
            "detail": "; ".join(
                f"{t['name']}: " + (f"image {t['confirmation']['image_id']} at {t['confirmation']['confirmed_at_s']:.0f} s"
                                    if t["confirmation"] else f"NOT confirmed ({t['why_not']})") for t in targets)
            + (f"; {len(false)} false confirmation(s): " + "; ".join(
                f"({f['x']:.0f}, {f['y']:.0f}) by image {f['image_id']}, which shows {f['shows']}" for f in false)
               if false else "; no false confirmation"),
        },
        "each confirming image within two TDMA cycles of its request": {
            "met": fast,
            "detail": "; ".join(f"{t['name']}: {t['confirmation']['tdma_cycles']} cycles" if t["confirmation"]
                                else f"{t['name']}: not confirmed" for t in targets) or none_text,
        },
    }
    metrics: dict[str, Any] = {
        "scenario": scn.to_dict(),
        # the key itself never goes into the outputs
        "config": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(cfg).items()
                   if k not in ("command_key", "scenario")},
        "operator": world.operator,
        "summary": _summary(targets, false, world.operator, goals),
        "success": success,
        "wall_seconds": round(wall, 1),
        "dive_seconds": scn.duration,
        "survey_end_s": round(world.survey_end - EPOCH, 1),
        "tdma_cycle_s": scn.cycle,
        "targets": targets,
        "false_confirmations": false,
        "decoys": [{"name": f"decoy {i + 1}", "kind": "rock", "x": t.x, "y": t.y,
                    "visited": any(c.planned and math.hypot(c.x - t.x, c.y - t.y) <= IDENTIFY_RADIUS
                                   for c in operator.candidates)}
                   for i, t in enumerate(world.rocks)],
        "candidates": candidates,
        "images_received": len(metas),
        "images_captured": len(world.camera_times),
        "link": link,
        "map_coverage": {str(k): v[-1][1] if v else 0.0 for k, v in coverage.items()},
        "bad_frames": {"topside": runners[TOPSIDE].node.stats.get("bad_frames", 0),
                       "vehicle": runners[VEHICLE].node.stats.get("bad_frames", 0)},
        "goals": goals,
    }
    charts = [
        line_chart({f"level {k} ({2**k} m)": v for k, v in sorted(coverage.items())},
                   title="Map filling in over time (fraction of the survey area held topside)",
                   xlabel="dive time (s)", ylabel="fraction",
                   markers=[(world.survey_end - EPOCH, "survey ends")] + [
                       (v - EPOCH, f"target {i + 1} identifiable at 1 m") for i, v in visible_at.items()]),
        line_chart({"capacity": link["capacity_series"], "used": link["used_series"],
                    "delivered": link["delivered_series"]},
                   title="Link use against capacity (cumulative bytes, vehicle to topside)",
                   xlabel="dive time (s)", ylabel="bytes"),
        timeline_chart([{"t": d.t, "kind": d.kind, "text": d.text} for d in decisions], t_end=scn.duration),
    ]
    for k in ("capacity_series", "used_series", "delivered_series"):
        link.pop(k, None)
    write_report(out, metrics, charts=charts, maps=map_svgs, images=images,
                 decisions=[asdict(d) for d in decisions])
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    with (out / "decisions.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["dive_time_s", "who", "kind", "text"])
        for d in decisions:
            w.writerow([d.t, d.who, d.kind, d.text])
    return metrics


def _obj(t: Target) -> dict[str, Any]:
    return {"x": t.x, "y": t.y, "length": t.length, "width": t.width, "height": t.height,
            "heading": round(t.heading, 1)}


def _crop(grid: np.ndarray, cell: float, x0: float, y0: float, xa: float, ya: float, xb: float, yb: float,
          ) -> tuple[np.ndarray, float, float]:
    """The part of a level grid (row 0 = south) inside [xa, xb] x [ya, yb]."""
    ny, nx = grid.shape
    c0 = max(math.floor((xa - x0) / cell), 0)
    c1 = min(math.ceil((xb - x0) / cell), nx)
    r0 = max(math.floor((ya - y0) / cell), 0)
    r1 = min(math.ceil((yb - y0) / cell), ny)
    if c1 <= c0 or r1 <= r0:
        return grid, x0, y0
    return grid[r0:r1, c0:c1], x0 + c0 * cell, y0 + r0 * cell


def _summary(targets: list[dict[str, Any]], false: list[dict[str, Any]], operator: str,
             goals: dict[str, dict[str, Any]]) -> str:
    """The outcome in words, from the judged metrics: the main goal first, then the others."""
    ok = [t for t in targets if t["confirmation"] is not None]
    missed = [t for t in targets if t["confirmation"] is None]
    main = bool(targets) and not missed and not false
    parts = [f"{'MET' if main else 'NOT MET'}: every true target confirmed by a received image that shows "
             "it, and nothing else confirmed."]
    if not targets:
        parts.append("This scenario has no targets.")
    elif not missed:
        parts.append(f"All {len(targets)} targets were confirmed.")
    else:
        parts.append(f"{len(ok)} of {len(targets)} targets were confirmed.")
    for t in ok:
        c = t["confirmation"]
        parts.append(f"{t['name'].capitalize()} at ({t['x']:.0f}, {t['y']:.0f}): image {c['image_id']}, "
                     f"{c['bytes']} B, confirmed at {c['confirmed_at_s']:.0f} s, {c['tdma_cycles']} TDMA cycles "
                     "after its request.")
    for t in missed:
        parts.append(f"{t['name'].capitalize()} at ({t['x']:.0f}, {t['y']:.0f}) was not confirmed: {t['why_not']}.")
    if false:
        parts.append(f"{len(false)} confirmation(s) of something that is not a target: "
                     + "; ".join(f"({f['x']:.0f}, {f['y']:.0f}) by image {f['image_id']}, which shows {f['shows']}"
                                 for f in false) + ".")
    elif targets:
        parts.append("Nothing that is not a target was confirmed.")
    others = [f"{name}: {'MET' if g['met'] else 'NOT MET'} ({g['detail']})" for name, g in goals.items()
              if not name.startswith("every target confirmed")]
    if others:
        parts.append("Other goals: " + "; ".join(others) + ".")
    if operator == "none":
        parts.append("No scripted operator ran (--operator none): only what a person did in the console counts.")
    return " ".join(parts)


def _link_summary(path: Path) -> dict[str, Any]:
    cap = used = delivered = 0
    cap_s: list[tuple[float, float]] = []
    used_s: list[tuple[float, float]] = []
    del_s: list[tuple[float, float]] = []
    sent = lost = frames = 0
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
            delivered += int(rec.get("delivered_bytes", rec.get("used_bytes") if n else 0) or 0)
            lost += int(rec.get("lost") or 0) if not isinstance(rec.get("lost"), list) else len(rec["lost"])
            frames += int(rec.get("frames") or 0)
            del_s.append((round(t, 1), delivered))
    return {"packets_sent": sent, "capacity_bytes": cap, "used_bytes": used, "delivered_bytes": delivered,
            "frames_lost": lost, "frame_loss": round(lost / frames, 4) if frames else None,
            "fill": round(used / cap, 4) if cap else None, "capacity_series": cap_s, "used_series": used_s,
            "delivered_series": del_s}


def iter_decisions(result: DemoResult) -> Iterator[str]:
    for d in result.decisions:
        yield f"{d.t:7.0f} s  {d.kind:<16} {d.text}"
