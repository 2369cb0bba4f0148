"""Whether topside holds what the vehicle sent: the checks that the fault suite
(``tests/test_faults.py``), the kill test (``tests/test_persist.py``) and the soak with faults
(``bench/soak_faults.py``) share. Each compares a vehicle sender with the topside receiver of the
same modality, as they are in memory (or as their stores restore them).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from coex import RequestRejected

from .bathymetry.product import MapLevel

__all__ = ["image_held", "images_missing", "map_converged", "series_complete"]


def map_converged(sender: Any, receiver: Any) -> bool:
    """Every level of the topside map (a bathymetry receiver's ``level-k`` products) equals the
    vehicle's map (``sender.map``) on the same cells, to the 0.1 m quantisation."""
    products = {p.key: p for p in receiver.products()}
    for k in range(int(sender.map.levels)):
        grid, x0, y0 = sender.map.grid(k)
        prod = products.get(f"level-{k}")
        if prod is None:
            return False
        if not isinstance(prod, MapLevel):
            return False
        cell = prod.cell_size
        r0 = round((prod.y0 - y0) / cell)
        c0 = round((prod.x0 - x0) / cell)
        got = prod.data
        rows, cols = np.nonzero(np.isfinite(grid))
        tr, tc = rows - r0, cols - c0  # the same cells in topside's mosaic
        inside = (tr >= 0) & (tr < got.shape[0]) & (tc >= 0) & (tc < got.shape[1])
        if not inside.all() or int(np.isfinite(got).sum()) != rows.size:
            return False
        if np.abs(got[tr, tc] - grid[rows, cols]).max(initial=0.0) > 0.05 + 1e-9:  # 0.1 m quantum
            return False
    return True


def image_held(sent: Any, got: Any) -> bool:
    """One image (the imagery sender's record ``sent``) is held topside (the receiver's record
    ``got``, or None) up to its goal, byte-exact, and decoded."""
    if got is None or got.contiguous() < sent.goal or got.image is None:
        return False
    return bool(bytes(got.buf[: sent.goal]) == sent.enc.body[: sent.goal])


def images_missing(sender: Any, receiver: Any, ids: Iterable[int] | None = None) -> list[int]:
    """The images of ``ids`` (default: every image the sender holds) that topside does not hold
    up to their goal (:func:`image_held`)."""
    want = sorted(sender.images) if ids is None else list(ids)
    return [i for i in want if i not in sender.images
            or not image_held(sender.images[i], receiver.images.get(i))]


def series_complete(sender: Any, receiver: Any, truth: Sequence[Any] = ()) -> bool:
    """Topside holds every block the vehicle closed, of every channel of ``truth`` (each with
    ``name``, ``times``, ``values``), with the vehicle's error bound, and every reconstructed
    value is within its bound of the true sample: in memory, or in the receiver's archive file
    (``keep`` and ``out_dir``)."""
    for data in truth:
        sent = sender.bound(data.name)
        try:
            held = {round(s, 3): b for s, _, b in receiver.bounds(data.name)}
        except RequestRejected:  # nothing of this channel received yet
            return False
        if not sent or any(held.get(round(s, 3), np.inf) > b + 1e-9 for s, _, b in sent):
            return False
        rec = receiver.held(data.name)  # what memory and the archive hold (docs/timeseries.md)
        idx = np.searchsorted(data.times, rec.times)
        idx = np.clip(idx, 0, len(data.times) - 1)
        same = np.isclose(data.times[idx], rec.times)
        err = np.abs(rec.values[same] - data.values[idx[same]])
        if not np.all(err <= rec.bounds[same] + 1e-6):
            return False
    return True
