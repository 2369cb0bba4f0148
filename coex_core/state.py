"""Explicit, versioned state of nodes, channel managers, senders and receivers (never pickle).

What a node holds (queues, acks, maps, images, series, requests) is saved by walking its objects
and writing only what this module knows how to write:

* ``None``, ``bool``, ``int``, ``float`` (NaN and infinities too), ``str``;
* ``list``, ``tuple``, ``dict`` (any such keys), ``set``, ``frozenset``, ``OrderedDict``,
  ``deque``;
* ``bytes`` / ``bytearray`` and numpy arrays (kept apart, in the container's array part);
  numpy scalars;
* the wire format's messages and their parts (``coex_core.messages``), by message type name;
* objects of classes **registered** with :func:`persistent` under a stable name (a plugin's
  own state classes: ``"bathymetry.Region"``), with a version, and the attributes that are not
  state (callbacks, clocks: ``transient``), which the class's ``_after_restore()`` rebuilds.

The persistence hooks are declared by the registered class itself: a class that defines
``_before_save(self)`` has it called just before its fields are read (a map writes its resident
tiles to its storage), one that defines ``_after_restore(self)`` has it called once the whole
state is restored. :func:`persistent` records at decoration time which of the two the class
declares (its own or inherited methods); nothing is looked up on the objects while saving or
loading.

Anything else is a :class:`StateError` naming the type and where it was found: nothing is saved
by accident, and renaming or moving a module does not break a saved dive (names are stable,
not module paths). An object reached twice is saved once and restored as one object (the
console and a node share a receiver).

The container (:func:`dumps` / :func:`loads`): ``b"COEXSTATE\\n"``, a 4-byte big-endian length,
that many bytes of UTF-8 JSON ``{"format": "coex-state", "version": 1, "classes": {name:
version}, "root": ...}``, then a numpy ``.npz`` archive (stored uncompressed: a node saves before every transmission; read with ``allow_pickle=False``) of the arrays
and byte strings the JSON refers to by index (``{"$a": i}``, ``{"$b": i}``). The tagged JSON
forms are listed in ``docs/persistence.md``.

In parts (:func:`dumps_parts` / :func:`loads_parts`, what a node store writes incrementally): the
same JSON document (``"version": 2``) with arrays and byte strings named by their content
(``{"$a": "<blake2b-128 hex>"}``) and an ``id`` only on objects reached twice, and the arrays by
name: what did not change between two saves gives the same text and names.
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import io
import json
import math
import struct
from collections import OrderedDict, deque
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np

from . import messages as _messages
from .errors import CoexError

__all__ = ["FORMAT", "PARTS_VERSION", "VERSION", "StateError", "dumps", "dumps_parts", "loads", "loads_parts",
           "persistent", "registered"]

FORMAT = "coex-state"
VERSION = 1
#: the document's version in parts (:func:`dumps_parts`)
PARTS_VERSION = 2
MAGIC = b"COEXSTATE\n"


class StateError(CoexError, ValueError):
    """A state that cannot be saved (an unknown type) or loaded (corrupt, unknown class, newer
    class version)."""


@dataclasses.dataclass(frozen=True)
class _Class:
    name: str
    cls: type
    version: int
    transient: frozenset[str]
    upgrade: Callable[[dict[str, Any], int], dict[str, Any]] | None
    #: the class declares ``_before_save(self)`` (called before its fields are read)
    before_save: bool = False
    #: the class declares ``_after_restore(self)`` (called once the whole state is restored)
    after_restore: bool = False


#: the persistence hooks a registered class may declare (:func:`persistent`)
_HOOKS = ("_before_save", "_after_restore")

_BY_NAME: dict[str, _Class] = {}
_BY_CLASS: dict[type, _Class] = {}

T = TypeVar("T", bound=type)


def persistent(name: str, *, version: int = 1, transient: tuple[str, ...] = (),
               upgrade: Callable[[dict[str, Any], int], dict[str, Any]] | None = None
               ) -> Callable[[T], T]:
    """Class decorator: objects of the class may be saved, under ``name`` (stable across module
    moves) and ``version``. ``transient`` attributes are not saved (restored as absent; the
    class's ``_after_restore()`` sets them), nor those a base class lists in its
    ``_state_transient`` class attribute. ``upgrade(fields, saved_version)`` turns the fields
    saved by an older version into this version's (without it, an older version loads as is,
    and a newer one is refused).

    The class may declare the persistence hooks ``_before_save(self)`` (called just before its
    fields are saved) and ``_after_restore(self)`` (called once everything is restored, in the
    order restored); which of them it declares is recorded here, once. A non-callable attribute
    of either name is a :class:`StateError`."""

    def deco(cls: T) -> T:
        old = _BY_NAME.get(name)
        if old is not None and old.cls.__qualname__ != cls.__qualname__:
            raise StateError(f"state name {name!r} is taken by {old.cls.__qualname__}")
        inherited = {t for k in cls.__mro__ for t in getattr(k, "_state_transient", ())}
        declared = {h: any(h in vars(k) for k in cls.__mro__) for h in _HOOKS}
        for h in _HOOKS:
            if declared[h] and not callable(getattr(cls, h)):
                raise StateError(f"{cls.__qualname__}.{h} is not a method (a persistence hook of {name!r})")
        entry = _Class(name, cls, int(version), frozenset(transient) | inherited, upgrade,
                       before_save=declared["_before_save"], after_restore=declared["_after_restore"])
        _BY_NAME[name] = entry
        _BY_CLASS[cls] = entry
        return cls

    return deco


def registered() -> dict[str, int]:
    """Every registered state class name and its version."""
    return {n: c.version for n, c in sorted(_BY_NAME.items())}


#: message classes whose saved form changed: name -> version (each change added optional fields,
#: so an older saved one loads with those fields at their defaults)
_MESSAGE_VERSIONS = {
    "SurveyStatus": 2,  # 0.2.0: detail
}


def _with_defaults(cls: type) -> Callable[[dict[str, Any], int], dict[str, Any]]:
    defaults = {f.name: f.default for f in dataclasses.fields(cls)  # type: ignore[arg-type]
                if f.default is not dataclasses.MISSING}

    def upgrade(fields: dict[str, Any], saved: int) -> dict[str, Any]:
        return {**defaults, **fields}

    return upgrade


def _register_messages() -> None:
    """The wire format's messages, their parts and enums, by class name ("msg.Subgrid")."""
    for obj in vars(_messages).values():
        if not isinstance(obj, type) or obj.__module__ != _messages.__name__:
            continue
        if dataclasses.is_dataclass(obj):
            version = _MESSAGE_VERSIONS.get(obj.__name__, 1)
            persistent("msg." + obj.__name__, version=version,
                       upgrade=_with_defaults(obj) if version > 1 else None)(obj)
        elif issubclass(obj, enum.Enum):
            persistent("msg." + obj.__name__)(obj)


