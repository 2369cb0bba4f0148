"""The deployment configuration of ``coex vehicle`` and ``coex topside`` (one TOML file per
node; ``docs/deploy.md`` documents every key, ``examples/`` holds complete ones).

:func:`load` reads a file and checks **everything** before anything is opened: each problem is
one sentence that names its key (``modems[0].uri: no transport 'micromodm' (known: ...)``), and
:class:`~coex_core.errors.ConfigError` lists them all. ``coex config check FILE`` prints them.
"""

from __future__ import annotations

import os
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from coex import CoexError, ConfigError, Problems
from coex.options import flag

__all__ = ["DEFAULT_MODALITIES", "DeployConfig", "FleetVehicle", "ModalityConfig", "check", "check_mapping",
           "check_problems", "from_mapping", "load"]

ROLES = ("vehicle", "topside")
#: streams and priorities of the built-in modalities when the file names none (NUI 2022:
#: map subgrids and image fragments 30, time series a little less; survey reports high)
DEFAULT_MODALITIES: dict[str, tuple[int, int]] = {
    "bathymetry": (3, 30), "imagery": (4, 30), "timeseries": (5, 20), "survey": (7, 90),
}
#: stream and priority of a built-in modality a file names without them (detections: a few
#: bytes each, ahead of the other science streams; not run unless the file names it: what a
#: vehicle looks for is the mission's)
STREAM_DEFAULTS: dict[str, tuple[int, int]] = {**DEFAULT_MODALITIES, "detections": (8, 100)}
#: the NUI 2022 cycle: 6 slots, topside in slots 0 and 3
NUI_SLOTS = ("topside", "vehicle", "vehicle", "topside", "vehicle", "vehicle")
TOP_KEYS = {"node", "modems", "tdma", "modalities", "status", "inputs", "autonomy", "console", "ros",
            "vehicles", "usbl"}
#: a vehicle's name in a fleet topside's ``[[vehicles]]`` (it names the vehicle in TDMA slots
#: and in the console's ``vehicle`` argument)
_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_-]{0,31}")


@dataclass
class ModalityConfig:
    name: str
    stream: int
    priority: int
    options: dict[str, Any] = field(default_factory=dict)
    ids: dict[int, int] = field(default_factory=dict)
    #: the stream's priority on a low link (docs/channel.md; None: ``priority`` always)
    low_priority: int | None = None


@dataclass
class ModemConfig:
    uri: str
    rate: int = 5
    frame_bytes: int | None = None
    spare: float | None = None
    packet_seconds: float | None = None
    #: the daemon refuses to start without this modem (default: it waits for it, as for a
    #: modem that goes away during the dive)
    required: bool = False


@dataclass
class FleetVehicle:
    """One vehicle of a fleet topside's ``[[vehicles]]`` (a network of several nodes)."""

    id: int
    name: str
    #: the key this topside shares with this vehicle alone (``command_key_file``), or None: the
    #: node's ``command_key`` (the network key) signs its commands
    command_key: bytes | None = None
    command_key_file: Path | None = None
    #: the modalities this vehicle carries (``modalities = ["imagery", "survey"]``): the topside
    #: has receivers for these alone; None: every one of the file's ``[modalities]``
    modalities: tuple[str, ...] | None = None


