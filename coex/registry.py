"""Plugins found by name: the entry-point groups (``coex.modalities``, ``coex.transports`` ...),
``load_modality`` / ``load_transport`` / ``load_detector`` / ``load(group, name)``,
``entry_points(group)`` and ``open_transport(uri)``.

The public face of :mod:`coex_core.registry` (``from coex.registry import ...``): a module of its own, so
that a plugin author's type checker finds it; the names are the core's (the same objects).
"""

from __future__ import annotations

from coex_core.registry import (
    CHECKER_GROUP,
    COMMAND_GROUP,
    MODALITY_GROUP,
    TRANSPORT_GROUP,
    PluginInfo,
    available,
    check_transport_uri,
    entry_points,
    load,
    load_detector,
    load_modality,
    load_transport,
    names,
    open_transport,
    transport_scheme,
)

__all__ = [
    "CHECKER_GROUP",
    "COMMAND_GROUP",
    "MODALITY_GROUP",
    "PluginInfo",
    "TRANSPORT_GROUP",
    "available",
    "check_transport_uri",
    "entry_points",
    "load",
    "load_detector",
    "load_modality",
    "load_transport",
    "names",
    "open_transport",
    "transport_scheme",
]
