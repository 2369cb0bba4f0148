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
import re
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from coex import CoexError, ConfigError, Problems
from coex.messages import LinkStatus

if TYPE_CHECKING:
    from coex_apps.vehicle.config import DeployConfig

__all__ = ["TopsideApp", "build_topside", "register", "run", "topside_app", "topside_config", "topside_from_config"]

log = logging.getLogger(__name__)

#: The receivers ``coex topside`` runs unless told otherwise: every built-in modality (``survey``
#: sends the operator's survey requests and follows their state).
DEFAULT_MODALITIES = ("bathymetry", "imagery", "timeseries", "survey", "detections")

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

    from .access import Access, OperatorsFile, secret_file_problem
    from .server import tls_context

    if (tls_cert is None) != (tls_key is None):
        raise ConfigError("give both --tls-cert and --tls-key")
    if tls_key:  # a secret other users may read is refused (docs/console.md)
        problem = secret_file_problem(tls_key, "TLS key")
        if problem:
            raise ConfigError(problem)
    tls = tls_context(tls_cert, tls_key) if tls_cert and tls_key else None
    if operators is not None:
        path = Path(operators)
        if not path.exists():
            raise ConfigError(f"no operators file {path} (make one: coex operators add NAME --role operator "
                              f"--file {path})")
        problem = secret_file_problem(path, "operators file")
        if problem:
            raise ConfigError(problem)
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
    p.add_argument("--rate", type=int, default=None,
                   help="Micromodem rate of packets (default: the URI's rate=, else 5)")
    p.add_argument("--slot", type=float, default=20.0,
                   help="TDMA slot length in seconds (NUI cycle of 6 slots, default 20)")
    p.add_argument("--guard", type=float, default=2.0, help="slot guard time (default 2 s)")
    p.add_argument("--packet-seconds", type=float, default=None, metavar="S",
                   help="time a packet takes on every modem (default: a full packet's airtime at the "
                        "rate; a link without airtime, LCM, MAVLink, MOOS, loopback, takes less: "
                        "docs/deploy.md, modems[0].packet_seconds)")
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
                   help="a reverse proxy whose X-Forwarded-For names the client (limits go by client "
                        "address) and whose X-Forwarded-Proto says https (Secure cookies); repeat it for several")
    p.add_argument("--public-origin", action="append", default=[], metavar="URL",
                   help="an origin the console's page is reached at besides its own address and names, "
                        "e.g. a reverse proxy's https://console.ship.example (scheme, host and port are "
                        "compared with a request's Origin); repeat it for several")
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
        from coex import RealClock, Runner

        #: the thread :meth:`start` runs the loop in (None: not started)
        self._thread: threading.Thread | None = None
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
        #: the ship's USBL and topside's drift estimate (``[usbl]``, :mod:`.usbl`), or None
        self.usbl: Any = None
        #: the vehicles heard nothing from (:class:`coex.PeerWatch`; set by :func:`topside_app`)
        self.peer_watch: Any = None
        self._last_status: dict[int, Any] = {}
        self._commands_seen = self._commands_version()
        self.runner = Runner(node, self.transports, RealClock(clock), store=store,
                             lock=hub.lock, after_step=[self._to_console],
                             snapshot_due=self._commands_changed, on_error=self._error)
        self.transports = self.runner.transports  # one dict: a link's transport may be swapped

    def _error(self, text: str) -> None:
        """The runner's errors to the log; the store's (a full disk, and its end) to the
        console's event log too: the operator must know what topside cannot keep."""
        log.warning("%s", text)
        if text.startswith("store"):
            for state in self._states():
                state._log(self.clock(), text, "warn")

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
        from coex import ResilientTransport

        self.hub.pump(self.node, now)
        if self.usbl is not None:
            self.usbl.poll(now, self._states())
        if self.peer_watch is not None:
            from .fleet import FleetHub

            for change in self.peer_watch.check(now):
                fleet = isinstance(self.hub, FleetHub)
                text = change.text(self.hub.names.get(change.peer, "") if fleet else "the vehicle")
                (log.warning if change.silent else log.info)("%s", text)
                states = self.hub.states() if fleet else {change.peer: self.hub.state}
                if change.peer in states:
                    states[change.peer]._log(now, text, "warn" if change.silent else "info")
        for link, tr in self.transports.items():
            self._modem_status(link, tr)
            if isinstance(tr, ResilientTransport):
                h = tr.health()
                for state in self._states():
                    state.set_own_modem(link, h.up, h.outages, h.down_total, h.last_down, h.last_error, now)

    def _states(self) -> list[Any]:
        """The console states: one, or a fleet's, one per vehicle."""
        from .fleet import FleetHub

        return list(self.hub.states().values()) if isinstance(self.hub, FleetHub) else [self.hub.state]

    def _commands_version(self) -> int:
        """Changes whenever the operator's commands do (sent, queued, answered)."""
        return sum(int(state.versions.get("commands", 0)) for state in self._states())

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
            if isinstance(status, LinkStatus) and status.link != link:
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
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=5.0)
        self.server.close()
        if self.ros is not None:
            self.ros.close()
        if self.usbl is not None:
            self.usbl.close()
        for tr in self.transports.values():
            tr.close()
        if self.store is not None:
            with self.hub.lock:
                try:
                    self.store.snapshot(self.node, self.clock())
                except CoexError as exc:  # a full disk: said, never a traceback
                    log.warning("last snapshot not saved: %s", exc)
                finally:
                    self.store.close()


