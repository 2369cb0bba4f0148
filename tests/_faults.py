"""Fault injection for the fault suite: a simulated acoustic channel that also duplicates,
reorders, bit-flips and truncates frames, failing modality wrappers, and a short dive with all
three modalities between a vehicle and a topside node (fixed seeds), and a store's SQLite
connection that refuses statements as a full or failing disk does."""

from __future__ import annotations

import dataclasses
import random
import sqlite3
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from coex import Runner, SimNetwork, SimulatedClock
from coex_core.acoustic import AcousticChannel, Arrival
from coex_core.channel import ChannelManager, LinkConfig, Schedule, StreamConfig
from coex_core.messages import Message
from coex_core.modality import ModalityReceiver, ModalitySender, Product
from coex_core.node import Node
from coex_plugins import convergence
from coex_plugins.bathymetry import BathymetryModality, BathymetryReceiver, BathymetrySender
from coex_plugins.imagery import ImageInput, ImageryModality, ImageryReceiver, ImagerySender
from coex_plugins.imagery.synth import seafloor
from coex_plugins.timeseries import TimeSeriesModality, TimeSeriesReceiver, TimeSeriesSender
from coex_plugins.timeseries import synth as ts_synth

from ._bathy_data import small_survey

TOPSIDE, VEHICLE = 1, 2
T0 = 1000.0


