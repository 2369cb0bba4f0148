"""pCoex: ``coex vehicle --moos MISSION.moos`` configured from a MOOS mission file
(``docs/moos.md``, ``examples/moos/``).

The ``ProcessConfig = pCoex`` block holds the same keys as the vehicle's TOML file, written as
dotted paths, one per line, and values that are TOML values when they parse as one, else
strings::

    ProcessConfig = pCoex
    {
      AppTick   = 4                                  // accepted, not used
      config    = vehicle.toml                       // optional: read first, the block overrides it
      node.id   = 2
      node.command_key_file = coex.key
      modems[0].uri = moos://${ServerHost}:${ServerPort}?name=pCoex_modem
      modalities.survey.options.geofence.radius = 500
      inputs[0].type = moos
      inputs[0].channels = { CTD_TEMP = "temperature" }
      autonomy.type = moos
    }

* MOOS keys are case-insensitive: every path segment is lowercased, except a quoted one
  (``inputs[0].channels."CTD_TEMP" = temperature``); keys of a TOML inline-table value keep
  their case.
* ``//`` starts a comment at the beginning of a line or after white space, outside double
  quotes (so ``moos://host`` is a value, as MOOS's own reader would need it quoted).
* ``${NAME}`` and ``${NAME:-default}`` are replaced by a ``define: NAME = value`` line of the
  file, by the mission's globals (``${ServerHost}``, ``${ServerPort}``, ``${Community}``,
  ``${LatOrigin}``, ``${LongOrigin}``), or by the environment.
* Defaults from the mission: ``node.role = "vehicle"``; ``node.origin`` from ``LatOrigin`` /
  ``LongOrigin``; the ``server`` of every ``moos`` input and of the ``moos`` autonomy from
  ``ServerHost:ServerPort``; their MOOS client names ``<process>_in`` and ``<process>_helm``;
  their ``time_warp`` and the ``warp`` of every ``moos://`` modem from ``MOOSTimeWarp``.
"""

from __future__ import annotations

import copy
import math
import os
import re
import tomllib
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from coex import ConfigError

from .config import DeployConfig, check_mapping, expand

__all__ = ["Mission", "check_mission", "load_mission", "parse_mission", "read_mission"]

GLOBALS = {"serverhost": "ServerHost", "serverport": "ServerPort", "community": "Community",
           "latorigin": "LatOrigin", "longorigin": "LongOrigin", "moostimewarp": "MOOSTimeWarp"}
#: block keys MOOS applications take that CoEx does not use
IGNORED = ("apptick", "commstick", "maxappticks")
_VAR = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?::-([^}]*))?\}")
_SEGMENT = re.compile(r'\s*(?:"([^"]*)"|([A-Za-z0-9_\-]+))\s*((?:\[\s*\d+\s*\])*)\s*')


class Mission:
    """A parsed mission file: its globals, its ``define:`` variables and its blocks."""

    def __init__(self) -> None:
        self.globals: dict[str, tuple[int, str]] = {}  # lowercased key -> (line, raw value)
        self.defines: dict[str, str] = {}
        self.blocks: dict[str, tuple[str, list[tuple[int, str, str]]]] = {}  # lower name -> (name, entries)


def _strip_comment(line: str) -> str:
    quoted = False
    for i, ch in enumerate(line):
        if ch == '"':
            quoted = not quoted
        elif not quoted and line.startswith("//", i) and (i == 0 or line[i - 1].isspace()):
            return line[:i]
    return line