def _schedule(text: str | None) -> Any:
    """``--schedule JSON`` as a :class:`~coex_core.channel.schedule.Schedule` (None without one)."""
    from coex import Schedule

    if not text:
        return None
    try:
        return Schedule.from_dict(json.loads(text))
    except (ValueError, KeyError, TypeError) as exc:
        raise ConfigError(f"invalid --schedule: {exc}") from exc


#: the option that gives a configuration key on the command line (problems are named by it)
_OPTIONS = (("node.id", "--node-id"), ("node.peer", "--vehicle-id"), ("node.store", "--store"),
            ("node.command_key_file", "--command-key-file"), ("tdma.slot_seconds", "--slot"),
            ("tdma.guard", "--guard"))


def _option(key: str, uris: Sequence[str]) -> str:
    """The command-line option that gave configuration key ``key`` (the key itself when none
    did: a :func:`build_topside` argument)."""
    modem = re.fullmatch(r"modems\[(\d+)\](?:\.(\w+))?", key)
    if modem and modem.group(2) in (None, "uri") and int(modem.group(1)) < len(uris):
        return f"--transport {uris[int(modem.group(1))]}"
    if modem and modem.group(2) == "rate":
        return "--rate"
    if modem and modem.group(2) == "packet_seconds":
        return "--packet-seconds"
    modality = re.fullmatch(r"modalities\.([^.]+)\.ids(?:\..*)?", key)
    if modality:
        return f"--remap-ids {modality.group(1)}"
    return dict(_OPTIONS).get(key, key)


