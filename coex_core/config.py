"""The one configuration convention of CoEx: a plugin's options, and the collector of a
configuration's problems.

A sender's or receiver's configuration is a plain mapping (from TOML, JSON or code). Every
component declares its options once, as an :class:`Options` schema of :class:`Option` fields
(type, default, range, unit, one line of doc), and merges with :func:`merged_config`: an
unknown key (a misspelling), a missing required one and a value of the wrong type or out of
range are each a problem naming the key, all of them in one
:class:`~coex_core.errors.ConfigError`, never silently ignored. A number is an ``int`` or a
finite ``float``: NaN, infinities, booleans and words (``"10"``, ``"soon"``) are refused.
The same fields check a modality's options, a vehicle adapter's, a transport URI's query
(:func:`coex_core.transport.parse_query`), the deployment file's numbers
(:meth:`Problems.number`) and a demo scenario's.

Every validator of a configuration (the options of a plugin, a node's deployment file, a vehicle
adapter's options, a demo scenario) collects its problems in one :class:`Problems`: it checks
**everything** before it refuses, each problem one sentence that names its key, and
:meth:`Problems.error` makes the one :class:`~coex_core.errors.ConfigError` that lists them all
(its ``problems`` holds each with its key).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, Literal

from .errors import ConfigError

__all__ = ["REQUIRED", "Option", "OptionKind", "Options", "Problem", "Problems", "anything", "flag", "inferred",
           "integer", "merged_config", "number", "shown", "text"]

#: what an :class:`Option` holds: ``number`` (an int or a finite float, taken as a float),
#: ``integer``, ``bool``, ``text`` (a string), ``any`` (checked by the component itself: a list,
#: a table)
OptionKind = Literal["number", "integer", "bool", "text", "any"]
#: the default of an option that must be given
REQUIRED: Final[Any] = ...


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
        """``data[k]`` checked as a (finite) number or an integer in ``lo..hi`` (an
        :class:`Option`'s check); ``default`` when it is not given or is wrong (a problem then)."""
        v = data.get(k, default)
        if v is default:
            return v
        option = Option("integer" if integer else "number", default, lo=lo, hi=hi, coerce=False)
        return option.checked(self, f"{key}.{k}" if key else k, v, default)


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
        if _NUMBER.problem(v) is not None:  # the one test of a number (Option.problem)
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
        if Option("integer", lo=lo, hi=hi).problem(v) is not None:
            self.said(key, f"{who}: option {key!r} must be an integer from {lo} to {hi}, not {v!r}")

    def option_bool(self, who: str, options: Mapping[str, Any], key: str) -> None:
        """A problem if ``key`` is given and is not true or false."""
        if key in options and Option("bool").problem(options[key]) is not None:
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
        """Problems a part found by itself (an adapter's options, a modality's) as problems of
        ``key``: each key under ``key`` (``inputs[0]`` and ``baud`` make ``inputs[0].baud``),
        and shown with it: ``"inputs[0].baud: text"`` when the part's problem was
        ``"baud: text"`` (an :class:`Option`'s), else ``"inputs[0]: sentence"``."""
        for q in other:
            full = f"{key}.{q.key}" if key and q.key else key or q.key
            if key and q.key and q.text.startswith(f"{q.key}: "):
                text = f"{full}: {q.text[len(q.key) + 2:]}"
            else:
                text = f"{key}: {q.text}" if key else q.text
            self.found.append(Problem(full, text))


def _is_number(v: Any) -> bool:
    """An int or a float (numpy's scalars too), never a bool."""
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and type(v).__name__ != "bool_"


def _bound(x: float) -> str:
    """A range's bound as written: an integral one in full (``10000000``), else ``:g``."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e16 else f"{x:g}"


def shown(v: Any) -> str:
    """A value as a configuration file writes it (``true``, ``nan``, ``-inf``, ``'soon'``)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float) and not math.isfinite(v):
        return "nan" if math.isnan(v) else "inf" if v > 0 else "-inf"
    return repr(v)