@dataclass
class DeployConfig:
    """One node's deployment, checked (see :func:`load`)."""

    path: Path
    role: str
    node_id: int
    peer: int
    origin_lat: float = 0.0
    origin_lon: float = 0.0
    command_key: bytes | None = None
    command_key_file: Path | None = None
    #: vehicle of a fleet: the key it shares with its topside alone (``node.peer_key_file``;
    #: the topside's ``[[vehicles]]`` ``command_key_file`` for this vehicle), or None
    peer_key: bytes | None = None
    store: Path | None = None
    snapshot_interval: float = 30.0
    log_level: str = "info"
    modems: list[ModemConfig] = field(default_factory=list)
    #: ``"topside"``, ``"vehicle"`` (the one vehicle, or this vehicle), a vehicle's name from
    #: ``[[vehicles]]`` or a node id
    slots: tuple[str | int, ...] = NUI_SLOTS
    slot_seconds: float = 20.0
    guard: float = 2.0
    epoch: float = 0.0
    #: ``[tdma] queue_status``: this node sends its queue status (a ``QueueStatus``, about 3 B
    #: a stream) once a TDMA cycle; default true on a vehicle, false on a topside
    queue_status: bool | None = None
    modalities: list[ModalityConfig] = field(default_factory=list)
    status_interval: float = 10.0
    inputs: list[dict[str, Any]] = field(default_factory=list)
    autonomy: dict[str, Any] = field(default_factory=lambda: {"type": "log"})
    console: dict[str, Any] = field(default_factory=dict)
    #: topside: the ``[ros]`` table (received products on ROS topics), None without one
    ros: dict[str, Any] | None = None
    #: topside: the ``[usbl]`` table (the ship's USBL tracking system, issue 56), None without one
    usbl: dict[str, Any] | None = None
    #: what the daemon will meet but can live with (a device not plugged in yet, a file not
    #: written yet), each naming its key; ``coex config check`` prints them
    warnings: list[str] = field(default_factory=list)
    #: the link id of the first modem (the others follow it: +1, +2 ...); 0 from a file,
    #: ``coex topside --link`` on the command line
    first_link: int = 0
    #: a TDMA schedule given whole (a :class:`~coex_core.channel.schedule.Schedule`: ``coex
    #: topside --schedule JSON``, ``build_topside(schedule=...)``) in place of ``slots``; None
    #: from a file
    explicit_schedule: Any = None
    #: topside: the vehicles of a fleet (``[[vehicles]]``), empty for the one vehicle of
    #: ``node.peer``
    vehicles: list[FleetVehicle] = field(default_factory=list)

    @property
    def fleet(self) -> bool:
        """A topside of several vehicles (``[[vehicles]]``)."""
        return bool(self.vehicles)

    def carries(self, peer: int | None, modality: str) -> bool:
        """Whether the topside takes ``modality`` from vehicle ``peer`` (a fleet's
        ``[[vehicles]]`` ``modalities``; None, a vehicle without the list: every modality)."""
        for v in self.vehicles:
            if v.id == peer and v.modalities is not None:
                return modality in v.modalities
        return True

    def vehicle_ids(self) -> list[int]:
        """The ids of the vehicles this topside talks to (``[[vehicles]]``, else ``node.peer``)."""
        return [v.id for v in self.vehicles] if self.vehicles else [self.peer] if self.role == "topside" else []

    @property
    def base_dir(self) -> Path:
        return self.path.parent

    def owners(self) -> list[int]:
        """The TDMA slot owners as node ids (a vehicle's name: its ``[[vehicles]]`` id)."""
        vehicle, topside = ((self.node_id, self.peer) if self.role == "vehicle" else (self.peer, self.node_id))
        names = {v.name: v.id for v in self.vehicles}
        return [s if isinstance(s, int) else topside if s == "topside" else vehicle if s == "vehicle"
                else names[s] for s in self.slots]

    def link_ids(self) -> list[int]:
        """The link id of each modem, in order."""
        return [self.first_link + i for i in range(len(self.modems))]

    def schedule(self) -> Any:
        from coex import Schedule

        if self.explicit_schedule is not None:
            return self.explicit_schedule
        return Schedule.simple(self.owners(), self.slot_seconds, self.guard, epoch=self.epoch)

    def options(self, modality: ModalityConfig) -> dict[str, Any]:
        """A modality's options as its sender or receiver takes them: values that name files
        (``out_dir``) taken from the configuration's directory."""
        out = dict(modality.options)
        for k in ("out_dir",):
            if isinstance(out.get(k), str):
                out[k] = str(self.base_dir / out[k])
        return out


def _entry_points(group: str) -> dict[str, Any]:
    from coex.registry import entry_points

    return entry_points(group)


def load(path: str | Path, role: str | None = None) -> DeployConfig:
    """Read and check a node's configuration. :class:`ConfigError` lists every problem, each
    naming its key. ``role`` (``"vehicle"`` or ``"topside"``) must match the file's
    ``node.role`` when given."""
    cfg, p = _parse(Path(path), role)
    p.check(str(path))
    assert cfg is not None
    return cfg


def check(path: str | Path, role: str | None = None) -> tuple[DeployConfig | None, list[str]]:
    """``(config, problems)``: what ``coex config check`` prints."""
    cfg, p = _parse(Path(path), role)
    return cfg, p.items


_VAR = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?::-([^}]*))?\}")


def expand(text: str) -> str:
    """``${NAME}`` and ``${NAME:-default}`` replaced by the environment variable (or the
    default), before the TOML is read: one file serves several machines (device paths, ports).
    :class:`ConfigError` for an unset variable without a default."""
    def sub(m: re.Match[str]) -> str:
        value = os.environ.get(m.group(1), m.group(2))
        if value is None:
            raise ConfigError(f"${{{m.group(1)}}} is not set and has no default (write ${{{m.group(1)}:-...}})")
        return value

    return _VAR.sub(sub, text)


def _parse(path: Path, role: str | None) -> tuple[DeployConfig | None, Problems]:
    p = Problems()
    try:
        raw = tomllib.loads(expand(path.read_text()))
    except ConfigError as exc:
        p.add("", str(exc))
        return None, p
    except OSError as exc:
        p.add("", f"cannot read the file: {exc.strerror or exc}")
        return None, p
    except tomllib.TOMLDecodeError as exc:
        p.add("", f"not valid TOML: {exc}")
        return None, p
    return check_problems(raw, path, role)


def from_mapping(raw: Mapping[str, Any], path: str | Path, role: str | None = None) -> DeployConfig:
    """A configuration given as the mapping a TOML file would hold (another front end, such as a
    MOOS mission file's ``ProcessConfig`` block, builds it); ``path`` is where relative file
    names are taken from (its directory). :class:`ConfigError` lists every problem."""
    cfg, p = check_problems(raw, Path(path), role)
    p.check(str(path))
    assert cfg is not None
    return cfg


