"""``coex vehicle --config vehicle.toml``: the vehicle node as a program.

One loop (the public :class:`coex.Runner` on the wall clock) drives the node over its modems;
after every step it polls the inputs (:mod:`.inputs`) and feeds what they read to the modality
senders through the runner (journaled in the store first, so a restart loses nothing), merges
navigation into the vehicle status it sends, hands the survey the vehicle should fly now to the
autonomy output (:mod:`.autonomy`) and feeds the autonomy's reports back to the survey sender.
A bad input item is logged and skipped; an input or autonomy that fails is logged and retried,
never a crash of the subsea process. SIGTERM (or Ctrl-C) shuts down cleanly: inputs and autonomy
closed, the node saved, the store closed; the next start resumes from the store.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from coex import CoexError, ConfigError, Nav, StoreError
from coex_plugins.options import LogOnce

from .build import build_node, link_configs
from .config import DeployConfig
from .faults import FAULT_PEER_SILENT, FAULT_STORE

__all__ = ["FAULT_PEER_SILENT", "FAULT_STORE", "VehicleApp", "build_node", "build_vehicle_node", "link_configs",
           "open_transports"]

log = logging.getLogger("coex.vehicle")

#: image files already taken (a watched directory read again after a restart), at most
TAKEN_MAX = 20000
#: the store's ``meta`` key of an image file taken: this, then "<path>|<time>"; set in the
#: transaction that journals the image, so a restart never takes a file twice
TAKEN_PREFIX = "vehicle.taken:"
#: images and autonomy reports held while the store cannot journal them (taken once it can)
HELD_MAX = 64


def open_transports(cfg: DeployConfig) -> dict[int, Any]:
    """One :class:`~coex_transports.recovery.ResilientTransport` per modem (link 0, 1, ...): a
    modem that goes away, or is not there at start, is reopened with backoff while the node runs
    on (``required = true`` makes one missing at start an error)."""
    from coex import ResilientTransport

    out: dict[int, Any] = {}
    try:
        for i, m in enumerate(cfg.modems):
            out[i] = ResilientTransport(m.uri, name=f"link {i}", required=m.required)
    except BaseException:
        for tr in out.values():
            tr.close()
        raise
    return out


def build_vehicle_node(cfg: DeployConfig, transports: Mapping[int, Any]) -> Any:
    """The vehicle node the configuration describes: ``build_node(cfg, "vehicle", transports)``
    (:mod:`.build`): its links, one sender per modality on its stream and priority (with the
    file's options and id remapping)."""
    return build_node(cfg, "vehicle", transports)


def _load(group: str, name: str) -> Any:
    from coex.registry import load

    return load(group, name)


class VehicleApp:
    """The vehicle daemon (see the module docstring). ``clock`` is the wall clock (tests may
    give another). ``transports`` (link id -> an open transport, one per ``[[modems]]`` entry)
    replaces the modems the configuration would open: a simulation's, a test's; the app closes
    them."""

    def __init__(self, cfg: DeployConfig, *, clock: Callable[[], float] = time.time,
                 transports: Mapping[int, Any] | None = None) -> None:
        from coex import InputContext, RealClock, Runner

        self.cfg = cfg
        self.clock = clock
        self.stop = threading.Event()
        #: the thread :meth:`start` runs the loop in (None: not started)
        self._thread: threading.Thread | None = None
        self.transports = dict(transports) if transports is not None else open_transports(cfg)
        self.store: Any = None
        self.inputs: list[Any] = []
        self.autonomy: Any = None
        try:
            if cfg.store is not None:
                from coex import NodeStore

                self.store = NodeStore(cfg.store, snapshot_interval=cfg.snapshot_interval)
                resumed = self.store.has_state()
                self.node = self.store.restore(lambda: build_vehicle_node(cfg, self.transports),
                                               log=lambda t: log.info("%s", t))
                if sorted(self.node.manager.links) != sorted(self.transports):
                    raise ConfigError(f"{cfg.store} holds a node with links {sorted(self.node.manager.links)}; "
                                      f"this configuration has {sorted(self.transports)}: give the same "
                                      "modems, or another node.store")
                if self.node.node_id != cfg.node_id:
                    raise ConfigError(f"{cfg.store} holds node {self.node.node_id}, not {cfg.node_id}")
                self.resumed = resumed
                if resumed:
                    log.info("resumed from %s (%d journal rows replayed)", cfg.store, self.store.stats["replayed"])
            else:
                self.node = build_vehicle_node(cfg, self.transports)
                self.resumed = False
            self.node.set_log(lambda t: log.info("%s", t))
            self.context = InputContext(cfg.origin_lat, cfg.origin_lon, str(cfg.base_dir), clock)
            self.runner = Runner(self.node, self.transports, RealClock(clock), store=self.store,
                                 after_step=[self._after_step], on_error=lambda t: log.warning("%s", t))
            for i, t in enumerate(cfg.inputs):
                cls = _load("coex.inputs", t["type"])
                opts = {k: v for k, v in t.items() if k not in ("type", "feeds")}
                self.add_input(cls(opts, self.context), t.get("feeds"), f"inputs[{i}] ({t['type']})")
            a = dict(cfg.autonomy)
            if a:
                self.autonomy = _load("coex.autonomy", a.pop("type"))(a, self.context)
        except BaseException:
            self._close_io()
            raise
        self.names = {m.name for m in cfg.modalities}
        #: the newest navigation, merged from every input that gives some
        self.nav: dict[str, float] = {}
        self.nav_time: float | None = None
        #: whether an input gives navigation (else a simulated autonomy's position stands in)
        self._nav_real = False
        self._last_status: float | None = None
        self._taken: list[str] = self._taken_files()
        self._taken_set = set(self._taken)
        #: while the store cannot journal: images (input, item) and autonomy reports held,
        #: taken once it can; streamed data not kept, counted by kind
        self._held: list[tuple[Any, Any]] = []
        self._not_kept: dict[str, int] = {}
        #: a small value to set in the store once it takes writes again
        self._unsaved: dict[str, str] = {}
        self._store_down = False
        #: hearing nothing from topside for ``SILENT_CYCLES`` TDMA cycles (logged, and a fault
        #: bit of the status topside gets)
        from coex_runtime.peers import PeerWatch

        self.peer_watch = PeerWatch(self.node.manager, [cfg.peer])
        self._peer_silent = False
        #: the survey lifecycle between the survey sender and the autonomy output (None: no
        #: autonomy, or no survey modality)
        self.lifecycle: Any = None
        if self.autonomy is not None and "survey" in self.names:
            from coex_plugins.autonomy.lifecycle import SurveyLifecycle

            store = self.store
            self.lifecycle = SurveyLifecycle(
                self.autonomy, self.node.sender("survey"), name=str(cfg.autonomy.get("type")),
                get=None if store is None else store.get, put=None if store is None else self._keep)
        self._broken: dict[str, float] = {}
        self._problem = LogOnce(log)
        #: what was taken; ``skipped``: the autonomy's reports not taken (an input's skipped items
        #: are counted by the input, ``Input.counts["skipped"]``: :meth:`summary` adds them up)
        self.counts: dict[str, int] = {"points": 0, "images": 0, "samples": 0, "nav": 0, "skipped": 0,
                                       "plans": 0, "reports": 0, "aids": 0}
        #: per link: (up, outages) last reported topside in a LinkHealth
        self._health_sent: dict[int, tuple[bool, int]] = {}

    def add_input(self, inp: Any, feeds: Any = None, key: str | None = None) -> Any:
        """Poll ``inp`` (an :class:`coex.Input`) like the ``[[inputs]]`` of the
        configuration: one made in code (a simulated sensor). ``feeds`` defaults to the input's
        own; ``key`` names it in the log. Open it yourself if the app is open already."""
        inp.coex_feeds = tuple(feeds if feeds is not None else type(inp).feeds)
        inp.coex_key = key or f"inputs[{len(self.inputs)}] ({inp.name})"
        self.inputs.append(inp)
        return inp

    # ------------------------------------------------------------------------ lifecycle
    def open(self) -> VehicleApp:
        for inp in self.inputs:
            self._guard(inp.coex_key, inp.open)
        if self.autonomy is not None:
            self._guard("autonomy", self.autonomy.open)
        return self

    def run(self) -> None:
        self.runner.run(stop=self.stop.is_set)

    def start(self) -> VehicleApp:
        self.open()
        self._thread = threading.Thread(target=self.run, name="coex-vehicle", daemon=True)
        self._thread.start()
        return self

    def _close_io(self) -> None:
        for inp in self.inputs:
            self._guard("close input", inp.close)
        if self.autonomy is not None:
            self._guard("close autonomy", self.autonomy.close)
        for tr in self.transports.values():
            self._guard("close transport", tr.close)

    def close(self) -> None:
        """Stop the loop, close inputs, autonomy and modems, save the node and close the store."""
        self.stop.set()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=10.0)
        self._close_io()
        if self.store is not None:
            try:
                self.store.snapshot(self.node, self.clock())
            except CoexError as exc:  # a full disk: said, never a traceback
                log.warning("last snapshot not saved: %s", exc)
            finally:
                self.store.close()
                self.store = None

    def _guard(self, what: str, fn: Callable[..., Any], *args: Any) -> Any:
        try:
            return fn(*args)
        except Exception as exc:  # an input or autonomy that fails never stops the vehicle
            now = self.clock()
            if now - self._broken.get(what, -1e18) > 60.0:
                log.warning("%s failed: %s: %s", what, type(exc).__name__, exc)
                self._broken[what] = now
            return None

    # ------------------------------------------------------------------------ the loop
    def _after_step(self, now: float) -> None:
        for inp in self.inputs:
            items = self._guard(inp.coex_key, inp.poll, now) or []
            for item in items:
                self._take(inp, item, now)
        self._store_state()
        for change in self.peer_watch.check(now):
            (log.warning if change.silent else log.info)("%s", change.text("topside"))
        self._peer_silent = self.peer_watch.any_silent()
        self._status(now)
        self._link_health(now)
        self._autonomy(now)

    def _keep(self, key: str, value: str) -> None:
        """A small value into the store now, or once it takes writes again."""
        try:
            self.store.set(key, value)
            self._unsaved.pop(key, None)
        except CoexError:
            self._unsaved[key] = value

    def faults(self) -> int:
        """The ``VehicleStatus.faults`` bits the daemon sets now: :data:`FAULT_STORE` while its
        store cannot keep anything new, :data:`FAULT_PEER_SILENT` while it hears nothing from
        topside (docs/deploy.md, "Faults shown topside")."""
        return (FAULT_STORE if self.runner.store_problem is not None else 0) | \
            (FAULT_PEER_SILENT if self._peer_silent else 0)

    def _store_state(self) -> None:
        """While the store cannot journal (a full disk): say once what is held and what is not
        kept; once it can again, take what was held and say what was not kept."""
        if self.store is None:
            return
        down = self.runner.store_problem is not None or self.store.problem is not None
        if down and not self._store_down:
            log.warning("store cannot keep anything new: link and commands run on; images wait in "
                        "their folder and survey reports are held (up to %d) until it writes again; "
                        "soundings and series samples taken meanwhile are not kept", HELD_MAX)
        self._store_down = down
        if down or not (self._held or self._unsaved or self._not_kept):
            return
        if not (self._held or self._not_kept):  # a small value to write again, nothing to say
            for key, value in list(self._unsaved.items()):
                self._keep(key, value)
            return
        held, self._held = self._held, []
        for key, value in list(self._unsaved.items()):
            self._keep(key, value)
        for inp, item in held:
            if inp is None:  # an autonomy report
                if self._ingest("survey", item, f"autonomy report {item!r}", hold=(None, item)):
                    self.counts["reports"] += 1
            else:
                self._image(inp, item)
        if self._not_kept:
            log.warning("store writes again: %d held item(s) taken now; not kept while it could not: %s",
                        len(held) - len(self._held),
                        ", ".join(f"{n} {name} input(s)" for name, n in sorted(self._not_kept.items())))
            self.counts["not_kept"] = self.counts.get("not_kept", 0) + sum(self._not_kept.values())
            self._not_kept = {}
        else:
            log.info("store writes again: %d held item(s) taken now", len(held) - len(self._held))

    def link_health(self) -> dict[int, Any]:
        """Each modem's :class:`~coex_transports.recovery.Health` (outages, time down); a link
        given as a plain transport (``transports=``) has none."""
        from coex import ResilientTransport

        return {lid: tr.health() for lid, tr in self.transports.items() if isinstance(tr, ResilientTransport)}

    def _link_health(self, now: float) -> None:
        """A LinkHealth topside whenever a modem went down or came back (sent on whichever link is
        up; the one that was down reports once it is back)."""
        from coex import to_stamp
        from coex.messages import LinkHealth

        health = self.link_health()
        for lid, h in health.items():
            key = (h.up, h.outages)
            if h.outages == 0 or self._health_sent.get(lid) == key:
                continue
            if not h.up and not any(o.up for other, o in health.items() if other != lid):
                continue  # nothing can carry it now: the report of its return says it all
            self._health_sent[lid] = key
            cap = 2**20 - 1
            self.node.push_link_health(LinkHealth(to_stamp(now), lid, h.up, min(h.outages, 255),
                                                  min(round(h.down_total), cap), min(round(h.last_down), cap)), now)

    def summary(self) -> dict[str, Any]:
        """What the vehicle took, for its shutdown line: :attr:`counts` with ``skipped`` the
        total of every input's skipped items and the autonomy reports not taken, and
        ``skipped_by_input`` (input key -> its skipped items)."""
        by_input = {inp.coex_key: int(inp.counts.get("skipped", 0)) for inp in self.inputs}
        return {**self.counts, "skipped": self.counts["skipped"] + sum(by_input.values()),
                "skipped_by_input": by_input}

    def _taken_files(self) -> list[str]:
        """The image files taken (oldest first): the store's marks (and the list an earlier
        version kept under ``vehicle.taken``)."""
        if self.store is None:
            return []
        old = json.loads(self.store.get("vehicle.taken", "[]") or "[]")
        return [*old, *(k[len(TAKEN_PREFIX):] for k in self.store.marked(TAKEN_PREFIX))]

    def _ingest(self, name: str, data: Any, what: str, source: Any = None, *, mark: str | None = None,
                hold: Any = None) -> bool:
        """``data`` to the sender of ``name`` through the runner (journaled first). While the
        store cannot journal it, ``hold`` (an item to take again) is held, or else the data is
        not kept (counted by ``name``)."""
        if name not in self.names:
            return False
        try:
            self.runner.ingest(name, data, mark=mark)
            return True
        except StoreError:
            if hold is not None and len(self._held) < HELD_MAX:
                self._held.append(hold)
            else:
                self._not_kept[name] = self._not_kept.get(name, 0) + 1
            return False
        except (CoexError, ValueError, TypeError) as exc:  # bad input: logged, skipped, nothing lost
            if source is not None:
                source.skip()  # counted as the input's
            else:
                self.counts["skipped"] += 1
            # once per kind of problem (a sensor sending the same bad sample every second must
            # not flood the log); every one is counted
            key = source.coex_key if source is not None else ""
            self._problem(f"{key}:{name}:{type(exc).__name__}", "%s not taken by %s: %s (further "
                          "ones like it are counted, not logged)", what, name, exc)
            return False

    def _take(self, inp: Any, item: Any, now: float) -> None:
        from coex import Image, Points, Samples

        feeds = inp.coex_feeds
        if isinstance(item, Points) and "bathymetry" in feeds:
            xyz = np.asarray(item.xyz, float)
            if xyz.ndim != 2 or xyz.shape[1] != 3:
                log.warning("%s: points of shape %s skipped (N x 3 expected)", inp.coex_key, xyz.shape)
                inp.skip()
                return
            if self._ingest("bathymetry", xyz, f"{len(xyz)} points from {inp.coex_key}", inp):
                self.counts["points"] += len(xyz)
        elif isinstance(item, Image) and "imagery" in feeds:
            self._image(inp, item)
        elif isinstance(item, Samples) and "timeseries" in feeds:
            if self._ingest("timeseries", (item.channel, np.asarray(item.times, float),
                                           np.asarray(item.values, float)),
                            f"samples of {item.channel!r} from {inp.coex_key}", inp):
                self.counts["samples"] += len(np.atleast_1d(item.times))
        elif isinstance(item, Nav) and "status" in feeds:
            self._nav(item)

    def _image(self, inp: Any, item: Any) -> None:
        from coex_plugins.imagery import ImageInput

        key = f"{item.path}|{item.time:.3f}" if item.path else None
        if key is not None and key in self._taken_set:
            return  # taken before a restart
        pixels = item.pixels
        if pixels is None and item.path:
            pixels = self._guard(f"{inp.coex_key} read {item.path}", _read_image, item.path)
            if pixels is None:
                inp.skip()
                return
        x, y = item.x, item.y
        if (x is None or y is None) and "x" in self.nav and inp.stamp_images:  # declared on Input
            x, y = self.nav["x"], self.nav["y"]
        data = ImageInput(np.asarray(pixels), time=item.time,
                          x=None if x is None else round(float(x), 1), y=None if y is None else round(float(y), 1))
        held = (inp, item if item.path is None else replace(item, pixels=None))  # read again when taken
        if self._ingest("imagery", data, f"image {item.path or ''} from {inp.coex_key}", inp,
                        mark=None if key is None or self.store is None else TAKEN_PREFIX + key, hold=held):
            self.counts["images"] += 1
            if key is not None:
                self._taken.append(key)
                self._taken_set.add(key)
                if len(self._taken) > TAKEN_MAX + 1000:  # the oldest marks go, a thousand at a time
                    gone, self._taken = self._taken[:-TAKEN_MAX], self._taken[-TAKEN_MAX:]
                    self._taken_set.difference_update(gone)
                    if self.store is not None:
                        with contextlib.suppress(CoexError):
                            self.store.delete([TAKEN_PREFIX + k for k in gone])

    def _nav(self, nav: Nav) -> None:
        fields = {"x": nav.x, "y": nav.y, "depth": nav.depth, "altitude": nav.altitude,
                  "heading": nav.heading, "speed": nav.speed}
        got = {k: v for k, v in fields.items() if v is not None and math.isfinite(v)}
        if ("x" not in got or "y" not in got) and nav.lat is not None and nav.lon is not None:
            got["x"], got["y"] = self.context.local(nav.lat, nav.lon)
        if not got:
            return
        self.nav.update(got)
        self.nav_time = nav.time
        self._nav_real = True
        self.counts["nav"] += 1

    def _status(self, now: float) -> None:
        from coex import to_stamp
        from coex.messages import VehicleMode, VehicleStatus

        if "x" not in self.nav or (self._last_status is not None
                                   and now - self._last_status < self.cfg.status_interval):
            return
        n = self.nav

        def clamp(v: float, lo: float, hi: float) -> float:
            return min(max(float(v), lo), hi)

        survey = self.node.sender("survey") if "survey" in self.names else None
        mode = VehicleMode.SURVEY if survey is not None and survey.active_plan() is not None else VehicleMode.UNKNOWN
        alt = n.get("altitude")
        status = VehicleStatus(
            to_stamp(self.nav_time or now), round(clamp(n["x"], -50000, 50000), 1),
            round(clamp(n["y"], -50000, 50000), 1), round(clamp(n.get("depth", 0.0), 0, 6000), 1),
            None if alt is None else round(clamp(alt, 0, 500), 1), round(float(n.get("heading", 0.0)) % 359.9, 1),
            round(clamp(n.get("speed", 0.0), 0, 5), 2), 0, mode, self.faults())
        self.node.push_status(status, now)
        self._last_status = now

    def _autonomy(self, now: float) -> None:
        """The survey lifecycle's step (:mod:`coex_plugins.autonomy.lifecycle`: hand over the survey
        to fly now, poll the output, end what ended, record late answers, abort on silence); its
        reports to the survey sender."""
        if self.lifecycle is None:
            return
        before = self.lifecycle.counts["submitted"]
        for report in self._guard("autonomy", self.lifecycle.step, now) or []:
            if self._ingest("survey", report, f"autonomy report {report!r}", hold=(None, report)):
                self.counts["reports"] += 1
        self.counts["plans"] += self.lifecycle.counts["submitted"] - before
        for fix in self.node.sender("survey").take_aids():  # topside's position fixes (issue 56)
            if self._guard("autonomy aid", self.autonomy.aid, fix, now):
                self.counts["aids"] += 1
            else:
                self._problem("no-aid", "a position fix from topside was not taken: the %s autonomy output "
                              "gives the vehicle's navigation no fixes (docs/autonomy.md)", self.cfg.autonomy.get("type"))
        if not self._nav_real:  # without navigation inputs, a simulated autonomy knows where it is
            xy = self._guard("autonomy position", self.autonomy.position, now)
            if xy is not None:
                self.nav.update(x=float(xy[0]), y=float(xy[1]))
                self.nav_time = now


def _read_image(path: str) -> np.ndarray:
    p = Path(path)
    if p.suffix.lower() in (".tif", ".tiff"):
        import tifffile

        return np.asarray(tifffile.imread(p))
    from PIL import Image

    with Image.open(p) as im:
        return np.asarray(im)