@dataclass(frozen=True)
class Option:
    """One declared option: its ``kind`` (:data:`OptionKind`), ``default`` (:data:`REQUIRED`: it
    must be given), the range ``lo..hi`` (``lo_open``: above ``lo``, not at it; ``hi_open``:
    below ``hi``), its ``unit``
    (``"s"``, ``"m"``, ``"B"``), the ``choices`` a text may take, ``none`` (None is a value:
    "not set"), a one-line ``doc``; ``coerce``: a number is taken as a float (else as given).

    :meth:`problem` is the one check of a value: a ``number`` is an ``int`` or a finite
    ``float``, never a bool, NaN, an infinity or a word; an ``integer`` an ``int``."""

    kind: OptionKind
    default: Any = REQUIRED
    doc: str = ""
    unit: str = ""
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    choices: tuple[Any, ...] = ()
    none: bool = False
    coerce: bool = True
    hi_open: bool = False

    @property
    def required(self) -> bool:
        return self.default is REQUIRED

    @property
    def numeric(self) -> bool:
        return self.kind in ("number", "integer")

    def _range(self, v: float | None = None) -> str:
        """Why ``v`` is out of range (``"is outside 1..8"``, ``"is below 0 s"``); with no
        value, the range itself (``"1..8"``, ``"above 0 s"``)."""
        unit = f" {self.unit}" if self.unit else ""
        lo = "" if self.lo is None else _bound(self.lo)
        hi = "" if self.hi is None else _bound(self.hi)
        closed = not (self.lo_open or self.hi_open)
        if v is None:
            if lo and hi and closed:
                return f"{lo}..{hi}{unit}"
            parts = ([f"above {lo}{unit}" if self.lo_open else f"at least {lo}{unit}"] if lo else []) + (
                [f"below {hi}{unit}" if self.hi_open else f"at most {hi}{unit}"] if hi else [])
            return " and ".join(parts)
        if lo and hi and closed:
            return f"is outside {lo}..{hi}{unit}"
        if self.hi is not None and (v > self.hi or (self.hi_open and v == self.hi)):
            return f"is not below {hi}{unit}" if self.hi_open else f"is above {hi}{unit}"
        return f"is not above {lo}{unit}" if self.lo_open else f"is below {lo}{unit}"

    def problem(self, v: Any) -> str | None:
        """What is wrong with ``v`` as this option's value (``"not a finite number, got nan"``),
        or None."""
        if v is None and (self.none or self.default is None):
            return None
        if self.kind == "any":
            return None
        if self.kind == "bool":
            return None if isinstance(v, bool) else f"true or false, got {shown(v)}"
        if self.kind == "text":
            if not isinstance(v, str):
                return f"a string, got {shown(v)}"
        elif self.kind == "integer":
            if not isinstance(v, numbers.Integral) or not _is_number(v):
                return f"not an integer, got {shown(v)}"
        elif not _is_number(v) or not math.isfinite(v):
            return f"not a finite number, got {shown(v)}"
        if self.choices and v not in self.choices:
            return f"one of {', '.join(map(shown, self.choices))}, got {shown(v)}"
        if self.numeric and ((self.lo is not None and (v < self.lo or (self.lo_open and v == self.lo)))
                             or (self.hi is not None and (v > self.hi or (self.hi_open and v == self.hi)))):
            return f"{shown(v)} {self._range(v)}"
        return None

    def value(self, v: Any) -> Any:
        """``v`` (that passed :meth:`problem`) as the component takes it: a number as a float."""
        if self.kind == "number" and self.coerce and v is not None:
            return float(v)
        if self.kind == "integer" and self.coerce and v is not None:
            return int(v)
        return v

    def checked(self, p: Problems, key: str, v: Any, fallback: Any = None) -> Any:
        """``v`` as :meth:`value`; a problem of ``key`` and ``fallback`` when it is wrong."""
        text = self.problem(v)
        if text is not None:
            p.add(key, text)
            return fallback
        return self.value(v)

    def describe(self) -> str:
        """Its type, range and unit in a few words (docs, ``coex plugins`` listings)."""
        what = {"number": "number", "integer": "integer", "bool": "true/false", "text": "string",
                "any": "value"}[self.kind]
        if self.choices:
            what += " (" + ", ".join(map(shown, self.choices)) + ")"
        if self.numeric and (self.lo is not None or self.hi is not None):
            what += ", " + self._range()
        elif self.unit:
            what += f" ({self.unit})"
        return what


def number(default: Any = REQUIRED, doc: str = "", *, unit: str = "", lo: float | None = None,
           hi: float | None = None, above: float | None = None, below: float | None = None,
           choices: tuple[float, ...] = (), none: bool = False) -> Option:
    """A number option (an int or a finite float, taken as a float): ``lo``/``hi`` inclusive,
    ``above``/``below`` exclusive, one of ``choices`` when given."""
    return Option("number", default, doc, unit, above if above is not None else lo,
                  below if below is not None else hi, above is not None, choices=choices, none=none,
                  hi_open=below is not None)


def integer(default: Any = REQUIRED, doc: str = "", *, unit: str = "", lo: int | None = None,
            hi: int | None = None, choices: tuple[int, ...] = (), none: bool = False) -> Option:
    """An integer option."""
    return Option("integer", default, doc, unit, lo, hi, choices=choices, none=none)


def flag(default: Any = REQUIRED, doc: str = "") -> Option:
    """A true/false option."""
    return Option("bool", default, doc)


