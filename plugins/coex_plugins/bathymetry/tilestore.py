"""The bathymetry plugin's one tile store, for the vehicle's map and the topside receiver.

Two parts, used by :class:`.quadtree.QuadtreeMap` (the vehicle's out-of-core map), by
:class:`.receiver.BathymetryReceiver` (its levels' tiles) and by :mod:`.overview` (the stored
chunks of a level's drawn overview):

* **The codec** (:func:`encode`, :func:`decode`): named float, integer and bool arrays as bytes,
  lossless. ``CXTS``, a version byte, flags (compressed, shuffled), then per array its name,
  kind, stored type and shape, then the arrays' bytes, as they are or grouped by significance
  (all first bytes, then all second ...: the high bytes of nearby values repeat, so they
  compress), zstd-compressed at ``level`` (0: not compressed). Integer arrays are stored in the smallest
  type that holds their values (a tile's sounding counts take one byte a cell), bool arrays one
  byte an element; :func:`decode` gives every array back in its own type and shape. It also
  reads every format stored before it (kept so that saved maps and stores still open): the
  map's ``CXT1`` tiles, the receiver's ``CXRT`` tiles and its ``CXOV`` overview chunks (zlib).
* **The cache** (:class:`TileCache`): resident tiles, least recently used first, under a memory
  budget in bytes; the tiles changed since they were last written (``dirty``); a tile leaving
  memory is written to a :class:`~coex_core.storage.Storage` first, and read back (decoded) when
  asked for again.
"""

from __future__ import annotations

import math
import struct
import zlib
from collections import OrderedDict
from collections.abc import Callable, Hashable, Iterable, Mapping
from typing import Any, Generic, TypeVar

import numpy as np
import numpy.typing as npt

from coex import StateError, Storage

__all__ = ["MAGIC", "TileCache", "decode", "encode"]

Array = npt.NDArray[Any]

#: The first bytes of a tile (or chunk) in the tile store's format.
MAGIC = b"CXTS"
_VERSION = 1
_HEAD = struct.Struct("<4sBBB")  # magic, version, flags (1: zstd, 2: shuffled), number of arrays
_ARRAY = struct.Struct("<BBB")  # kind, stored type, ndim (then the name and the shape)

# Type codes (the kind of an array and the type its bytes are stored in), never renumbered.
_TYPES: tuple[np.dtype[Any], ...] = tuple(np.dtype(t).newbyteorder("<") for t in (
    "bool", "u1", "u2", "u4", "u8", "i1", "i2", "i4", "i8", "f4", "f8"))
_CODE = {t: i for i, t in enumerate(_TYPES)}
_UNSIGNED = (_TYPES[1], _TYPES[2], _TYPES[3], _TYPES[4])
_SIGNED = (_TYPES[5], _TYPES[6], _TYPES[7], _TYPES[8])

_zstd: dict[int, Any] = {}


def _compressor(level: int) -> Any:
    c = _zstd.get(level)
    if c is None:
        import zstandard

        c = _zstd[level] = zstandard.ZstdCompressor(level=level)
    return c


def _decompressor() -> Any:
    d = _zstd.get(-1)
    if d is None:
        import zstandard

        d = _zstd[-1] = zstandard.ZstdDecompressor()
    return d


def _shuffle(a: Array) -> bytes:
    """Bytes of ``a`` grouped by significance (all first bytes, then all second ...)."""
    if a.itemsize == 1:
        return np.ascontiguousarray(a).tobytes()
    return np.ascontiguousarray(a.reshape(-1).view(np.uint8).reshape(-1, a.itemsize).T).tobytes()


def _unshuffle(b: bytes | memoryview, dtype: np.dtype[Any], count: int) -> Array:
    raw = np.frombuffer(b, np.uint8, count * dtype.itemsize)
    if dtype.itemsize == 1:
        return raw.view(dtype).copy()
    return raw.reshape(dtype.itemsize, count).T.copy().view(dtype).reshape(-1)


def _kind(a: Array) -> np.dtype[Any]:
    dt = a.dtype
    if dt.kind == "b":
        return _TYPES[0]
    if dt.kind in "ui" or dt.kind == "f":
        t = dt.newbyteorder("<")
        if t in _CODE:
            return t
    raise TypeError(f"the tile store holds bool, integer and float arrays, not {dt}")


