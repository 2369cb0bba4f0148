"""Watching a directory (or one file) for new files that have finished being written, reading
image files into pixel arrays, and the ``<file>.json`` sidecar with a capture time and position.

Used by the ``directory`` and ``points`` inputs (and ``mavlink`` for captured images)."""

from __future__ import annotations

import fnmatch
import json
import logging
import math
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from coex import Input, InputContext

from ..options import LogOnce, Problems

__all__ = ["DirectoryWatch", "Sidecar", "as_pixels", "decode_image", "read_image", "read_sidecar", "split_patterns"]

log = logging.getLogger(__name__)


def split_patterns(text: str) -> tuple[str, ...]:
    """``"*.tif, *.png"`` -> ``("*.tif", "*.png")`` (lower case: matching ignores case)."""
    return tuple(p.strip().lower() for p in text.split(",") if p.strip())


def _matches(name: str, patterns: tuple[str, ...]) -> bool:
    low = name.lower()
    return any(fnmatch.fnmatchcase(low, p) for p in patterns)


@dataclass
class _Pending:
    size: int
    mtime_ns: int
    since: float  # daemon time at which this size and mtime were first seen


class DirectoryWatch:
    """New files in a directory (not recursive), or one file, once they have settled.

    A file is *settled* when its size and modification time have not changed for ``settle``
    seconds: either across polls (measured on the daemon's clock, ``now``) or because its
    modification time is already that old on the wall clock. A file is taken once per
    (name, size, mtime): rewriting it makes it new again. Hidden files (``.name``, what ``rsync``
    and many writers use while writing) are ignored. With ``existing`` false, what is in the
    directory at :meth:`open` is skipped (a single named file is always taken). Taken files are
    remembered in memory only, also across close and :meth:`open` of the same object; after a
    restart of the process, ``existing`` true takes everything again (not feeding it twice is
    left to the daemon, which journals what it was fed)."""

    def __init__(self, path: str | Path, patterns: tuple[str, ...], settle: float, existing: bool,
                 interval: float = 0.0) -> None:
        self.path = Path(path)
        self.patterns = patterns
        self.settle = float(settle)
        self.existing = bool(existing)
        self.interval = float(interval)
        self._taken: dict[str, tuple[int, int]] = {}
        self._pending: dict[str, _Pending] = {}
        self._last_scan = -math.inf
        self._opened = False
        self._missing_logged = False
        self.single_file = self._is_single_file()

    def _is_single_file(self) -> bool:
        """Whether the path names one file rather than a directory to watch (a path that does
        not exist yet is a file when its name matches the patterns)."""
        if self.path.is_dir():
            return False
        return self.path.is_file() or _matches(self.path.name, self.patterns)

    def open(self, now: float | None = None) -> None:
        if self._opened:
            return
        self._opened = True
        if not self.existing and not self.single_file:
            for name, st in self._scan():
                self._taken[name] = (st.st_size, st.st_mtime_ns)

    def _scan(self) -> list[tuple[str, os.stat_result]]:
        """(name, stat) of every candidate file now; [] (logged once) when the path is missing."""
        out: list[tuple[str, os.stat_result]] = []
        if self._missing_logged:  # it did not exist: it may have been created as either
            self.single_file = self._is_single_file()
        try:
            if self.single_file:
                st = self.path.stat()
                return [(self.path.name, st)]
            with os.scandir(self.path) as it:
                for entry in it:
                    if entry.name.startswith(".") or not _matches(entry.name, self.patterns):
                        continue
                    try:
                        if entry.is_file():
                            out.append((entry.name, entry.stat()))
                    except OSError:  # removed while listing
                        continue
        except OSError as exc:
            if not self._missing_logged:
                log.warning("input watch %s: %s (will keep looking)", self.path, exc)
                self._missing_logged = True
            return []
        self._missing_logged = False
        return out

    def _file(self, name: str) -> Path:
        return self.path if self.single_file else self.path / name

    def poll(self, now: float) -> list[tuple[Path, os.stat_result]]:
        """Files that settled since the last call, oldest first (by modification time)."""
        if not self._opened:
            self.open(now)
        if now - self._last_scan < self.interval:
            return []
        self._last_scan = now
        found = self._scan()
        names = {name for name, _ in found}
        # forget what is gone, so the memory stays the size of the directory
        for gone in [n for n in self._taken if n not in names]:
            del self._taken[gone]
        for gone in [n for n in self._pending if n not in names]:
            del self._pending[gone]
        wall = time.time()
        ready: list[tuple[Path, os.stat_result]] = []
        for name, st in found:
            key = (st.st_size, st.st_mtime_ns)
            if self._taken.get(name) == key:
                continue
            seen = self._pending.get(name)
            if seen is None or (seen.size, seen.mtime_ns) != key:
                seen = self._pending[name] = _Pending(st.st_size, st.st_mtime_ns, now)
            if now - seen.since >= self.settle or wall - st.st_mtime >= self.settle:
                del self._pending[name]
                self._taken[name] = key
                ready.append((self._file(name), st))
        ready.sort(key=lambda item: (item[1].st_mtime_ns, item[0].name))
        return ready

    def next_event(self, now: float) -> float | None:
        """When the first file now being written may have settled (None when none is)."""
        if not self._pending:
            return None
        due = min(p.since for p in self._pending.values()) + self.settle
        return max(due, self._last_scan + self.interval)


