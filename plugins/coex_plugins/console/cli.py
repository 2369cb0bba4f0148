"""``coex topside --transport URI [--http 127.0.0.1:8080] [--store FILE]``: a topside node with the
console.

The node runs the channel manager and every modality receiver that loads (bathymetry, imagery,
time series, survey), over one transport, on the wall clock (TDMA slots come from the shared epoch).
The console is served at ``http://HOST:PORT/``; every operator action becomes a wire-format
command sent by the node.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from coex_core.errors import CoexError, ConfigError

__all__ = ["TopsideApp", "build_topside", "register", "run"]

log = logging.getLogger(__name__)

#: The receivers ``coex topside`` runs unless told otherwise: every built-in modality (``survey``
#: sends the operator's survey requests and follows their state).
DEFAULT_MODALITIES = ("bathymetry", "imagery", "timeseries", "survey", "detections")

#: The NUI 2022 cycle: 6 slots, topside (node 1) in slots 0 and 3, the vehicle in the others.
NUI_OWNERS = (1, 2, 2, 1, 2, 2)


def _hostport(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit():
        raise argparse.ArgumentTypeError(f"expected HOST:PORT, got {text!r}")
    return host or "127.0.0.1", int(port)


def _names(text: str) -> dict[int, str]:
    out: dict[int, str] = {}
    for part in filter(None, (x.strip() for x in text.split(","))):
        sid, sep, name = part.partition("=")
        if not sep or not sid.strip().isdigit() or not name.strip():
            raise argparse.ArgumentTypeError(f"expected ID=NAME, got {part!r}")
        out[int(sid)] = name.strip()
    return out


def parse_remap(text: str) -> tuple[str, dict[int, int]]:
    """``NAME:OWN=WIRE[,OWN=WIRE...]`` (``--remap-ids``): a modality's third-party ids as the
    deployment carries them on the wire."""
    name, sep, pairs = text.partition(":")
    out: dict[int, int] = {}
    for part in filter(None, (x.strip() for x in pairs.split(","))):
        a, eq, b = part.partition("=")
        if not eq or not a.strip().isdigit() or not b.strip().isdigit():
            raise argparse.ArgumentTypeError(f"expected OWN=WIRE (two type ids), got {part!r}")
        out[int(a)] = int(b)
    if not sep or not name.strip() or not out:
        raise argparse.ArgumentTypeError(f"expected NAME:OWN=WIRE[,OWN=WIRE...], got {text!r}")
    return name.strip(), out


def console_access(host: str, operators: str | Path | None, insecure_open: bool,
                   tls_cert: str | None, tls_key: str | None, session_hours: float = 12.0,
                   idle_minutes: float = 30.0) -> tuple[Any, Any]:
    """The console's sign-in (:class:`~.access.Access`, or None) and TLS context (or None);
    :class:`ConfigError` for a console that would be open to the network without sign-in."""
    import ipaddress

    from .access import Access, OperatorsFile
    from .server import tls_context

    if (tls_cert is None) != (tls_key is None):
        raise ConfigError("give both --tls-cert and --tls-key")
    tls = tls_context(tls_cert, tls_key) if tls_cert and tls_key else None
    if operators is not None:
        path = Path(operators)
        if not path.exists():
            raise ConfigError(f"no operators file {path} (make one: coex operators add NAME --role operator "
                              f"--file {path})")
        return Access(OperatorsFile(path), session_hours=session_hours, idle_minutes=idle_minutes), tls
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = False
    if not loopback:
        if not insecure_open:
            raise ConfigError(
                f"refusing to serve the console on {host} without sign-in: anyone who reaches the port "
                "could command the vehicle. Give --operators FILE (coex operators add ...), or "
                "--insecure-open if this network is trusted (docs/console.md)")
        log.warning("INSECURE: the console on %s has no sign-in: anyone who reaches it commands the "
                    "vehicle (--insecure-open)", host)
    if tls is not None:
        log.warning("TLS without an operators file: the console is encrypted but open to anyone who reaches it")
    return None, tls


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "topside", help="run a topside node and serve the web console",
        description="Run a topside node over a transport and serve the web console "
                    "(map, images, time series, link and queues) on HTTP.")
    p.add_argument("--config", metavar="FILE",
                   help="the topside's configuration file (TOML, docs/deploy.md): node, modems, "
                        "TDMA, modalities, store and console in one place; replaces the options below")
    p.add_argument("--transport", metavar="URI", action="append",
                   help="transport URI (micromodem:///dev/ttyUSB0, mavlink:..., lcm:..., "
                        "moos://HOST:PORT?name=..., loopback://name); repeat it for several modems (links --link, "
                        "--link + 1, ...)")
    p.add_argument("--http", type=_hostport, default=("127.0.0.1", 8080), metavar="HOST:PORT",
                   help="where to serve the console (default 127.0.0.1:8080; port 0 = any)")
    p.add_argument("--node-id", type=int, default=1, help="topside node id (default 1)")
    p.add_argument("--vehicle-id", type=int, default=2, help="vehicle node id (default 2)")
    p.add_argument("--link", type=int, default=0, help="link id of the transport (default 0)")
    p.add_argument("--rate", type=int, default=5, help="Micromodem rate of packets (default 5)")
    p.add_argument("--slot", type=float, default=20.0,
                   help="TDMA slot length in seconds (NUI cycle of 6 slots, default 20)")
    p.add_argument("--guard", type=float, default=2.0, help="slot guard time (default 2 s)")
    p.add_argument("--schedule", metavar="JSON",
                   help='explicit schedule: {"slots": [{"owner": 1, "duration": 20, '
                        '"guard": 2}, ...], "epoch": 0}')
    p.add_argument("--stream-names", type=_names, default={}, metavar="ID=NAME,...",
                   help="names of the vehicle's streams for the queue table, e.g. "
                        "3=map,4=images,5=series")
    p.add_argument("--modalities", default=",".join(DEFAULT_MODALITIES),
                   help="comma-separated receivers to run (default: all built-in, "
                        f"{','.join(DEFAULT_MODALITIES)})")
    p.add_argument("--remap-ids", type=parse_remap, action="append", default=[],
                   metavar="NAME:OWN=WIRE,...",
                   help="carry modality NAME's third-party type ids OWN as WIRE on the wire (the "
                        "vehicle remaps them alike; spec/third-party-ids.md); repeat per modality")
    p.add_argument("--operators", metavar="FILE",
                   help="operators file (coex operators add ...): everyone signs in; operators "
                        "command, viewers watch. Required to listen beyond the loopback address")
    p.add_argument("--insecure-open", action="store_true",
                   help="listen beyond loopback without sign-in (a trusted network only; logged loudly)")
    p.add_argument("--tls-cert", metavar="PEM", help="serve HTTPS with this certificate chain")
    p.add_argument("--tls-key", metavar="PEM", help="the certificate's private key")
    p.add_argument("--session-hours", type=float, default=12.0,
                   help="a sign-in lasts this long (default 12 h)")
    p.add_argument("--idle-minutes", type=float, default=30.0,
                   help="a sign-in not used for this long ends; an open console page is use (default 30)")
    p.add_argument("--allowed-host", action="append", default=[], metavar="NAME",
                   help="a name the console is reached by besides the loopback names and the --http "
                        "address (a ship's DNS name, a reverse proxy's); other Host headers are refused "
                        "(DNS rebinding). Repeat it for several")
    p.add_argument("--trusted-proxy", action="append", default=[], metavar="ADDRESS",
                   help="a reverse proxy whose X-Forwarded-For names the client (sign-in limits go by "
                        "client address); repeat it for several")
    p.add_argument("--command-key-file", metavar="PATH",
                   help="shared command key (hex, or at least 16 raw bytes): every command is "
                        "signed (spec section 10); the vehicle must have the same key")
    p.add_argument("--store", metavar="FILE",
                   help="SQLite file keeping everything received and the console's state: "
                        "after a crash or kill, the same command resumes where it was")
    p.set_defaults(func=run)


class TopsideApp:
    """A topside node, its transports (one per link id: several modems), the console hub and
    server, and the loop driving them: the public :class:`coex.Runner`, with the console's lock
    held around each step and a hook that moves the node's events to the console."""

    def __init__(self, node: Any, transports: dict[int, Any], hub: Any, server: Any,
                 clock: Callable[[], float], *, store: Any = None) -> None:
        from coex_transports.runner import RealClock, Runner

        self.node = node
        #: A :class:`coex.NodeStore` (or None): journal and snapshots.
        self.store = store
        self.transports = dict(transports)
        self.hub = hub
        self.server = server
        self.clock = clock
        self.stop = threading.Event()
        #: the products on ROS topics (``[ros]``), or None
        self.ros: Any = None
        self._last_status: dict[int, Any] = {}
        self._commands_seen = self._commands_version()
        self.runner = Runner(node, self.transports, RealClock(clock), store=store,
                             lock=hub.lock, after_step=[self._to_console],
                             snapshot_due=self._commands_changed,
                             on_error=lambda text: log.warning("%s", text))
        self.transports = self.runner.transports  # one dict: a link's transport may be swapped

    @property
    def errors(self) -> list[str]:
        """The runner's recent transport and store errors."""
        return list(self.runner.errors)

    @property
    def url(self) -> str:
        return str(self.server.url)

    @property
    def link(self) -> int:
        """The first link id."""
        return int(next(iter(self.transports)))

    @property
    def transport(self) -> Any:
        """The transport of the first link."""
        return self.transports[self.link]

    def step(self) -> float:
        """One pass of the runner: take waiting frames, let the node send, move events to the
        console. Returns when the node next needs attention."""
        return float(self.runner.step())

    def _to_console(self, now: float) -> None:
        from coex_transports.recovery import ResilientTransport

        self.hub.pump(self.node, now)
        for link, tr in self.transports.items():
            self._modem_status(link, tr)
            if isinstance(tr, ResilientTransport):
                h = tr.health()
                self.hub.state.set_own_modem(link, h.up, h.outages, h.down_total, h.last_down, h.last_error, now)

    def _commands_version(self) -> int:
        """Changes whenever the operator's commands do (sent, queued, answered)."""
        return int(self.hub.state.versions.get("commands", 0))

    def _commands_changed(self) -> bool:
        """Whether the store must be saved now: the operator's commands changed."""
        sent = self._commands_version()
        changed = sent != self._commands_seen
        self._commands_seen = sent
        return changed

    def _modem_status(self, link: int, transport: Any) -> None:
        """Receive statistics of topside's own modem (a transport with ``link_status()``, like
        the Micromodem's), shown with the link."""
        try:
            status = transport.link_status()
        except Exception as exc:  # statistics are a nicety: never stop the loop for them
            self.runner._error(f"link {link} status: {exc}")
            return
        if status is not None and status != self._last_status.get(link):
            self._last_status[link] = status
            if getattr(status, "link", link) != link:
                status = replace(status, link=link)
            self.hub.messages([status], self.clock(), link)

    def run(self) -> None:
        """Drive the node until :attr:`stop` is set."""
        self.runner.run(stop=self.stop.is_set)

    def start(self) -> TopsideApp:
        self._thread = threading.Thread(target=self.run, name="coex-topside", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self.stop.set()
        thread = getattr(self, "_thread", None)
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=5.0)
        self.server.close()
        if self.ros is not None:
            self.ros.close()
        for tr in self.transports.values():
            tr.close()
        if self.store is not None:
            with self.hub.lock:
                try:
                    self.store.snapshot(self.node, self.clock())
                finally:
                    self.store.close()