def _narrow(a: Array, kind: np.dtype[Any]) -> np.dtype[Any]:
    """The smallest type that holds the integer array ``a`` (its kind otherwise)."""
    if kind.kind not in "ui" or a.size == 0:
        return kind
    lo, hi = int(a.min()), int(a.max())
    for t in _UNSIGNED if lo >= 0 else _SIGNED:
        info = np.iinfo(t)
        if info.min <= lo and hi <= info.max:
            return t if t.itemsize <= kind.itemsize else kind
    return kind


def encode(arrays: Mapping[str, Array], level: int = 1, *, shuffle: bool = True) -> bytes:
    """Named arrays (bool, integer or float, any shape) as bytes, losslessly: zstd at ``level``
    (0: not compressed) of their values, byte-shuffled unless ``shuffle`` is False, integers
    in the smallest type that holds them. :func:`decode` gives them back.

    Shuffling suits smooth values whose low bytes vary (the map's sums); values from a few
    repeating levels (the receiver's cells, whole decimetres and NaN) compress better as they
    are, where zstd finds whole repeated elements."""
    if len(arrays) > 255:
        raise ValueError("at most 255 arrays in one tile")
    head, parts = [], []
    for name, value in arrays.items():
        a = np.asarray(value)
        kind = _kind(a)
        stored = _narrow(a, kind)
        key = name.encode()
        if len(key) > 255 or a.ndim > 255:
            raise ValueError(f"array {name!r}: name or dimensions too long")
        head.append(_ARRAY.pack(_CODE[kind], _CODE[stored], a.ndim) + bytes([len(key)]) + key
                    + struct.pack(f"<{a.ndim}I", *a.shape))
        a = a.astype(stored, copy=False)
        parts.append(_shuffle(a) if shuffle else np.ascontiguousarray(a).tobytes())
    payload = b"".join(parts)
    flags = 2 if shuffle else 0
    if level > 0:
        payload, flags = _compressor(int(level)).compress(payload), flags | 1
    return _HEAD.pack(MAGIC, _VERSION, flags, len(head)) + b"".join(head) + payload


def decode(data: bytes) -> dict[str, Array]:
    """The named arrays of a tile in any format the plugin ever stored: the tile store's
    (``CXTS``) and, from before it, the map's ``CXT1`` tiles (``count``, ``stats``), the
    receiver's ``CXRT`` tiles (``held``, ``stamp``, ``received``, ``values``) and ``CXOV``
    overview chunks (``step``, ``mean``, and ``count`` when it has counts). Raises
    ``ValueError`` when the bytes are none of them or damaged."""
    magic = bytes(data[:4])
    import zstandard

    try:
        if magic == MAGIC:
            return _decode_cxts(data)
        if magic == b"CXT1":
            return _decode_cxt1(data)
        if magic == b"CXRT":
            return _decode_cxrt(data)
        if magic == b"CXOV":
            return _decode_cxov(data)
    except (struct.error, zlib.error, zstandard.ZstdError, IndexError, KeyError, UnicodeDecodeError) as exc:
        raise ValueError(f"damaged {magic!r} tile ({exc})") from exc
    raise ValueError(f"not a stored tile (starts {magic!r})")


def _decode_cxts(data: bytes) -> dict[str, Array]:
    _, version, flags, count = _HEAD.unpack_from(data)
    if version != _VERSION:
        raise ValueError(f"tile store format version {version} (this one reads {_VERSION})")
    o = _HEAD.size
    heads = []
    for _ in range(count):
        kind, stored, ndim = _ARRAY.unpack_from(data, o)
        o += _ARRAY.size
        n = data[o]
        name = bytes(data[o + 1:o + 1 + n]).decode()
        o += 1 + n
        shape = struct.unpack_from(f"<{ndim}I", data, o)
        o += 4 * ndim
        heads.append((name, _TYPES[kind], _TYPES[stored], shape))
    payload = memoryview(data)[o:]
    if flags & 1:
        payload = memoryview(_decompressor().decompress(bytes(payload)))
    out: dict[str, Array] = {}
    p = 0
    for name, kind, stored, shape in heads:
        size = int(np.prod(shape, dtype=np.int64))
        nb = size * stored.itemsize
        if p + nb > len(payload):
            raise ValueError(f"array {name!r} truncated")
        if flags & 2:
            a = _unshuffle(payload[p:p + nb], stored, size)
        else:
            a = np.frombuffer(payload[p:p + nb], stored, size).copy()
        p += nb
        out[name] = a.astype(kind.newbyteorder("="), copy=False).reshape(shape)
    if p != len(payload):
        raise ValueError(f"{len(payload) - p} bytes left over")
    return out


