"""What the vehicle's adapters (inputs and autonomy outputs) share: option checks (collected in
``coex_core.config.Problems``, re-exported here), logging a
problem once, headings, the import of an optional library with the extra that installs it, and
the MOOS connection."""

from __future__ import annotations

import importlib
import logging
import math
import re
from collections.abc import Callable, Mapping
from types import ModuleType
from typing import Any

from coex import PluginLoadError, Problems
from coex.moos import MAX_TIME_WARP
from coex.options import Option, number

__all__ = [
    "LogOnce",
    "Problems",
    "serial_device",
    "check_lcm_url",
    "check_mavlink_connection",
    "compass_from_enu_yaw",
    "compile_path",
    "finite",
    "need",
    "time_warp",
    "yaw_of_quaternion",
]


def need(module: str, extra: str) -> ModuleType:
    """Import an optional library, or raise :class:`PluginLoadError` naming the extra."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise PluginLoadError(
            f"this input needs {module.split('.')[0]}: pip install 'coexploration[{extra}]' ({exc})"
        ) from exc


class LogOnce:
    """Logs each distinct problem (by key) once, then counts it quietly: a camera writing a broken
    file every second must not flood the vehicle's log."""

    #: distinct problems remembered; beyond it the oldest are forgotten (and may be logged again)
    LIMIT = 4096

    def __init__(self, logger: logging.Logger) -> None:
        self.logger = logger
        self.counts: dict[str, int] = {}

    def __call__(self, key: str, message: str, *args: Any, level: int = logging.WARNING) -> None:
        n = self.counts.get(key, 0)
        if n == 0 and len(self.counts) >= self.LIMIT:  # a dive of broken files: stay bounded
            del self.counts[next(iter(self.counts))]
        self.counts[key] = n + 1
        if n == 0:
            self.logger.log(level, message, *args)


def serial_device(connection: Any) -> list[tuple[str, str, str]]:
    """The serial device of a pymavlink connection string (``/dev/ttyACM0``, ``/dev/ttyUSB0,57600``),
    as an :meth:`Adapter.paths` entry of the option ``connection``; none for a network one."""
    if not isinstance(connection, str) or not connection.startswith("/"):
        return []
    return [("connection", connection.split(",", 1)[0], "device")]


# --------------------------------------------------------------------------- option checks
# (the checks themselves are coex_core.config.Problems' option_* methods: the one checker)
#: pymavlink's connection kinds that take ``HOST:PORT`` (``mavutil.mavlink_connection``)
MAVLINK_NET_KINDS = ("udpin", "udpout", "udpbcast", "udp", "tcp", "tcpin", "mcast", "wsserver")
#: its other kinds (a Unix socket, a websocket URL, a CSV log): taken as given
MAVLINK_OTHER_KINDS = ("uds", "unix", "ws", "wss", "csv")


def check_mavlink_connection(p: Problems, who: str, options: Mapping[str, Any], key: str = "connection") -> None:
    """A problem if option ``key`` (a pymavlink connection string) is given and pymavlink would
    not open it: ``KIND:HOST:PORT`` needs one of pymavlink's kinds (``udpin``, ``udpout``,
    ``tcp`` ...; a misspelt ``udpinn:`` would be taken for a file name and retried for ever)
    and a port 1..65535; a serial device (``/dev/ttyACM0``, ``/dev/ttyUSB0,57600``) or a bare
    ``HOST:PORT`` (UDP) is taken as pymavlink takes it."""
    v = options.get(key)
    if not isinstance(v, str) or not v or v.startswith("/") or ":" not in v:
        return  # not a string (said elsewhere), a device or a file
    kind, _, rest = v.partition(":")
    if kind in MAVLINK_OTHER_KINDS:
        return
    if kind in MAVLINK_NET_KINDS:
        host, sep, port = rest.rpartition(":")
        if kind == "mcast" and not rest:
            return  # pymavlink's default group
    else:
        host, sep, port = v.rpartition(":")
        if ":" in host or not host:
            p.said(key, f"{who}: option {key!r}: {kind!r} is not a pymavlink connection kind (known: "
                        f"{', '.join(MAVLINK_NET_KINDS + MAVLINK_OTHER_KINDS)}; or a serial device), in {v!r}")
            return
    listens = kind in ("udpin", "tcpin", "udp", "wsserver")  # port 0: any free port
    if not sep or not port.isdigit() or not int(not listens) <= int(port) <= 65535:
        p.said(key, f"{who}: option {key!r} must end in a port 1..65535 ({kind}:HOST:PORT), not {v!r}")
    elif not host and not listens:
        p.said(key, f"{who}: option {key!r} needs a host ({kind}:HOST:PORT), not {v!r}")


