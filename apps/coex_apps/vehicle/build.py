"""A node built from its checked configuration: the one place a :class:`DeployConfig` becomes
a :class:`~coex_core.node.Node` (its links, and its modalities' senders or receivers), for the
vehicle daemon (``coex vehicle``) and the topside console (``coex topside``, from a file or its
command-line options) alike."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from coex import CoexError, ConfigError

from .config import ROLES, DeployConfig

__all__ = ["build_node", "link_configs"]


def link_configs(cfg: DeployConfig, transports: Mapping[int, Any]) -> list[Any]:
    """One :class:`~coex_core.channel.manager.LinkConfig` per open transport (link id -> a
    transport; link ``cfg.first_link + i`` is ``cfg.modems[i]``): the modem's rate, its frames
    (``frame_bytes``, else the rate's frame capped at the transport's MTU), ``spare`` and
    ``packet_seconds`` when given, the configuration's schedule, sent to the peer (a topside of
    several vehicles: to every node, ``dst`` 0, each message and command then naming its
    vehicle; a Micromodem topside in a fleet needs ``dest=0``, docs/micromodem.md)."""
    from coex import LinkConfig
    from coex_core.acoustic import rate_info

    schedule = cfg.schedule()
    out = []
    for lid, tr in transports.items():
        m = cfg.modems[lid - cfg.first_link]
        fb = m.frame_bytes or min(rate_info(m.rate).frame_bytes, int(tr.mtu))
        kw: dict[str, Any] = {} if m.spare is None else {"spare": m.spare}
        if m.packet_seconds is not None:
            kw["packet_seconds"] = m.packet_seconds
        dst = 0 if len(cfg.vehicles) > 1 else cfg.peer
        out.append(LinkConfig(lid, schedule, rate=m.rate, frame_bytes=fb, dst=dst, **kw))
    return out


def build_node(cfg: DeployConfig, role: str, transports: Mapping[int, Any], *,
               missing: list[str] | None = None) -> Any:
    """The node ``cfg`` describes for ``role`` (``"vehicle"`` or ``"topside"``, the
    configuration's own) over ``transports`` (:func:`link_configs`), with the command key.

    A vehicle gets one sender per modality on its stream and priority (with the file's options
    and id remapping) and sends its queue status once a TDMA cycle (``[tdma] queue_status``: a
    topside too when true); a modality that cannot be
    made is an error. A topside gets one receiver per modality (options, id remapping); one that
    cannot be made (a plugin not installed, an extra missing) is left out and said in
    ``missing`` (``"modality NAME not available: why"``), the console runs on without it. A
    topside of several vehicles (``[[vehicles]]``) gets one receiver per modality and vehicle
    (``add_receiver(..., peer=id)``, saved under ``name@id``; a vehicle's ``modalities``, when
    given, only for those) and the vehicles' own command
    keys (``peer_keys``); a vehicle with ``node.peer_key_file`` holds its key the same way."""
    from coex import ChannelManager, Node, StreamConfig, load_modality

    if role not in ROLES or role != cfg.role:
        raise ConfigError(f"this configuration is the {cfg.role}'s, not the {role}'s")
    kw: dict[str, Any] = {}
    if cfg.queue_status if cfg.queue_status is not None else role == "vehicle":
        kw["queue_status_interval"] = cfg.slot_seconds * len(cfg.slots)
    keys = {v.id: v.command_key for v in cfg.vehicles if v.command_key is not None}
    if cfg.peer_key is not None:  # a vehicle's key shared with its topside alone
        keys = {cfg.peer: cfg.peer_key}
    if keys:
        kw["peer_keys"] = keys
    node = Node(ChannelManager(cfg.node_id, link_configs(cfg, transports), command_key=cfg.command_key, **kw))
    peers: list[int | None] = [v.id for v in cfg.vehicles] if cfg.fleet else [None]
    for m in cfg.modalities:
        if role == "vehicle":
            cls = load_modality(m.name)
            opts = cfg.options(m)
            if m.name == "bathymetry":  # the map's metadata names the local grid's origin: node.origin
                opts.setdefault("origin_lat", cfg.origin_lat)
                opts.setdefault("origin_lon", cfg.origin_lon)
            sender = cls().sender(opts or None)
            node.add_sender(cls, sender, StreamConfig(m.stream, m.name, priority=m.priority,
                                                      low_priority=m.low_priority), ids=m.ids or None)
            continue
        mine = [peer for peer in peers if cfg.carries(peer, m.name)]
        try:
            cls = load_modality(m.name)
            receivers = [cls().receiver(_peer_options(cfg, m, peer) or None) for peer in mine]
        except (CoexError, ImportError, AttributeError, TypeError) as exc:
            if missing is not None:
                missing.append(f"modality {m.name} not available: {exc}")
            continue
        for peer, receiver in zip(mine, receivers, strict=True):
            node.add_receiver(cls, receiver, ids=m.ids or None, peer=peer)
    return node


def _peer_options(cfg: DeployConfig, m: Any, peer: int | None) -> dict[str, Any]:
    """A receiver's options; in a fleet where several vehicles carry the modality, files it
    writes (``out_dir``) go to a folder per vehicle (``out_dir/NAME``)."""
    out = cfg.options(m)
    several = sum(cfg.carries(v.id, m.name) for v in cfg.vehicles) > 1
    if peer is not None and several and isinstance(out.get("out_dir"), str):
        name = {v.id: v.name for v in cfg.vehicles}[peer]
        out["out_dir"] = str(Path(out["out_dir"]) / name)
    return out