def check_mapping(raw: Mapping[str, Any], path: Path, role: str | None) -> tuple[DeployConfig | None, list[str]]:
    """``(config, problems)`` of a configuration mapping (see :func:`from_mapping`)."""
    cfg, p = check_problems(raw, path, role)
    return cfg, p.items


def check_problems(raw: Mapping[str, Any], path: Path, role: str | None) -> tuple[DeployConfig, Problems]:
    """The configuration a mapping describes and its :class:`~coex_core.config.Problems` (each
    with its key: a front end other than a file, like ``coex topside``'s options, names them its
    own way)."""
    p = Problems()
    p.unknown(raw, TOP_KEYS, "")
    node = p.table(raw.get("node"), "node")
    p.unknown(node, {"role", "id", "peer", "origin", "command_key_file", "peer_key_file", "store",
                     "snapshot_interval", "log_level"}, "node")
    cfg = _node(raw, node, p, path, role)
    infos = _modems(raw, p, cfg)
    _tdma(raw, p, cfg)
    _airtime(p, cfg, infos)
    _modalities(raw, p, cfg)
    _carried(p, cfg)
    if cfg.role == "vehicle":
        _vehicle_tables(raw, p, cfg)
    else:
        for k in ("inputs", "autonomy", "status"):
            if k in raw:
                p.add(k, "only a vehicle node has inputs, an autonomy and a status")
        _console(raw, p, cfg)
        _ros(raw, p, cfg)
        _usbl(raw, p, cfg)
    cfg.warnings = p.warnings
    return cfg, p


def _node(raw: Mapping[str, Any], node: dict[str, Any], p: Problems, path: Path, role: str | None) -> DeployConfig:
    """The ``[node]`` table (role, ids, origin, snapshots, log level, keys, store) and a fleet
    topside's ``[[vehicles]]``: the configuration they start."""
    # required, also when the caller knows the role (coex vehicle, coex topside): the daemon
    # refuses what coex config check refuses
    r = node.get("role")
    if r not in ROLES:
        p.add("node.role", f"'vehicle' or 'topside', got {r!r}" if r is not None else
              "missing: say whether this node is the 'vehicle' or the 'topside'")
        r = role or "vehicle"
    elif role is not None and r != role:
        p.add("node.role", f"this file configures the {r}, not the {role} (run coex {r} --config ...)")
    if "id" not in node:
        p.add("node.id", "missing: this node's id (1..15; topside is usually 1, the vehicle 2)")
    nid = p.number(node, "id", "node", 2 if r == "vehicle" else 1, lo=1, hi=15, integer=True)
    peer = p.number(node, "peer", "node", 1 if r == "vehicle" else 2, lo=1, hi=15, integer=True)
    if peer == nid:
        p.add("node.peer", f"the other node's id must differ from this node's ({nid})")
    cfg = DeployConfig(path=path.resolve(), role=r, node_id=nid, peer=peer)
    origin = p.table(node.get("origin"), "node.origin")
    p.unknown(origin, {"lat", "lon"}, "node.origin")
    cfg.origin_lat = float(p.number(origin, "lat", "node.origin", 0.0, lo=-90, hi=90))
    cfg.origin_lon = float(p.number(origin, "lon", "node.origin", 0.0, lo=-180, hi=180))
    if r == "topside" and "vehicles" in raw:
        _vehicles(raw, p, cfg, "peer" in node)
    elif "vehicles" in raw:
        p.add("vehicles", "only a topside lists vehicles (a vehicle names its topside in node.peer)")
    cfg.snapshot_interval = float(p.number(node, "snapshot_interval", "node", 30.0, lo=1, hi=3600))
    level = node.get("log_level", "info")
    if level not in ("debug", "info", "warning", "error"):
        p.add("node.log_level", f"debug, info, warning or error, got {level!r}")
    cfg.log_level = str(level)
    _node_keys(node, p, cfg)
    _store(node, p, cfg)
    return cfg


def _node_keys(node: Mapping[str, Any], p: Problems, cfg: DeployConfig) -> None:
    """``node.command_key_file`` (the network key) and a vehicle's ``node.peer_key_file``."""
    keyfile = node.get("command_key_file")
    if keyfile is not None:
        cfg.command_key, cfg.command_key_file = _key(p, cfg, keyfile, "node.command_key_file")
    if node.get("peer_key_file") is None:
        return
    if cfg.role != "vehicle":
        p.add("node.peer_key_file", "a topside gives each vehicle's own key in [[vehicles]] command_key_file")
    elif keyfile is None:
        p.add("node.peer_key_file", "a key shared with the topside alone needs the network key in "
                                    "node.command_key_file (broadcast commands are signed with it)")
    else:
        cfg.peer_key = _key(p, cfg, node["peer_key_file"], "node.peer_key_file")[0]