# --------------------------------------------------------------------------- images
def read_image(path: str | Path) -> np.ndarray:
    """The pixels of an image file: ``H x W`` or ``H x W x 3``, uint8 or uint16.

    TIFF with tifffile (first page), everything else with Pillow. Alpha is dropped, palettes are
    expanded, other sample types are converted (see :func:`as_pixels`). Raises ``OSError`` or
    ``ValueError`` when the file cannot be read."""
    p = Path(path)
    if p.suffix.lower() in (".tif", ".tiff"):
        import tifffile

        try:
            return as_pixels(tifffile.imread(p, key=0))
        except (ValueError, OSError):
            raise
        except Exception as exc:  # tifffile raises its own errors on damaged files
            raise ValueError(f"{type(exc).__name__}: {exc}") from exc
    from PIL import Image as PILImage

    with PILImage.open(p) as img:
        return _pil_pixels(img)


def decode_image(data: bytes) -> np.ndarray:
    """The pixels of an encoded image (JPEG, PNG ... anything Pillow reads), as
    :func:`read_image` gives them. Raises ``OSError`` or ``ValueError`` on bad data."""
    import io

    from PIL import Image as PILImage

    with PILImage.open(io.BytesIO(data)) as img:
        return _pil_pixels(img)


def _pil_pixels(img: Any) -> np.ndarray:
    img.load()
    if img.mode.startswith("I;16"):
        return as_pixels(np.asarray(img).astype(np.uint16))
    if img.mode in ("1", "LA", "La"):
        return as_pixels(np.asarray(img.convert("L")))
    if img.mode not in ("L", "RGB", "I", "F"):  # palette, alpha, CMYK, YCbCr ...
        img = img.convert("RGB")
    return as_pixels(np.asarray(img))


def as_pixels(array: Any) -> np.ndarray:
    """An image array as CoEx takes it: ``H x W`` or ``H x W x 3``, uint8 or uint16.

    Planar ``3 x H x W`` is made interleaved, a fourth (alpha) or a second channel is dropped.
    bool becomes 0/255; integers that fit in 0..65535 become uint16; anything else (floats,
    negative or large integers) is stretched from its finite minimum and maximum onto 0..65535
    (NaN becomes 0)."""
    a = np.asarray(array)
    while a.ndim > 3 and a.shape[0] == 1:
        a = a[0]
    if a.ndim == 3 and a.shape[0] in (3, 4) and a.shape[-1] not in (1, 2, 3, 4):
        a = np.moveaxis(a, 0, -1)
    if a.ndim == 3 and a.shape[-1] in (1, 2):
        a = a[..., 0]
    elif a.ndim == 3 and a.shape[-1] == 4:
        a = a[..., :3]
    if not (a.ndim == 2 or (a.ndim == 3 and a.shape[-1] == 3)) or a.size == 0:
        raise ValueError(f"not an image array: shape {a.shape}")
    if a.dtype in (np.uint8, np.uint16):
        return np.ascontiguousarray(a)
    if a.dtype == np.bool_:
        return a.astype(np.uint8) * np.uint8(255)
    if np.issubdtype(a.dtype, np.integer) and a.min() >= 0 and a.max() <= 65535:
        return a.astype(np.uint16)
    if not np.issubdtype(a.dtype, np.number) or np.iscomplexobj(a):
        raise ValueError(f"not an image array: dtype {a.dtype}")
    f = a.astype(np.float64)
    good = np.isfinite(f)
    if not good.any():
        return np.zeros(a.shape, np.uint16)
    lo, hi = float(f[good].min()), float(f[good].max())
    scaled = (f - lo) * (65535.0 / (hi - lo)) if hi > lo else np.zeros_like(f)
    return np.where(good, np.rint(scaled), 0).astype(np.uint16)


