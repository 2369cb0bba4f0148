"""Outlier rejection of a batch of soundings against the map and the batch itself (the rules are
in :mod:`.quadtree`'s docstring: a cell's mean where it is dense, else the 4 x 4 or 16 x 16-cell
block around it, judged twice so that outliers do not shift their own reference)."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from ._arrays import _pool

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


def screen(
    m: int,
    tile: int,
    c_map: FloatArray,
    s_map: FloatArray,
    ss_map: FloatArray,
    flat: IntArray,
    local: IntArray,
    inv: IntArray,
    z: FloatArray,
    n_b: npt.NDArray[Any],
    s_b: npt.NDArray[Any],
    ss_b: npt.NDArray[Any],
    *,
    min_count: int,
    threshold: float,
    k: float,
) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
    """Which soundings of a batch to keep, and which could be judged.

    ``m`` tiles of ``tile x tile`` cells; ``c_map``, ``s_map``, ``ss_map`` the map's count, sum and
    sum of squares per cell of those tiles, ``n_b``, ``s_b``, ``ss_b`` the batch's; per sounding
    ``z``, its cell among all (``flat``), within its tile (``local``) and its tile (``inv``).

    Two passes: the first judges every sounding against references that may include the
    outliers themselves; the second recomputes the references from the map and the soundings
    the first pass kept, and judges again (a clipped, robust mean per cell and per block)."""
    size = m * tile * tile
    row = local >> (tile.bit_length() - 1)
    col = local & (tile - 1)
    blocks = []
    for f in (4, 16):  # 4 x 4 cells (level 2), then 16 x 16 cells (level 4) where sparser
        if f > tile:
            break
        tf = tile // f
        blocks.append(((tf, f), inv * (tf * tf) + (row // f) * tf + (col // f)))

    def judge(c: FloatArray, sm: FloatArray, ss: FloatArray) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
        mean = sm / np.maximum(c, 1)
        dense = c[flat] >= min_count
        bad = dense & (np.abs(z - mean[flat]) > threshold)
        judged = dense.copy()
        for (tf, f), b in blocks:
            cb = _pool(c, m, tf, f, np.add).ravel()
            sb = _pool(sm, m, tf, f, np.add).ravel()
            ssb = _pool(ss, m, tf, f, np.add).ravel()
            mb = sb / np.maximum(cb, 1)
            sd = np.sqrt(np.maximum(ssb / np.maximum(cb, 1) - mb * mb, 0.0))
            thr = np.maximum(threshold, k * sd[b])
            here = ~judged & (cb[b] >= min_count)
            bad |= here & (np.abs(z - mb[b]) > thr)
            judged |= here
        return ~bad, judged

    keep, judged = judge(c_map + n_b, s_map + s_b, ss_map + ss_b)
    if keep.all():
        return keep, judged
    w = keep.astype(np.float64)
    n_k = np.bincount(flat, weights=w, minlength=size)
    s_k = np.bincount(flat, weights=z * w, minlength=size)
    ss_k = np.bincount(flat, weights=z * z * w, minlength=size)
    return judge(c_map + n_k, s_map + s_k, ss_map + ss_k)