def topside_config(transport_uri: str | Sequence[str], *, node_id: int = 1, vehicle_id: int = 2,
                   link: int = 0, rate: int | None = None, schedule: Any = None, slot: float = 20.0,
                   guard: float = 2.0, modalities: Sequence[str] = DEFAULT_MODALITIES,
                   remap_ids: Mapping[str, Mapping[int, int]] | None = None, store: str | Path | None = None,
                   command_key_file: str | Path | None = None,
                   receiver_options: Mapping[str, Mapping[str, Any]] | None = None,
                   link_options: Sequence[Mapping[str, Any]] | None = None,
                   required: Sequence[bool] | None = None, ros: Mapping[str, Any] | None = None,
                   missing: list[str] | None = None) -> DeployConfig:
    """The topside's :class:`~coex_apps.vehicle.config.DeployConfig` from ``coex topside``'s
    options (and :func:`build_topside`'s arguments), checked by the one checker of a
    configuration file (:func:`~coex_apps.vehicle.config.check_problems`): :class:`ConfigError`
    lists every problem, each named by its option (``--node-id: 20 is outside 1..15``).

    ``transport_uri`` one or more modems (links ``link``, ``link + 1`` ...); ``rate`` every
    modem's (None: the URI's ``rate=``, else 5); ``schedule`` a whole
    :class:`~coex_core.channel.schedule.Schedule` (``--schedule``), else the NUI cycle of
    ``slot`` and ``guard`` seconds; ``modalities`` the receivers (a modality not installed, or
    whose extra is missing, is left out and said in ``missing``, as the console always did);
    ``remap_ids``, ``receiver_options`` by modality name; ``link_options`` and ``required`` by
    modem (the keys of a file's ``[[modems]]``); ``store`` None: none."""
    from coex_apps.vehicle.config import STREAM_DEFAULTS, check_problems

    uris = [transport_uri] if isinstance(transport_uri, str) else list(transport_uri)
    if not uris:
        raise ConfigError("give at least one transport URI")
    unknown = sorted(set(remap_ids or {}) - set(modalities))
    if unknown:
        raise ConfigError(f"--remap-ids names modalities not run here: {', '.join(unknown)}")
    modems: list[dict[str, Any]] = []
    for i, uri in enumerate(uris):
        m: dict[str, Any] = {"uri": uri}
        if rate is not None:
            m["rate"] = rate
        if required and i < len(required):
            m["required"] = bool(required[i])
        if link_options and i < len(link_options):
            m.update(link_options[i] or {})
        modems.append(m)
    # a modality without a built-in stream gets a free one: the checker asks every modality for
    # its stream, which a topside's receiver does not use
    taken = {STREAM_DEFAULTS[n][0] for n in modalities if n in STREAM_DEFAULTS}
    free = iter([s for s in range(1, 32) if s not in taken])
    table: dict[str, dict[str, Any]] = {}
    for name in modalities:
        t: dict[str, Any] = {} if name in STREAM_DEFAULTS else {"stream": next(free, 31)}
        if (receiver_options or {}).get(name):
            t["options"] = dict((receiver_options or {})[name])
        if (remap_ids or {}).get(name):
            t["ids"] = {str(k): v for k, v in (remap_ids or {})[name].items()}
        table[name] = t
    node: dict[str, Any] = {"role": "topside", "id": node_id, "peer": vehicle_id,
                            "store": False if store is None else str(store)}
    if command_key_file is not None:
        node["command_key_file"] = str(command_key_file)
    raw: dict[str, Any] = {"node": node, "modems": modems, "modalities": table}
    if schedule is None:
        raw["tdma"] = {"slot_seconds": slot, "guard": guard}
    if ros is not None:
        raw["ros"] = dict(ros)
    # relative file names (--store, --command-key-file) are taken from the working directory
    cfg, found = check_problems(raw, Path.cwd() / "coex-topside", "topside")
    problems = Problems()
    left_out = set()
    for problem in found:
        key, text = problem.key, problem.text
        if key.startswith("modalities.") and key[len("modalities."):] in table:  # not installed, no extra
            left_out.add(key[len("modalities."):])
            if missing is not None:
                missing.append(f"modality {key[len('modalities.'):]} not available: {text[len(key) + 2:]}")
        elif text.startswith(f"{key}: ") and _option(key, uris) != key:
            problems.said(key, f"{_option(key, uris)}: {text[len(key) + 2:]}")
        else:
            problems.said(key, text)
    problems.check()
    cfg.modalities = [m for m in cfg.modalities if m.name not in left_out]
    cfg.first_link = link
    cfg.explicit_schedule = schedule
    return cfg