def parse_mission(text: str) -> tuple[Mission, list[str]]:
    """The structure of a mission file: ``(mission, problems)``."""
    m, problems = Mission(), []
    block: tuple[str, list[tuple[int, str, str]]] | None = None
    pending: str | None = None  # a ProcessConfig line waiting for its "{"
    for n, raw in enumerate(text.splitlines(), 1):
        line = _strip_comment(raw).strip()
        if not line:
            continue
        if line.lower().startswith("define:"):
            key, sep, value = line[7:].partition("=")
            if sep:
                m.defines[key.strip()] = value.strip()
            continue
        if pending is not None:
            if line != "{":
                problems.append(f"line {n}: '{{' expected after ProcessConfig = {pending}")
                pending = None
                continue
            block = (pending, [])
            if pending.lower() in m.blocks:
                problems.append(f"line {n}: a second ProcessConfig = {pending} block")
            m.blocks[pending.lower()] = block
            pending = None
            continue
        if block is not None:
            if line == "}":
                block = None
                continue
            key, sep, value = line.partition("=")
            if not sep or not key.strip():
                problems.append(f"line {n}: 'key = value' expected, got {line!r}")
                continue
            block[1].append((n, key.strip(), value.strip()))
            continue
        key, sep, value = line.partition("=")
        if not sep:
            problems.append(f"line {n}: 'key = value' expected, got {line!r}")
            continue
        if key.strip().lower() == "processconfig":
            name = value.strip()
            if name.endswith("{"):
                name = name[:-1].strip()
                block = (name, [])
                m.blocks[name.lower()] = block
            else:
                pending = name
            continue
        m.globals[key.strip().lower()] = (n, value.strip())
    if block is not None or pending is not None:
        problems.append("the last ProcessConfig block has no closing '}'")
    return m, problems


def _expander(variables: Mapping[str, str]) -> Any:
    def sub(text: str) -> str:
        def one(mt: re.Match[str]) -> str:
            name = mt.group(1)
            if name in variables:
                return variables[name]
            value = os.environ.get(name, mt.group(2))
            if value is None:
                raise ConfigError(f"${{{name}}} is not set and has no default (write ${{{name}:-...}})")
            return value

        return _VAR.sub(one, text)

    return sub


def _value(text: str) -> Any:
    """A TOML value when the text is one, else the text."""
    if text == "":
        return ""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def _path(key: str) -> list[str | int] | None:
    """``modems[0].uri`` -> ["modems", 0, "uri"]; quoted segments keep their case, the others are
    lowercased (MOOS keys are case-insensitive). None if it is not a key path."""
    out: list[str | int] = []
    pos = 0
    while True:
        mt = _SEGMENT.match(key, pos)
        if mt is None or mt.end() == pos:
            return None
        out.append(mt.group(1) if mt.group(1) is not None else mt.group(2).lower())
        out += [int(i) for i in re.findall(r"\d+", mt.group(3))]
        pos = mt.end()
        if pos == len(key):
            return out
        if key[pos] != ".":
            return None
        pos += 1


def _show(path: list[str | int]) -> str:
    text = ""
    for p in path:
        text += f"[{p}]" if isinstance(p, int) else (("." if text else "") + (p if re.fullmatch(r"[a-z0-9_\-]+", p)
                                                                               else f'"{p}"'))
    return text


def _set(root: dict[str, Any], path: list[str | int], value: Any) -> str | None:
    """Set ``value`` at ``path``; a problem in words, or None."""
    node: Any = root
    for i, seg in enumerate(path):
        last = i == len(path) - 1
        if isinstance(seg, int):
            if not isinstance(node, list):
                return f"{_show(path[:i])} is not a list"
            while len(node) <= seg:
                node.append(None)
        elif not isinstance(node, dict):
            return f"{_show(path[:i]) or 'the configuration'} is not a table"
        if last:
            node[seg] = value
        elif (node[seg] if isinstance(seg, int) else node.get(seg)) is None:
            node[seg] = {} if isinstance(path[i + 1], str) else []
        node = node[seg]
    return None


def _holes(data: Any, where: str, problems: list[str]) -> None:
    if isinstance(data, dict):
        for k, v in data.items():
            _holes(v, f"{where}.{k}" if where else str(k), problems)
    elif isinstance(data, list):
        for i, v in enumerate(data):
            if v is None:
                problems.append(f"{where}[{i}]: missing (a later {where}[...] is given)")
            else:
                _holes(v, f"{where}[{i}]", problems)