_register_messages()


# --------------------------------------------------------------------------------- encode

class _Writer:
    def __init__(self, by_content: bool = False) -> None:
        #: :func:`dumps_parts`: arrays named by their content, shared objects alone numbered
        self.by_content = by_content
        self.named: dict[str, np.ndarray] = {}
        self.objects: list[dict[str, Any]] = []
        self.refs: list[dict[str, Any]] = []
        self._names: list[str] = []
        self.blobs: list[np.ndarray] = []
        #: id() of an array or byte string already written -> its blob (written once, and
        #: restored as one object where several places share it)
        self.blob_of: dict[int, int] = {}
        self.memo: dict[int, int] = {}
        self.keep: list[Any] = []  # objects whose id() is in memo stay alive while writing
        self.used: dict[str, int] = {}

    def blob(self, arr: np.ndarray, source: Any) -> int:
        known = self.blob_of.get(id(source))
        if known is not None:
            return self._names[known] if self.by_content else known  # type: ignore[return-value]
        if self.by_content:  # the name is the content's (a second equal array: "<hash>.1", ...)
            digest = hashlib.blake2b(arr.data if arr.flags.c_contiguous else arr.tobytes(), digest_size=16)
            digest.update(f"{arr.dtype.str}{arr.shape}".encode())
            base = name = digest.hexdigest()
            k = 0
            while name in self.named:
                k += 1
                name = f"{base}.{k}"
            self.named[name] = arr
            self._names.append(name)
            self.blobs.append(arr)
            self.blob_of[id(source)] = len(self.blobs) - 1
            self.keep.append(source)
            return name  # type: ignore[return-value]
        self.blobs.append(arr)
        self.blob_of[id(source)] = len(self.blobs) - 1
        self.keep.append(source)
        return len(self.blobs) - 1

    def enc(self, x: Any, path: str) -> Any:
        if x is None or isinstance(x, bool | str):
            return x
        if isinstance(x, enum.Enum):
            c = self._cls(x, path)
            return {"$e": c.name, "v": x.value}
        if isinstance(x, int) and type(x) is int:
            return x
        if isinstance(x, float) and type(x) is float:
            return x if math.isfinite(x) else {"$f": repr(x)}
        if isinstance(x, np.ndarray):
            if x.dtype == object:
                raise StateError(f"{path}: numpy array of Python objects")
            return {"$a": self.blob(np.ascontiguousarray(x), x)}
        if isinstance(x, np.generic):
            return {"$n": x.dtype.str, "v": self.enc(x.item(), path)}
        if isinstance(x, bytes | bytearray):
            tag = "$b" if isinstance(x, bytes) else "$ba"
            return {tag: self.blob(np.frombuffer(bytes(x), np.uint8), x)}
        if isinstance(x, list) and type(x) is list:
            if _plain(x):
                return list(x)
            return [self.enc(v, f"{path}[{i}]") for i, v in enumerate(x)]
        if type(x) is tuple:
            if _plain(x):
                return {"$t": list(x)}
            return {"$t": [self.enc(v, f"{path}[{i}]") for i, v in enumerate(x)]}
        if type(x) in (set, frozenset):
            items = [self.enc(v, f"{path}{{}}") for v in x]
            return {"$s" if type(x) is set else "$fs": items}
        if type(x) is deque:
            return {"$q": [self.enc(v, f"{path}[{i}]") for i, v in enumerate(x)], "max": x.maxlen}
        if type(x) in (dict, OrderedDict):
            items = [[self.enc(k, f"{path}.key"), self.enc(v, f"{path}[{k!r}]")]
                     for k, v in x.items()]
            return {"$d" if type(x) is dict else "$od": items}
        return self._object(x, path)

    def _cls(self, x: Any, path: str) -> _Class:
        c = _BY_CLASS.get(type(x))
        if c is None:
            raise StateError(f"{path}: a {type(x).__module__}.{type(x).__qualname__} is not "
                             f"registered state (coex_core.state.persistent){_hint(type(x))}")
        self.used[c.name] = c.version
        return c

    def _object(self, x: Any, path: str) -> Any:
        c = self._cls(x, path)
        ref = self.memo.get(id(x))
        if ref is not None:
            r = {"$r": ref}
            self.refs.append(r)
            return r
        ref = self.memo[id(x)] = len(self.memo)
        self.keep.append(x)
        if c.before_save:  # e.g. a map writes its resident tiles to its storage first
            x._before_save()
        fields = _fields(x)
        o = {"$o": c.name, "id": ref, "f": {}}
        self.objects.append(o)
        o["f"] = {k: self.enc(v, f"{path}.{k}") for k, v in fields.items() if k not in c.transient}
        return o

    def renumber(self) -> None:
        """Only objects reached twice keep an id, numbered in order: adding an object to a
        queue leaves the rest of the document's text as it was."""
        shared = sorted({int(r["$r"]) for r in self.refs})
        new = {old: i for i, old in enumerate(shared)}
        for o in self.objects:
            if o["id"] in new:
                o["id"] = new[o["id"]]
            else:
                del o["id"]
        for r in self.refs:
            r["$r"] = new[int(r["$r"])]