def _schedule(args: argparse.Namespace) -> Any:
    from coex_core.channel.schedule import Schedule

    if args.schedule:
        try:
            d = json.loads(args.schedule)
            return Schedule.from_dict(d)
        except (ValueError, KeyError, TypeError) as exc:
            raise ConfigError(f"invalid --schedule: {exc}") from exc
    owners = [args.node_id if o == 1 else args.vehicle_id for o in NUI_OWNERS]
    return Schedule.simple(owners, args.slot, args.guard)


def build_topside(transport_uri: str | Sequence[str], host: str = "127.0.0.1", port: int = 8080,
                  *, node_id: int = 1, vehicle_id: int = 2, link: int = 0, rate: int = 5,
                  schedule: Any = None,
                  modalities: tuple[str, ...] = DEFAULT_MODALITIES,
                  stream_names: dict[int, str] | None = None,
                  clock: Callable[[], float] = time.time,
                  command_key: bytes | None = None,
                  store: str | Path | None = None,
                  snapshot_interval: float = 30.0,
                  remap_ids: dict[str, dict[int, int]] | None = None,
                  operators: str | Path | None = None, insecure_open: bool = False,
                  tls_cert: str | None = None, tls_key: str | None = None,
                  session_hours: float = 12.0, idle_minutes: float = 30.0,
                  allowed_hosts: Sequence[str] = (), trusted_proxies: Sequence[str] = (),
                  receiver_options: dict[str, dict[str, Any]] | None = None,
                  link_options: Sequence[dict[str, Any]] | None = None,
                  required: Sequence[bool] | None = None,
                  ros: dict[str, Any] | None = None,
                  transports: Mapping[int, Any] | None = None) -> TopsideApp:
    """Open the transports (several URIs: several modems, link ids ``link``, ``link + 1`` ...),
    build the topside node and its receivers, serve the console (not yet driving the node: call
    ``start()`` or ``run()``). With ``command_key`` every command is authenticated (spec
    section 10).

    With ``store`` (an SQLite file, :class:`coex_transports.store.NodeStore`) every received
    frame is journaled before the node sees it and the node with its console state (map, images,
    series, requests, goals, schedules, command log) is saved before each transmission, after
    each operator command and at most every ``snapshot_interval`` seconds otherwise; when the
    file already holds a topside, that one is resumed (its settings win over the arguments).

    ``remap_ids`` maps a modality name to its third-party ids as carried on the wire
    (``{"ctd": {130: 4130}}``; spec/third-party-ids.md).

    ``operators`` (an operators file, ``coex operators``) makes the console ask everyone to
    sign in: operators command, viewers watch. A console on a non-loopback address refuses to
    start without one, unless ``insecure_open`` (logged loudly). ``tls_cert`` and ``tls_key``
    serve HTTPS; ``allowed_hosts`` are names the console answers to besides the loopback ones
    and ``host``; ``trusted_proxies`` reverse proxies whose ``X-Forwarded-For`` is believed.
    ``receiver_options`` gives a modality's receiver its options by name;
    ``link_options`` (one mapping per transport) sets LinkConfig fields (``rate``,
    ``frame_bytes``, ``spare``, ``packet_seconds``) link by link. Each transport is a
    :class:`~coex_transports.recovery.ResilientTransport`: a modem that goes away or is not
    there yet is reopened with backoff (``required[i]`` true: an error at start instead).
    ``ros`` (the options of :class:`~coex_plugins.console.ros.RosProducts`) publishes what
    arrives on ROS topics for rviz. ``transports`` (link id -> an open transport, one per URI)
    replaces the transports the URIs would open: a simulation's, a test's (the URIs then only
    name the links); the app closes them."""
    access, tls = console_access(host, operators, insecure_open, tls_cert, tls_key, session_hours,
                                 idle_minutes)
    from coex_core.channel.manager import ChannelManager, LinkConfig
    from coex_core.channel.schedule import Schedule
    from coex_core.node import Node
    from coex_core.registry import load_modality
    from coex_transports.recovery import ResilientTransport

    from .node import NodeCommands
    from .server import ConsoleHub, serve
    from .state import MAX_IMAGES, ConsoleState

    if schedule is None:
        schedule = Schedule.simple([node_id if o == 1 else vehicle_id for o in NUI_OWNERS],
                                   20.0, 2.0)
    unknown = sorted(set(remap_ids or {}) - set(modalities))
    if unknown:
        raise ConfigError(f"--remap-ids names modalities not run here: {', '.join(unknown)}")
    uris = [transport_uri] if isinstance(transport_uri, str) else list(transport_uri)
    if not uris:
        raise ConfigError("give at least one transport URI")
    links: dict[int, Any] = {}
    nstore: Any = None
    try:
        from coex_core.acoustic import rate_info

        if transports is not None:
            links.update(transports)  # closed with the rest on an error
            if sorted(transports) != [link + i for i in range(len(uris))]:
                raise ConfigError(f"transports for links {sorted(transports)}, expected "
                                  f"{[link + i for i in range(len(uris))]} (one per URI)")
        for i, uri in enumerate(uris if transports is None else ()):
            # a modem that goes away (or is not there yet) is reopened while the console runs on
            links[link + i] = ResilientTransport(uri, name=f"link {link + i}",
                                                 required=bool(required and i < len(required) and required[i]))
        extra = list(link_options or [])
        cfgs = [LinkConfig(lid, schedule, rate=rate,
                           frame_bytes=min(rate_info(rate).frame_bytes, int(tr.mtu)),
                           dst=vehicle_id) for lid, tr in links.items()]
        for i, lc in enumerate(cfgs):  # per-link settings of a configuration file
            if i < len(extra) and extra[i]:
                cfgs[i] = replace(lc, **extra[i])
        missing: list[str] = []

        def fresh() -> Any:
            node = Node(ChannelManager(node_id, cfgs, command_key=command_key))
            for name in modalities:
                try:
                    cls = load_modality(name)
                    receiver = cls().receiver((receiver_options or {}).get(name) or None)
                except (CoexError, ImportError, AttributeError, TypeError) as exc:
                    log.warning("modality %s not available: %s", name, exc)
                    missing.append(f"modality {name} not available: {exc}")
                    continue
                node.add_receiver(cls, receiver, ids=(remap_ids or {}).get(name))
            return node

        hubs: list[Any] = []

        def wire(node: Any, extra: Any) -> None:
            """The console around ``node``: a fresh one, or the one saved with it."""
            if isinstance(extra, dict) and isinstance(extra.get("state"), ConsoleState):
                state = extra["state"]
            else:
                names = {s.id: s.config.name for s in node.manager.streams}
                names.update(stream_names or {})
                state = ConsoleState(node_id=node_id, vehicle_id=vehicle_id, stream_names=names,
                                     receivers=dict(node.receivers()))
                for lid in links:
                    state.set_schedule(lid, schedule)
            # the node's receivers are what the console shows (the saved console holds the
            # same objects as the restored node: they were saved in one document)
            state.receivers = dict(node.receivers())
            state.own_receivers = False
            from coex_plugins.imagery.receiver import ImageryReceiver

            images = state.receivers.get("imagery")
            if isinstance(images, ImageryReceiver):  # the console keeps what the receiver keeps
                state.max_images = min(MAX_IMAGES, images.max_images)
            hub = ConsoleHub(state, NodeCommands(node, clock), clock)
            rx = state.receivers.get("bathymetry")
            if rx is not None and hasattr(rx, "request_area"):
                hub.actions.map_receiver = state.region_source = rx
            hubs.append(hub)

        if store is None:
            node = fresh()
            wire(node, None)
        else:
            from coex_transports.store import NodeStore

            nstore = NodeStore(store, snapshot_interval=snapshot_interval)
            resumed = nstore.has_state()
            node = nstore.restore(fresh, log=None, clock=None, before_replay=wire)
            if sorted(node.manager.links) != sorted(links):
                raise ConfigError(
                    f"{store} holds a node with links {sorted(node.manager.links)}, this run has "
                    f"{sorted(links)}: give the same transports, or another --store")
            if node.node_id != node_id:
                raise ConfigError(f"{store} holds topside node {node.node_id}, not {node_id}")
            if resumed:
                log.info("resumed from %s (%d journal rows replayed)", store,
                         nstore.stats["replayed"])
        node.set_log(lambda text: log.info("%s", text))
        hub = hubs[-1]
        state = hub.state
        for text in missing:
            state._log(0.0, text, "warn")
        if nstore is not None:
            if nstore.restored_extra is not None or nstore.stats["replayed"]:
                state._log(clock(), f"resumed from {store}: {nstore.stats['replayed']} "
                                    "journaled frames replayed")
            nstore.extra = lambda: {"state": hub.state}
        server = serve(hub, host, port, access=access, tls=tls, allowed_hosts=list(allowed_hosts),
                       trusted_proxies=list(trusted_proxies))
    except BaseException:
        for tr in links.values():
            tr.close()
        if nstore is not None:
            nstore.close()
        raise
    app = TopsideApp(node, links, hub, server, clock, store=nstore)
    if ros is not None:
        from .ros import RosProducts

        try:
            app.ros = RosProducts(ros, lock=hub.lock, clock=clock).attach(node)
        except BaseException:
            app.close()
            raise
    return app


