"""The plugin registry: modalities and transports found through entry points.

Groups: ``coex.modalities`` (a :class:`~coex_core.modality.Modality` subclass),
``coex.transports`` (a :class:`~coex_core.transport.Transport` subclass), ``coex.detectors``
(a :class:`~coex_core.detect.Detector` subclass, run on the vehicle by the ``detections``
modality) and ``coex.commands`` (a function that adds a sub-command to the ``coex`` command
line). Built-in plugins register
exactly as a third party does, in ``pyproject.toml``::

    [project.entry-points."coex.modalities"]
    sonar_pings = "my_package.pings:PingModality [extra]"

Loading is lazy: nothing is imported until asked for. A plugin whose optional dependencies are
missing raises :class:`~coex_core.errors.PluginLoadError` naming the extra to install.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any
from urllib.parse import urlsplit

from .errors import PluginLoadError, PluginNotFound

if TYPE_CHECKING:
    from importlib import metadata

__all__ = [
    "MODALITY_GROUP",
    "TRANSPORT_GROUP",
    "COMMAND_GROUP",
    "CHECKER_GROUP",
    "PluginInfo",
    "available",
    "load_detector",
    "load_modality",
    "load_transport",
    "load",
    "open_transport",
    "check_transport_uri",
    "entry_points",
    "names",
    "transport_scheme",
]

MODALITY_GROUP = "coex.modalities"
TRANSPORT_GROUP = "coex.transports"
COMMAND_GROUP = "coex.commands"
#: the conformance kit's runner behind ``coex plugins check``: ``main(names, pytest_args) -> int``
CHECKER_GROUP = "coex.checkers"
#: the vehicle daemon's adapters (``coex vehicle``): inputs from the vehicle's middleware and
#: outputs to its autonomy; listed by ``coex plugins``, loaded only by the daemon
INPUT_GROUP = "coex.inputs"
AUTONOMY_GROUP = "coex.autonomy"
#: onboard detectors (:mod:`coex_core.detect`), run by the ``detections`` modality on the vehicle
DETECTOR_GROUP = "coex.detectors"


@dataclass(frozen=True)
class PluginInfo:
    """What ``coex plugins`` lists: one registered plugin and whether it can load."""

    group: str
    name: str
    target: str
    distribution: str
    version: str
    extras: tuple[str, ...]
    status: str
    error: str = ""


def _entry_points(group: str) -> dict[str, metadata.EntryPoint]:
    # imported here: importlib.metadata pulls in socket and threading, which the core avoids at import
    from importlib import metadata

    found: dict[str, metadata.EntryPoint] = {}
    for ep in metadata.entry_points(group=group):
        found.setdefault(ep.name, ep)
    return found


def entry_points(group: str) -> dict[str, metadata.EntryPoint]:
    """Every plugin registered in ``group``, by name (the first of a name wins), not loaded: the
    one place CoEx reads entry points (modalities, transports, commands, inputs, autonomy
    outputs, conformance inputs ...)."""
    return _entry_points(group)


def names(group: str) -> list[str]:
    """The names registered in ``group``, sorted."""
    return sorted(_entry_points(group))


def _dist_name(ep: metadata.EntryPoint) -> tuple[str, str]:
    dist = getattr(ep, "dist", None)
    if dist is None:
        return "?", "?"
    return dist.metadata["Name"], dist.version


def load(group: str, name: str) -> Any:
    """Import and return the object registered as ``name`` in ``group``."""
    eps = _entry_points(group)
    if name not in eps:
        known = ", ".join(sorted(eps)) or "none"
        raise PluginNotFound(f"no {group} plugin named {name!r} (registered: {known})")
    ep = eps[name]
    try:
        return ep.load()
    except ImportError as exc:
        dist, _ = _dist_name(ep)
        hint = ""
        if ep.extras:
            hint = f"; install it with: pip install '{dist}[{','.join(ep.extras)}]'"
        raise PluginLoadError(
            f"{group} plugin {name!r} needs a missing module ({exc.name or exc}){hint}"
        ) from exc


def load_modality(name: str) -> Any:
    """The :class:`~coex_core.modality.Modality` class registered as ``name``."""
    return load(MODALITY_GROUP, name)


def load_detector(name: str) -> Any:
    """The :class:`~coex_core.detect.Detector` class registered as ``name``."""
    return load(DETECTOR_GROUP, name)


def load_transport(name: str) -> Any:
    """The :class:`~coex_core.transport.Transport` class registered as ``name``."""
    return load(TRANSPORT_GROUP, name)


def transport_scheme(uri: str) -> str:
    """The scheme of a transport URI (the text before the first ``:``), which picks the plugin."""
    scheme = urlsplit(uri).scheme or uri.split(":", 1)[0]
    if not scheme:
        raise PluginNotFound(f"transport URI {uri!r} has no scheme")
    return scheme


def open_transport(uri: str) -> Any:
    """Create a transport from a URI; the scheme (text before the first ``:``) picks the plugin.

    ``micromodem:///dev/ttyUSB0?rate=5``, ``mavlink:udpout:127.0.0.1:14550``,
    ``lcm:udpm://239.255.76.67:7667?ttl=0``, ``loopback://name``."""
    return load_transport(transport_scheme(uri)).from_uri(uri)


def check_transport_uri(uri: str) -> Any:
    """Check a transport URI as :func:`open_transport` would take it, opening nothing: the
    plugin's :meth:`~coex_core.transport.Transport.check_uri` (a
    :class:`~coex_core.transport.UriInfo`, or None when the plugin cannot check without
    opening); :class:`~coex_core.errors.ConfigError` for a bad URI, PluginNotFound /
    PluginLoadError for an unknown or uninstalled scheme."""
    return load_transport(transport_scheme(uri)).check_uri(uri)


def available(check: bool = True) -> list[PluginInfo]:
    """Every registered modality, transport, input, autonomy output and detector; with
    ``check`` each is imported to report status."""
    out = []
    for group in (MODALITY_GROUP, TRANSPORT_GROUP, INPUT_GROUP, AUTONOMY_GROUP, DETECTOR_GROUP):
        for name, ep in sorted(_entry_points(group).items()):
            dist, version = _dist_name(ep)
            status, error = "registered", ""
            if check:
                try:
                    obj = ep.load()
                    status = "ok"
                    version = str(getattr(obj, "version", version) or version)
                except ImportError as exc:
                    own = ep.value.split(":", 1)[0]
                    missing = getattr(exc, "name", None) or ""
                    if missing and (own == missing or own.startswith(missing + ".")):
                        status, error = "broken", f"module {missing} not found"
                    else:
                        status = "missing dependency"
                        error = f"pip install '{dist}[{','.join(ep.extras)}]'" if ep.extras else str(exc)
                except Exception as exc:  # a broken third-party plugin must not break the listing
                    status, error = "error", f"{type(exc).__name__}: {exc}"
            out.append(PluginInfo(group, name, ep.value, dist, version, tuple(ep.extras), status, error))
    return out