# --------------------------------------------------------------------------- sidecars
@dataclass(frozen=True)
class Sidecar:
    """What a ``<file>.json`` sidecar says (any part may be None)."""

    time: float | None = None
    x: float | None = None
    y: float | None = None


def _sidecar_paths(path: Path) -> tuple[Path, Path]:
    return path.with_name(path.name + ".json"), path.with_suffix(".json")


def read_sidecar(path: str | Path, context: InputContext) -> Sidecar | None:
    """The sidecar of a data file: ``image.png.json`` (else ``image.json``), a JSON object with
    ``time`` (seconds since the Unix epoch) and ``x``, ``y`` (metres east / north of the origin)
    or ``lat``, ``lon`` (degrees). None when there is none; a damaged one is logged and ignored."""
    p = Path(path)
    for side in _sidecar_paths(p):
        if side == p or not side.is_file():
            continue
        try:
            doc = json.loads(side.read_text(encoding="utf-8"))
            if not isinstance(doc, dict):
                raise ValueError("not a JSON object")
        except (OSError, ValueError) as exc:
            log.warning("sidecar %s ignored: %s", side, exc)
            return None
        t, x, y = _num(doc, "time"), _num(doc, "x"), _num(doc, "y")
        if x is None or y is None:
            lat, lon = _num(doc, "lat"), _num(doc, "lon")
            x, y = context.local(lat, lon) if lat is not None and lon is not None else (None, None)
        return Sidecar(t, x, y)
    return None


def _num(doc: dict[str, Any], key: str) -> float | None:
    v = doc.get(key)
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        return None
    return float(v)


class WatchedInput(Input):
    """An input that watches a directory (or one file) for new files: ``path`` (relative to the
    configuration's directory), ``pattern``, ``settle``, ``existing``, ``interval``. Subclasses
    turn each settled file into items in :meth:`poll`."""

    #: what ``path`` names, for ``coex config check`` (:meth:`paths`)
    path_kind = "folder"

    @classmethod
    def check(cls, options: Mapping[str, Any]) -> Problems:
        """The watch's options beyond their declared types and ranges: ``path`` and ``pattern``
        (at least one pattern) not empty. A subclass adds its own to these."""
        p, who = Problems(), f"input {cls.name!r}"
        p.option_str(who, options, "path", nonempty=True)
        p.option_str(who, options, "pattern", nonempty=True)
        if isinstance(options.get("pattern"), str) and options["pattern"].strip() \
                and not split_patterns(options["pattern"]):
            p.said("pattern", f"{who}: option 'pattern' holds no pattern")
        return p

    @classmethod
    def paths(cls, options: Mapping[str, Any]) -> list[tuple[str, str, str]]:
        return [("path", str(options["path"]), cls.path_kind)] if isinstance(options.get("path"), str) else []

    def __init__(self, options: Mapping[str, Any], context: InputContext) -> None:
        super().__init__(options, context)
        #: a problem with one file logged once (by the subclass's module logger)
        self._problem = LogOnce(logging.getLogger(type(self).__module__))
        path = Path(self.config["path"]).expanduser()
        if not path.is_absolute():
            path = Path(context.base_dir) / path
        self.watch = DirectoryWatch(path, split_patterns(self.config["pattern"]),
                                    self.config["settle"], self.config["existing"],
                                    self.config["interval"])

    def open(self) -> None:
        self.watch.open()