def topside_from_config(path: str, clock: Callable[[], float] = time.time, *,
                        transports: Mapping[int, Any] | None = None) -> TopsideApp:
    """The topside node, its modems and console as a configuration file describes them
    (``transports``: see :func:`build_topside`)."""
    from coex_plugins.vehicle.config import load

    cfg = load(path, "topside")
    c = cfg.console
    host, _, port = str(c.get("http", "127.0.0.1:8080")).rpartition(":")

    def rel(k: str) -> str | None:
        return str(cfg.base_dir / c[k]) if c.get(k) else None

    names = {m.stream: m.name for m in cfg.modalities}
    names.update({int(k): str(v) for k, v in (c.get("stream_names") or {}).items()})
    return build_topside(
        [m.uri for m in cfg.modems], host or "127.0.0.1", int(port), node_id=cfg.node_id, vehicle_id=cfg.peer,
        rate=cfg.modems[0].rate, schedule=cfg.schedule(), modalities=tuple(m.name for m in cfg.modalities),
        stream_names=names, clock=clock, command_key=cfg.command_key, store=cfg.store,
        snapshot_interval=cfg.snapshot_interval,
        remap_ids={m.name: m.ids for m in cfg.modalities if m.ids} or None, operators=rel("operators"),
        insecure_open=bool(c.get("insecure_open", False)), tls_cert=rel("tls_cert"), tls_key=rel("tls_key"),
        session_hours=float(c.get("session_hours", 12.0)),
        receiver_options={m.name: cfg.options(m) for m in cfg.modalities},
        link_options=[{k: v for k, v in (("rate", m.rate), ("frame_bytes", m.frame_bytes), ("spare", m.spare),
                                          ("packet_seconds", m.packet_seconds)) if v is not None}
                      for m in cfg.modems],
        required=[m.required for m in cfg.modems], ros=cfg.ros, transports=transports,
        idle_minutes=float(c.get("idle_minutes", 30.0)), allowed_hosts=[str(h) for h in c.get("allowed_hosts", [])],
        trusted_proxies=[str(h) for h in c.get("trusted_proxies", [])])


