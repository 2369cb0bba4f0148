"""The 2022 CoExploration system's sizes, for comparisons (``coex bathy``, benchmarks)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["size_2022"]


def size_2022(present: npt.ArrayLike, q: npt.ArrayLike) -> int:
    """Bytes of the 2022 encoding of the same subgrid: a 16-byte header and one byte per cell
    (two when the block's range exceeds 255 vertical units)."""
    pa = np.asarray(present, bool)
    qa = np.asarray(q, np.int64)[pa]
    if qa.size == 0:
        return 16 + pa.size
    rng = int(qa.max() - qa.min())
    return 16 + pa.size * (1 if rng <= 255 else 2)