# ------------------------------------------------------------------ formats stored before CXTS

_CXT1_COUNTS = (_TYPES[1], _TYPES[2], _TYPES[3], _TYPES[10])


def _decode_cxt1(data: bytes) -> dict[str, Array]:
    """The map's tiles before the tile store: ``CXT1``, the count's type code (u1, u2, u4, f8),
    zstd of the byte-shuffled count and then the sums, sums of squares and times (float64)."""
    if data[4] > 3:
        raise ValueError(f"CXT1 count type {data[4]}")
    dt = _CXT1_COUNTS[data[4]]
    payload = _decompressor().decompress(bytes(data[5:]))
    tt, rest = divmod(len(payload), dt.itemsize + 24)
    if rest:
        raise ValueError(f"CXT1 payload of {len(payload)} bytes")
    nc = tt * dt.itemsize
    return {"count": _unshuffle(payload[:nc], dt, tt).astype(np.float64),
            "stats": _unshuffle(payload[nc:], _TYPES[10], 3 * tt).reshape(3, tt)}


_CXRT = struct.Struct("<4sBBBB")


def _decode_cxrt(data: bytes) -> dict[str, Array]:
    """The receiver's tiles before the tile store: ``CXRT``, version 1, flags (1: zlib), ``n``
    subgrids a side of ``side`` cells, then held (u1), stamps, arrival times and cells (f8)."""
    _, version, flags, n, side = _CXRT.unpack_from(data)
    if version != 1:
        raise ValueError(f"CXRT version {version}")
    payload = bytes(data[_CXRT.size:])
    if flags & 1:
        payload = zlib.decompress(payload)
    cells = (n * side) ** 2
    if len(payload) != n * n * 17 + cells * 8:
        raise ValueError(f"CXRT payload of {len(payload)} bytes")
    o = n * n
    return {"held": np.frombuffer(payload, np.uint8, n * n).reshape(n, n).astype(bool),
            "stamp": np.frombuffer(payload, "<f8", n * n, o).reshape(n, n).astype(np.float64),
            "received": np.frombuffer(payload, "<f8", n * n, o + 8 * n * n).reshape(n, n).astype(np.float64),
            "values": np.frombuffer(payload, "<f8", cells, o + 16 * n * n)
            .reshape(n * side, n * side).astype(np.float64)}


_CXOV = struct.Struct("<4sBBBBI")


def _decode_cxov(data: bytes) -> dict[str, Array]:
    """Overview chunks before the tile store: ``CXOV``, version 1, flags (1: zlib), whether it
    has counts, a pad byte, the step (u4), then a square of means (f8, or f4 with counts) and
    of counts (f4)."""
    _, version, flags, counted, _, step = _CXOV.unpack_from(data)
    if version != 1:
        raise ValueError(f"CXOV version {version}")
    payload = bytes(data[_CXOV.size:])
    if flags & 1:
        payload = zlib.decompress(payload)
    n = len(payload) // 8
    side = math.isqrt(n)
    if side * side * 8 != len(payload):
        raise ValueError(f"CXOV payload of {len(payload)} bytes")
    out = {"step": np.array([step], np.int64)}
    if counted:
        out["mean"] = np.frombuffer(payload, "<f4", n).reshape(side, side).astype(np.float32)
        out["count"] = np.frombuffer(payload, "<f4", n, 4 * n).reshape(side, side).astype(np.float32)
    else:
        out["mean"] = np.frombuffer(payload, "<f8", n).reshape(side, side).astype(np.float64)
    return out


# ---------------------------------------------------------------------------------- the cache

K = TypeVar("K", bound=Hashable)
V = TypeVar("V")


