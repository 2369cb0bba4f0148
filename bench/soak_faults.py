"""Soak with faults: a day-long vehicle dive at time compression, with the field's faults injected.

The production pieces run as they do on a ship, in one process on one simulated clock:

* **Real:** the vehicle daemon (:class:`coex_apps.vehicle.daemon.VehicleApp`, built from a
  TOML configuration by :func:`coex_apps.vehicle.config.load`: its runner, SQLite store,
  inputs and autonomy handling, link health reports) and the topside console node
  (:func:`coex_apps.console.cli.topside_from_config`: runner, store, console state, HTTP
  server on a free loopback port; its products written to ``products/``: every image as TIFF
  and PNG by the imagery receiver's ``out_dir``, which keeps the newest :data:`TOPSIDE_IMAGES`
  in memory, and each series block older than :data:`SERIES_KEEP` appended to a CSV by the
  time-series receiver's ``keep`` and ``out_dir``); each modem link a
  :class:`~coex_transports.recovery.ResilientTransport` around the real Micromodem NMEA driver
  (:class:`~coex_transports.micromodem.MicromodemTransport`); the MAVLink mission upload of the
  ``mavlink`` autonomy output over UDP on loopback; the ``moos`` input reading navigation from a
  real MOOSDB (when there is one, found as ``tests/_moos.py`` finds it; without one that fault
  is left out, saying why, and the sensors give navigation instead); SQLite files on disk.
* **Simulated:** the two Micromodem-2s and the acoustic channel (rate 5, NUI TDMA of 6 x 20 s
  slots, 20 % frame loss; :class:`~coex_transports.micromodem.simulator.ModemNetwork`) and the
  clock (the daemons, the links' backoff and the autonomy read it; it jumps from event to event,
  so a day runs in minutes); the sensors (an input adapter polled by the daemon like any
  ``[[inputs]]`` entry: the 256 m site surveyed with a 96-beam multibeam again and again, a
  camera image every 5 minutes, two sensor channels at 1 Hz, as ``bench/soak.py``); the
  autopilot (pymavlink's side of the mission protocol, ``MissionPeer``, stepped on the
  simulated clock, flying one waypoint every 30 s); the operator (asks for the newest image in
  full every hour, and sends three surveys).

Faults (full run):

* the vehicle's modem stream **cut ten times** for 1-10 minutes (its serial cable pulled:
  :meth:`ModemNetwork.unplug`; the driver's port fails, the link reopens with backoff and fails
  while the cable is out);
* **topside killed** twice (abandoned as by ``kill -9``: no last snapshot, its port and HTTP
  socket released as the kernel would) and restarted a minute later from its store;
* the **autopilot silent for an hour** (its process gone: nothing answers on its port); a
  survey sent meanwhile must end REJECTED with reason AUTONOMY_NO_ANSWER;
* **MOOSDB restarted** (SIGKILL, then started again on the same port): navigation must resume.

Then a drain without faults or new data, until topside holds everything (or two hours). Checks
(``checks`` in the JSON): every fault planned was injected; every map cell, image (to its goal,
byte-exact, decoded) and time-series block (with the vehicle's error bound) that the vehicle
sent is held topside (``coex_plugins.convergence``, the fault suite's checks): an image counts
when topside held it byte-exact to its goal and its TIFF and PNG were written from at least the
goal's bytes (checked every 10 minutes while the vehicle keeps it, since both sides keep a
bounded number in memory), a series block when it is in topside's memory or its archive file; the surveys
ended as expected; the outages both ends counted (topside from ``LinkHealth``) equal the cuts;
navigation came back after each MOOSDB restart; RSS and both stores flat after the first hour
(slopes within :data:`FLAT`; judged on runs of four hours or more); the daemons' log records
within :data:`LOG_RECORDS_PER_HOUR`. Measured every simulated hour: the process's RSS, the two
store files (SQLite with its WAL), what the nodes hold; the log records the daemons emitted (by
logger); wall time. JSON in ``bench/results/soak_faults.json`` (``soak_faults-quick.json``); the
hourly samples so far in ``soak_faults.partial.json`` while it runs (left there by a run cut
short).

    python bench/soak_faults.py [--hours 24] [--quick] [--seed S] [--keep DIR]

``--quick`` runs 2 simulated hours of a lighter load (a 64 m site, 32 beams, 64 x 96 images) with
two cuts, one topside kill, 20 silent autopilot minutes and one MOOSDB restart. Exit status 1
when a check fails.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import random
import shutil
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

if str(Path(__file__).resolve().parent) not in sys.path:  # imported from elsewhere (the smoke test)
    sys.path.append(str(Path(__file__).resolve().parent))

from soak import camera_image, peak_mb, rss_mb, sensor_series, survey_passes

from coex_apps.console.cli import TopsideApp, topside_from_config
from coex_apps.vehicle.config import load
from coex_apps.vehicle.daemon import VehicleApp
from coex_core import state
from coex_core.acoustic import AcousticChannel
from coex_core.adapters import Image, Input, Item, Nav, Points, Samples
from coex_plugins import convergence
from coex_plugins.autonomy.mavpeer import MissionPeer
from coex_transports.micromodem.simulator import ModemNetwork, SimLoop
from coex_transports.recovery import ResilientTransport
from coex_transports.testing import free_port as _free_udp_port

ROOT = Path(__file__).resolve().parents[1]
VEHICLE, TOPSIDE = 2, 1
HOUR = 3600.0
KEY = "5eed" * 16
VEHICLE_URI = f"micromodem:///dev/coex-sim/modem{VEHICLE}?src={VEHICLE}&dest={TOPSIDE}&rate=5"
TOPSIDE_URI = f"micromodem:///dev/coex-sim/modem{TOPSIDE}?src={TOPSIDE}&dest={VEHICLE}&rate=5"
SITE = 256.0
#: the bench's own MOOS client (publishes navigation as the vehicle's navigation would)
NAV_CLIENT = "soak_nav"
#: what "flat after the first hour" means here: the least-squares slope of the hourly samples
#: from hour 1 to the end of the dive, at most (MB/h). Topside holds every sample of the day's
#: two series (what it is for), so its store may grow by that much.
FLAT = {"rss": 2.0, "vehicle_store": 0.25, "topside_store": 1.0}
#: log records from the daemons per simulated hour, at most (a state change is a line)
LOG_RECORDS_PER_HOUR = 20
#: topside's working state: the newest images in memory (``max_images``) and the newest
#: two hours of each series (``keep``); everything it received is written to the products
#: folder as it comes (images) or leaves memory (series)
TOPSIDE_IMAGES = 32
SERIES_KEEP = 7200.0


# ------------------------------------------------------------------------------ the plan
@dataclass
class Faults:
    """What goes wrong, in seconds from the start of the dive."""

    #: (start, length) of each cut of the vehicle's modem stream
    cuts: list[tuple[float, float]] = field(default_factory=list)
    #: (time, seconds down) of each topside kill -9 and restart
    kills: list[tuple[float, float]] = field(default_factory=list)
    #: (start, end) of the autopilot's silence
    silent: tuple[float, float] | None = None
    #: moments of a MOOSDB restart
    moos_restarts: list[float] = field(default_factory=list)
    #: (time, expected end state) of the operator's surveys
    surveys: list[tuple[float, str]] = field(default_factory=list)


def plan(hours: float, *, cuts: int, kills: int, silent: float, moos: int, seed: int) -> Faults:
    """Faults spread over the dive after its first hour (its first quarter, for a short dive) and
    before its last half hour: each cut (1-10 min) at a random moment of its own share of that
    span; kills and MOOSDB restarts at random moments of theirs; the silence in the middle.
    Surveys: 20 min before the silence, 10 min into it, 10 min after it."""
    rng = random.Random(seed)
    span = (min(HOUR, hours * HOUR / 4), hours * HOUR - min(HOUR / 2, hours * HOUR / 4))
    f = Faults()

    def moments(n: int, length: float = 0.0) -> list[float]:
        w = (span[1] - span[0]) / max(n, 1)
        return [span[0] + i * w + rng.uniform(0.0, max(w - length, 0.0)) for i in range(n)]

    lengths = [rng.uniform(60.0, 600.0) for _ in range(cuts)]
    f.cuts = [(t, d) for t, d in zip(moments(cuts, 600.0), lengths, strict=True)]
    f.kills = [(t, 60.0) for t in moments(kills)]
    f.moos_restarts = moments(moos)
    if silent > 0:
        middle = span[0] + 0.5 * (span[1] - span[0]) - silent / 2
        start = max(rng.uniform(middle - 600.0, middle + 600.0), span[0] + 1200.0)
        f.silent = (start, start + silent)
        f.surveys = [(start - 1200.0, "completed"), (start + min(600.0, silent / 2), "rejected"),
                     (start + silent + 600.0, "completed")]
    return f


# ------------------------------------------------------------------------------ sensors
class SimSensors(Input):
    """The simulated sensors, as an input adapter the daemon polls: multibeam passes over the site,
    a camera image every 5 minutes, two sensor channels sampled at 1 Hz (a minute per item),
    and navigation every 10 s when ``nav`` (no MOOSDB). Nothing after ``end``."""

    name = "soak-sensors"
    feeds = ("bathymetry", "imagery", "timeseries", "status")
    options: ClassVar[dict[str, tuple[Any, str]]] = {}
    #: images carry no position: the daemon stamps them with the newest navigation
    stamp_images = True

    def __init__(self, context: Any, *, start: float, end: float, seed: int, series: Sequence[Any],
                 nav: bool, site: float = SITE, beams: int = 96, image: tuple[int, int] = (120, 160)) -> None:
        super().__init__({}, context)
        self.passes, self.pass_seconds = survey_passes(seed, site, beams)
        self.image = image
        self.series = series
        self.end, self.nav = end, nav
        self._pass_start, self._ping = start + 10.0, 0
        self._next_photo, self._next_samples, self._next_nav = start + 60.0, start + 60.0, start
        self.photos = 0

    def poll(self, now: float) -> list[Item]:
        out: list[Item] = []
        now = min(now, self.end)
        while True:  # multibeam: pass after pass
            t, xyz = self.passes[self._ping]
            if self._pass_start + t > now:
                break
            out.append(Points(self._pass_start + t, xyz))
            self._ping += 1
            if self._ping == len(self.passes):
                self._ping, self._pass_start = 0, self._pass_start + self.pass_seconds
        while self._next_photo <= now:
            self.photos += 1
            out.append(Image(self._next_photo, camera_image(self.photos, self.image)))
            self._next_photo += 300.0
        while self._next_samples <= now:
            t1 = self._next_samples
            for s in self.series:
                sel = (s.times >= t1 - 60.0) & (s.times < t1)
                out.append(Samples(s.name, s.times[sel], s.values[sel]))
            self._next_samples += 60.0
        if self.nav and now >= self._next_nav:
            x, y = track(now)
            out.append(Nav(now, x=x, y=y, depth=480.0, altitude=20.0, heading=90.0, speed=1.5))
            self._next_nav = now + 10.0
        return out


def track(t: float) -> tuple[float, float]:
    """Where the vehicle is (a circle over the site, 20 min a turn)."""
    a = 2 * math.pi * (t % 1200.0) / 1200.0
    return round(SITE / 2 + 100.0 * math.cos(a), 2), round(SITE / 2 + 100.0 * math.sin(a), 2)


# ------------------------------------------------------------------------------ the log
class LogCount(logging.Handler):
    """Counts the log records of the daemons by logger (INFO and above) and keeps them in a file;
    the bench's own stand-ins (the autopilot peer, the navigation publisher) are counted apart."""

    def __init__(self, path: Path) -> None:
        super().__init__(logging.INFO)
        self.by_logger: Counter[str] = Counter()
        self.bench: Counter[str] = Counter()
        self.clock: Callable[[], float] = lambda: 0.0
        self.t0 = 0.0
        self.file = path.open("w")
        self.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        text = self.format(record)
        ours = record.name.endswith(".mavpeer") or NAV_CLIENT in record.getMessage()
        (self.bench if ours else self.by_logger)[record.name] += 1
        self.file.write(f"{(self.clock() - self.t0) / HOUR:8.3f} h {'(bench) ' if ours else ''}{text}\n")

    @property
    def total(self) -> int:
        return sum(self.by_logger.values())

    def close(self) -> None:
        self.file.close()
        super().close()