def _store(node: Mapping[str, Any], p: Problems, cfg: DeployConfig) -> None:
    """``node.store``: the node's SQLite store (default ``ROLE.sqlite``), or false: none."""
    r = cfg.role
    store = node.get("store", f"{r}.sqlite")
    if store is False:
        cfg.store = None
    elif isinstance(store, str) and store:
        cfg.store = cfg.base_dir / store
        from coex_runtime.store import check_store

        for err in check_store(cfg.store):  # what the daemon's store would refuse at start
            if err.kind == "full":  # the daemon starts, and writes its store once there is room
                p.warn("node.store", str(err))
            else:
                p.add("node.store", str(err))
    else:
        p.add("node.store", f"a file name (default {r}.sqlite) or false, got {store!r}")


def _vehicle_tables(raw: Mapping[str, Any], p: Problems, cfg: DeployConfig) -> None:
    """A vehicle's ``[status]``, ``[[inputs]]`` and ``[autonomy]``; the topside's tables refused."""
    status = p.table(raw.get("status"), "status")
    p.unknown(status, {"interval"}, "status")
    cfg.status_interval = float(p.number(status, "interval", "status", 10.0, lo=1, hi=3600))
    _inputs(raw, p, cfg)
    _autonomy(raw, p, cfg)
    for k in ("console",):
        if k in raw:
            p.add(k, "only a topside node has a console")
    if "ros" in raw:
        p.add("ros", "only a topside node publishes its products on ROS: a vehicle reads ROS with "
                     "[[inputs]] type = \"ros\" and flies surveys with [autonomy] type = \"ros\"")
    if "usbl" in raw:
        p.add("usbl", "only a topside node reads the ship's USBL (a vehicle takes position fixes through "
                      "its survey modality's aiding option, docs/navigation.md)")


def _modems(raw: Mapping[str, Any], p: Problems, cfg: DeployConfig) -> list[Any]:
    """``[[modems]]`` into ``cfg.modems``; returns what each URI said (its ``UriInfo``, None when
    it could not be checked), in order."""
    modems = raw.get("modems")
    infos: list[Any] = []
    if not isinstance(modems, list) or not modems:
        p.add("modems", "at least one [[modems]] table with a transport uri "
                        "(micromodem:///dev/ttyUSB0?rate=5, mavlink:udpout:host:port, lcm:udpm://...)")
        return infos
    known = _entry_points("coex.transports")
    for i, m in enumerate(modems):
        key = f"modems[{i}]"
        m = p.table(m, key)
        p.unknown(m, {"uri", "rate", "frame_bytes", "spare", "packet_seconds", "required"}, key)
        uri = m.get("uri")
        if not isinstance(uri, str) or not uri:
            p.add(f"{key}.uri", "missing: the transport URI")
            continue
        scheme = uri.split(":", 1)[0]
        info = None
        if scheme not in known:
            p.add(f"{key}.uri", f"no transport {scheme!r} (known: {', '.join(sorted(known))})")
        else:
            info = _check_uri(uri, f"{key}.uri", p, cfg)
            if info is not None:
                _addresses(info, f"{key}.uri", p, cfg)
        rate = p.number(m, "rate", key, None, lo=0, hi=6, integer=True)
        if info is not None and info.rate is not None:
            if rate is None:
                rate = info.rate  # the modem's rate, from its URI
            elif rate != info.rate:
                p.add(f"{key}.rate", f"{rate}, but the modem's URI says rate={info.rate}: give one rate "
                                     "(the channel plans its packets for this one)")
        fb = p.number(m, "frame_bytes", key, None, lo=16, hi=4096, integer=True)
        spare = p.number(m, "spare", key, None, lo=0, hi=1)
        packet = p.number(m, "packet_seconds", key, None, lo=0.001, hi=600)
        required = m.get("required", False)
        if not isinstance(required, bool):
            p.add(f"{key}.required", f"true or false, got {required!r}")
            required = False
        cfg.modems.append(ModemConfig(uri, 5 if rate is None else int(rate), fb, spare, packet, required))
        infos.append(info)
    return infos


def _addresses(info: Any, key: str, p: Problems, cfg: DeployConfig) -> None:
    """A modem that addresses its packets (``UriInfo.src``, ``dest``) must send as this node and
    to its peer (or to every node): anything else is a link that carries nothing."""
    peers = [v.id for v in cfg.vehicles] if cfg.fleet else [cfg.peer]
    if info.src is not None and info.src != cfg.node_id:
        given = f"src={info.src}" if "src=" in info.uri else f"src {info.src} (the default: the URI gives no src=)"
        p.add(key, f"the modem sends as {given}, but this node is {cfg.node_id} (node.id): its peer would "
                   f"take its packets for another node's; give src={cfg.node_id}")
    if info.dest is None:
        return
    if info.dest == cfg.node_id:
        p.add(key, f"dest={info.dest} is this node's own id: its packets would go to itself and reach nobody "
                   f"(give dest={peers[0] if len(peers) == 1 else 0}, or 0: every node)")
    elif cfg.fleet and info.dest != 0:
        p.add(key, f"dest={info.dest}: a topside of several vehicles sends to every node (dest=0), or the other "
                   "vehicles never hear it")
    elif info.dest not in (0, *peers):
        p.add(key, f"dest={info.dest} is neither the peer's id ({peers[0]}, node.peer) nor 0 (every node): the "
                   "peer's modem would not take its packets")