def run(args: argparse.Namespace) -> int:
    if args.config:
        try:
            app = topside_from_config(args.config)
        except (CoexError, OSError) as exc:
            print(f"coex topside: {exc}", file=sys.stderr)
            return 2
        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s",
                            force=True)
        print(f"CoEx console on {app.url} (topside node {app.node.node_id}, from {args.config})", flush=True)
        return _serve(app)
    if not args.transport:
        print("coex topside: give --config FILE or at least one --transport URI", file=sys.stderr)
        return 2
    host, port = args.http
    try:
        key = None
        if args.command_key_file:
            from coex_core.auth import parse_key

            try:
                key = parse_key(Path(args.command_key_file).read_bytes())
            except OSError as exc:
                raise ConfigError(f"cannot read --command-key-file: {exc}") from exc
        app = build_topside(
            args.transport, host, port, node_id=args.node_id, vehicle_id=args.vehicle_id,
            link=args.link, rate=args.rate, schedule=_schedule(args),
            modalities=tuple(m for m in args.modalities.split(",") if m),
            stream_names=args.stream_names, command_key=key, store=args.store,
            remap_ids=dict(args.remap_ids), operators=args.operators, insecure_open=args.insecure_open,
            tls_cert=args.tls_cert, tls_key=args.tls_key, session_hours=args.session_hours,
            idle_minutes=args.idle_minutes, allowed_hosts=args.allowed_host,
            trusted_proxies=args.trusted_proxy)
    except (CoexError, OSError) as exc:
        print(f"coex topside: {exc}", file=sys.stderr)
        return 2
    print(f"CoEx console on {app.url} (topside node {args.node_id}, "
          f"{', '.join(args.transport)})", flush=True)
    return _serve(app)


