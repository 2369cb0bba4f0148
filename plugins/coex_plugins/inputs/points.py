"""The ``points`` input: soundings from ``.npy`` (``N x 3``, or a structured array with x, y, z
fields) and ``.csv`` files (x, y, z columns, header optional) for the bathymetry map.

``path`` is one file or a directory watched like the ``directory`` input's (a file is read once
its size and modification time have settled; rewriting it makes it new again). Each file
becomes one :class:`~coex.Points` item, timed by its sidecar ``<file>.json`` ``{"time": ...}``
when there is one, else by its modification time. Rows with a NaN or infinite coordinate are
dropped. A file that cannot be read, or holds no finite point, is logged once, skipped and
counted (``counts["skipped"]``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import ClassVar

import numpy as np

from coex import Item, Points
from coex.options import REQUIRED, Option, flag, number, text

from ._files import WatchedInput, read_sidecar

__all__ = ["PointsInput", "finite_rows"]


def finite_rows(xyz: np.ndarray) -> np.ndarray:
    """The rows of an ``N x 3`` array whose three coordinates are finite, as float64."""
    a = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    return a[np.isfinite(a).all(axis=1)]


class PointsInput(WatchedInput):
    """Point files (see the module docstring)."""

    name = "points"
    feeds = ("bathymetry",)
    options: ClassVar[Mapping[str, Option]] = {
        "path": text(REQUIRED, "a .npy / .csv file, or a directory to watch for them"),
        "pattern": text("*.npy,*.csv", "comma-separated file name patterns in a directory, case ignored"),
        "settle": number(1.0, "seconds a file's size and mtime must stay unchanged before it is read",
                         unit="s", lo=0),
        "existing": flag(False, "also take the files already in the directory when the input opens "
                                "(a single named file is always taken)"),
        "interval": number(0.5, "seconds between two scans of the directory", unit="s", lo=0),
    }

    path_kind = "file or folder"

    def poll(self, now: float) -> list[Item]:
        items: list[Item] = []
        for path, st in self.watch.poll(now):
            if path.suffix.lower() not in (".npy", ".csv", ".txt", ".xyz"):
                self._problem(f"type:{path.suffix}", "input points: %s is not .npy or .csv, skipped", path)
                self.skip()
                continue
            try:
                from coex_plugins.bathymetry.points import iter_points

                chunks = [xyz for _, xyz in iter_points(path)]
            except Exception as exc:  # InputError, or anything a damaged file provokes
                self._problem(f"read:{path}", "input points: cannot read %s, skipped (%s)", path, exc)
                self.skip()
                continue
            side = read_sidecar(path, self.context)
            t = side.time if side is not None and side.time is not None else st.st_mtime
            before = len(items)
            for xyz in chunks:
                good = finite_rows(xyz)
                if len(good):
                    items.append(Points(t, good))
            if len(items) == before:
                self._problem(f"empty:{path}", "input points: %s holds no finite point, skipped", path)
                self.skip()
        return items

    def next_event(self, now: float) -> float | None:
        return self.watch.next_event(now)