def build_topside(transport_uri: str | Sequence[str], host: str = "127.0.0.1", port: int = 8080,
                  *, node_id: int = 1, vehicle_id: int = 2, link: int = 0, rate: int | None = None,
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
                  public_origins: Sequence[str] = (),
                  receiver_options: dict[str, dict[str, Any]] | None = None,
                  link_options: Sequence[dict[str, Any]] | None = None,
                  required: Sequence[bool] | None = None,
                  ros: dict[str, Any] | None = None,
                  transports: Mapping[int, Any] | None = None) -> TopsideApp:
    """Open the transports (several URIs: several modems, link ids ``link``, ``link + 1`` ...),
    build the topside node and its receivers, serve the console (not yet driving the node: call
    ``start()`` or ``run()``). The node's settings are checked as a configuration file's
    (:func:`topside_config`, every problem at once); the node is built by the one
    ``build_node(config, "topside", transports)`` of ``coex vehicle`` and ``coex topside
    --config``. With ``command_key`` every command is authenticated (spec section 10).
    ``rate`` is every modem's (None: the URI's ``rate=``, else 5).

    With ``store`` (an SQLite file, :class:`coex_runtime.store.NodeStore`) every received
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
    and ``host``; ``trusted_proxies`` reverse proxies whose ``X-Forwarded-For`` is believed;
    ``public_origins`` origins the page is reached at besides the console's own (a proxy's).
    ``receiver_options`` gives a modality's receiver its options by name;
    ``link_options`` (one mapping per transport) sets a modem's ``rate``, ``frame_bytes``,
    ``spare``, ``packet_seconds`` (the keys of a file's ``[[modems]]``) link by link. Each
    transport is a :class:`~coex_transports.recovery.ResilientTransport`: a modem that goes away
    or is not there yet is reopened with backoff (``required[i]`` true: an error at start
    instead). ``ros`` (the options of :class:`~coex_apps.console.ros.RosProducts`) publishes
    what arrives on ROS topics for rviz. ``transports`` (link id -> an open transport, one per
    URI) replaces the transports the URIs would open: a simulation's, a test's (the URIs then
    only name the links); the app closes them."""
    missing: list[str] = []
    cfg = topside_config(transport_uri, node_id=node_id, vehicle_id=vehicle_id, link=link, rate=rate,
                         schedule=schedule, modalities=modalities, remap_ids=remap_ids, store=store,
                         receiver_options=receiver_options, link_options=link_options, required=required,
                         ros=ros, missing=missing)
    cfg.command_key = command_key
    cfg.snapshot_interval = snapshot_interval
    return topside_app(cfg, host, port, clock=clock, transports=transports, stream_names=stream_names,
                       missing=missing, operators=operators, insecure_open=insecure_open, tls_cert=tls_cert,
                       tls_key=tls_key, session_hours=session_hours, idle_minutes=idle_minutes,
                       allowed_hosts=allowed_hosts, trusted_proxies=trusted_proxies,
                       public_origins=public_origins)


def topside_app(cfg: DeployConfig, host: str = "127.0.0.1", port: int = 8080, *,
                clock: Callable[[], float] = time.time, transports: Mapping[int, Any] | None = None,
                stream_names: Mapping[int, str] | None = None, missing: Sequence[str] = (),
                operators: str | Path | None = None, insecure_open: bool = False,
                tls_cert: str | None = None, tls_key: str | None = None,
                session_hours: float = 12.0, idle_minutes: float = 30.0,
                allowed_hosts: Sequence[str] = (), trusted_proxies: Sequence[str] = (),
                public_origins: Sequence[str] = ()) -> TopsideApp:
    """The topside a checked :class:`~coex_apps.vehicle.config.DeployConfig` describes (from
    a file, :func:`topside_from_config`, or the options, :func:`build_topside`): its transports
    (one per modem, or ``transports``), the node of ``build_node(cfg, "topside", ...)``, the
    store (``cfg.store``), the console served on ``host:port`` with the sign-in and TLS of the
    other arguments (see :func:`build_topside`), and the products on ROS (``cfg.ros``).
    ``missing``: modalities already left out, shown in the console's log."""
    access, tls = console_access(host, operators, insecure_open, tls_cert, tls_key, session_hours,
                                 idle_minutes)
    from .server import serve

    links: dict[int, Any] = {}
    build = _TopsideBuild(cfg, links, clock, stream_names, missing)
    try:
        _open_links(cfg, transports, links)
        node = build.restored()
        hub = build.hubs[-1]
        _announce(hub, build.left_out, build.nstore, cfg.store, clock)
        server = serve(hub, host, port, access=access, tls=tls, allowed_hosts=list(allowed_hosts),
                       trusted_proxies=list(trusted_proxies), public_origins=list(public_origins))
    except BaseException:
        for tr in links.values():
            tr.close()
        if build.nstore is not None:
            build.nstore.close()
        raise
    app = TopsideApp(node, links, hub, server, clock, store=build.nstore)
    _attach_feeds(app, cfg, node, hub, clock)
    return app


