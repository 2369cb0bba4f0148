"""The dive's run: the simulated world, both nodes, their Micromodems and the operator on one
simulated clock."""

from __future__ import annotations

import contextlib
import functools
import json
import math
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from coex import AcousticChannel, Node, ProductUpdated, Received, Rejected, Runner, SimulatedClock
from coex.messages import VehicleStatus
from coex_core.loopback import SimClock
from coex_plugins.bathymetry.sim import Seafloor, Survey, simulate_survey
from coex_plugins.imagery import ImageInput
from coex_plugins.timeseries import synth as ts_synth
from coex_transports.micromodem.simulator import ModemNetwork, SimLoop

from .autonomy import Autonomy
from .camera import CameraModel, SandTexture, render_labelled
from .config import (
    CAMERA,
    CAMERA_PERIOD,
    CAMERA_SPEED,
    EPOCH,
    HOLD_ALTITUDE,
    LINK_STREAM,
    TOPSIDE,
    VEHICLE,
    Decision,
    DemoConfig,
    DemoResult,
)
from .failures import failure_counts, identify_radius
from .navigation import DiveNavigation
from .operator import MIN_SCORE, Operator
from .outcome import World, finish, vehicle_summary
from .timing import ResponseTimer
from .truth import FrameTruth, frame_truth
from .world import (
    Leg,
    SurveyedCells,
    Track,
    area_fraction,
    build_fleet,
    build_nodes,
    dive_schedule,
    image_files,
    load_image,
    rng_for,
    schedule_series,
    vehicle_status,
)


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


def _start_gui(cfg: DemoConfig, topside: Node, vehicle: Node, log: Callable[..., None]) -> Any:
    from coex_apps.console import serve
    from coex_apps.console.cli import console_access
    from coex_apps.console.hub import ConsoleHub

    host, _, port = cfg.http.rpartition(":")
    host = host or "127.0.0.1"
    # the same rule as coex topside: beyond loopback only with sign-in (or --insecure-open)
    access, _ = console_access(host, cfg.operators, cfg.insecure_open, None, None)
    server = serve(topside, host, int(port), access=access,
                   stream_names={s.id: s.config.name for s in vehicle.manager.streams})  # the vehicle's queues
    hub = server.hub
    assert isinstance(hub, ConsoleHub)  # one node's console, not a fleet's
    act = hub.act

    def logged(action: str, args: dict[str, Any], operator: str = "") -> list[Any]:
        """What a person does in the console goes into the decision list too (with their name
        when they signed in)."""
        now = hub.clock()
        by = f"{operator}: " if operator else ""
        try:
            sent = act(action, args, operator) if operator else act(action, args)
        except Exception as exc:
            log(now, "console action", f"{by}{action} {json.dumps(args, default=str)} refused: {exc}", "person")
            raise
        log(now, "console action", f"{by}{action} {json.dumps(args, default=str)}", "person")
        return sent

    hub.act = logged  # type: ignore[method-assign]  # the console has no action hook yet (issue 53, console)
    print(f"coex demo: web console at {server.url} (the dive runs at {cfg.speed:g}x)", file=sys.stderr)
    return server