#: values written as themselves (a finite float too)
_PLAIN = frozenset((int, str, bool, float, type(None)))


def _plain(items: list[Any] | tuple[Any, ...]) -> bool:
    """Whether every item is written as itself (the common list of ints of a message: written
    without visiting each item, which costs most of a snapshot's time)."""
    return all(type(v) in _PLAIN for v in items) and all(
        math.isfinite(v) for v in items if type(v) is float)


def _hint(cls: type) -> str:
    """Why an unregistered class may look registered: a registered base class (registration is
    not inherited) or a registered class of the same name (``@dataclass(slots=True)`` made a new
    class after ``@persistent`` registered the first)."""
    for base in cls.__mro__[1:]:
        entry = _BY_CLASS.get(base)
        if entry is not None and base is not object:
            return (f": its base class {base.__qualname__} is registered as {entry.name!r}, but "
                    f"@persistent is not inherited; register the subclass under a name of its own")
    same = [e for e in _BY_NAME.values() if e.cls.__qualname__ == cls.__qualname__
            and e.cls.__module__ == cls.__module__ and e.cls is not cls]
    if same:
        return (f": another class of that name is registered as {same[0].name!r}; with "
                f"@dataclass(slots=True), which makes a new class, put @persistent above @dataclass")
    return ""