class TileCache(Generic[K, V]):
    """Resident tiles (least recently used first) under a memory budget, spilled to a storage.

    ``budget``: bytes the resident tiles may take (a number, or a function asked each time:
    the map's budget shrinks as its index grows); beyond it the least recently used tiles leave
    memory (never those a call protects, nor the last ``min_resident``). A tile that changed
    since it was last written (:meth:`add`, :meth:`touch`; ``dirty``) is written to
    ``storage`` as it leaves, and :meth:`sync` writes them all. Its owner says how: ``name``
    (the tile's key in the storage), ``encode`` (its bytes, usually :func:`encode` of its
    arrays), ``decode`` (the tile from its bytes, usually through :func:`decode`), ``nbytes``
    (memory it holds); ``written(key, tile, size)`` is told of every write, ``dropped(tile)`` of
    every tile that left memory (to reuse its arrays). A failed write raises, unless
    ``failed(exc)`` is given: then the tile stays in memory and eviction stops for now."""

    def __init__(self, *, name: Callable[[K], str], encode: Callable[[K, V], bytes],
                 decode: Callable[[K, bytes], V], nbytes: Callable[[V], int],
                 budget: int | Callable[[], int], min_resident: int = 1,
                 written: Callable[[K, V, int], None] | None = None,
                 dropped: Callable[[V], None] | None = None,
                 failed: Callable[[Exception], None] | None = None,
                 storage: Storage | None = None, owner: str = "tile store",
                 resident: OrderedDict[K, V] | None = None, dirty: Iterable[K] = ()) -> None:
        self._name, self._encode, self._decode, self._size = name, encode, decode, nbytes
        self._budget = budget
        self.min_resident = int(min_resident)
        self._written, self._dropped, self._failed = written, dropped, failed
        self.storage = storage
        self.owner = owner
        #: the resident tiles, least recently used first
        self.resident: OrderedDict[K, V] = OrderedDict() if resident is None else resident
        #: resident tiles the storage lacks or holds older
        self.dirty: set[K] = set(dirty)
        self.nbytes = sum(self._size(v) for v in self.resident.values())

    @property
    def budget(self) -> int:
        b = self._budget
        return int(b() if callable(b) else b)

    def __len__(self) -> int:
        return len(self.resident)

    def __contains__(self, key: object) -> bool:
        return key in self.resident

    def peek(self, key: K) -> V | None:
        """The tile if resident (it stays where it is in the order), else None."""
        return self.resident.get(key)

    def get(self, key: K, protect: Iterable[K] = ()) -> V:
        """Tile ``key``: resident (now the most recently used), else read back from the storage
        (others may leave memory, not ``protect``). Raises :class:`StateError` when the
        storage is not attached or lacks it."""
        t = self.resident.get(key)
        if t is not None:
            self.resident.move_to_end(key)
            return t
        name = self._name(key)
        if self.storage is None:
            raise StateError(f"{self.owner}: its tiles are in the node's storage, which is not "
                             "attached (Node.attach_storage; NodeStore.restore does it)")
        data = self.storage.get(name)
        if data is None:
            raise StateError(f"{self.owner}: tile {name} is missing from its storage")
        t = self._decode(key, data)
        return self._insert(key, t, protect, dirty=False)

    def add(self, key: K, tile: V, protect: Iterable[K] = ()) -> V:
        """A new tile (dirty: the storage lacks it), now the most recently used."""
        return self._insert(key, tile, protect, dirty=True)

    def _insert(self, key: K, tile: V, protect: Iterable[K], dirty: bool) -> V:
        old = self.resident.pop(key, None)
        if old is not None:
            self.nbytes -= self._size(old)
        self.resident[key] = tile
        self.nbytes += self._size(tile)
        if dirty:
            self.dirty.add(key)
        if self.nbytes > self.budget:
            self.evict({key, *protect})
        return tile

    def touch(self, key: K) -> None:
        """Resident tile ``key`` changed: the storage's copy is out of date."""
        self.dirty.add(key)

    def evict(self, protect: Iterable[K] = ()) -> None:
        """Least recently used tiles out of memory (written first when dirty) until the rest
        fit in the budget."""
        keep = set(protect)
        budget = self.budget
        res = self.resident
        while self.nbytes > budget and len(res) > self.min_resident:
            victim = next((k for k in res if k not in keep), None)
            if victim is None:
                return
            t = res[victim]
            if victim in self.dirty and not self.write(victim, t):
                res.move_to_end(victim)  # the storage failed: it stays (the owner was told)
                return
            del res[victim]
            self.nbytes -= self._size(t)
            if self._dropped is not None:
                self._dropped(t)

    def write(self, key: K, tile: V) -> bool:
        """Write ``tile`` (resident or not) to the storage now. False if the storage failed and
        ``failed`` was told."""
        if self.storage is None:
            raise StateError(f"{self.owner}: no storage attached to write tiles to")
        data = self._encode(key, tile)
        try:
            self.storage.put(self._name(key), data)
        except Exception as exc:
            if self._failed is None:
                raise
            self._failed(exc)
            return False
        self.dirty.discard(key)
        if self._written is not None:
            self._written(key, tile, len(data))
        return True

    def sync(self) -> None:
        """Write every resident tile that changed since it was last written."""
        for key in [k for k in self.resident if k in self.dirty]:
            self.write(key, self.resident[key])