def _open_links(cfg: DeployConfig, transports: Mapping[int, Any] | None, links: dict[int, Any]) -> None:
    """Topside's links into ``links``: the ``transports`` given (one per modem), else one
    :class:`~coex.ResilientTransport` per modem (a modem that goes away, or is not there yet, is
    reopened while the console runs on)."""
    from coex import ResilientTransport

    if transports is not None:
        links.update(transports)  # closed with the rest on an error
        if sorted(transports) != cfg.link_ids():
            raise ConfigError(f"transports for links {sorted(transports)}, expected "
                              f"{cfg.link_ids()} (one per URI)")
        return
    for lid, m in zip(cfg.link_ids(), cfg.modems, strict=False):
        links[lid] = ResilientTransport(m.uri, name=f"link {lid}", required=m.required)


class _TopsideBuild:
    """Topside's node (``build_node``) and its console hub, fresh or restored from the store
    with the console saved with it (:meth:`restored`)."""

    def __init__(self, cfg: DeployConfig, links: dict[int, Any], clock: Callable[[], float],
                 stream_names: Mapping[int, str] | None, missing: Sequence[str]) -> None:
        self.cfg, self.links, self.clock, self.stream_names = cfg, links, clock, stream_names
        self.schedule = cfg.schedule()
        #: modalities left out (said in the log and in each console)
        self.left_out = list(missing)
        self.hubs: list[Any] = []
        self.nstore: Any = None

    def fresh(self) -> Any:
        from coex_apps.vehicle.build import build_node

        built: list[str] = []
        node = build_node(self.cfg, "topside", self.links, missing=built)
        for text in built:
            log.warning("%s", text)
        self.left_out.extend(built)
        return node

    def new_state(self, node: Any, vehicle: int) -> Any:
        from .state import ConsoleState

        names = {s.id: s.config.name for s in node.manager.streams}
        names.update(self.stream_names or {})
        state = ConsoleState(node_id=self.cfg.node_id, vehicle_id=vehicle, stream_names=names,
                             receivers=dict(node.receivers()))
        for lid in self.links:
            state.set_schedule(lid, self.schedule)
        return state

    def vehicle_hub(self, node: Any, state: Any) -> Any:
        """The console of one vehicle around ``node``: the node's receivers are what it shows
        (the saved console holds the same objects as the restored node: they were saved in one
        document)."""
        from .node import NodeCommands
        from .server import ConsoleHub
        from .state import MAX_IMAGES

        state.receivers = dict(node.receivers())
        state.own_receivers = False
        from coex_plugins.imagery.receiver import ImageryReceiver

        images = state.receivers.get("imagery")
        if isinstance(images, ImageryReceiver):  # the console keeps what the receiver keeps
            state.max_images = min(MAX_IMAGES, images.max_images)
        hub = ConsoleHub(state, NodeCommands(node, self.clock), self.clock)
        from coex_plugins.bathymetry import BathymetryReceiver

        rx = state.receivers.get("bathymetry")
        if isinstance(rx, BathymetryReceiver):
            hub.actions.map_receiver = state.region_source = rx
        return hub

    def wire(self, node: Any, extra: Any) -> None:
        """The console around ``node``: a fresh one, or the one saved with it (a fleet:
        one console state per vehicle, each with that vehicle's receivers)."""
        from .fleet import fleet_hub
        from .state import ConsoleState

        cfg = self.cfg
        if cfg.fleet:
            saved = extra.get("states") if isinstance(extra, dict) else None
            states = {v.id: saved.get(str(v.id)) for v in cfg.vehicles} if isinstance(saved, dict) else {}
            self.hubs.append(fleet_hub(node, {v.id: v.name for v in cfg.vehicles}, self.clock, states=states,
                                       stream_names=self.stream_names, schedule=self.schedule))
            return
        if isinstance(extra, dict) and isinstance(extra.get("state"), ConsoleState):
            state = extra["state"]
        else:
            state = self.new_state(node, cfg.peer)
        self.hubs.append(self.vehicle_hub(node, state))

    def restored(self) -> Any:
        """The node with its console: fresh without a store, else restored from it (its journal
        replayed) and checked against this run's links and node id."""
        for text in self.left_out:
            log.warning("%s", text)
        store = self.cfg.store
        if store is None:
            node = self.fresh()
            self.wire(node, None)
        else:
            from coex import NodeStore

            self.nstore = nstore = NodeStore(store, snapshot_interval=self.cfg.snapshot_interval)
            resumed = nstore.has_state()
            node = nstore.restore(self.fresh, log=None, clock=None, before_replay=self.wire)
            if sorted(node.manager.links) != sorted(self.links):
                raise ConfigError(
                    f"{store} holds a node with links {sorted(node.manager.links)}, this run has "
                    f"{sorted(self.links)}: give the same transports, or another --store")
            if node.node_id != self.cfg.node_id:
                raise ConfigError(f"{store} holds topside node {node.node_id}, not {self.cfg.node_id}")
            if resumed:
                log.info("resumed from %s (%d journal rows replayed)", store,
                         nstore.stats["replayed"])
        node.set_log(lambda text: log.info("%s", text))
        return node