def _fields(x: Any) -> dict[str, Any]:
    out: dict[str, Any] = dict(getattr(x, "__dict__", {}))
    for cls in type(x).__mro__:
        for slot in getattr(cls, "__slots__", ()):
            if slot not in ("__dict__", "__weakref__") and hasattr(x, slot):
                out[slot] = getattr(x, slot)
    return out


def dumps(root: Any) -> bytes:
    """The container bytes of ``root`` (see the module docstring); :class:`StateError` names
    the first thing that is not state."""
    w = _Writer()
    doc = {"format": FORMAT, "version": VERSION, "root": w.enc(root, "root")}
    doc["classes"] = dict(sorted(w.used.items()))
    text = json.dumps(doc, separators=(",", ":"), allow_nan=False).encode()
    buf = io.BytesIO()
    arrays: dict[str, Any] = {f"b{i}": b for i, b in enumerate(w.blobs)}
    np.savez(buf, **arrays)
    return MAGIC + struct.pack(">I", len(text)) + text + buf.getvalue()


def dumps_parts(root: Any) -> tuple[bytes, dict[str, np.ndarray]]:
    """``root`` as :func:`dumps` saves it, in parts a store can write apart: the document's
    UTF-8 JSON text (container version 2: arrays and byte strings referred to by the name of
    their content, ``{"$a": "<blake2b-128 hex>"}``, a second distinct equal one by
    ``"<hex>.1"``; only objects reached twice carry an ``id``) and the arrays by those names.
    What did not change between two saves gives the same text and names (see
    ``docs/persistence.md``, "Incremental snapshots"); :func:`loads_parts` reads it."""
    w = _Writer(by_content=True)
    doc = {"format": FORMAT, "version": 2, "root": w.enc(root, "root")}
    w.renumber()
    doc["classes"] = dict(sorted(w.used.items()))
    return json.dumps(doc, separators=(",", ":"), allow_nan=False).encode(), dict(w.named)


def loads_parts(text: bytes, arrays: Any) -> Any:
    """The object :func:`dumps_parts` wrote (``arrays``: its arrays by name)."""
    try:
        doc = json.loads(bytes(text).decode())
    except Exception as exc:
        raise StateError(f"corrupt CoEx state: {exc}") from exc
    return _load_doc(doc, arrays)


# --------------------------------------------------------------------------------- decode

