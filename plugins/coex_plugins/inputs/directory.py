"""The ``directory`` input: new image files in a watched directory (the 2022 system's "transmit
directory") become :class:`~coex.Image` items for the imagery sender.

A file is taken once its size and modification time have not changed for ``settle`` seconds, so
a half-written file is never read. Its pixels are read here (TIFF with tifffile, PNG / JPEG /
PGM ... with Pillow). Its time and position come from a sidecar ``<image>.json`` (or
``<stem>.json``) ``{"time": ..., "x": ..., "y": ...}`` (or ``"lat"``, ``"lon"``) when there is
one, else the time is the file's modification time and the position is unknown (x, y None):
with ``nav = true`` the daemon then stamps the image with the newest vehicle position.
A file that cannot be read is logged once, skipped and counted (``counts["skipped"]``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import ClassVar

from coex import Image, Item
from coex.options import REQUIRED, Option, flag, number, text

from ._files import WatchedInput, read_image, read_sidecar

__all__ = ["DirectoryInput"]


IMAGE_PATTERNS = "*.tif,*.tiff,*.png,*.jpg,*.jpeg,*.pgm"


class DirectoryInput(WatchedInput):
    """Images written into a directory (see the module docstring)."""

    name = "directory"
    feeds = ("imagery",)
    options: ClassVar[Mapping[str, Option]] = {
        "path": text(REQUIRED, "the directory to watch (relative to the configuration file's directory)"),
        "pattern": text(IMAGE_PATTERNS, "comma-separated file name patterns, case ignored"),
        "settle": number(1.0, "seconds a file's size and mtime must stay unchanged before it is read",
                         unit="s", lo=0),
        "existing": flag(False, "also take the files already there when the input opens"),
        "nav": flag(False, "the daemon stamps images without a sidecar position with the newest "
                           "vehicle position"),
        "interval": number(0.5, "seconds between two scans of the directory", unit="s", lo=0),
    }

    def poll(self, now: float) -> list[Item]:
        items: list[Item] = []
        for path, st in self.watch.poll(now):
            try:
                pixels = read_image(path)
            except Exception as exc:  # any reader error: skip the file, never stop the daemon
                self._problem(f"read:{path}", "input directory: cannot read %s, skipped (%s: %s)",
                              path, type(exc).__name__, exc)
                self.skip()
                continue
            side = read_sidecar(path, self.context)
            t = side.time if side is not None and side.time is not None else st.st_mtime
            x = side.x if side is not None else None
            y = side.y if side is not None else None
            items.append(Image(t, pixels=pixels, path=str(path), x=x, y=y))
        return items

    def next_event(self, now: float) -> float | None:
        return self.watch.next_event(now)