def _airtime(p: Problems, cfg: DeployConfig, infos: list[Any]) -> None:
    """Every TDMA slot of this link's nodes must hold a packet before its guard
    (``LinkConfig.packet_time``: ``packet_seconds``, else the airtime of a full packet at the
    modem's rate): in a shorter one nothing is ever sent, and the link carries nothing."""
    from coex import LinkConfig
    from coex_core.acoustic import rate_info

    if any(k.startswith("tdma") for k in p.keys()) or len(infos) != len(cfg.modems):
        return  # the schedule itself is wrong: said already
    try:
        schedule = cfg.schedule()
    except CoexError:
        return
    nodes = {cfg.node_id, cfg.peer, *(v.id for v in cfg.vehicles)}
    slots = [s for s in schedule.slots if s.owner in nodes]
    for i, (m, info) in enumerate(zip(cfg.modems, infos, strict=True)):
        try:
            ri = rate_info(m.rate)
            fb = m.frame_bytes or min(ri.frame_bytes, int(info.mtu) if info is not None else ri.frame_bytes)
            link = LinkConfig(i, schedule, rate=m.rate, frame_bytes=fb, packet_seconds=m.packet_seconds)
        except CoexError:
            continue  # the rate or the frame size is wrong: said already
        need = link.packet_time
        short = [s for s in slots if s.duration - s.guard < need]
        if not short:
            continue
        s = min(short, key=lambda s: s.duration - s.guard)
        how = (f"modems[{i}].packet_seconds" if m.packet_seconds is not None
               else f"the airtime of a full rate-{m.rate} packet")
        p.add("tdma.slot_seconds", f"a {s.duration:g} s slot less its {s.guard:g} s guard leaves "
                                   f"{s.duration - s.guard:g} s, shorter than a packet on modems[{i}] ({need:.2f} s, "
                                   f"{how}): nothing would ever be sent in it. Make the slots longer, or, on a "
                                   f"link without airtime (LCM, MAVLink, MOOS, a simulation), set "
                                   f"modems[{i}].packet_seconds to the time a packet takes (coex topside: "
                                   f"--packet-seconds; docs/deploy.md)")


def _check_uri(uri: str, key: str, p: Problems, cfg: DeployConfig) -> Any:
    """A transport URI through the transport's own parser (``Transport.check_uri``), opening
    nothing, exactly as the daemon's links take it; devices and files it names that are not
    there now are warnings (the daemon waits for a modem)."""
    from coex import check_transport_uri

    try:
        info = check_transport_uri(uri)
    except ConfigError as exc:
        p.add(key, str(exc))
        return None
    except CoexError as exc:  # not installed (PluginLoadError names the extra)
        p.add(key, str(exc))
        return None
    if info is None:
        p.warn(key, f"the {uri.split(':', 1)[0]} transport cannot check its URI without opening it: "
                    "the daemon will open it at start")
        return None
    for path in info.paths:  # opened as given (a device path), like the transport will
        p.path(key, path, "the node waits for the modem")
    return info


def _vehicles(raw: Mapping[str, Any], p: Problems, cfg: DeployConfig, peer_given: bool) -> None:
    """A fleet topside's ``[[vehicles]]``: ``id``, ``name``, ``command_key_file``."""
    vs = raw.get("vehicles")
    if not isinstance(vs, list) or not vs:
        p.add("vehicles", "a list of [[vehicles]] tables, each with an id and a name")
        return
    if peer_given:
        p.add("node.peer", "give the vehicles in [[vehicles]] or the one vehicle in node.peer, not both")
    ids: dict[int, str] = {}
    names: set[str] = set()
    for i, v in enumerate(vs):
        key = f"vehicles[{i}]"
        v = p.table(v, key)
        p.unknown(v, {"id", "name", "command_key_file", "modalities"}, key)
        if "id" not in v:
            p.add(f"{key}.id", "missing: the vehicle's node id (1..15)")
            continue
        vid = p.number(v, "id", key, None, lo=1, hi=15, integer=True)
        if vid is None:
            continue
        vid = int(vid)
        name = v.get("name", f"vehicle{vid}")
        if not isinstance(name, str) or not _NAME.fullmatch(name) or name in ("topside", "vehicle"):
            p.add(f"{key}.name", "a name of 1 to 32 letters, digits, '-' or '_' starting with a letter "
                                 f"(not 'topside' or 'vehicle'), got {name!r}")
            name = f"vehicle{vid}"
        if vid == cfg.node_id:
            p.add(f"{key}.id", f"{vid} is this topside's own id (node.id)")
        elif vid in ids:
            p.add(f"{key}.id", f"{vid} is already {ids[vid]}'s id")
        if name in names:
            p.add(f"{key}.name", f"{name!r} names another vehicle already")
        ids[vid] = name
        names.add(name)
        fv = FleetVehicle(vid, name)
        mods = v.get("modalities")
        if mods is not None:
            if not isinstance(mods, list) or not mods or not all(isinstance(m, str) for m in mods):
                p.add(f"{key}.modalities", f"a list of the modalities this vehicle carries, got {mods!r}")
            else:
                fv.modalities = tuple(mods)
        keyfile = v.get("command_key_file")
        if keyfile is not None:
            fv.command_key, fv.command_key_file = _key(p, cfg, keyfile, f"{key}.command_key_file")
            if "command_key_file" not in p.table(raw.get("node"), "node"):
                p.add(f"{key}.command_key_file", "a vehicle's own key needs the network key in "
                                                 "node.command_key_file (it signs commands to every vehicle)")
        cfg.vehicles.append(fv)
    if cfg.vehicles:
        cfg.peer = cfg.vehicles[0].id