def _serve(app: TopsideApp) -> int:
    if app.store is not None:
        st = app.store
        resumed = st.restored_extra is not None or st.stats["replayed"] > 0
        print(f"store {app.store.path}: " + (f"resumed ({st.stats['replayed']} journaled frames "
                                         "replayed)" if resumed else "new"), flush=True)

    from coex_transports.runner import sigterm_as_interrupt

    with sigterm_as_interrupt():  # a polite stop (SIGTERM) saves the store like Ctrl-C
        try:
            app.run()
        except KeyboardInterrupt:
            pass
        finally:
            app.close()
    return 0


# ------------------------------------------------------------------ coex operators
def register_operators(subparsers: Any) -> None:
    """``coex operators add|role|remove|list``: the console's operators file."""
    p = subparsers.add_parser("operators", help="manage who may sign in to the console (operators "
                                                "command, viewers watch)")
    p.add_argument("--file", default="coex-operators.json", help="the operators file (default "
                   "coex-operators.json; created with mode 0600)")
    sub = p.add_subparsers(dest="op", metavar="ACTION", required=True)
    a = sub.add_parser("add", help="add or replace an operator; prints a new random token unless "
                                   "--password-stdin")
    a.add_argument("name")
    a.add_argument("--role", choices=["operator", "viewer"], required=True)
    a.add_argument("--password-stdin", action="store_true", help="read a password (12+ characters, "
                   "not a common one) from standard input instead of making a token")
    ro = sub.add_parser("role", help="change someone's role, keeping their password (a running console "
                                     "applies it at once)")
    ro.add_argument("name")
    ro.add_argument("--role", choices=["operator", "viewer"], required=True)
    r = sub.add_parser("remove", help="remove an operator (a running console ends their sessions at once)")
    r.add_argument("name")
    sub.add_parser("list", help="names and roles")
    p.set_defaults(func=_operators)


def _operators(args: argparse.Namespace) -> int:
    from .access import OperatorsFile

    try:
        f = OperatorsFile(args.file)
        if args.op == "list":
            for op in sorted(f.operators.values(), key=lambda o: o.name):
                print(f"{op.name}\t{op.role}")
            if not f.operators:
                print(f"(nobody in {args.file})", file=sys.stderr)
            return 0
        if args.op == "role":
            f.set_role(args.name, args.role)
            f.save()
            print(f"{args.name} is now {args.role} in {args.file}")
            return 0
        if args.op == "remove":
            f.remove(args.name)
            f.save()
            print(f"removed {args.name} from {args.file}")
            return 0
        secret = sys.stdin.readline().rstrip("\n") if args.password_stdin else None
        made = f.add(args.name, args.role, secret)
        f.save()
        print(f"{args.name} ({args.role}) saved in {args.file}")
        if made is not None:
            print(f"token (shown once, give it to {args.name}): {made}")
        return 0
    except ConfigError as exc:
        print(f"coex operators: {exc}", file=sys.stderr)
        return 2

