"""The topside receiver's tiles: ``n x n`` subgrids of one level per tile (cells, and per
subgrid its stamp, arrival time and whether it is held), their stored form (the plugin's tile
store, :mod:`.tilestore`: named arrays, byte-shuffled, zstd; tiles stored before it in ``CXRT``
form still read), and the per-level index and statistics the receiver keeps beside them."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from coex import StateError, Storage, persistent

from . import tilestore

__all__ = ["LevelIndex", "LevelStats", "Tile", "decode_tile", "encode_tile", "same_storage", "tile_name",
           "tile_nbytes"]


def tile_name(key: tuple[int, int, int]) -> str:
    """Where tile ``(level, tx, ty)`` is in the receiver's storage."""
    return f"tile/{key[0]}/{key[1]}/{key[2]}"


@persistent("bathymetry.Tile")
class Tile:
    """``n x n`` subgrids of one level: cells (row 0 = south, NaN where nothing) and, per
    subgrid, stamp, arrival time and whether it is held. ``dirty`` (the storage lacks it) is
    what the receiver's tile cache knew when the tile was saved with the receiver's state."""

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
    """A tile's stored form: the tile store's codec at zstd level ``compression`` (0: none),
    not shuffled (the cells are whole decimetres, or NaN, which compress best as they are)."""
    return tilestore.encode({"held": t.held, "stamp": t.stamp, "received": t.received, "values": t.values},
                            compression, shuffle=False)


def decode_tile(data: bytes, n: int, side: int, where: str) -> Tile:
    """A stored tile of ``n x n`` subgrids of ``side`` cells (the tile store's form, or the
    ``CXRT`` form stored before it)."""
    try:
        arrays = tilestore.decode(data)
        t = object.__new__(Tile)
        t.held = arrays["held"].astype(bool, copy=False)
        t.stamp = arrays["stamp"].astype(np.float64, copy=False)
        t.received = arrays["received"].astype(np.float64, copy=False)
        t.values = arrays["values"].astype(np.float64, copy=False)
        shapes = (t.held.shape, t.stamp.shape, t.received.shape, t.values.shape)
        if shapes != ((n, n), (n, n), (n, n), (n * side, n * side)):
            raise ValueError(f"shapes {shapes}, not a tile of {n} x {n} subgrids of {side} cells")
    except (ValueError, KeyError) as exc:
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
    return a is b or (a is not None and a.same_keys(b))  # declared on Storage