class FaultyChannel(AcousticChannel):
    """An :class:`AcousticChannel` whose arrivals are also tampered with: each received frame is
    duplicated (``dup``), bit-flipped (``flip``, one random bit) or truncated (``truncate``)
    with the given probabilities, and a packet is held back and delivered after the next one
    (``reorder``). ``counts`` says what was done."""

    def __init__(self, *, dup: float = 0.0, reorder: float = 0.0, flip: float = 0.0,
                 truncate: float = 0.0, fault_seed: int = 0, **kw: Any) -> None:
        super().__init__(**kw)
        self.dup, self.reorder, self.flip, self.truncate = dup, reorder, flip, truncate
        self._rng = random.Random(fault_seed)
        self._held: list[Arrival] = []
        self.counts = {"dup": 0, "reorder": 0, "flip": 0, "truncate": 0}

    def _tamper(self, frame: bytes) -> list[bytes]:
        rng = self._rng
        out = frame
        if out and rng.random() < self.flip:
            bit = rng.randrange(len(out) * 8)
            out = out[:bit // 8] + bytes([out[bit // 8] ^ (1 << (bit % 8))]) + out[bit // 8 + 1:]
            self.counts["flip"] += 1
        if len(out) > 1 and rng.random() < self.truncate:
            out = out[:rng.randrange(1, len(out))]
            self.counts["truncate"] += 1
        if rng.random() < self.dup:
            self.counts["dup"] += 1
            return [out, out]
        return [out]

    def poll(self, now: float) -> list[Arrival]:
        got = super().poll(now)
        out: list[Arrival] = []
        for a in got:
            frames: list[bytes | None] = []
            for f in a.frames:
                frames.extend([None] if f is None else self._tamper(f))
            a = dataclasses.replace(a, frames=frames)
            if self._rng.random() < self.reorder:
                self._held.append(a)  # overtaken by the next packet
                self.counts["reorder"] += 1
                continue
            out.append(a)
            out.extend(self._held)
            self._held.clear()
        return out


class _Every:
    """Counts calls; every ``every``-th one is told to fail."""

    every: int
    calls: int
    raised: int

    def _boom(self) -> bool:
        self.calls += 1
        if self.calls % self.every == 0:
            self.raised += 1
            return True
        return False


class FailingSender(_Every, ModalitySender):
    """A sender that raises on every ``every``-th call of ``fill`` and ``handle`` (and of
    ``ingest`` with ``fail_ingest``) and otherwise defers to ``inner``."""

    def __init__(self, inner: ModalitySender, every: int = 3, fail_ingest: bool = False) -> None:
        self.inner, self.every, self.calls, self.raised = inner, every, 0, 0
        self.fail_ingest = fail_ingest

    def ingest(self, data: Any, now: float) -> None:
        if self.fail_ingest and self._boom():
            raise RuntimeError("sensor driver crashed")
        self.inner.ingest(data, now)

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        if self._boom():
            raise RuntimeError("fill crashed")
        return self.inner.fill(max_bytes, now)

    def handle(self, message: Message, now: float) -> list[Message]:
        if self._boom():
            raise RuntimeError("handle crashed")
        return self.inner.handle(message, now)


class FailingReceiver(_Every, ModalityReceiver):
    """A receiver whose every ``every``-th ``receive`` raises after ``inner`` took the message
    (a bug in building a product), and whose ``poll`` raises every ``every``-th call."""

    def __init__(self, inner: ModalityReceiver, every: int = 5) -> None:
        self.inner, self.every, self.calls, self.raised = inner, every, 0, 0

    def receive(self, message: Message, now: float) -> list[Product]:
        out = self.inner.receive(message, now)
        if self._boom():
            raise ValueError("receiver bug")
        return out

    def poll(self, now: float) -> list[Message]:
        if self._boom():
            raise ValueError("receiver poll bug")
        return self.inner.poll(now)

    def products(self) -> list[Product]:
        return self.inner.products()


@dataclass
class Dive:
    """A vehicle (bathymetry survey, four camera images, two sensor channels) and topside, with
    the operator asking for image 1 in full; built by :func:`build_dive`."""

    vehicle: Node
    topside: Node
    bathy: BathymetrySender
    images: ImagerySender
    series: TimeSeriesSender
    map_rx: BathymetryReceiver
    image_rx: ImageryReceiver
    series_rx: TimeSeriesReceiver
    inputs: list[tuple[float, Callable[[float], None]]] = field(default_factory=list)
    series_data: list[Any] = field(default_factory=list)
    #: the vehicle's sensor data: (time, modality name, data for its sender's ingest)
    feed: list[tuple[float, str, Any]] = field(default_factory=list)
    end_of_data: float = 0.0


def schedule() -> Schedule:
    # fast TDMA: 4 s slots (one rate-5 packet each), topside 1 of 4
    return Schedule.simple([TOPSIDE, VEHICLE, VEHICLE, VEHICLE], 4.0, 0.5, epoch=0.0)


def sensor_feed(survey: Any, series_data: list[Any], minutes: int = 15) -> list[tuple[float, str, Any]]:
    """The vehicle's inputs in time order: multibeam pings (batches of 20), four camera
    images, sensor samples every minute."""
    feed: list[tuple[float, str, Any]] = []
    times = np.asarray(survey.times, dtype=float)
    shift = T0 - float(times[0])
    for t, xyz in survey.pings(batch=20):
        feed.append((float(t) + shift, "bathymetry", xyz))
    for i in range(4):
        t = T0 + 30.0 + 60.0 * i
        feed.append((t, "imagery", ImageInput(seafloor(64, 96, seed=20 + i), time=t, x=float(i), y=0.0)))
    for k in range(0, 60 * minutes, 60):
        feed.append((T0 + k + 60.0, "timeseries", {
            s.name: (s.times[(s.times >= T0 + k) & (s.times < T0 + k + 60)],
                     s.values[(s.times >= T0 + k) & (s.times < T0 + k + 60)]) for s in series_data}))
    feed.sort(key=lambda f: f[0])
    return feed


def build_dive(*, wrap_sender: Callable[[ModalitySender], ModalitySender] | None = None,
               wrap_receiver: Callable[[ModalityReceiver], ModalityReceiver] | None = None,
               crc: bool = False, minutes: int = 15, packet_seconds: float | None = None,
               ack_timeout: float | None = None) -> Dive:
    """``crc``: the CoEx frame CRC on (needed where the link itself does not check frames);
    ``minutes`` of sensor data; ``packet_seconds``: the time a packet takes (default: a rate-5
    packet's airtime; less for a link without airtime such as LCM); ``ack_timeout``: when an
    unacked frame's messages (and unacked image bytes) may go again (default: one TDMA cycle;
    10 s for images)."""
    sched = schedule()
    vehicle = Node(ChannelManager(VEHICLE, [LinkConfig(0, sched, rate=5, dst=TOPSIDE, crc=crc,
                                                       packet_seconds=packet_seconds,
                                                       ack_timeout=ack_timeout)]))
    topside = Node(ChannelManager(TOPSIDE, [LinkConfig(0, sched, rate=5, dst=VEHICLE, crc=crc,
                                                       packet_seconds=packet_seconds,
                                                       ack_timeout=ack_timeout)]))
    _, survey = small_survey(64.0, 200)
    bathy = BathymetryModality().sender({"levels": 3, "send_delay": 5.0})
    images = ImageryModality().sender({"layer_bytes": [40, 80, 160, 320, 640, 1200], "default_goal": "layer:2",
                                       "rto": ack_timeout or 10.0, "progress_interval": 60.0})
    series_data = ts_synth.dataset(duration=60.0 * minutes, period=2.0, seed=3, t0=T0)
    series = TimeSeriesModality().sender({"channels": [s.channel() for s in series_data]})
    map_rx = BathymetryModality().receiver({"levels": 3})
    image_rx = ImageryModality().receiver({"retry": 10.0, "max_tries": 1000})
    series_rx = TimeSeriesModality().receiver(None)
    wrap = wrap_sender or (lambda s: s)
    # the vehicle's inputs go through the (maybe failing) senders the node uses
    w_bathy, w_images, w_series = wrap(bathy), wrap(images), wrap(series)
    vehicle.add_sender(BathymetryModality, w_bathy, StreamConfig(3, "map", priority=40, ack_required=True))
    vehicle.add_sender(ImageryModality, w_images, StreamConfig(4, "images", priority=30))
    vehicle.add_sender(TimeSeriesModality, w_series, StreamConfig(5, "series", priority=20))
    wrap_rx = wrap_receiver or (lambda r: r)
    topside.add_receiver(BathymetryModality, wrap_rx(map_rx))
    topside.add_receiver(ImageryModality, wrap_rx(image_rx))
    topside.add_receiver(TimeSeriesModality, wrap_rx(series_rx))
    dive = Dive(vehicle, topside, bathy, images, series, map_rx, image_rx, series_rx,
                series_data=series_data)
    dive.feed = sensor_feed(survey, series_data, minutes)
    for t, name, data in dive.feed:
        dive.inputs.append((t, lambda now, name=name, data=data: vehicle.sender(name).ingest(data, now)))
    dive.inputs.append((T0 + 200.0, lambda now: image_rx.request_goal(1, "full", now=now)))
    dive.end_of_data = max(t for t, _ in dive.inputs)
    return dive


def run_sim(dive: Dive, channel: AcousticChannel, until: float) -> SimNetwork:
    """The dive over a simulated channel (SimNetwork); inputs ingested at their times. An input
    that raises (a failing sensor driver) is counted in ``net.input_errors``."""
    net = SimNetwork({0: channel}, SimulatedClock(start=T0))
    net.add_node(dive.vehicle, (0.0, 0.0, 500.0))
    net.add_node(dive.topside, (100.0, 0.0, 0.0))
    errors: list[str] = []

    def guarded(fn: Callable[[float], None]) -> Callable[[float], None]:
        def call(now: float) -> None:
            try:
                fn(now)
            except Exception as exc:  # the vehicle's input loop survives a failing driver
                errors.append(str(exc))
        return call

    for t, fn in dive.inputs:
        net.at(t, guarded(fn))
    net.run(until)
    net.input_errors = errors  # type: ignore[attr-defined]
    return net


def run_modems(dive: Dive, until: float, reboots: list[float], loss: float = 0.1, seed: int = 1) -> Any:
    """The dive through the Micromodem simulator (NMEA drivers), the vehicle's modem rebooted
    at each time of ``reboots``."""
    from coex_core.loopback import SimClock
    from coex_transports.micromodem.simulator import ModemNetwork, SimLoop

    clock = SimClock(T0)
    net = ModemNetwork({TOPSIDE: (100.0, 0.0, 0.0), VEHICLE: (0.0, 0.0, 500.0)},
                       channel=AcousticChannel(loss=loss, seed=seed), clock=clock)
    runners = [Runner(dive.vehicle, {0: net.transport(VEHICLE, rate=5, dest=TOPSIDE)}, SimulatedClock(sim=clock)),
               Runner(dive.topside, {0: net.transport(TOPSIDE, rate=5, dest=VEHICLE)}, SimulatedClock(sim=clock))]
    loop = SimLoop(net, runners, max_step=1.0)
    for t, fn in dive.inputs:
        loop.at(t, fn)
    for t in reboots:
        loop.at(t, lambda now: net.modems[VEHICLE].reboot(now))
    loop.run(until)
    return net, runners


# ------------------------------------------------------------------------------ checks
# (the checks themselves are coex_plugins.convergence's, shared with the soak benchmark)


def map_converged(dive: Dive) -> bool:
    """Every level of the topside map equals the vehicle's map (to the 0.1 m quantisation)."""
    return convergence.map_converged(dive.bathy, dive.map_rx)


def images_complete(dive: Dive) -> bool:
    """Every image reached its goal topside (image 1: in full), decoded."""
    s = dive.images
    if len(s.images) < 4 or s.images[1].goal != s.images[1].total:
        return False
    return not convergence.images_missing(s, dive.image_rx)


def series_complete(dive: Dive) -> bool:
    """Topside holds every block the vehicle closed, of every channel, with the vehicle's error
    bound, and every reconstructed value is within its bound of the true sample."""
    return convergence.series_complete(dive.series, dive.series_rx, dive.series_data)


# ------------------------------------------------------------------ a failing disk under a store
def sqlite_full() -> sqlite3.Error:
    """The error SQLite raises when the disk is full."""
    err = sqlite3.OperationalError("database or disk is full")
    err.sqlite_errorcode = 13  # type: ignore[attr-defined]
    err.sqlite_errorname = "SQLITE_FULL"  # type: ignore[attr-defined]
    return err


def sqlite_ioerr() -> sqlite3.Error:
    """The error SQLite raises on a failing device."""
    err = sqlite3.OperationalError("disk I/O error")
    err.sqlite_errorcode = 10  # type: ignore[attr-defined]
    err.sqlite_errorname = "SQLITE_IOERR"  # type: ignore[attr-defined]
    return err


class FaultyDb:
    """A store's SQLite connection on a failing disk, counting the statements it runs (the
    store's write points, in order, in ``sql``). Two faults, either or both:

    - ``fail_at``: the ``fail_at``-th statement raises ``error`` (as SQLite does when the disk
      fills or fails mid-transaction: the statement fails, the transaction may stay open);
    - ``full``: while true, every write is refused with SQLITE_FULL; reads (SELECT, PRAGMA,
      ROLLBACK) go through. Set it false to give the disk room again."""

    def __init__(self, real: sqlite3.Connection, fail_at: int | None = None,
                 error: sqlite3.Error | None = None, *, full: bool = False) -> None:
        self.real, self.fail_at, self.full = real, fail_at, full
        self.error = error if error is not None else sqlite_full()
        self.n, self.failed = 0, False
        self.sql: list[str] = []

    def _tick(self, sql: str) -> None:
        self.n += 1
        self.sql.append(" ".join(sql.split()))
        if self.full and not sql.lstrip().upper().startswith(("SELECT", "PRAGMA", "ROLLBACK")):
            raise sqlite_full()
        if self.n == self.fail_at:
            self.failed = True
            raise self.error

    def execute(self, sql: str, *args: Any) -> Any:
        self._tick(sql)
        return self.real.execute(sql, *args)

    def executemany(self, sql: str, *args: Any) -> Any:
        self._tick(sql)
        return self.real.executemany(sql, *args)

    @property
    def in_transaction(self) -> bool:
        return self.real.in_transaction

    def close(self) -> None:
        self.real.close()
