"""How the map's tiles are stored (:class:`.quadtree.QuadtreeMap` out of core): the name of a
tile in the map's storage and its lossless ``CXT1`` format (zstd of byte-shuffled statistics)."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from coex_core.errors import CoexError

FloatArray = npt.NDArray[np.float64]


def _tile_name(key: tuple[int, int]) -> str:
    return f"tile/{key[0]}/{key[1]}"


_TILE_MAGIC = b"CXT1"
_COUNT_TYPES = (np.uint8, np.uint16, np.uint32, np.float64)
_zstd: Any = None


def _codec() -> Any:
    global _zstd
    if _zstd is None:
        import zstandard

        _zstd = (zstandard.ZstdCompressor(level=1), zstandard.ZstdDecompressor())
    return _zstd


def _shuffle(a: npt.NDArray[Any]) -> bytes:
    """Bytes of ``a`` grouped by significance (all first bytes, then all second...): the high
    bytes of nearby elevations repeat, so they compress."""
    return np.ascontiguousarray(a.reshape(-1).view(np.uint8).reshape(-1, a.itemsize).T).tobytes()


def _unshuffle(b: bytes, dtype: Any) -> npt.NDArray[Any]:
    size = np.dtype(dtype).itemsize
    return np.ascontiguousarray(np.frombuffer(b, np.uint8).reshape(size, -1).T).view(dtype).reshape(-1)


def _encode_tile(cells: FloatArray) -> bytes:
    """A tile's cells as bytes (lossless): ``CXT1``, the count's type code, then zstd of the
    byte-shuffled count (the smallest unsigned type that holds it) and sums, sums of squares and
    times (float64)."""
    cmax = float(cells[0].max())
    code = 3
    for i, dt in enumerate(_COUNT_TYPES[:3]):
        if cmax <= np.iinfo(dt).max:
            code = i
            break
    count = cells[0].astype(_COUNT_TYPES[code])
    payload = _shuffle(count) + _shuffle(cells[1:])
    return _TILE_MAGIC + bytes([code]) + _codec()[0].compress(payload)


def _decode_tile(data: bytes, out: FloatArray) -> None:
    if data[:4] != _TILE_MAGIC or data[4] > 3:
        raise CoexError("a stored map tile is not in the CXT1 format")
    dt = _COUNT_TYPES[data[4]]
    payload = _codec()[1].decompress(data[5:])
    tt = out.shape[1]
    nc = tt * np.dtype(dt).itemsize
    out[0] = _unshuffle(payload[:nc], dt)
    out[1:] = _unshuffle(payload[nc:], np.float64).reshape(3, tt)