class _Reader:
    def __init__(self, blobs: Any, versions: dict[str, int]) -> None:
        self.blobs = blobs
        self.versions = versions
        self.memo: dict[int, Any] = {}
        self.arrays: dict[int, Any] = {}
        self.restored: list[Any] = []

    def dec(self, x: Any) -> Any:
        if x is None or isinstance(x, bool | int | float | str):
            return x
        if isinstance(x, list):
            return [self.dec(v) for v in x]
        if not isinstance(x, dict) or len(x) == 0:
            raise StateError(f"malformed state value {x!r:.60}")
        tag = next(iter(x))
        v = x[tag]
        if tag == "$f":
            return float(v)
        if tag == "$a":
            if v not in self.arrays:
                self.arrays[v] = np.array(self.blobs[_blob_name(v)])
            return self.arrays[v]
        if tag == "$b":
            return np.asarray(self.blobs[_blob_name(v)]).tobytes()
        if tag == "$ba":
            return bytearray(np.asarray(self.blobs[_blob_name(v)]).tobytes())
        if tag == "$n":
            return np.dtype(v).type(self.dec(x["v"]))
        if tag == "$t":
            return tuple(self.dec(i) for i in v)
        if tag == "$s":
            return {self.dec(i) for i in v}
        if tag == "$fs":
            return frozenset(self.dec(i) for i in v)
        if tag == "$q":
            return deque((self.dec(i) for i in v), maxlen=x.get("max"))
        if tag == "$d":
            return {self.dec(k): self.dec(i) for k, i in v}
        if tag == "$od":
            return OrderedDict((self.dec(k), self.dec(i)) for k, i in v)
        if tag == "$e":
            return self._class(v).cls(x["v"])
        if tag == "$r":
            try:
                return self.memo[int(v)]
            except KeyError:
                raise StateError(f"state refers to object {v} before it is defined") from None
        if tag == "$o":
            return self._object(x)
        raise StateError(f"unknown state tag {tag!r}")

    def _class(self, name: str) -> _Class:
        c = _BY_NAME.get(name)
        if c is None:
            raise StateError(f"the state holds a {name!r}, which this installation does not "
                             "know (a plugin missing?)")
        return c

    def _object(self, x: dict[str, Any]) -> Any:
        c = self._class(x["$o"])
        saved = int(self.versions.get(c.name, c.version))
        if saved > c.version:
            raise StateError(f"{c.name} was saved by a newer version ({saved} > {c.version})")
        obj: Any = object.__new__(c.cls)
        if "id" in x:  # (version 2 numbers only the objects reached twice)
            self.memo[int(x["id"])] = obj
        fields = {k: self.dec(v) for k, v in x["f"].items()}
        if saved < c.version and c.upgrade is not None:
            fields = c.upgrade(fields, saved)
        for k, v in fields.items():
            object.__setattr__(obj, k, v)
        if c.after_restore:
            self.restored.append(obj)
        return obj


def loads(data: bytes) -> Any:
    """The object :func:`dumps` wrote. Each restored object of a class that declares
    ``_after_restore()`` (:func:`persistent`) has it called once everything is restored (in the
    order restored)."""
    if not data.startswith(MAGIC) or len(data) < len(MAGIC) + 4:
        raise StateError("not a CoEx state (no COEXSTATE header)")
    (n,) = struct.unpack(">I", data[len(MAGIC):len(MAGIC) + 4])
    start = len(MAGIC) + 4
    try:
        doc = json.loads(data[start:start + n].decode())
        blobs = np.load(io.BytesIO(data[start + n:]), allow_pickle=False)
    except Exception as exc:  # bad JSON, a damaged zip archive: never a crash of the caller
        raise StateError(f"corrupt CoEx state: {exc}") from exc
    return _load_doc(doc, blobs)


def _blob_name(v: Any) -> str:
    """The array part's name: ``b<i>`` in the container, the content's name in parts."""
    return v if isinstance(v, str) else f"b{int(v)}"


def _load_doc(doc: Any, blobs: Any) -> Any:
    if not isinstance(doc, dict):
        raise StateError("corrupt CoEx state: the document is not an object")
    if doc.get("format") != FORMAT:
        raise StateError(f"not a {FORMAT} document")
    if int(doc.get("version", 0)) > PARTS_VERSION:
        raise StateError(f"state container version {doc['version']} is newer than {PARTS_VERSION}")
    reader = _Reader(blobs, {str(k): int(v) for k, v in doc.get("classes", {}).items()})
    try:
        root = reader.dec(doc["root"])
    except StateError:
        raise
    except Exception as exc:  # a missing array, a wrong field: the file is damaged
        raise StateError(f"corrupt CoEx state: {exc}") from exc
    for obj in reader.restored:  # the objects of classes that declare the hook, in order
        obj._after_restore()
    return root