def read_mission(path: str | Path, process: str = "pCoex", *, host: str | None = None,
                 port: int | None = None) -> tuple[dict[str, Any] | None, list[str]]:
    """The configuration mapping (as a TOML file would hold it) of a mission file's
    ``ProcessConfig = <process>`` block, and the problems found. ``host``/``port`` replace the
    mission's ``ServerHost``/``ServerPort`` (``--moos-host``/``--moos-port``)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        return None, [f"cannot read the mission file: {exc.strerror or exc}"]
    mission, problems = parse_mission(text)
    glob = _mission_globals(mission, host, port, problems)
    server_host, server_port = glob["serverhost"], glob["serverport"]
    if not server_port.isdigit() or not 0 < int(server_port) < 65536:
        problems.append(f"ServerPort: a TCP port, got {server_port!r}")
    warp = _warp(glob.get("moostimewarp", "1"), problems)
    variables = {**{GLOBALS[k]: v for k, v in glob.items() if k in GLOBALS}, **mission.defines}
    found = mission.blocks.get(process.lower())
    if found is None:
        names = ", ".join(b[0] for b in mission.blocks.values()) or "none"
        return None, [*problems, f"no ProcessConfig = {process} block (blocks: {names})"]
    raw, entries = _block_entries(found[1], _expander(variables), path, problems)
    toml_origin = copy.deepcopy(raw.get("node", {}).get("origin")) if isinstance(raw.get("node"), dict) else None
    given = _set_entries(raw, entries, problems)
    _holes(raw, "", problems)
    if problems:
        return raw, problems
    _mission_origin(raw, glob, given, toml_origin, problems)
    _moos_clients(raw, process, f"{server_host}:{server_port}", warp)
    return raw, problems


def _mission_globals(mission: Mission, host: str | None, port: int | None, problems: list[str]) -> dict[str, str]:
    """The mission's global settings (lower-case names, ``${...}`` expanded), with the
    command line's ``host``/``port`` and MOOS's defaults (localhost:9000)."""
    sub = _expander(mission.defines)
    glob: dict[str, str] = {}
    for low, (n, value) in mission.globals.items():
        try:
            glob[low] = sub(value)
        except ConfigError as exc:
            problems.append(f"line {n}: {exc}")
    if host is not None:
        glob["serverhost"] = host
    if port is not None:
        glob["serverport"] = str(port)
    glob.setdefault("serverhost", "localhost")
    glob.setdefault("serverport", "9000")
    return glob


def _block_entries(lines: list[tuple[int, str, str]], sub: Callable[[str], str], path: Path, problems: list[str],
                   ) -> tuple[dict[str, Any], list[tuple[int, str, str]]]:
    """A ProcessConfig block's lines, expanded: the TOML file its ``config`` line names (read,
    or ``{}``) and the other configuration lines ``(line, key, value)`` (MOOS's own skipped)."""
    raw: dict[str, Any] = {}
    entries = []
    for n, key, value in lines:
        try:
            value = sub(value)
        except ConfigError as exc:
            problems.append(f"line {n}: {key}: {exc}")
            continue
        if key.lower() in IGNORED:
            continue
        if key.lower() == "config":
            toml = path.parent / value.strip('"')
            try:
                raw = tomllib.loads(expand(toml.read_text()))
            except OSError as exc:
                problems.append(f"line {n}: config: cannot read {toml}: {exc.strerror or exc}")
            except (ConfigError, tomllib.TOMLDecodeError) as exc:
                problems.append(f"line {n}: config: {toml}: {exc}")
            continue
        entries.append((n, key, value))
    return raw, entries


def _set_entries(raw: dict[str, Any], entries: list[tuple[int, str, str]], problems: list[str]) -> dict[str, int]:
    """Each ``key = value`` line set into ``raw`` by its path; returns each key's line."""
    given: dict[str, int] = {}
    for n, key, value in entries:
        kp = _path(key)
        if kp is None or not isinstance(kp[0], str):
            problems.append(f"line {n}: {key!r} is not a configuration key (node.id, modems[0].uri, "
                            "inputs[0].type, modalities.survey.options.geofence.radius ...)")
            continue
        shown = _show(kp)
        if shown in given:
            problems.append(f"{shown}: given twice (lines {given[shown]} and {n})")
            continue
        given[shown] = n
        why = _set(raw, kp, _value(value))
        if why is not None:
            problems.append(f"{shown}: {why} (line {n})")
    return given


def _mission_origin(raw: dict[str, Any], glob: dict[str, str], given: dict[str, int], toml_origin: Any,
                    problems: list[str]) -> None:
    """The node's role (a vehicle) and origin (the mission's ``LatOrigin``/``LongOrigin``)
    unless the block gives them; a TOML file's other origin is a problem."""
    node = raw.setdefault("node", {})
    if not isinstance(node, dict):
        return
    node.setdefault("role", "vehicle")
    lat, lon = glob.get("latorigin"), glob.get("longorigin")
    if lat is not None and lon is not None and not any(k.startswith("node.origin") for k in given):
        try:
            origin = {"lat": float(lat), "lon": float(lon)}
        except ValueError:
            problems.append(f"LatOrigin, LongOrigin: numbers, got {lat!r}, {lon!r}")
        else:
            if toml_origin is not None and toml_origin != origin:
                problems.append(f"node.origin: the TOML file's {toml_origin} is not the mission's LatOrigin, "
                                f"LongOrigin {origin} (MOOS x, y are metres from the mission's origin)")
            node["origin"] = origin


def _moos_clients(raw: dict[str, Any], process: str, server: str, warp: float) -> None:
    """The MOOS inputs and autonomy output talk to the mission's MOOSDB (``server``) under names
    of the process, and every MOOS client (modems too) takes the mission's time warp."""
    inputs = raw.get("inputs")
    moos = [t for t in inputs if isinstance(t, dict) and t.get("type") == "moos"] if isinstance(inputs, list) else []
    for i, t in enumerate(moos):
        t.setdefault("server", server)
        t.setdefault("name", f"{process}_in" if len(moos) == 1 else f"{process}_in{i}")
    autonomy = raw.get("autonomy")
    helm: list[dict[str, Any]] = [autonomy] if isinstance(autonomy, dict) and autonomy.get("type") == "moos" else []
    for t in helm:
        t.setdefault("server", server)
        t.setdefault("name", f"{process}_helm")
    if warp != 1.0:  # MOOS times are warped: every MOOS client of pCoex takes the mission's warp
        for t in [*moos, *helm]:
            t.setdefault("time_warp", warp)
        for m in raw.get("modems") or []:
            uri = m.get("uri") if isinstance(m, dict) else None
            if isinstance(uri, str) and uri.startswith("moos:") and not re.search(r"[?&]warp=", uri):
                m["uri"] = uri + ("&" if "?" in uri else "?") + f"warp={warp:g}"


def _warp(text: str, problems: list[str]) -> float:
    """The mission's ``MOOSTimeWarp`` (MOOS takes a number above 0, at most 400)."""
    from coex.moos import MAX_TIME_WARP

    try:
        warp = float(text)
    except ValueError:
        warp = math.nan
    if not 0 < warp <= MAX_TIME_WARP:
        problems.append(f"MOOSTimeWarp: a number above 0 and at most {MAX_TIME_WARP:g}, got {text!r}")
        return 1.0
    return warp


def check_mission(path: str | Path, process: str = "pCoex", *, host: str | None = None,
                  port: int | None = None) -> tuple[DeployConfig | None, list[str]]:
    """``(config, problems)`` of a mission file's pCoex block (``coex config check``)."""
    raw, problems = read_mission(path, process, host=host, port=port)
    if raw is None or problems:
        return None, problems
    return check_mapping(raw, Path(path), "vehicle")


def load_mission(path: str | Path, process: str = "pCoex", *, host: str | None = None,
                 port: int | None = None) -> DeployConfig:
    """The vehicle's configuration from a mission file; :class:`ConfigError` lists every problem."""
    cfg, problems = check_mission(path, process, host=host, port=port)
    if problems:
        raise ConfigError(f"{path}: " + "; ".join(problems) if len(problems) == 1 else
                          f"{path}: {len(problems)} problems:\n  " + "\n  ".join(problems))
    assert cfg is not None
    return cfg