# ------------------------------------------------------------------------------ the soak
def _inline(d: dict[str, Any]) -> str:
    """A TOML inline table (strings and numbers)."""
    return "{ " + ", ".join(f"{k} = {json.dumps(v)}" for k, v in d.items()) + " }"


def _sizes(path: Path) -> float:
    """An SQLite store's bytes on disk, with its WAL and shared memory files (MB)."""
    return sum(p.stat().st_size for p in (path, Path(f"{path}-wal"), Path(f"{path}-shm")) if p.exists()) / 2**20


def _slope(hours: list[float], values: list[float]) -> float:
    return float(np.polyfit(hours, values, 1)[0]) if len(hours) >= 2 else 0.0


class Soak:
    """The vehicle and topside daemons over simulated modems, with the faults of ``faults`` (see
    the module docstring). :meth:`run` returns the measured figures and the checks."""

    def __init__(self, workdir: Path, hours: float, faults: Faults, *, seed: int = 1,
                 moosdb: str | None = None, drain: float = 2 * HOUR, light: bool = False,
                 progress: Callable[[str], Any] = print) -> None:
        self.dir = Path(workdir)
        #: ``light``: a 64 m site, 32 beams, 64 x 96 images (a smoke test's load)
        self.load: dict[str, Any] = dict(site=64.0, beams=32, image=(64, 96)) if light else {}
        self.hours, self.faults, self.seed, self.drain = hours, faults, seed, drain
        self.say = progress
        self.net = ModemNetwork({TOPSIDE: (300.0, 400.0, 0.0), VEHICLE: (0.0, 0.0, 500.0)},
                                channel=AcousticChannel(loss=0.2, seed=seed))
        self.t0 = self.net.now
        self.end = self.t0 + hours * HOUR
        self.loop = SimLoop(self.net, max_step=1.0)
        self.series = sensor_series(hours * HOUR, seed, self.t0)
        self.moos: Any = None
        self.moos_why = ""
        self.nav_pub: Any = None
        if moosdb is not None:
            from coex_transports.moos.testing import MoosDB

            self.moos = MoosDB(moosdb, community="coex_soak")
        self.mav_port = _free_udp_port()
        self.peer: MissionPeer | None = None
        self.topside: TopsideApp | None = None
        self.log = LogCount(self.dir / "daemons.log")
        #: topside's products folder (images as TIFF and PNG, the series' archive as CSV)
        self.products = self.dir / "products"
        self.samples: list[dict[str, Any]] = []
        self.delivered: set[int] = set()
        self.restarts = 0
        self._topside_written = self._topside_snapshots = self._topside_state = 0  # of the topside processes killed
        # snapshot bytes written, state bytes saved, snapshots (vehicle, topside) at the last sample
        self._written = self._state = self._count = (0, 0)
        self.cuts_done = 0
        self.silenced = self.autopilot_back = self.moos_restarted = 0
        self.surveys: list[tuple[int, str, float]] = []
        self.nav_changes: list[float] = []
        self._last_nav: float | None = None
        self.wall0 = time.perf_counter()
        #: where the hourly samples go as they are taken (None: nowhere)
        self.partial: Path | None = None

    # ------------------------------------------------------------------ set-up
    def _configs(self) -> None:
        (self.dir / "coex.key").write_text(KEY)
        channels = "[" + ", ".join(_inline(s.channel()) for s in self.series) + "]"
        modalities = """
[modalities.bathymetry]
stream = 3
priority = 40
BATHY
[modalities.imagery]
stream = 4
priority = 30
[modalities.timeseries]
stream = 5
priority = 20
OPTIONS
[modalities.survey]
stream = 7
priority = 90
SURVEY
"""
        common = """
[tdma]
slots = ["topside", "vehicle", "vehicle", "topside", "vehicle", "vehicle"]
slot_seconds = 20
guard = 2
"""
        moos = "" if self.moos is None else f"""
[[inputs]]
type = "moos"
server = "127.0.0.1:{self.moos.port}"
name = "pCoex_nav"
"""
        (self.dir / "vehicle.toml").write_text(f"""
[node]
role = "vehicle"
id = {VEHICLE}
peer = {TOPSIDE}
command_key_file = "coex.key"
store = "vehicle.sqlite"
[[modems]]
uri = "{VEHICLE_URI}"
[status]
interval = 10
[autonomy]
type = "mavlink"
connection = "udpout:127.0.0.1:{self.mav_port}"
{moos}""" + common + modalities.replace("BATHY", "options = { send_delay = 20.0 }").replace(
            "OPTIONS", f"options = {{ channels = {channels} }}").replace(
            "SURVEY", "options = { geofence = { radius = 500.0, min_altitude = 2.0 } }"))
        (self.dir / "topside.toml").write_text(f"""
[node]
role = "topside"
id = {TOPSIDE}
peer = {VEHICLE}
command_key_file = "coex.key"
store = "topside.sqlite"
[[modems]]
uri = "{TOPSIDE_URI}"
[console]
http = "127.0.0.1:0"
""" + common + modalities.replace("BATHY", "").replace(
            "stream = 4\n", f"stream = 4\noptions = {{ max_images = {TOPSIDE_IMAGES}, out_dir = "
            f"{json.dumps(str(self.products / 'images'))} }}\n").replace(
            "OPTIONS", f"options = {{ keep = {SERIES_KEEP}, out_dir = {json.dumps(str(self.products / 'series'))} }}"
        ).replace("SURVEY", ""))

    def _link(self, uri: str) -> ResilientTransport:
        """A modem link as the daemons make it, on the simulated modems and clock."""
        return ResilientTransport(uri, name="link 0", clock=lambda: self.net.now, sleep=self.net.run_for,
                                  opener=self.net.open_uri)

    def start(self) -> None:
        root = logging.getLogger()
        self._level = root.level
        root.addHandler(self.log)
        root.setLevel(logging.INFO)
        self.log.clock, self.log.t0 = (lambda: self.net.now), self.t0
        self._configs()
        if self.moos is not None:
            from coex_transports.moos import MoosClient

            self.moos.start()
            self.nav_pub = MoosClient("127.0.0.1", self.moos.port, NAV_CLIENT)
            self.nav_pub.connect(timeout=5.0)
            self.loop.every(5.0, self._publish_nav, start=self.t0)
        clock = lambda: self.net.now  # noqa: E731
        cfg = load(self.dir / "vehicle.toml", "vehicle")
        self.vehicle = VehicleApp(cfg, clock=clock, transports={0: self._link(VEHICLE_URI)})
        self.sensors = SimSensors(self.vehicle.context, start=self.t0, end=self.end, seed=self.seed,
                                  series=self.series, nav=self.moos is None, **self.load)
        self.vehicle.add_input(self.sensors, key="sensors (simulated)")
        self.vehicle.open()
        self.loop.runners.append(self.vehicle.runner)
        self._start_topside(self.t0)
        self.peer = MissionPeer(f"udpin:127.0.0.1:{self.mav_port}", fly_interval=30.0)
        self.loop.after.append(self._each_pass)
        f = self.faults
        for t, length in f.cuts:
            self.loop.at(self.t0 + t, self._cut)
            self.loop.at(self.t0 + t + length, self._plug)
        for t, down in f.kills:
            self.loop.at(self.t0 + t, lambda now, down=down: self._kill(now, down))
        if f.silent is not None:
            self.loop.at(self.t0 + f.silent[0], self._silence)
            self.loop.at(self.t0 + f.silent[1], self._autopilot_back)
        for t in f.moos_restarts:
            if self.moos is not None:
                self.loop.at(self.t0 + t, self._restart_moos)
        for t, expect in f.surveys:
            self.loop.at(self.t0 + t, lambda now, expect=expect: self._survey(now, expect))
        self.loop.every(HOUR, self._ask_full_image, start=self.t0 + HOUR / 2, until=self.end)
        self.loop.every(600.0, self._mark_images, start=self.t0 + 600.0)

    def _start_topside(self, now: float) -> None:
        self.topside = topside_from_config(str(self.dir / "topside.toml"), lambda: self.net.now,
                                           transports={0: self._link(TOPSIDE_URI)})
        self.loop.runners.append(self.topside.runner)

    # ------------------------------------------------------------------ the faults
    def _cut(self, now: float) -> None:
        self.cuts_done += 1
        self.net.unplug(VEHICLE)

    def _plug(self, now: float) -> None:
        self.net.plug(VEHICLE)

    def _kill(self, now: float, down: float) -> None:
        """Topside dies as by kill -9: no shutdown and no last snapshot; the kernel closes its
        serial port, its listening socket and its files."""
        app = self.topside
        assert app is not None
        self.loop.runners.remove(app.runner)
        app.server.close()
        for tr in app.transports.values():
            tr.close()
        if app.store is not None:
            self._topside_written += app.store.stats["snapshot_bytes"]
            self._topside_state += app.store.stats["state_bytes"]
            self._topside_snapshots += app.store.stats["snapshots"]
            app.store.close()  # closes the file (nothing written: no snapshot)
        self.topside = None
        self.restarts += 1
        self.loop.at(now + down, self._start_topside)

    def _silence(self, now: float) -> None:
        assert self.peer is not None
        self.peer.close()  # the autopilot's process is gone: nothing answers on its port
        self.peer = None
        self.silenced += 1

    def _autopilot_back(self, now: float) -> None:
        self.peer = MissionPeer(f"udpin:127.0.0.1:{self.mav_port}", fly_interval=30.0)
        self.autopilot_back += 1

    def _restart_moos(self, now: float) -> None:
        self.moos.restart()
        self.moos_restarted += 1

    # ------------------------------------------------------------------ the operator
    def _survey(self, now: float, expect: str) -> None:
        app = self.topside
        if app is None:  # topside is down: the operator tries again in a minute
            self.loop.at(now + 60.0, lambda t: self._survey(t, expect))
            return
        rx = app.node.receiver("survey")
        with app.hub.lock:
            cmd = rx.request("line", SITE / 2 - 60.0, SITE / 2 - 40.0, now, heading=90.0, length=120.0,
                             altitude=5.0)
        self.surveys.append((cmd.survey_id, expect, now))

    def _ask_full_image(self, now: float) -> None:
        app = self.topside
        if app is None:
            return
        rx = app.node.receiver("imagery")
        with app.hub.lock:
            if rx.images:
                rx.request_goal(max(rx.images), "full", now=now)

    def _publish_nav(self, now: float) -> None:
        if now > self.end:
            return
        x, y = track(now)
        for var, value in (("NAV_X", x), ("NAV_Y", y), ("NAV_DEPTH", 480.0), ("NAV_ALTITUDE", 20.0),
                           ("NAV_HEADING", 90.0), ("NAV_SPEED", 1.5)):
            self.nav_pub.notify(var, value, time=now)

    def _each_pass(self, now: float) -> None:
        if self.peer is not None:
            self.peer.step(now)
        if self.vehicle.nav_time != self._last_nav:
            self._last_nav = self.vehicle.nav_time
            self.nav_changes.append(now)

    # ------------------------------------------------------------------ measuring
    def _mark_images(self, now: float | None = None) -> None:
        """Images the vehicle keeps that topside holds to their goal and has written out (both
        keep a bounded number in memory: marked while both have them, every 10 minutes): byte-
        exact in topside's memory, and its TIFF and PNG in the products folder, written from at
        least the goal's bytes (the TIFF's description)."""
        tx = self.vehicle.node.sender("imagery")
        if self.topside is None:
            return
        rx = self.topside.node.receiver("imagery")
        for i, img in tx.images.items():
            if i not in self.delivered and convergence.image_held(img, rx.images.get(i)) \
                    and self._written_out(i, img.goal):
                self.delivered.add(i)

    def _written_out(self, image_id: int, goal: int) -> bool:
        base = self.products / "images" / f"image_{image_id:04d}"
        tiff, png = Path(f"{base}.tiff"), Path(f"{base}.png")
        if not (tiff.exists() and png.exists()):
            return False
        import tifffile

        with tifffile.TiffFile(tiff) as f:
            desc = f.pages[0].description or ""
        words = desc.split()
        return "bytes" in words and int(words[words.index("bytes") + 1]) >= goal

    def _sample(self, hour: float) -> dict[str, Any]:
        self._mark_images()
        tx = self.vehicle.node.sender("imagery")
        top = self.topside
        written = (self.vehicle.store.stats["snapshot_bytes"], self._topside_written
                   + (top.store.stats["snapshot_bytes"] if top is not None else 0))
        saved = (self.vehicle.store.stats["state_bytes"], self._topside_state
                 + (top.store.stats["state_bytes"] if top is not None else 0))
        count = (self.vehicle.store.stats["snapshots"], self._topside_snapshots
                 + (top.store.stats["snapshots"] if top is not None else 0))
        since = (self.samples[-1]["hour"] if self.samples else 0.0, hour)
        per_h = [(a - b) / 2**20 / max(since[1] - since[0], 1e-9) for a, b in zip(written, self._written, strict=True)]
        size = [(a - b) / 2**20 / max(n - m, 1) for a, b, n, m in zip(saved, self._state, count, self._count, strict=True)]
        self._written, self._state, self._count = written, saved, count
        s = {
            "hour": round(hour, 3),
            "rss_mb": round(rss_mb(), 1),
            "vehicle_store_mb": round(_sizes(self.dir / "vehicle.sqlite"), 2),
            "topside_store_mb": round(_sizes(self.dir / "topside.sqlite"), 2),
            "vehicle_snapshots_mb_per_h": round(per_h[0], 1),
            "topside_snapshots_mb_per_h": round(per_h[1], 1),
            "vehicle_snapshot_mb": round(size[0], 2),
            "topside_snapshot_mb": round(size[1], 2),
            "vehicle_imagery_state_mb": round(len(state.dumps(tx)) / 2**20, 2),
            "images_vehicle": len(tx.images),
            "images_topside": len(top.node.receiver("imagery").images) if top is not None else None,
            "image_files": len(list((self.products / "images").glob("image_*.tiff"))),
            "products_mb": round(sum(p.stat().st_size for p in self.products.rglob("*") if p.is_file()) / 2**20, 2),
            "images_taken": self.sensors.photos,
            "images_delivered": len(self.delivered),
            "log_records": self.log.total,
            "wall_s": round(time.perf_counter() - self.wall0, 1),
        }
        self.samples.append(s)
        if self.partial is not None:  # a run cut short still leaves its figures
            self.partial.write_text(json.dumps({"complete": False, "hours": self.hours, "seed": self.seed,
                                                "samples": self.samples}, indent=2))
        self.say(f"  hour {s['hour']:5.2f}: RSS {s['rss_mb']:6.1f} MB, stores {s['vehicle_store_mb']:6.2f} + "
                 f"{s['topside_store_mb']:6.2f} MB, products {s['products_mb']:.2f} MB (snapshots {s['vehicle_snapshot_mb']:.2f} + "
                 f"{s['topside_snapshot_mb']:.2f} MB, written {s['vehicle_snapshots_mb_per_h']:.0f} + "
                 f"{s['topside_snapshots_mb_per_h']:.0f} MB/h), images {s['images_delivered']}/{s['images_taken']} held "
                 f"topside ({s['images_vehicle']} kept on the vehicle), log {s['log_records']} records "
                 f"(wall {s['wall_s']:.0f} s)")
        return s

    def converged(self) -> dict[str, bool]:
        top = self.topside
        assert top is not None
        v, t = self.vehicle.node, top.node
        self._mark_images()
        taken = set(range(self.sensors.photos))  # the sender's ids: 0, 1, ...
        return {
            "map": convergence.map_converged(v.sender("bathymetry"), t.receiver("bathymetry")),
            "images": taken <= self.delivered,
            "series": convergence.series_complete(v.sender("timeseries"), t.receiver("timeseries"), self.series),
        }

    # ------------------------------------------------------------------ the run
    def run(self) -> dict[str, Any]:
        self.start()
        try:
            self._sample(0.0)
            h = 1
            while self.t0 + h * HOUR <= self.end + 1e-6:
                self.loop.run(self.t0 + h * HOUR)
                self._sample(float(h))
                h += 1
            self.loop.run(self.end)
            while True:  # the drain: no faults, no new data; checked every 5 minutes
                while self.topside is None:
                    self.loop.run(self.net.now + 60.0)
                ok = self.converged()
                if all(ok.values()) or self.net.now - self.end >= self.drain:
                    break
                self.loop.run(self.net.now + 300.0)
            drain = self.net.now - self.end
            if drain >= 1.0:
                self._sample((self.net.now - self.t0) / HOUR)
            return self._result(ok, drain)
        finally:
            self.close()

    def _result(self, ok: dict[str, bool], drain: float) -> dict[str, Any]:
        top = self.topside
        assert top is not None
        survey_rx = top.node.receiver("survey")
        surveys = []
        for sid, expect, at in self.surveys:
            rec = survey_rx.surveys.get(sid)
            state = None if rec is None else rec.state
            reason = None if rec is None else rec.reason
            want = "AUTONOMY_NO_ANSWER" if expect == "rejected" else None
            surveys.append({"survey": sid, "sent_h": round((at - self.t0) / HOUR, 3), "expected": expect,
                            "expected_reason": want, "state": state, "reason": reason,
                            "ok": state == expect and (want is None or reason == want)})
        vm = top.hub.state.links.get(0, {}).get("vehicle_modem") or {}
        dive = [s for s in self.samples if 1.0 <= s["hour"] <= self.hours]
        hours = [s["hour"] for s in dive]
        nav_gaps = np.diff(self.nav_changes) if len(self.nav_changes) > 1 else np.zeros(0)
        after_restart = [
            min((c - (self.t0 + r) for c in self.nav_changes if c > self.t0 + r), default=None)
            for r in self.faults.moos_restarts] if self.moos is not None else []
        health = self.vehicle.link_health()[0]
        res: dict[str, Any] = {
            "hours": self.hours,
            "seed": self.seed,
            "converged": ok,
            "drain_minutes": round(drain / 60.0, 1),
            "images_taken": self.sensors.photos,
            "images_held_topside": len(self.delivered),
            "images_missing": sorted(set(range(self.sensors.photos)) - self.delivered),
            "cuts": [{"start_h": round(t / HOUR, 3), "minutes": round(d / 60.0, 1)} for t, d in self.faults.cuts],
            "cuts_done": self.cuts_done,
            "vehicle_link": {"outages": health.outages, "down_minutes": round(health.down_total / 60.0, 1),
                             "reopen_attempts_last": health.attempts},
            "topside_heard": {"outages": vm.get("outages"), "down_minutes":
                              None if vm.get("down_total") is None else round(vm["down_total"] / 60.0, 1)},
            "topside_kills": [{"at_h": round(t / HOUR, 3), "down_s": d} for t, d in self.faults.kills],
            "topside_restarts": self.restarts,
            "autopilot_silent_h": None if self.faults.silent is None else
            [round(x / HOUR, 3) for x in self.faults.silent],
            "surveys": surveys,
            "moosdb": "restarted at " + ", ".join(f"{r / HOUR:.3f} h" for r in self.faults.moos_restarts)
            if self.moos is not None else f"not run: {self.moos_why}",
            "nav_updates": len(self.nav_changes),
            "nav_longest_gap_s": round(float(nav_gaps.max()), 1) if nav_gaps.size else None,
            "nav_back_after_restart_s": [None if a is None else round(a, 1) for a in after_restart],
            "rss_mb_hour1": dive[0]["rss_mb"] if dive else None,
            "rss_mb_end": self.samples[-1]["rss_mb"],
            "peak_rss_mb": round(max(peak_mb(), *(s["rss_mb"] for s in self.samples)), 1),
            "rss_slope_mb_per_h": round(_slope(hours, [s["rss_mb"] for s in dive]), 2),
            "vehicle_store_slope_mb_per_h": round(_slope(hours, [s["vehicle_store_mb"] for s in dive]), 3),
            "topside_store_slope_mb_per_h": round(_slope(hours, [s["topside_store_mb"] for s in dive]), 3),
            "log_records": self.log.total,
            "log_by_logger": dict(self.log.by_logger.most_common()),
            "bench_log_records": dict(self.log.bench),
            "vehicle_not_sent_frames": dict(self.vehicle.runner.not_sent),
            "vehicle_packets": self.vehicle.node.manager.stats["packets"],
            "wall_seconds": round(time.perf_counter() - self.wall0, 1),
            "samples": self.samples,
        }
        f = self.faults
        judged = len(hours) >= 3 and hours[-1] - hours[0] >= 3.0  # slopes over three hours at least
        flat = FLAT
        res["checks"] = {
            # every fault planned was injected
            "faults_injected": self.cuts_done == len(f.cuts) and self.restarts == len(f.kills)
            and self.silenced == self.autopilot_back == (f.silent is not None)
            and (self.moos is None or self.moos_restarted == len(f.moos_restarts)),
            "data_held_topside": all(ok.values()),
            "surveys_ended_as_expected": all(s["ok"] for s in surveys),
            "outages_counted_both_ends": res["topside_heard"]["outages"] == len(f.cuts) == health.outages,
            "navigation_back_after_moosdb_restart": None if self.moos is None
            else all(a is not None for a in after_restart),
            # flat after the first hour (None: too short a run to judge)
            "rss_flat": res["rss_slope_mb_per_h"] <= flat["rss"] if judged else None,
            "vehicle_store_flat": res["vehicle_store_slope_mb_per_h"] <= flat["vehicle_store"] if judged else None,
            "topside_store_flat": res["topside_store_slope_mb_per_h"] <= flat["topside_store"] if judged else None,
            "log_bounded": self.log.total <= LOG_RECORDS_PER_HOUR * max(self.hours, 1.0),
        }
        res["flat_limits_mb_per_h"] = dict(flat)
        res["faults_injected"] = {"cuts": self.cuts_done, "topside_kills": self.restarts,
                                  "autopilot_silenced": self.silenced, "autopilot_back": self.autopilot_back,
                                  "moosdb_restarts": self.moos_restarted}
        res["ok"] = all(v is not False for v in res["checks"].values())
        return res

    def close(self) -> None:
        for part in (self.topside, self.vehicle if hasattr(self, "vehicle") else None):
            if part is not None:
                try:
                    part.close()
                except Exception as exc:  # report, and close the rest
                    self.say(f"closing {type(part).__name__}: {exc}")
        if self.peer is not None:
            self.peer.close()
        if self.nav_pub is not None:
            self.nav_pub.close()
        if self.moos is not None:
            self.moos.close()
        logging.getLogger().removeHandler(self.log)
        logging.getLogger().setLevel(getattr(self, "_level", logging.WARNING))
        self.log.close()