def _key(p: Problems, cfg: DeployConfig, keyfile: Any, key: str) -> tuple[bytes | None, Path | None]:
    """A command key file's key (a problem under ``key`` if it cannot be read)."""
    from coex_core.auth import parse_key

    kp = cfg.base_dir / str(keyfile)
    try:
        key_bytes = parse_key(kp.read_bytes())
        if os.name == "posix" and kp.stat().st_mode & 0o077:  # warned, not refused: git keeps no modes
            p.warn(key, f"{kp} can be read by other users (mode {kp.stat().st_mode & 0o777:04o}): "
                        f"chmod 600 {kp}")
        return key_bytes, kp
    except OSError as exc:
        p.add(key, f"cannot read {kp}: {exc.strerror or exc}")
    except (CoexError, ValueError) as exc:
        p.add(key, str(exc))
    return None, None


#: ``[tdma] queue_status`` (the one declaration of the key)
QUEUE_STATUS = flag(None, "send this node's queue status once a TDMA cycle (default: true on a "
                                  "vehicle, false on a topside)")


def _tdma(raw: Mapping[str, Any], p: Problems, cfg: DeployConfig) -> None:
    t = p.table(raw.get("tdma"), "tdma")
    p.unknown(t, {"slots", "slot_seconds", "guard", "epoch", "queue_status"}, "tdma")
    slots = t.get("slots", list(NUI_SLOTS))
    names = {v.name: v.id for v in cfg.vehicles}
    if (not isinstance(slots, list) or not slots or len(slots) > 32
            or any(not (s in ("topside", "vehicle") or s in names
                        or (isinstance(s, int) and not isinstance(s, bool) and 1 <= s <= 15)) for s in slots)):
        what = "'topside', a vehicle's name or id" if cfg.fleet else "'topside' / 'vehicle' entries or node ids"
        p.add("tdma.slots", f"a list of 1 to 32 {what}, got {slots!r}")
    elif cfg.fleet:
        if "vehicle" in slots:
            p.add("tdma.slots", "with several [[vehicles]], name each slot's vehicle (its name or id), "
                                "not 'vehicle'")
            return
        cfg.slots = tuple(slots)
        owners = set(cfg.owners())
        for s in slots:
            if isinstance(s, int) and s not in names.values() and s != cfg.node_id:
                p.add("tdma.slots", f"node {s} is neither this topside nor one of the [[vehicles]]")
        if cfg.node_id not in owners:
            p.add("tdma.slots", "the topside needs at least one slot")
        silent = [v.name for v in cfg.vehicles if v.id not in owners]
        if silent:
            p.add("tdma.slots", f"every vehicle needs at least one slot: {', '.join(silent)} has none")
    else:
        cfg.slots = tuple(slots)
        owners = set(cfg.owners())
        topside, vehicle = ((cfg.peer, cfg.node_id) if cfg.role == "vehicle" else (cfg.node_id, cfg.peer))
        if topside not in owners or vehicle not in owners:
            p.add("tdma.slots", "both the topside and the vehicle need at least one slot")
        others = sorted(owners - {topside, vehicle})
        if others and cfg.role == "topside":
            p.add("tdma.slots", f"node {', '.join(map(str, others))} is neither this topside nor its vehicle "
                                "(node.peer): list a fleet's vehicles in [[vehicles]]")
    cfg.slot_seconds = float(p.number(t, "slot_seconds", "tdma", 20.0, lo=0.5, hi=600))
    cfg.guard = float(p.number(t, "guard", "tdma", 2.0, lo=0, hi=25.5))
    if cfg.guard >= cfg.slot_seconds:
        p.add("tdma.guard", f"the guard ({cfg.guard:g} s) must be shorter than a slot ({cfg.slot_seconds:g} s)")
    cfg.epoch = float(p.number(t, "epoch", "tdma", 0.0))
    if "queue_status" in t:
        cfg.queue_status = QUEUE_STATUS.checked(p, "tdma.queue_status", t["queue_status"])