def check_lcm_url(p: Problems, who: str, options: Mapping[str, Any], key: str = "url") -> None:
    """A problem if option ``key`` (an LCM provider URL; empty: the default) is given and LCM
    would not open it (``coex.lcm.check_provider_url``: a port above 65535, an address that is
    not multicast, an unknown option)."""
    v = options.get(key)
    if not isinstance(v, str) or not v:
        return
    from coex import ConfigError
    from coex.lcm import check_provider_url

    try:
        check_provider_url(v)
    except ConfigError as exc:
        p.said(key, f"{who}: option {key!r}: {exc}")


def time_warp(doc: str) -> Option:
    """The declared option of a MOOS community's ``MOOSTimeWarp``: a number above 0 and at most
    MOOS's ``MAX_TIME_WARP`` (400), default 1."""
    return number(1.0, doc, above=0, hi=MAX_TIME_WARP)


# --------------------------------------------------------------------------- values
_SEGMENT = r"[A-Za-z_][A-Za-z0-9_]*(?:\[\d+\])?"
_PATH = re.compile(rf"^-?\s*{_SEGMENT}(?:\.{_SEGMENT})*$")


def check_scale(p: Problems, who: str, option: str, key: str, entry: Mapping[str, Any], names: Any,
                table: str, what: str) -> None:
    """The ``scale`` table of entry ``key`` (``own[0]``) of a list-of-tables ``option``:
    ``what = factor``, each name one of ``names`` (the entry's ``table``), each factor a finite
    number. Its problems are problems of ``option``."""
    scale = entry.get("scale", {})
    if not isinstance(scale, Mapping):
        p.said(option, f"{who}: option '{key}.scale' must be a table of {what} = factor")
        return
    for name, factor in scale.items():
        if name not in names:
            p.said(option, f"{who}: option '{key}.scale.{name}' scales nothing (not in '{key}.{table}')")
        if number().problem(factor) is not None:
            p.said(option, f"{who}: option '{key}.scale.{name}' must be a number")


def compile_path(path: str) -> tuple[Callable[[Any], Any], str]:
    """A getter for a field path (``"-pos[2]"``, ``"pose.position.x"``) and the name of its
    first field; ValueError if the path is not one. The ``lcm`` input's ``own`` types and the
    ``ros`` input's ``series`` take fields with it."""
    if not isinstance(path, str) or not _PATH.match(path.strip()):
        raise ValueError(f"{path!r} is not a field path (name, name[index], a.b, optional leading -)")
    text = path.strip()
    negate = text.startswith("-")
    steps: list[tuple[str, int | None]] = []
    for seg in text.lstrip("-").strip().split("."):
        name, _, index = seg.partition("[")
        steps.append((name, int(index[:-1]) if index else None))

    def get(msg: Any) -> Any:
        v = msg
        for name, index in steps:
            v = getattr(v, name)
            if index is not None:
                v = v[index]
        if negate:
            import numpy as np

            v = -np.asarray(v, dtype=np.float64) if isinstance(v, list | tuple | np.ndarray) else -v
        return v

    return get, steps[0][0]


def finite(v: Any) -> float | None:
    """``v`` as a float, or None when it is missing, not a number, NaN or infinite."""
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def yaw_of_quaternion(x: float, y: float, z: float, w: float) -> float | None:
    """The yaw (rotation about z, radians, counter-clockwise) of a quaternion, or None if it is
    all zeros (unset orientation) or not finite."""
    n = x * x + y * y + z * z + w * w
    if not math.isfinite(n) or n < 1e-12:
        return None
    # atan2 of unnormalised terms: the same angle for any scale of the quaternion
    return math.atan2(2.0 * (w * z + x * y), w * w + x * x - y * y - z * z)


def compass_from_enu_yaw(yaw: float) -> float:
    """A compass heading (degrees clockwise from north, 0..360) from an ENU yaw (radians
    counter-clockwise from east, as ROS gives it): yaw 0 (east) is heading 90."""
    return (90.0 - math.degrees(yaw)) % 360.0


def moos_client(client: Any, host: str, port: int, name: str, variables: list[str],
                time_warp: float = 1.0) -> Any:
    """The MOOS input's and autonomy output's connection: ``client`` (made here when None, on
    the community's ``time_warp``) with every one of ``variables`` registered, connecting (and
    reconnecting) in its own thread; never waits for MOOSDB."""
    if client is None:
        from coex.moos import MoosClient

        client = MoosClient(host, port, name, time_warp=time_warp)
    for var in variables:
        client.register(var, 0.0)
    client.connect(timeout=0.0)
    return client
