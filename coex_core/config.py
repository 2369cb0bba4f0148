"""The one configuration convention of CoEx: a plugin's options, and the collector of a
configuration's problems.

A sender's or receiver's configuration is a plain mapping (from TOML, JSON or code). Every
plugin declares its options with their defaults and merges with :func:`merged_config`: an
unknown key (a misspelling) is a :class:`~coex_core.errors.ConfigError` that names the key and
lists the known ones, never silently ignored.

Every validator of a configuration (the options of a plugin, a node's deployment file, a vehicle
adapter's options, a demo scenario) collects its problems in one :class:`Problems`: it checks
**everything** before it refuses, each problem one sentence that names its key, and
:meth:`Problems.error` makes the one :class:`~coex_core.errors.ConfigError` that lists them all
(its ``problems`` holds each with its key).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .errors import ConfigError

__all__ = ["Problem", "Problems", "merged_config"]


@dataclass(frozen=True)
class Problem:
    """One problem of a configuration: the ``key`` it is about (``modems[0].uri``,
    ``survey.altitude``, an option's name; ``""`` for the whole) and the sentence shown."""

    key: str
    text: str

    def __str__(self) -> str:
        return self.text


class Problems:
    """The problems (and warnings) of one configuration, collected rather than raised one by one
    (see the module docstring). ``add`` words a problem ``"key: text"``; ``said`` keeps a
    sentence that already names its key in its own words."""

    def __init__(self) -> None:
        self.found: list[Problem] = []
        #: what the node will meet but can live with (a device not plugged in yet)
        self.warned: list[Problem] = []

    # ------------------------------------------------------------------ collecting
    def add(self, key: str, text: str) -> None:
        """A problem shown as ``"key: text"`` (``text`` alone when ``key`` is empty)."""
        self.found.append(Problem(key, f"{key}: {text}" if key else text))

    def said(self, key: str, sentence: str) -> None:
        """A problem about ``key`` shown as ``sentence`` (which names the key itself)."""
        self.found.append(Problem(key, sentence))

    def extend(self, key: str, texts: Iterable[str]) -> None:
        """Each of ``texts`` (what a part checked by itself found) as a problem of ``key``."""
        for text in texts:
            self.add(key, text)

    def merge(self, other: Iterable[Problem]) -> None:
        """Problems another collector found (a :class:`ConfigError`'s ``problems``)."""
        self.found.extend(other)

    def warn(self, key: str, text: str) -> None:
        self.warned.append(Problem(key, f"{key}: {text}" if key else text))

    # ------------------------------------------------------------------ what was found
    @property
    def items(self) -> list[str]:
        """The problems as shown, in the order found."""
        return [p.text for p in self.found]

    @property
    def warnings(self) -> list[str]:
        return [p.text for p in self.warned]

    def keys(self) -> list[str]:
        """The keys of the problems, in the order found."""
        return [p.key for p in self.found]

    def __bool__(self) -> bool:
        return bool(self.found)

    def __len__(self) -> int:
        return len(self.found)

    def __iter__(self) -> Iterator[Problem]:
        return iter(self.found)

    def error(self, where: str = "") -> ConfigError:
        """The :class:`ConfigError` listing every problem (``where``, a file, before them): one
        problem on one line, several as ``"N problems:"`` and one per line. Its ``problems``
        are the :class:`Problem` s."""
        texts = self.items
        head = f"{where}: " if where else ""
        if len(texts) == 1:
            exc = ConfigError(head + texts[0])
        else:
            exc = ConfigError(f"{head}{len(texts)} problems:\n  " + "\n  ".join(texts))
        exc.problems = tuple(self.found)
        return exc

    def check(self, where: str = "") -> None:
        """Raise :meth:`error` if any problem was found."""
        if self.found:
            raise self.error(where)

    # ------------------------------------------------------------------ common checks
    def path(self, key: str, path: str | Path, what: str, *, folder: bool = False) -> None:
        """A warning when ``path`` (a device, a file or a folder the node will open) is not there now."""
        p = Path(path)
        if folder and not p.is_dir():
            self.warn(key, f"no folder {p} now ({what})")
        elif not folder and not p.exists():
            self.warn(key, f"{p} does not exist now ({what})")

    def table(self, data: Any, key: str) -> dict[str, Any]:
        """``data`` as a table (a problem when it is not one; ``{}`` for None)."""
        if data is None:
            return {}
        if not isinstance(data, Mapping):
            self.add(key, f"a table, got {type(data).__name__}")
            return {}
        return dict(data)

    def unknown(self, data: Mapping[str, Any], known: set[str] | tuple[str, ...], key: str) -> None:
        """A problem for each key of ``data`` not in ``known``."""
        for k in data:
            if k not in known:
                self.add(f"{key}.{k}" if key else k, f"unknown key (known: {', '.join(sorted(known))})")

    def number(self, data: Mapping[str, Any], k: str, key: str, default: Any, *, lo: float | None = None,
               hi: float | None = None, integer: bool = False) -> Any:
        """``data[k]`` checked as a (finite) number or an integer in ``lo..hi``; ``default``
        when it is not given or is wrong (a problem then)."""
        v = data.get(k, default)
        if v is default:
            return v
        ok = isinstance(v, int) if integer else isinstance(v, int | float)
        if isinstance(v, bool) or not ok or (not integer and not math.isfinite(v)):
            self.add(f"{key}.{k}", f"{'an integer' if integer else 'a number'}, got {v!r}")
            return default
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            self.add(f"{key}.{k}", f"{v!r} is outside {lo:g}..{hi:g}" if lo is not None and hi is not None
                     else f"{v!r} is below {lo:g}" if lo is not None else f"{v!r} is above {hi:g}")
            return default
        return v


    # ------------------------------------------------------------------ an adapter's options
    # (``who`` names the adapter in the sentence, e.g. ``"input 'nmea'"``; each problem's key is
    # the option's name; an option not given is no problem: its default applies)
    def option_str(self, who: str, options: Mapping[str, Any], key: str, *, nonempty: bool = False) -> None:
        """A problem if ``key`` is given and is not a string (or is empty when ``nonempty``)."""
        if key not in options:
            return
        v = options[key]
        if not isinstance(v, str):
            self.said(key, f"{who}: option {key!r} must be a string, not {v!r}")
        elif nonempty and not v.strip():
            self.said(key, f"{who}: option {key!r} must not be empty")

    def option_number(self, who: str, options: Mapping[str, Any], key: str, *, minimum: float | None = None,
                      positive: bool = False) -> None:
        """A problem if ``key`` is given and is not a finite number in range."""
        if key not in options:
            return
        v = options[key]
        if not _is_number(v) or not math.isfinite(v):
            self.said(key, f"{who}: option {key!r} must be a number, not {v!r}")
        elif positive and v <= 0:
            self.said(key, f"{who}: option {key!r} must be greater than 0, not {v!r}")
        elif minimum is not None and v < minimum:
            self.said(key, f"{who}: option {key!r} must be at least {minimum}, not {v!r}")

    def option_int(self, who: str, options: Mapping[str, Any], key: str, lo: int, hi: int) -> None:
        """A problem if ``key`` is given and is not an integer in ``lo..hi``."""
        if key not in options:
            return
        v = options[key]
        if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
            self.said(key, f"{who}: option {key!r} must be an integer from {lo} to {hi}, not {v!r}")

    def option_bool(self, who: str, options: Mapping[str, Any], key: str) -> None:
        """A problem if ``key`` is given and is not true or false."""
        if key in options and not isinstance(options[key], bool):
            self.said(key, f"{who}: option {key!r} must be true or false, not {options[key]!r}")

    def option_choice(self, who: str, options: Mapping[str, Any], key: str, choices: tuple[str, ...]) -> None:
        """A problem if ``key`` is given and is not one of ``choices``."""
        if key in options and options[key] not in choices:
            self.said(key, f"{who}: option {key!r} must be one of {', '.join(map(repr, choices))}, "
                           f"not {options[key]!r}")

    def option_host_port(self, who: str, options: Mapping[str, Any], key: str) -> None:
        """A problem if ``key`` is given, not empty, and not ``host:port``."""
        v = options.get(key, "")
        if v == "":
            return
        if isinstance(v, str):
            host, sep, port = v.rpartition(":")
            if sep and host and port.isdigit() and 0 <= int(port) <= 65535:
                return
        self.said(key, f"{who}: option {key!r} must be 'host:port' (e.g. '0.0.0.0:10110'), not {v!r}")

    def option_tables(self, who: str, options: Mapping[str, Any], key: str, known: tuple[str, ...], *,
                      hint: str, entry_hint: str = "") -> Iterator[tuple[str, Mapping[str, Any]]]:
        """The entries of option ``key``, a list of tables (``[[inputs.KEY]]``), each with its
        name ``KEY[i]``: a problem of ``key`` when the value is not a list (``hint`` shows how
        to write it), for each entry that is not a table (``entry_hint`` after "a table") and
        each unknown key of an entry (``known``). Yields the tables, each after its own
        problems, so an entry's further problems follow them in order."""
        value = options[key]
        if not isinstance(value, list):
            self.said(key, f"{who}: option {key!r} must be a list of tables ({hint})")
            return
        for i, entry in enumerate(value):
            name = f"{key}[{i}]"
            if not isinstance(entry, Mapping):
                self.said(key, f"{who}: option {name!r} must be a table{entry_hint}")
                continue
            for k in entry:
                if k not in known:
                    self.said(key, f"{who}: unknown option '{name}.{k}' (known: {', '.join(known)})")
            yield name, entry

    def nest(self, key: str, other: Iterable[Problem]) -> None:
        """Problems a part found by itself (an adapter's options) as problems of ``key``: each
        shown ``"key: text"``, its key under ``key`` (``inputs[0]`` and ``baud`` make
        ``inputs[0].baud``)."""
        for q in other:
            self.found.append(Problem(f"{key}.{q.key}" if key and q.key else key or q.key,
                                      f"{key}: {q.text}" if key else q.text))


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def merged_config(config: Mapping[str, Any] | None, defaults: Mapping[str, Any],
                  what: str = "") -> dict[str, Any]:
    """``defaults`` updated with ``config``; :class:`ConfigError` naming every key not in
    ``defaults`` (``what`` names the component in the message, e.g. ``"imagery sender"``)."""
    if config is not None and not isinstance(config, Mapping):
        raise ConfigError(f"{what or 'the'} configuration must be a mapping, "
                          f"got {type(config).__name__}")
    cfg = dict(defaults)
    p = Problems()
    for key, value in (config or {}).items():
        if key not in defaults:
            p.said(str(key), f"unknown {what + ' ' if what else ''}option {key!r} "
                             f"(known: {', '.join(sorted(map(str, defaults)))})")
            continue
        cfg[key] = value
    p.check()
    return cfg