def report(r: dict[str, Any]) -> list[str]:
    """The figures, in lines."""
    c = r["converged"]
    lines = [
        f"held topside after a {r['drain_minutes']} min drain: map {'yes' if c['map'] else 'NO'}, images "
        f"{r['images_held_topside']}/{r['images_taken']}{' (missing ' + str(r['images_missing']) + ')' if r['images_missing'] else ''}, "
        f"series {'yes' if c['series'] else 'NO'}",
        f"modem cuts: {len(r['cuts'])} injected ({', '.join(str(x['minutes']) for x in r['cuts'])} min); the vehicle "
        f"counted {r['vehicle_link']['outages']} outages ({r['vehicle_link']['down_minutes']} min down), topside "
        f"heard of {r['topside_heard']['outages']} ({r['topside_heard']['down_minutes']} min)",
        f"topside killed and restarted {r['topside_restarts']} times",
        "surveys: " + "; ".join(f"#{s['survey']} at {s['sent_h']} h: {s['state']}"
                                + (f" {s['reason']}" if s['reason'] else "")
                                + ("" if s["ok"] else f" (expected {s['expected']}"
                                   + (f" {s['expected_reason']})" if s["expected_reason"] else ")"))
                                for s in r["surveys"]),
        f"MOOSDB: {r['moosdb']}; navigation updates {r['nav_updates']}, longest gap {r['nav_longest_gap_s']} s, "
        f"back {r['nav_back_after_restart_s']} s after each restart",
        f"RSS {r['rss_mb_hour1']} MB at hour 1, {r['rss_mb_end']} MB at the end, peak {r['peak_rss_mb']} MB; "
        f"slope after hour 1: RSS {r['rss_slope_mb_per_h']} MB/h, stores {r['vehicle_store_slope_mb_per_h']} "
        f"(vehicle) and {r['topside_store_slope_mb_per_h']} (topside) MB/h",
        f"log: {r['log_records']} records from the daemons "
        + ", ".join(f"{k} {v}" for k, v in r["log_by_logger"].items()),
        "checks: " + ", ".join(f"{k} {'-' if v is None else 'yes' if v else 'NO'}" for k, v in r["checks"].items()),
        f"wall {r['wall_seconds']} s; {'ALL CHECKS PASSED' if r['ok'] else 'A CHECK FAILED'}",
    ]
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--hours", type=float, default=24.0)
    p.add_argument("--quick", action="store_true", help="2 simulated hours of a lighter load, fewer faults")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--keep", metavar="DIR", help="work in DIR and keep it (stores, configurations, the log)")
    args = p.parse_args(argv)
    hours = 2.0 if args.quick else args.hours
    if args.quick:
        faults = plan(hours, cuts=2, kills=1, silent=1200.0, moos=1, seed=args.seed)
    else:
        faults = plan(hours, cuts=10, kills=2, silent=HOUR, moos=1, seed=args.seed)
    from coex_transports.moos.testing import find_moosdb

    exe, why = find_moosdb()
    if exe is None:
        print(f"MOOSDB fault left out: {why}")
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="coex-soak-faults-"))
    work.mkdir(parents=True, exist_ok=True)
    print(f"soak with faults: {hours:g} simulated hours in {work}; cuts at "
          + ", ".join(f"{t / HOUR:.2f} h ({d / 60:.1f} min)" for t, d in faults.cuts)
          + "; topside killed at " + ", ".join(f"{t / HOUR:.2f} h" for t, _ in faults.kills)
          + ("" if faults.silent is None else
             f"; autopilot silent {faults.silent[0] / HOUR:.2f}-{faults.silent[1] / HOUR:.2f} h")
          + ("" if exe is None else "; MOOSDB restarted at " + ", ".join(f"{t / HOUR:.2f} h" for t in faults.moos_restarts)),
          flush=True)
    soak = Soak(work, hours, faults, seed=args.seed, moosdb=exe, light=args.quick,
                progress=lambda t: print(t, flush=True))
    soak.moos_why = why
    out = ROOT / "bench" / "results"
    out.mkdir(parents=True, exist_ok=True)
    name = "soak_faults-quick.json" if args.quick else "soak_faults.json"
    soak.partial = out / name.replace(".json", ".partial.json")
    try:
        r = soak.run()
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    r["date"] = time.strftime("%Y-%m-%d")
    r["command"] = "python bench/soak_faults.py" + (" --quick" if args.quick else f" --hours {hours:g}") + \
        (f" --seed {args.seed}" if args.seed != 1 else "")
    for line in report(r):
        print(line)
    (out / name).write_text(json.dumps(r, indent=2))
    soak.partial.unlink(missing_ok=True)
    return 0 if r["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