class DiveRun:
    """One dive: the world (seafloor, objects, survey, track), the link (two simulated
    Micromodems on one acoustic channel, each node's real driver talking NMEA to its modem), the
    two nodes, the operator, the vehicle's autonomy (it flies the survey commands that crossed
    the link), and the timed events (sensor data, status, the operator's rounds, the camera) on
    one simulated clock. :meth:`run` runs it and writes the
    outputs (:mod:`coex_apps.demo.outcome`)."""

    def __init__(self, config: DemoConfig, on_decision: Callable[[Decision], None] | None = None) -> None:
        #: everything the dive holds open (the link log, the pseudo-terminals, the console's
        #: server): released when the dive ends, however it ends (:meth:`close`)
        self.resources = contextlib.ExitStack()
        try:
            self._setup(config, on_decision)
        except BaseException:
            self.resources.close()
            raise

    def close(self) -> None:
        """Release everything the dive holds open (idempotent)."""
        self.resources.close()

    def _setup(self, config: DemoConfig, on_decision: Callable[[Decision], None] | None) -> None:
        self.cfg = cfg = config
        self.scn, self.operator_mode = scn, operator_mode = config.resolved()
        self.on_decision = on_decision
        self.out = out = Path(cfg.out)
        (out / "images").mkdir(parents=True, exist_ok=True)
        (out / "map").mkdir(exist_ok=True)
        self.wall0 = time.perf_counter()
        self.decisions: list[Decision] = []
        self._build_world()
        self._build_link()
        #: issue 56: dead reckoning that drifts, the ship's USBL, topside's estimate (docs/navigation.md)
        self.navsim = DiveNavigation(self)
        self.resources.callback(self.navsim.close)  # the USBL's UDP socket and input
        # the camera pass: the operator's survey commands cross the link, the vehicle's autonomy
        # flies them (with --operator none, its own transect through the centre of the site)
        self.half = 30.0 if not cfg.quick else 15.0
        self.reserve = 2 * scn.cycle  # the last frames need time to come up before the dive ends
        mid = scn.area / 2
        # in a fleet dive this is the camera vehicle's autonomy (on its own track); the mapper's
        # only holds once its survey is over (it is never sent a survey command)
        self.autonomy = Autonomy(self.senders["survey"], self.camera_track, self.at, self.end,
                                 camera_altitude=scn.camera_altitude, camera_speed=CAMERA_SPEED,
                                 mission=None if operator_mode == "script" else
                                 ((mid, mid - self.half), (mid, mid + self.half)),
                                 nav=self.navsim.model(self.navsim.camera_vehicle))
        self.mapper_autonomy = None if self.fleet is None else Autonomy(
            self.fleet.mapper_senders["survey"], self.track, self.at, self.end,
            camera_altitude=scn.camera_altitude, camera_speed=CAMERA_SPEED, nav=self.navsim.model(VEHICLE))
        # what the camera saw, for the referee alone (frames showing an object)
        self.frames: dict[float, FrameTruth] = {}
        floor = self.floor
        # the operator sees what topside received (through topside's navigation) and nothing of
        # the truth: one rule set for every dive, one vehicle or a fleet
        self.operator = Operator(self.topside, self.navsim.views(self.receivers),
                                 (floor.x0, floor.y0, floor.x0 + floor.size, floor.y0 + floor.size),
                                 self.log, camera_altitude=scn.camera_altitude,
                                 cycle=scn.cycle, active=operator_mode == "script")
        self.operator.epoch = EPOCH
        self.received_track: list[tuple[float, float]] = []
        #: the camera vehicle's positions as topside received them (a fleet dive)
        self.received_camera_track: list[tuple[float, float]] = []
        #: the map's completeness per level over time: the site's surveyed cells, in the frame the
        #: vehicle placed them, that topside's received level holds (issue 54: ``map_coverage``)
        self.coverage: dict[int, list[tuple[float, float]]] = {}
        #: the true site's cells that topside's corrected map holds (``map_coverage_corrected``:
        #: completeness and the correction's placement at the site's edges together)
        self.coverage_corrected: dict[int, list[tuple[float, float]]] = {}
        self.visible_at: dict[int, float] = {}
        # timed events (simulated): sensor data, status, operator, camera
        self._schedule()

    # ------------------------------------------------------------------------ set-up
    def log(self, now: float, kind: str, text: str, who: str = "script") -> None:
        d = Decision(round(now - EPOCH, 1), kind, text, who)
        self.decisions.append(d)
        if self.on_decision is not None:
            self.on_decision(d)

    def at(self, t: float, fn: Callable[[float], None]) -> None:
        self.loop.at(t, fn)

    def _build_world(self) -> None:
        """Cars (the targets) and boulders (decoys) where the operator does not know, the
        seafloor, the camera and the survey."""
        cfg, scn = self.cfg, self.scn
        self.cars, self.rocks = scn.place(cfg.seed)
        self.floor = Seafloor(size=scn.area, depth=scn.water_depth, relief=scn.relief,
                              ripple_amplitude=scn.ripple_amplitude, targets=self.cars + self.rocks,
                              seed=cfg.seed)
        self.texture: Callable[[np.ndarray, np.ndarray], np.ndarray] = SandTexture(seed=cfg.seed)
        if cfg.images is not None:  # the sand built from real frames (docs/demo.md)
            from .seabed import RealSandTexture, sand_frames

            self.texture = RealSandTexture([load_image(f) for f in sand_frames(image_files(cfg.images))], seed=cfg.seed)
        self.camera = CameraModel()
        self.track = Track(self.floor)
        #: the track the camera flies: the vehicle's, or in a fleet dive the camera vehicle's own
        #: (it descends at the centre of the site and holds there until sent somewhere)
        self.camera_track = Track(self.floor) if scn.fleet else self.track
        self.descent = 300.0 if not cfg.quick else 120.0
        self.survey: Survey = simulate_survey(
            self.floor, altitude=scn.survey_altitude, line_spacing=scn.line_spacing or None,
            speed=scn.survey_speed, ping_rate=2.0, beams=256, t0=EPOCH + self.descent,
            turn_time=60.0 if not cfg.quick else 20.0, seed=cfg.seed + 1)
        self.survey_end = float(self.survey.times[-1]) if len(self.survey) else EPOCH + self.descent
        self.end = EPOCH + scn.duration

    def _build_link(self) -> None:
        """Two simulated Micromodems on one acoustic channel; each node's driver talks NMEA to
        its modem through a real pseudo-terminal pair; a runner per node."""
        cfg, scn, out = self.cfg, self.scn, self.out
        self.clock = clock = SimClock(EPOCH)
        self.channel = AcousticChannel(loss=scn.loss.independent(), burst=scn.loss.burst(),
                                       range_loss=scn.loss.range_loss(), seed=cfg.seed)
        self.net = net = ModemNetwork({TOPSIDE: (scn.ship[0], scn.ship[1], 0.0), VEHICLE: (0.0, 0.0, 0.0)},
                                      channel=self.channel, clock=clock, ptys=True)
        self.resources.callback(net.close)  # the pseudo-terminals (the nodes open their modems on it)
        self.series = ts_synth.dataset(duration=max(scn.duration, 1200.0), period=1.0, seed=cfg.seed,
                                       t0=EPOCH)
        self.fleet = None
        if scn.fleet:
            # issue 43: three nodes on one network; topside's modem broadcasts (dest 0,
            # docs/micromodem.md), each frame header names the vehicle it is for
            net.add_modem(CAMERA, (scn.area / 2, scn.area / 2, 0.0))
            self.fleet = fleet = build_fleet(out, [s.channel() for s in self.series], cfg.command_key, scn,
                                             network=net, auto_fill=self.operator_mode != "script",
                                             geofence=cfg.geofence)
            self.vehicle, self.topside, self.receivers = fleet.mapper, fleet.topside, fleet.receivers
            self.senders = {**fleet.mapper_senders, **fleet.camera_senders}  # the survey: the camera's
            nodes, modems = {VEHICLE: fleet.mapper, TOPSIDE: fleet.topside, CAMERA: fleet.camera}, fleet.modems
        else:
            self.vehicle, self.topside, self.senders, self.receivers, modems = build_nodes(
                out, [s.channel() for s in self.series], cfg.command_key, scn, network=net,
                auto_fill=self.operator_mode != "script", geofence=cfg.geofence)
            nodes = {VEHICLE: self.vehicle, TOPSIDE: self.topside}
        self.link_log = self.resources.enter_context((out / "link.jsonl").open("w"))
        self.runners = {node_id: Runner(nodes[node_id], {0: modems[node_id]}, SimulatedClock(sim=clock),
                                        link_log=self.link_log) for node_id in (VEHICLE, TOPSIDE, CAMERA)
                        if node_id in nodes}
        self.vehicle_modem = self.runners[VEHICLE].transports[0]
        #: the dive's one loop: the modems, the timed events, the runners (then :meth:`_after_runners`; :meth:`_heard` at the end of each pass)
        self.loop = SimLoop(net, list(self.runners.values()))
        self.loop.after.append(self._after_runners)
        self.loop.settled.append(self._heard)
        self.timer = ResponseTimer(self.topside, dive_schedule(scn), VEHICLE, EPOCH)

    def _schedule(self) -> None:
        scn, track = self.scn, self.track
        survey, off = self.survey, 0
        self.surveyed = SurveyedCells(self.floor, float(self.senders["bathymetry"].config["resolution"]))
        for t, xyz in survey.pings(batch=20):
            track.add_sample(float(t), float(np.mean(xyz[:, 0])), float(np.mean(xyz[:, 1])),
                             scn.survey_altitude)
            rows = slice(off, off + len(xyz))
            off += len(xyz)
            def ingest(now: float, xyz: np.ndarray = xyz, rows: slice = rows) -> None:
                placed = self.navsim.soundings(xyz, survey.ping[rows], survey.times[rows])
                # the referee: where the vehicle put the site's valid soundings (not the wild ones)
                self.surveyed.add(xyz, placed, ~survey.outlier[rows])
                self.senders["bathymetry"].ingest(placed, now)

            self.at(float(t), ingest)
        track.samples.sort()
        track.legs.append(Leg(EPOCH, EPOCH + self.descent, (0.0, 0.0), (0.0, 0.0), scn.survey_altitude))
        schedule_series(self.at, self.senders["timeseries"], self.series, EPOCH, self.end)
        t = EPOCH
        while t < self.end:
            self.at(t, self.push_status)
            t += 10.0
        t = EPOCH + scn.cycle / 2
        while t < self.end:
            self.at(t, self.every_half_cycle)
            t += scn.cycle / 2
        # the survey over, the vehicle's autonomy takes over (it holds until told otherwise). The
        # operator decides the camera pass 30 s before that at the latest, at the start of a
        # topside slot, so that its survey commands reach the vehicle as its survey ends (it queues
        # them until then); then at every topside slot for the candidates found meanwhile, while
        # camera time remains
        if self.fleet is None:
            self.camera_start = self.survey_end
            self.at(self.survey_end, self.start_autonomy)
            self.at(self.survey_end + 30.0, self.camera_phase)
            rounds = self.topside_slots(self.survey_end + 30.0 - scn.cycle, self.end - self.reserve)
            first = max((t for t in rounds if t <= self.survey_end + 30.0), default=self.survey_end + 30.0)
        else:
            # a fleet: the camera vehicle descends at the centre of the site while the mapper
            # starts its survey, then holds; the operator sends it to candidates from then on, at
            # every topside slot, while the mapper keeps mapping (it holds when its survey ends)
            self.camera_start = EPOCH + self.descent
            mid = (scn.area / 2, scn.area / 2)
            self.camera_track.legs.append(Leg(EPOCH, self.camera_start, mid, mid, HOLD_ALTITUDE))
            self.at(self.camera_start, self.start_autonomy)
            self.at(self.survey_end, self.start_mapper_autonomy)
            self.at(self.survey_end + 30.0, self.camera_phase)  # the map's end-of-survey requests
            rounds = self.topside_slots(self.camera_start, self.end - self.reserve)
            first = rounds[0] if rounds else self.camera_start
        for t in [first] + [t for t in rounds if t > first]:
            self.at(t, functools.partial(self.camera_round, first=t == first))
        self._shot = iter(range(10**9))
        self.taken: list[float] = []
        #: every message a node refused, by name (``metrics.json`` ``failures.rejections``)
        self.rejections: list[dict[str, Any]] = []
        self.hfov = math.tan(math.radians(self.camera.hfov_deg) / 2)
        t = self.camera_start + CAMERA_PERIOD
        while t < self.end:
            self.at(t, self.take_picture)
            t += CAMERA_PERIOD

    # ------------------------------------------------------------------------ events
    def push_status(self, now: float) -> None:
        status = vehicle_status(self.track, now)
        self.channel.set_position(VEHICLE, (status.x, status.y, status.depth or 0.0))  # range loss
        self.vehicle.push_status(self.navsim.status(VEHICLE, status, now), now)  # where it believes it is
        if self.fleet is not None:
            status = vehicle_status(self.camera_track, now)
            self.channel.set_position(CAMERA, (status.x, status.y, status.depth or 0.0))
            self.fleet.camera.push_status(self.navsim.status(CAMERA, status, now), now)

    def push_link_status(self, now: float) -> None:
        status = self.vehicle_modem.link_status()
        if status is not None:
            self.vehicle.manager.push(LINK_STREAM, status, now)

    def every_half_cycle(self, now: float) -> None:
        operator = self.operator
        views = operator.measured(now)
        operator.watch_map(now, views)
        operator.watch_images(now)
        self.push_link_status(now)
        raw = self.receivers["bathymetry"]  # what topside received, in the vehicle's frame
        for level in range(0, 4):
            stamp = round(now - EPOCH, 1)
            p = raw.level_product(level) if raw.geometry(level) is not None else None
            frac = 0.0 if p is None or p.data is None else self.surveyed.fraction(
                np.asarray(p.data, dtype=float), float(p.cell_size), (float(p.x0), float(p.y0)))
            self.coverage.setdefault(level, []).append((stamp, round(frac, 4)))
            g = operator.level_grid(level)
            frac = 0.0 if g is None else area_fraction(g[0], g[1], g[2], self.floor)
            self.coverage_corrected.setdefault(level, []).append((stamp, round(frac, 4)))
        # judged against the truth: a target-like bump of the received 1 m map where a target is
        for i, tgt in enumerate(self.cars):
            if i not in self.visible_at and any(v.score >= MIN_SCORE and math.hypot(v.x - tgt.x, v.y - tgt.y)
                                                <= identify_radius(tgt) for v in views):
                self.visible_at[i] = now

    def topside_slots(self, t0: float, t1: float) -> list[float]:
        """Start times of topside's TDMA slots in ``[t0, t1)``."""
        scn = self.scn
        mine = [i * scn.slot_seconds for i, owner in enumerate(scn.slots) if owner == "topside"]
        k = math.floor((t0 - EPOCH) / scn.cycle)
        out = []
        while EPOCH + k * scn.cycle < t1:
            out += [t for t in (EPOCH + k * scn.cycle + o for o in mine) if t0 <= t < t1]
            k += 1
        return out

    def camera_phase(self, now: float) -> None:
        """The survey is over (and its last data had time to come up): the operator turns to the
        camera pass (fewer map requests, the overview maps)."""
        self.operator.camera_phase = True

    def start_mapper_autonomy(self, now: float) -> None:
        """A fleet dive: the mapper's survey is over; it holds (nobody sends it anywhere)."""
        if self.mapper_autonomy is not None:
            self.mapper_autonomy.start(now)

    def start_autonomy(self, now: float) -> None:
        self.autonomy.start(now)
        if self.autonomy.mission is not None:
            self.log(now, "camera pass", "no operator script: the vehicle makes its own camera transect "
                     "through the centre of the site", "system")

    def camera_round(self, now: float, first: bool = False) -> None:
        """The operator's camera-pass round: survey commands for the candidates not yet sent."""
        self.operator.camera_round(now, end=self.end, reserve=self.reserve, half=self.half, first=first,
                                   free_at=self.camera_start)

    def take_picture(self, now: float) -> None:
        track, camera, cars, rocks = self.camera_track, self.camera, self.cars, self.rocks
        if not any(leg.camera and leg.t0 <= now <= leg.t1 for leg in track.legs):
            return  # the camera runs on the transects only
        x, y, depth, alt, heading = track.position(now)
        k = next(self._shot)
        self.taken.append(now)
        rendered, labels = render_labelled(self.floor.ground, x, y, -depth, heading, targets=cars,
                                           rocks=rocks, texture=self.texture, camera=camera,
                                           rng=rng_for(self.cfg.seed, 100 + k))
        img = rendered
        if self.cfg.zero_labels:  # the check that nobody but the referee reads them (docs/demo.md)
            labels = np.zeros_like(labels)
        areas, pixel = {}, {}
        for i, o in enumerate(cars + rocks, 1):
            rounded = o.shape in ("dome", "mound")
            areas[i] = o.length * o.width * (math.pi / 4 if rounded else 1.0)
            # the renderer draws an object's top over its footprint: a pixel covers the seafloor's
            pixel[i] = (2 * max(alt, 0.3) * self.hfov / camera.width) ** 2
        ft = frame_truth(now, x, y, heading, img, labels, len(cars), areas, pixel)
        if ft is not None:
            self.frames[now] = ft
        bx, by = self.navsim.believed(self.navsim.camera_vehicle, now, x, y)  # where the vehicle believes it took it
        self.senders["imagery"].ingest(ImageInput(img, time=now, x=round(bx, 1), y=round(by, 1)), now)

    # ------------------------------------------------------------------------ the loop
    def run(self) -> DemoResult:
        """Run the dive to its end on the simulated clock, then judge it and write the outputs.
        Whatever happens, everything the dive held open is released."""
        with self.resources:
            return self._run()

    def _run(self) -> DemoResult:
        cfg, clock, net, end = self.cfg, self.clock, self.net, self.end
        server = _start_gui(cfg, self.topside, self.vehicle, self.log) if cfg.gui else None
        if server is not None:
            self.resources.callback(server.close)
        if server is not None and self.navsim.active:  # the console shows and applies topside's navigation
            server.hub.state.navigation = self.navsim.navigation
        lock = server.hub.lock if server is not None else contextlib.nullcontext()
        progress = _Progress(self.scn.duration, cfg.progress)
        loop = self.loop
        if server is not None:  # pace the dive so that a person at the console can act
            loop.max_step, loop.speed, loop.lock = 1.0, cfg.speed, lock
        loop.settled.append(lambda now: progress.update(now - EPOCH))
        loop.run(end)
        progress.close()
        self.link_log.close()
        ptys = net.pty_paths()
        if server is not None:  # the console stops saying "live"
            server.hub.update(lambda st: st.end_contact(clock.now, "the dive is over"))
        if server is not None and cfg.linger:
            _stop_on_interrupt()
            print(f"coex demo: the dive is over; the console stays at {server.url} (Ctrl+C to stop)",
                  file=sys.stderr)
            try:
                while True:
                    time.sleep(3600)
            except KeyboardInterrupt:
                pass
        return self._outputs(ptys)

    def _after_runners(self, now: float) -> None:
        """After the runners, each pass of the loop: the autonomies."""
        self.navsim.vehicle_aids(now)  # a position fix arrived: the vehicle's navigation takes it when due
        self.autonomy.check(now)  # a survey command arrived: the vehicle flies it
        if self.mapper_autonomy is not None:
            self.mapper_autonomy.check(now)

    def _heard(self, now: float) -> None:
        """At the end of each pass of the loop: what topside heard, the channel's log."""
        clock = self.clock
        camera = CAMERA if self.fleet is not None else VEHICLE
        for ev in self.topside.events():
            if isinstance(ev, Rejected):
                self._rejected(TOPSIDE, ev)
            elif isinstance(ev, Received) and isinstance(ev.message, VehicleStatus):
                status = self.navsim.heard_status(ev.src, ev.message, clock.now)  # corrected
                if ev.src == camera:  # the operator follows the vehicle with the camera
                    self.operator.on_status(status, clock.now)
                if ev.src == VEHICLE:
                    self.received_track.append((status.x, status.y))
                else:
                    self.received_camera_track.append((status.x, status.y))
            elif isinstance(ev, ProductUpdated) and ev.modality == "survey":
                self.operator.on_survey(dict(ev.product.meta), clock.now)
        self.navsim.topside_aids(clock.now)  # topside aids the vehicle's navigation when it is time
        for ev in self.vehicle.events():
            if isinstance(ev, Rejected):
                self._rejected(VEHICLE, ev)
        if self.fleet is not None:
            for ev in self.fleet.camera.events():
                if isinstance(ev, Rejected):
                    self._rejected(CAMERA, ev)
        for rec in self.channel.log():  # what arrived, per packet and receiver: delivered or lost frames
            self.link_log.write(json.dumps(rec, sort_keys=True, separators=(",", ":")) + "\n")

    def _rejected(self, node: int, ev: Rejected) -> None:
        """A message a node refused: kept with its reason for the metrics (the count alone does
        not say what to look at)."""
        self.rejections.append({"node": node, "time_s": round(ev.time - EPOCH, 1),
                                "message": type(ev.message).__name__, "reason": ev.reason})

    def _outputs(self, ptys: dict[int, str]) -> DemoResult:
        cfg, scn, out = self.cfg, self.scn, self.out
        wall = time.perf_counter() - self.wall0
        surveys = self.autonomy.summary()
        if self.fleet is None:
            vehicles = [vehicle_summary(VEHICLE, "vehicle (multibeam and camera)", self.runners[VEHICLE],
                                        out / "link.jsonl", surveys=surveys, images_captured=len(self.taken),
                                        received_positions=len(self.received_track))]
        else:
            assert self.mapper_autonomy is not None
            vehicles = [vehicle_summary(VEHICLE, "mapping AUV (multibeam)", self.runners[VEHICLE], out / "link.jsonl",
                                        surveys=self.mapper_autonomy.summary(), images_captured=0,
                                        received_positions=len(self.received_track)),
                        vehicle_summary(CAMERA, "camera vehicle", self.runners[CAMERA], out / "link.jsonl",
                                        surveys=surveys, images_captured=len(self.taken),
                                        received_positions=len(self.received_camera_track))]
        world = World(scn, self.floor, self.cars, self.rocks, self.survey_end, self.frames,
                      self.received_track, self.taken, self.operator_mode, self.autonomy.camera_legs(),
                      surveys, vehicles)
        navigation = self.navsim.metrics(self.cars, self.operator.candidates, self.autonomy.camera_legs(), self.end)
        metrics = finish(out, cfg, world, self.operator, self.navsim.views(self.receivers), self.coverage,
                         self.visible_at, self.decisions, wall, self.runners, self.timer.summary(),
                         navigation=navigation)
        metrics["map_coverage_corrected"] = {str(k): v[-1][1] if v else 0.0
                                             for k, v in self.coverage_corrected.items()}
        self.navsim.close()
        metrics["modems"] = {"nmea_over": {str(k): v for k, v in ptys.items()}, "rate": scn.modem_rate,
                             "tdma": f"{len(scn.slots)} x {scn.slot_seconds:g} s, guard {scn.guard_seconds:g} s; "
                                     f"topside slots {', '.join(str(i) for i, s in enumerate(scn.slots) if s == 'topside')}; "
                                     f"vehicle slots {', '.join(str(i) for i, s in enumerate(scn.slots) if s == 'vehicle')}"
                                     + (f"; camera vehicle slots {', '.join(str(i) for i, s in enumerate(scn.slots) if s == 'camera')}"
                                        if scn.fleet else "")}
        metrics["authentication"] = {
            "enabled": cfg.command_key is not None,
            "signed_frames": self.topside.manager.stats["signed"],
            "rejected_frames": self.vehicle.stats["unauthenticated"],
        }
        metrics["failures"] = {**failure_counts(self.runners), "rejections": self.rejections}
        (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
        return DemoResult(out, metrics, self.decisions)


def _stop_on_interrupt() -> None:
    """Ctrl+C (SIGINT) and SIGTERM end the lingering console, even when the process was started
    with SIGINT ignored (a background job of a non-interactive shell inherits that)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return

    def stop(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, stop)


def run_demo(config: DemoConfig, *, on_decision: Callable[[Decision], None] | None = None) -> DemoResult:
    """Run one demo dive (:class:`DiveRun`) and write its outputs to ``config.out``."""
    from coex_plugins.imagery.codec import set_threads

    threads = config.codec_threads
    set_threads(min(os.cpu_count() or 1, 4) if threads is None else threads)
    return DiveRun(config, on_decision).run()