def text(default: Any = REQUIRED, doc: str = "", *, choices: tuple[str, ...] = (), none: bool = False) -> Option:
    """A string option (one of ``choices`` when given)."""
    return Option("text", default, doc, choices=choices, none=none)


def anything(default: Any = REQUIRED, doc: str = "") -> Option:
    """An option the component checks itself (a list, a table)."""
    return Option("any", default, doc)


def inferred(default: Any, doc: str = "") -> Option:
    """The option a bare default declares (a plain ``{name: default}`` mapping, an adapter's
    ``(default, doc)``): a float or an int default a number (kept as given), a bool one true or
    false, anything else a value the component checks itself."""
    if isinstance(default, bool):
        return Option("bool", default, doc)
    if isinstance(default, int | float) and not isinstance(default, bool):
        return Option("number", default, doc, coerce=False)
    return Option("any", default, doc)


class Options(Mapping[str, Option]):
    """A component's declared options, by name (the schema :func:`merged_config` checks):
    ``Options(send_delay=number(20.0, "...", unit="s", lo=0), ...)``, or
    :meth:`inferred` from a plain mapping of defaults."""

    def __init__(self, fields: Mapping[str, Option] | None = None, /, **more: Option) -> None:
        self._fields: dict[str, Option] = {**(fields or {}), **more}

    @classmethod
    def of(cls, declared: Mapping[str, Any]) -> Options:
        """``declared`` as an :class:`Options`: itself, or each value an :class:`Option`, a
        ``(default, doc)`` pair or a bare default (:func:`inferred`)."""
        if isinstance(declared, Options):
            return declared
        out: dict[str, Option] = {}
        for k, v in declared.items():
            if isinstance(v, Option):
                out[str(k)] = v
            elif isinstance(v, tuple) and len(v) == 2 and isinstance(v[1], str):
                out[str(k)] = inferred(v[0], v[1])
            else:
                out[str(k)] = inferred(v)
        return cls(out)

    def __getitem__(self, key: str) -> Option:
        return self._fields[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._fields)

    def __len__(self) -> int:
        return len(self._fields)

    def __or__(self, other: Mapping[str, Option]) -> Options:
        return Options({**self._fields, **other})

    def defaults(self) -> dict[str, Any]:
        """Each option's default (required ones left out)."""
        return {k: o.default for k, o in self._fields.items() if not o.required}

    def numeric(self) -> list[str]:
        """The names of the number and integer options."""
        return [k for k, o in self._fields.items() if o.numeric]

    def check(self, config: Mapping[str, Any] | None, p: Problems, key: str = "", *, what: str = "",
              ignore: Iterable[str] = ()) -> dict[str, Any]:
        """``config`` merged over the defaults and coerced; every problem into ``p`` under
        ``key`` (``modalities.bathymetry.options`` makes ``modalities.bathymetry.options.send_delay``):
        a key not declared (nor in ``ignore``), a required one missing, a value :meth:`Option.problem`
        refuses (its default kept then). ``what`` names the component ("bathymetry sender")."""
        def full(k: str) -> str:
            return f"{key}.{k}" if key else k

        out = self.defaults()
        if config is not None and not isinstance(config, Mapping):
            p.add(key, f"the {what + ' ' if what else ''}options must be a table, got {type(config).__name__}")
            return out
        skip = set(ignore)
        given = config or {}
        for k, v in given.items():
            if k in skip:
                continue
            option = self._fields.get(str(k))
            if option is None:
                p.said(full(str(k)), f"unknown {what + ' ' if what else ''}option {str(k)!r} "
                                     f"(known: {', '.join(sorted(self))})")
                continue
            out[str(k)] = option.checked(p, full(str(k)), v, option.default)
        for k, option in self._fields.items():
            if option.required and k not in given:
                p.add(full(k), f"missing{': ' + option.doc if option.doc else ''}")
        return out


#: any finite number (the adapters' ``option_number``)
_NUMBER = Option("number")


def merged_config(config: Mapping[str, Any] | None, defaults: Mapping[str, Any],
                  what: str = "") -> dict[str, Any]:
    """``config`` checked against the declared options (an :class:`Options`, or a plain mapping
    of defaults, :meth:`Options.of`) and merged over their defaults, numbers as floats: one
    :class:`ConfigError` (``what`` names the component, e.g. ``"imagery sender"``) listing
    every problem, each keyed by its option (``send_delay: not a finite number, got nan``; an
    unknown one ``unknown imagery sender option 'x' (known: ...)``)."""
    if config is not None and not isinstance(config, Mapping):
        raise ConfigError(f"{what or 'the'} configuration must be a mapping, got {type(config).__name__}")
    p = Problems()
    cfg = Options.of(defaults).check(config, p, what=what)
    p.check()
    return cfg