def _announce(hub: Any, left_out: list[str], nstore: Any, store: Path | None, clock: Callable[[], float]) -> None:
    """What each console says first (the modalities left out, a resumed store) and what the store
    saves with the node (the console states)."""
    from .fleet import FleetHub

    states = list(hub.states().values()) if isinstance(hub, FleetHub) else [hub.state]
    for state in states:
        for text in left_out:
            state._log(0.0, text, "warn")
    if nstore is None:
        return
    if nstore.restored_extra is not None or nstore.stats["replayed"]:
        for state in states:
            state._log(clock(), f"resumed from {store}: {nstore.stats['replayed']} "
                                "journaled frames replayed")
    if isinstance(hub, FleetHub):
        fleet = hub
        nstore.extra = lambda: {"states": {str(v): st for v, st in fleet.states().items()}}
    else:
        nstore.extra = lambda: {"state": hub.state}


def _attach_feeds(app: TopsideApp, cfg: DeployConfig, node: Any, hub: Any, clock: Callable[[], float]) -> None:
    """The running topside's feeds: the ship's USBL (``cfg.usbl``), the watch on silent
    vehicles and the products on ROS (``cfg.ros``); on an error the app is closed."""
    if cfg.usbl is not None:
        from .usbl import UsblFeed

        try:
            app.usbl = UsblFeed(cfg, clock).attach(app._states())
            app.usbl.open()
        except BaseException:
            app.close()
            raise
    from coex import PeerWatch

    app.peer_watch = PeerWatch(node.manager, cfg.vehicle_ids())  # a vehicle not heard: said
    if cfg.ros is not None:
        from .ros import RosProducts

        try:
            app.ros = RosProducts(cfg.ros, lock=hub.lock, clock=clock).attach(node)
        except BaseException:
            app.close()
            raise


def topside_from_config(path: str, clock: Callable[[], float] = time.time, *,
                        transports: Mapping[int, Any] | None = None) -> TopsideApp:
    """The topside node, its modems and console as a configuration file describes them
    (``transports``: see :func:`build_topside`)."""
    from coex_apps.vehicle.config import load

    cfg = load(path, "topside")
    c = cfg.console
    host, _, port = str(c.get("http", "127.0.0.1:8080")).rpartition(":")

    def rel(k: str) -> str | None:
        return str(cfg.base_dir / c[k]) if c.get(k) else None

    names = {m.stream: m.name for m in cfg.modalities}
    names.update({int(k): str(v) for k, v in (c.get("stream_names") or {}).items()})
    return topside_app(
        cfg, host or "127.0.0.1", int(port), clock=clock, transports=transports, stream_names=names,
        operators=rel("operators"), insecure_open=bool(c.get("insecure_open", False)), tls_cert=rel("tls_cert"),
        tls_key=rel("tls_key"), session_hours=float(c.get("session_hours", 12.0)),
        idle_minutes=float(c.get("idle_minutes", 30.0)), allowed_hosts=[str(h) for h in c.get("allowed_hosts", [])],
        trusted_proxies=[str(h) for h in c.get("trusted_proxies", [])],
        public_origins=[str(h) for h in c.get("public_origins", [])])


