"""The dive's nodes as deployment configurations: each node of the demo is described by the
mapping a ``coex vehicle`` / ``coex topside`` TOML file would hold (``docs/deploy.md``), checked
by the checker of ``coex config check`` (:func:`~coex_apps.vehicle.config.from_mapping`) and
built by the one :func:`~coex_apps.vehicle.build.build_node` the daemons use. The streams and
priorities of the modalities are the deployment's defaults
(:data:`~coex_apps.vehicle.config.STREAM_DEFAULTS`); the demo gives only what is its own: the
modalities' options, the images' priority on a low link, the scenario's TDMA cycle and modem.

Each node's modem is a ``micromodem:`` URI whose device is only a name: the demo opens it on its
simulated network (:meth:`~coex_transports.micromodem.simnetwork.ModemNetwork.open_uri`), so
the URI's ``src``, ``dest`` and ``rate`` are the modem's settings, as on a vehicle.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from coex import Node
from coex_apps.vehicle.build import build_node
from coex_apps.vehicle.config import DeployConfig, from_mapping

from .config import CAMERA, DEFAULT_LAYERS, EPOCH, LAYER_PSNR, TOPSIDE, VEHICLE
from .scenario import Scenario

__all__ = ["FLEET_NAMES", "build", "modem_uri", "node_mapping", "receiver_modalities", "sender_modalities"]

#: the images' priority on a low link (docs/channel.md): the answers to the operator's
#: requests go before the map's coarse coverage
IMAGES_LOW_PRIORITY = 90


def modem_uri(node: int, dest: int, rate: int) -> str:
    """The ``micromodem:`` URI of ``node``'s simulated modem (its device is only a name)."""
    return f"micromodem:///dev/coex-demo-modem{node}?src={node}&dest={dest}&rate={rate}"


def sender_modalities(names: Sequence[str], channels: list[dict[str, Any]], geofence: Mapping[str, Any],
                      confirm_layers: int) -> dict[str, dict[str, Any]]:
    """A vehicle's ``[modalities]`` table for the modalities ``names`` (in that order): the
    map's send delay, the images' quality marks and goals (``confirm_layers``: the goal of an
    image the operator asks for), the sensor channels, the survey's geofence and the vehicle's
    relief detector (car-sized anomalies of its full-resolution map score highest)."""
    table: dict[str, dict[str, Any]] = {
        "bathymetry": {"options": {"send_delay": 20.0}},
        "imagery": {"low_priority": IMAGES_LOW_PRIORITY,
                    "options": {"layer_psnr": list(LAYER_PSNR), "default_goal": f"layer:{DEFAULT_LAYERS}",
                                "request_goal": f"layer:{confirm_layers}"}},
        "timeseries": {"options": {"channels": channels}},
        "survey": {"options": {"geofence": dict(geofence)}},
        "detections": {"options": {"detectors": [{"type": "relief"}]}},
    }
    return {name: table[name] for name in names}


def receiver_modalities(out: Path, auto_fill: bool,
                        names: Sequence[str] = ("bathymetry", "imagery", "timeseries", "survey", "detections"),
                        ) -> dict[str, dict[str, Any]]:
    """Topside's ``[modalities]`` table for ``names`` (in that order): the map
    (``auto_fill=False`` when the scripted operator asks for the map's holes itself), the
    images (written to ``out/images``), the time series, the survey's answers and the
    detections."""
    table: dict[str, dict[str, Any]] = {
        "bathymetry": {"options": {"auto_fill": auto_fill}},
        "imagery": {"options": {"out_dir": str(out / "images")}},
        "timeseries": {}, "survey": {}, "detections": {}}
    return {name: table[name] for name in names}


#: the names of a fleet's vehicles in topside's ``[[vehicles]]``
FLEET_NAMES = {VEHICLE: "mapper", CAMERA: "camera"}


def _slots(scn: Scenario, role: str, node_id: int) -> list[str | int]:
    """The scenario's TDMA slots as ``tdma.slots`` names them for this node: ``"topside"``,
    ``"vehicle"`` (a vehicle's own slots; topside's one vehicle), a fleet topside's vehicles by
    name and, in a vehicle's file, another vehicle by its id."""
    ids = {"topside": TOPSIDE, "vehicle": VEHICLE, "camera": CAMERA}
    out: list[str | int] = []
    for s in scn.slots:
        owner = ids[s]
        if owner == TOPSIDE:
            out.append("topside")
        elif role == "topside" and scn.fleet:
            out.append(FLEET_NAMES[owner])
        elif role == "topside" or owner == node_id:
            out.append("vehicle")
        else:
            out.append(owner)
    return out


def node_mapping(scn: Scenario, role: str, node_id: int, peer: int, modalities: Mapping[str, Any], *,
                 spare: float | None = None, vehicles: Mapping[int, Sequence[str]] | None = None) -> dict[str, Any]:
    """The deployment configuration of one node of the dive, as the mapping of a TOML file:
    no store (the dive keeps nothing), its simulated modem (its packets go to ``peer``;
    ``spare``: the share of a packet spare traffic may fill) and the scenario's TDMA cycle.
    ``vehicles`` (a fleet's topside): each vehicle's id and the modalities it carries, listed
    in ``[[vehicles]]`` (named :data:`FLEET_NAMES`); its modem then sends to every node."""
    modem: dict[str, Any] = {"uri": modem_uri(node_id, 0 if vehicles else peer, scn.modem_rate)}
    if spare is not None:
        modem["spare"] = spare
    raw: dict[str, Any] = {
        "node": {"role": role, "id": node_id, "store": False},
        "modems": [modem],
        "tdma": {"slots": _slots(scn, role, node_id), "slot_seconds": scn.slot_seconds,
                 "guard": scn.guard_seconds, "epoch": EPOCH,
                 # the demo's topside reports its own queues once a cycle too (it always has: the
                 # dives measured for issue 50 were run so; a few uplink bytes a cycle change what
                 # each packet carries, docs/demo.md "The code")
                 "queue_status": True},
        "modalities": dict(modalities),
    }
    if vehicles:
        raw["vehicles"] = [{"id": vid, "name": FLEET_NAMES[vid], "modalities": list(names)}
                           for vid, names in vehicles.items()]
    else:
        raw["node"]["peer"] = peer
    return raw


def build(raw: Mapping[str, Any], out: Path, network: Any, command_key: bytes | None) -> tuple[Node, Any]:
    """The node ``raw`` describes, checked as ``coex config check`` checks a file (a problem is a
    :class:`~coex_core.errors.ConfigError` naming its key) and built by ``build_node`` over its
    modem opened on the simulated ``network``; ``command_key`` is the key a file would give in
    ``node.command_key_file``. Returns the node and its modem."""
    role = str(raw["node"]["role"])
    cfg: DeployConfig = from_mapping(raw, out / f"{role}{raw['node']['id']}.toml", role)
    cfg = dataclasses.replace(cfg, command_key=command_key)
    transports = {lid: network.open_uri(m.uri) for lid, m in zip(cfg.link_ids(), cfg.modems, strict=True)}
    node: Node = build_node(cfg, role, transports)
    return node, transports[cfg.first_link]