def _modalities(raw: Mapping[str, Any], p: Problems, cfg: DeployConfig) -> None:
    known = _entry_points("coex.modalities")
    table = p.table(raw.get("modalities"), "modalities")
    if "modalities" not in raw:
        table = {name: {} for name in DEFAULT_MODALITIES if name in known}
    streams: dict[int, str] = {}
    for name, m in table.items():
        key = f"modalities.{name}"
        m = p.table(m, key)
        p.unknown(m, {"stream", "priority", "low_priority", "options", "ids", "enabled"}, key)
        if m.get("enabled", True) is False:
            continue
        if name not in known:
            p.add(key, f"no modality {name!r} installed (known: {', '.join(sorted(known))})")
            continue
        d_stream, d_prio = STREAM_DEFAULTS.get(name, (None, 30))
        stream = p.number(m, "stream", key, d_stream, lo=1, hi=31, integer=True)
        if stream is None:
            p.add(f"{key}.stream", "missing: the stream (queue) id of this modality, 1..31")
            continue
        if stream in streams:
            p.add(f"{key}.stream", f"stream {stream} is already {streams[stream]}'s")
        streams[stream] = name
        prio = p.number(m, "priority", key, d_prio, lo=0, hi=127, integer=True)
        low = p.number(m, "low_priority", key, None, lo=0, hi=127, integer=True) if "low_priority" in m else None
        options = p.table(m.get("options"), f"{key}.options")
        ids: dict[int, int] = {}
        for own, wire_id in p.table(m.get("ids"), f"{key}.ids").items():
            try:
                ids[int(own)] = int(wire_id)
            except (TypeError, ValueError):
                p.add(f"{key}.ids.{own}", f"type ids are integers, got {own!r} = {wire_id!r}")
        mc = ModalityConfig(name, int(stream), int(prio), options, ids, None if low is None else int(low))
        # the modality checks its own options with their declared schema (merged_config), each
        # problem keyed by its option: modalities.bathymetry.options.send_delay
        try:
            cls = known[name].load()
            side = cls().sender if cfg.role == "vehicle" else cls().receiver
            side(cfg.options(mc) or None)
        except ConfigError as exc:
            if exc.problems:
                p.nest(f"{key}.options", exc.problems)
            else:
                p.add(f"{key}.options", str(exc))
        except ImportError as exc:
            p.add(key, f"cannot load the {name} plugin: {exc} (install its extra: pip install "
                       f"'coexploration[{name}]')")
        except (CoexError, TypeError, ValueError) as exc:
            p.add(f"{key}.options", f"{type(exc).__name__}: {exc}")
        cfg.modalities.append(mc)


def _carried(p: Problems, cfg: DeployConfig) -> None:
    """A fleet vehicle's ``modalities`` name modalities of this topside."""
    running = [m.name for m in cfg.modalities]
    for i, v in enumerate(cfg.vehicles):
        for name in v.modalities or ():
            if name not in running:
                p.add(f"vehicles[{i}].modalities", f"{name!r} is not one of this topside's modalities "
                                                   f"({', '.join(running) or 'none'})")


def _adapter(kind: str, group: str, table: Mapping[str, Any], key: str, p: Problems) -> Any:
    known = _entry_points(group)
    t = table.get("type")
    if t not in known:
        p.add(f"{key}.type", f"{'missing' if t is None else repr(t) + ' is not installed'} "
                             f"(known {kind}s: {', '.join(sorted(known))})")
        return None
    try:
        return known[t].load()
    except ImportError as exc:
        p.add(f"{key}.type", f"cannot load {kind} {t!r}: {exc}")
        return None


def _inputs(raw: Mapping[str, Any], p: Problems, cfg: DeployConfig) -> None:
    from coex import FEEDS, adapter_check

    inputs = raw.get("inputs", [])
    if not isinstance(inputs, list):
        p.add("inputs", "a list of [[inputs]] tables")
        return
    running = {m.name for m in cfg.modalities}
    for i, t in enumerate(inputs):
        key = f"inputs[{i}]"
        t = p.table(t, key)
        cls = _adapter("input", "coex.inputs", t, key, p)
        if cls is None:
            continue
        feeds = t.get("feeds", list(cls.feeds))
        if not isinstance(feeds, list) or any(f not in cls.feeds for f in feeds):
            p.add(f"{key}.feeds", f"a list of what {t['type']} can feed ({', '.join(cls.feeds)}), got {feeds!r}")
        else:
            for f in feeds:
                if f in FEEDS and f != "status" and f not in running:
                    p.add(f"{key}.feeds", f"feeds {f}, but the {f} modality does not run on this node")
        options = {k: v for k, v in t.items() if k not in ("type", "feeds")}
        problems = adapter_check(cls, options)
        p.nest(key, problems)
        if not problems:
            _paths(cls, options, key, p, cfg)
        cfg.inputs.append(dict(t))