def run(args: argparse.Namespace) -> int:
    if args.config:
        # before the app starts its threads: the ROS node's thread puts back the logging it found
        # after rospy's set-up, so configured later the log would keep the level of before (the
        # ROS master's loss, a warning, logged; its return, information, not)
        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s",
                            force=True)
        try:
            app = topside_from_config(args.config)
        except (CoexError, OSError) as exc:
            print(f"coex topside: {exc}", file=sys.stderr)
            return 2
        except Exception as exc:  # what no check foresaw: named, never a traceback
            print(f"coex topside: cannot start: {type(exc).__name__}: {exc}", file=sys.stderr)
            return 2
        from .fleet import FleetHub

        fleet = (", vehicles " + ", ".join(f"{n} ({v})" for v, n in app.hub.names.items())
                 if isinstance(app.hub, FleetHub) else "")
        print(f"CoEx console on {app.url} (topside node {app.node.node_id}{fleet}, from {args.config})", flush=True)
        return _serve(app)
    if not args.transport:
        print("coex topside: give --config FILE or at least one --transport URI", file=sys.stderr)
        return 2
    host, port = args.http
    try:
        missing: list[str] = []
        cfg = topside_config(
            args.transport, node_id=args.node_id, vehicle_id=args.vehicle_id, link=args.link, rate=args.rate,
            schedule=_schedule(args.schedule), slot=args.slot, guard=args.guard,
            modalities=tuple(m for m in args.modalities.split(",") if m), remap_ids=dict(args.remap_ids),
            store=args.store, command_key_file=args.command_key_file, missing=missing,
            link_options=None if args.packet_seconds is None else
            [{"packet_seconds": args.packet_seconds} for _ in args.transport])
        app = topside_app(
            cfg, host, port, stream_names=args.stream_names, missing=missing, operators=args.operators,
            insecure_open=args.insecure_open, tls_cert=args.tls_cert, tls_key=args.tls_key,
            session_hours=args.session_hours, idle_minutes=args.idle_minutes, allowed_hosts=args.allowed_host,
            trusted_proxies=args.trusted_proxy, public_origins=args.public_origin)
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

    from coex_runtime.runner import sigterm_as_interrupt

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
    file_help = "the operators file (default coex-operators.json; created with mode 0600)"
    p.add_argument("--file", default="coex-operators.json", help=file_help)
    # --file also after the action (coex operators add ana --role operator --file ops.json)
    here = argparse.ArgumentParser(add_help=False)
    here.add_argument("--file", default=argparse.SUPPRESS, help=file_help)
    sub = p.add_subparsers(dest="op", metavar="ACTION", required=True)
    a = sub.add_parser("add", parents=[here], help="add or replace an operator; prints a new random token "
                                                   "unless --password-stdin")
    a.add_argument("name")
    a.add_argument("--role", choices=["operator", "viewer"], required=True)
    a.add_argument("--password-stdin", action="store_true", help="read a password (12+ characters, "
                   "not a common one) from standard input instead of making a token")
    ro = sub.add_parser("role", parents=[here], help="change someone's role, keeping their password (a running console "
                                     "applies it at once)")
    ro.add_argument("name")
    ro.add_argument("--role", choices=["operator", "viewer"], required=True)
    r = sub.add_parser("remove", parents=[here], help="remove an operator (a running console ends their sessions at once)")
    r.add_argument("name")
    sub.add_parser("list", parents=[here], help="names and roles")
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

