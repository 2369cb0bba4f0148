"""The topside receiver's tile store: ``n x n`` subgrids of one level per tile (cells, and per
subgrid its stamp, arrival time and whether it is held), the tiles' stored form (a small header,
raw arrays, zlib), and the per-level index and statistics the receiver keeps beside them."""

from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass

import numpy as np

from coex_core.state import StateError, persistent
from coex_core.storage import Storage

__all__ = ["LevelIndex", "LevelStats", "Tile", "decode_tile", "encode_tile", "same_storage", "tile_nbytes"]

_TILE_HEADER = struct.Struct("<4sBBBB")
_TILE_MAGIC = b"CXRT"


@persistent("bathymetry.Tile")
class Tile:
    """``n x n`` subgrids of one level: cells (row 0 = south, NaN where nothing) and, per
    subgrid, stamp, arrival time and whether it is held. ``dirty``: the storage lacks it."""

    def __init__(self, n: int, side: int) -> None:
        self.values = np.full((n * side, n * side), np.nan)
        self.stamp = np.zeros((n, n))
        self.received = np.zeros((n, n))
        self.held = np.zeros((n, n), bool)
        self.dirty = True

    @property
    def nbytes(self) -> int:
        return int(self.values.nbytes + self.stamp.nbytes + self.received.nbytes + self.held.nbytes)


def tile_nbytes(n: int, side: int) -> int:
    return (n * side) ** 2 * 8 + n * n * 17


def encode_tile(t: Tile, compression: int) -> bytes:
    n = t.held.shape[0]
    side = t.values.shape[0] // n
    payload = b"".join((t.held.astype(np.uint8).tobytes(), t.stamp.astype("<f8").tobytes(),
                        t.received.astype("<f8").tobytes(), t.values.astype("<f8").tobytes()))
    flags = 0
    if compression > 0:
        payload, flags = zlib.compress(payload, compression), 1
    return _TILE_HEADER.pack(_TILE_MAGIC, 1, flags, n, side) + payload


def decode_tile(data: bytes, n: int, side: int, where: str) -> Tile:
    try:
        magic, version, flags, tn, tside = _TILE_HEADER.unpack_from(data)
        if magic != _TILE_MAGIC or version != 1 or (tn, tside) != (n, side):
            raise ValueError(f"header {magic!r} v{version} {tn}x{tside}")
        payload = data[_TILE_HEADER.size:]
        if flags & 1:
            payload = zlib.decompress(payload)
        buf = bytearray(payload)
        cells = (n * side) ** 2
        if len(buf) != n * n * 17 + cells * 8:
            raise ValueError(f"{len(buf)} bytes")
        t = object.__new__(Tile)
        t.held = np.frombuffer(buf, np.uint8, n * n).reshape(n, n).astype(bool)
        o = n * n
        t.stamp = np.frombuffer(buf, "<f8", n * n, o).reshape(n, n).astype(np.float64)
        o += 8 * n * n
        t.received = np.frombuffer(buf, "<f8", n * n, o).reshape(n, n).astype(np.float64)
        o += 8 * n * n
        t.values = np.frombuffer(buf, "<f8", cells, o).reshape(n * side, n * side).astype(np.float64)
    except (ValueError, struct.error, zlib.error) as exc:
        raise StateError(f"bathymetry receiver: stored tile {where} is damaged ({exc})") from exc
    t.dirty = False
    return t


@persistent("bathymetry.LevelIndex", transient=("pos",))
class LevelIndex:
    """Every tile of one level, and per tile a summary written whenever the tile is (its
    resident copy may be newer): subgrids held, newest and oldest stamp, oldest arrival, and the
    bytes the storage holds for it."""

    def __init__(self) -> None:
        self.n = 0
        self.keys = np.zeros((0, 2), np.int64)
        self.count = np.zeros(0, np.int64)
        self.newest = np.zeros(0)
        self.oldest = np.zeros(0)
        self.oldest_rx = np.zeros(0)
        self.stored = np.zeros(0, np.int64)
        self.pos: dict[tuple[int, int], int] = {}

    def _after_restore(self) -> None:
        self.pos = {(int(a), int(b)): i for i, (a, b) in enumerate(self.keys[:self.n].tolist())}

    def add(self, tx: int, ty: int) -> int:
        if self.n == len(self.count):
            cap = max(16, 2 * self.n)
            self.keys = np.resize(self.keys, (cap, 2))
            for name in ("count", "newest", "oldest", "oldest_rx", "stored"):
                setattr(self, name, np.resize(getattr(self, name), cap))
        i = self.n
        self.keys[i] = (tx, ty)
        self.count[i], self.stored[i] = 0, 0
        self.newest[i], self.oldest[i], self.oldest_rx[i] = -math.inf, math.inf, math.inf
        self.pos[(tx, ty)] = i
        self.n += 1
        return i

    def summarise(self, i: int, t: Tile) -> None:
        held = t.held
        n = int(np.count_nonzero(held))
        self.count[i] = n
        if n:
            st = t.stamp[held]
            self.newest[i], self.oldest[i] = st.max(), st.min()
            self.oldest_rx[i] = t.received[held].min()
        else:
            self.newest[i], self.oldest[i], self.oldest_rx[i] = -math.inf, math.inf, math.inf


@persistent("bathymetry.LevelStats")
@dataclass
class LevelStats:
    """What a level holds, kept as subgrids come: counts, stamps, extent (subgrid indices,
    end exclusive, of everything received) and depth range. ``stale``: the oldest stamp or
    arrival (or the newest stamp) left with a subgrid replaced or forgotten; recomputed from
    the tile summaries when asked."""

    subgrids: int = 0
    cells: int = 0
    newest: float = -math.inf
    oldest: float = math.inf
    oldest_rx: float = math.inf
    stale: bool = False
    ix0: int = 0
    iy0: int = 0
    ix1: int = 0
    iy1: int = 0
    zmin: float = math.inf
    zmax: float = -math.inf


def same_storage(a: Storage | None, b: Storage | None) -> bool:
    """Whether two storages are the same keys: the same object, or the same part (``child``)
    of the same storage, as a node attaching its storage again gives."""
    if a is b:
        return True
    pa, pb = getattr(a, "parent", None), getattr(b, "parent", None)
    return pa is not None and same_storage(pa, pb) and getattr(a, "prefix", None) == getattr(b, "prefix", None)