def _paths(cls: Any, options: Mapping[str, Any], key: str, p: Problems, cfg: DeployConfig) -> None:
    """Warnings for the files, folders and devices an adapter declares (``Adapter.paths``) that
    are not there now."""
    for option, path, kind in cls.paths(options):
        where = Path(path).expanduser()
        if kind != "device" and not where.is_absolute():
            where = cfg.base_dir / where
        p.path(f"{key}.{option}", where, f"the {cls.kind} {cls.name!r} waits for it" if kind != "folder" else
               f"the {cls.kind} {cls.name!r} watches it", folder=kind == "folder")


def _autonomy(raw: Mapping[str, Any], p: Problems, cfg: DeployConfig) -> None:
    from coex import adapter_check

    if "autonomy" not in raw and "survey" not in {m.name for m in cfg.modalities}:
        cfg.autonomy = {}
        return  # no survey commands: nothing to fly them
    t = p.table(raw.get("autonomy", {"type": "log"}), "autonomy")
    t.setdefault("type", "log")
    cls = _adapter("autonomy output", "coex.autonomy", t, "autonomy", p)
    if cls is None:
        return
    options = {k: v for k, v in t.items() if k != "type"}
    problems = adapter_check(cls, options)
    p.nest("autonomy", problems)
    if not problems:
        _paths(cls, options, "autonomy", p, cfg)
    cfg.autonomy = dict(t)
    if "survey" not in {m.name for m in cfg.modalities}:
        p.add("autonomy", "an autonomy output needs the survey modality ([modalities.survey])")


def _ros(raw: Mapping[str, Any], p: Problems, cfg: DeployConfig) -> None:
    """Topside: the ``[ros]`` table (``coex_apps.console.ros.RosProducts``)."""
    if "ros" not in raw:
        return
    from coex_apps.console.ros import RosProducts

    t = p.table(raw.get("ros"), "ros")
    p.merge(RosProducts.check(t))
    cfg.ros = t


def _usbl(raw: Mapping[str, Any], p: Problems, cfg: DeployConfig) -> None:
    """Topside: the ``[usbl]`` table, the ship's USBL tracking system
    (:class:`coex_plugins.navigation.UsblInput` options, and ``apply``)."""
    if "usbl" not in raw:
        return
    from coex import adapter_check

    try:
        from coex_plugins.navigation import UsblInput
    except ImportError as exc:
        p.add("usbl", f"the USBL input cannot load: {exc} (pip install 'coexploration[navigation]')")
        return
    t = p.table(raw.get("usbl"), "usbl")
    options = {k: v for k, v in t.items() if k != "apply"}
    if not isinstance(t.get("apply", True), bool):
        p.add("usbl.apply", f"true or false (apply the drift correction topside), got {t.get('apply')!r}")
    problems = adapter_check(UsblInput, options)
    p.nest("usbl", problems)
    if not problems:
        _paths(UsblInput, options, "usbl", p, cfg)
    cfg.usbl = dict(t)


def _console(raw: Mapping[str, Any], p: Problems, cfg: DeployConfig) -> None:
    c = p.table(raw.get("console"), "console")
    p.unknown(c, {"http", "operators", "insecure_open", "tls_cert", "tls_key", "session_hours",
                  "idle_minutes", "allowed_hosts", "trusted_proxies", "public_origins", "stream_names"}, "console")
    http = c.get("http", "127.0.0.1:8080")
    _host, sep, port = str(http).rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535:
        p.add("console.http", f"HOST:PORT, got {http!r}")
    for k in ("operators", "tls_cert", "tls_key"):
        if k in c:
            if not isinstance(c[k], str):
                p.add(f"console.{k}", f"a file name, got {c[k]!r}")
            elif not (cfg.base_dir / c[k]).exists():
                p.add(f"console.{k}", f"no file {cfg.base_dir / c[k]}")
            elif k != "tls_cert":  # secrets other users may read are refused (docs/console.md)
                from coex_apps.console.access import secret_file_problem

                problem = secret_file_problem(cfg.base_dir / c[k], "operators file" if k == "operators" else "TLS key")
                if problem:
                    p.add(f"console.{k}", problem)
    if not isinstance(c.get("insecure_open", False), bool):
        p.add("console.insecure_open", "true or false")
    p.number(c, "session_hours", "console", 12.0, lo=0.01, hi=24 * 365)
    p.number(c, "idle_minutes", "console", 30.0, lo=0.1, hi=24 * 60 * 365)
    for k in ("allowed_hosts", "trusted_proxies", "public_origins"):
        v = c.get(k, [])
        if not isinstance(v, list) or not all(isinstance(h, str) and h for h in v):
            p.add(f"console.{k}", f"a list of names or addresses, got {v!r}")
        elif k == "public_origins":
            from urllib.parse import urlsplit

            for h in v:
                parts = urlsplit(h)
                if parts.scheme not in ("http", "https") or not parts.hostname or parts.path not in ("", "/"):
                    p.add("console.public_origins", f"an origin is scheme://host[:port] (http or https), got {h!r}")
    cfg.console = c
