"""The console's adapter layer: what topside knows, as JSON, and operator actions as commands.

* :class:`ConsoleState` takes received messages (:meth:`~ConsoleState.apply_message`), receiver
  products (:meth:`~ConsoleState.apply_product`) and node events (:meth:`~ConsoleState.apply_event`)
  and keeps everything the console shows. :meth:`~ConsoleState.snapshot` gives the whole state
  as plain JSON-able data; each section (``vehicle``, ``map``, ``images``, ``series``, ``link``,
  ``queues``, ``commands``, ``log``) has a version, so :meth:`~ConsoleState.changes` gives only
  the sections that changed since a client last looked (the server pushes those).
* :class:`ConsoleActions` turns an operator action into wire-format command messages
  (:mod:`coex_core.messages`) and hands each one to ``send`` (the topside node's send path);
  every command is recorded in the state so the page shows "requested" until the vehicle
  answers (``CommandAck``/``MapRoiReply``) or the data arrives.

Nothing here does I/O or reads a clock: time enters as ``now``. The server adds the locking.
"""

from __future__ import annotations

import math
import zlib
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from coex_core import messages as m
from coex_core.errors import RequestRejected
from coex_core.state import persistent
from coex_core.timefmt import to_stamp, unwrap

__all__ = [
    "SECTIONS",
    "ConsoleActions",
    "ConsoleState",
    "png_bytes",
    "elevation_rgb",
]

#: The sections of a snapshot, in the order the page lays them out.
SECTIONS = ("vehicle", "map", "images", "series", "link", "queues", "commands", "log")

#: Largest region one MapRoiRequest may list stamps for (the wire format's limit).
MAX_ROI_HELD = 64
#: Largest side of a gap-filling request.
MAX_ROI_SIDE = 16
#: Refuse a region of more than this many subgrids (split into many requests otherwise).
MAX_ROI_SUBGRIDS = 64 * 64

FloatArray = npt.NDArray[np.float64]


# ------------------------------------------------------------------------------ rendering


def png_bytes(rgb: npt.NDArray[np.uint8]) -> bytes:
    """A PNG file of an ``H x W x 3`` (RGB) or ``H x W x 4`` (RGBA) uint8 image, row 0 at the top."""
    img = np.ascontiguousarray(rgb, dtype=np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    h, w, c = img.shape
    if c not in (3, 4):
        raise ValueError(f"expected 3 or 4 channels, got {c}")
    raw = np.zeros((h, 1 + w * c), np.uint8)  # filter byte 0 (None) before each row
    raw[:, 1:] = img.reshape(h, w * c)

    def chunk(tag: bytes, data: bytes) -> bytes:
        body = tag + data
        return len(data).to_bytes(4, "big") + body + zlib.crc32(body).to_bytes(4, "big")

    ihdr = w.to_bytes(4, "big") + h.to_bytes(4, "big") + bytes([8, 6 if c == 4 else 2, 0, 0, 0])
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr)
            + chunk(b"IDAT", zlib.compress(raw.tobytes(), 6)) + chunk(b"IEND", b""))


# A perceptually ordered colour ramp for depth (deep = dark blue, shallow = yellow).
_RAMP_POS = np.array([0.0, 0.25, 0.5, 0.75, 1.0])
_RAMP_RGB = np.array([[38, 20, 90], [40, 95, 160], [40, 160, 140], [140, 205, 80], [250, 230, 60]],
                     float)


def elevation_rgb(z: FloatArray, lo: float, hi: float, cell: float = 1.0) -> npt.NDArray[np.uint8]:
    """RGBA image of an elevation grid (row 0 = south): colour ramp times a hillshade; NaN cells
    are transparent. The image is flipped so that north is up."""
    z = np.asarray(z, float)
    ok = np.isfinite(z)
    span = max(hi - lo, 1e-9)
    t = np.clip((np.where(ok, z, lo) - lo) / span, 0.0, 1.0)
    rgb = np.stack([np.interp(t, _RAMP_POS, _RAMP_RGB[:, k]) for k in range(3)], axis=-1)
    from coex_plugins.bathymetry import hillshade  # the one hillshade (light from the NW)

    rgb *= (0.55 + 0.45 * hillshade(z, cell))[..., None]
    out = np.zeros((*z.shape, 4), np.uint8)
    out[..., :3] = np.clip(rgb, 0, 255).astype(np.uint8)
    out[..., 3] = np.where(ok, 255, 0)
    return out[::-1]


def _grey_thumbnail(img: npt.NDArray[Any], max_side: int = 160) -> npt.NDArray[np.uint8]:
    a = np.asarray(img)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.dtype != np.uint8:
        f = a.astype(float)
        lo, hi = float(np.nanmin(f)), float(np.nanmax(f))
        a = ((f - lo) / max(hi - lo, 1e-9) * 255).astype(np.uint8)
    step = max(1, math.ceil(max(a.shape[0], a.shape[1]) / max_side))
    return np.ascontiguousarray(a[::step, ::step])


def _num(x: float | None, nd: int = 3) -> float | None:
    if x is None:
        return None
    x = float(x)
    return round(x, nd) if math.isfinite(x) else None


# ---------------------------------------------------------------------------- map model


@persistent("console.Tile")
@dataclass
class _Tile:
    stamp: int
    t: float
    received: float
    z: FloatArray


@persistent("console.Level")
@dataclass
class _Level:
    level: int
    cell: float
    side: int
    tiles: dict[tuple[int, int], _Tile] = field(default_factory=dict)
    version: int = 0
    png: bytes | None = None
    png_version: int = -1
    summary: tuple[int, Any, Any, int] | None = None
    #: Fed by raw Subgrid messages (exact stamps), not by assembled level products.
    raw: bool = False


@persistent("console.RoiRequest")
@dataclass
class _RoiRequest:
    request_id: int
    level: int
    x0: int
    y0: int
    w: int
    h: int
    sent: float
    held: dict[tuple[int, int], int | None]
    status: str = "requested"
    queued: int | None = None
    received: int = 0
    done_at: float | None = None
    #: The bathymetry receiver's region object when the receiver sends (and retries) it.
    region: Any = None


@persistent("console.Image")
@dataclass
class _Image:
    image_id: int
    announce: m.ImageAnnounce | None = None
    t: float | None = None
    ranges: list[tuple[int, int]] = field(default_factory=list)
    goal: tuple[str, int] | None = None
    version: int = 0
    thumb: bytes | None = None
    thumb_version: int = -1
    decoded: Any = None
    decoded_version: int = -1
    decoded_meta: dict[str, Any] = field(default_factory=dict)

    @property
    def bytes_received(self) -> int:
        return sum(b - a for a, b in self.ranges)

    def add_range(self, a: int, b: int) -> bool:
        before = self.bytes_received
        merged: list[tuple[int, int]] = []
        for s, e in sorted([*self.ranges, (a, b)]):
            if merged and s <= merged[-1][1]:
                merged[-1] = (merged[-1][0], max(merged[-1][1], e))
            else:
                merged.append((s, e))
        self.ranges = merged
        return self.bytes_received != before


@persistent("console.Command")
@dataclass
class _Command:
    command_id: int
    kind: str
    summary: str
    sent: float
    message: m.Message
    status: str = "sent"
    answered: float | None = None
    roi_key: int | None = None


@persistent("console.State", transient=("_region_ids",))
class ConsoleState:
    """Everything the console shows, built from messages, products and events.

    ``stream_names`` names queue streams (id -> name); ``schedules`` gives the TDMA schedule of
    each link (``link -> coex_core.channel.schedule.Schedule`` or anything with ``to_dict()``, or
    a plain dict ``{"version", "epoch", "slots": [{"owner", "duration", "guard", ...}]}``);
    ``node_id`` is topside's node id (its slots are drawn as "ours")."""

    def __init__(
        self,
        *,
        node_id: int = 1,
        vehicle_id: int = 2,
        stream_names: Mapping[int, str] | None = None,
        schedules: Mapping[int, Any] | None = None,
        max_track: int = 5000,
        max_log: int = 200,
        auto_targets: bool = True,
    ) -> None:
        self.node_id = node_id
        self.vehicle_id = vehicle_id
        self.now = 0.0
        self.stream_names = dict(stream_names or {})
        self.versions: dict[str, int] = dict.fromkeys(SECTIONS, 0)
        # vehicle
        self.status: m.VehicleStatus | None = None
        self.status_t: float | None = None
        self.track: deque[tuple[float, float, float, float]] = deque(maxlen=max_track)
        # map
        self.map_meta: m.MapMetadata | None = None
        self.levels: dict[int, _Level] = {}
        self.targets: list[dict[str, Any]] = []
        #: Flag candidate targets on the finest level (threshold in metres, minimum cells).
        self.auto_targets = auto_targets
        self.target_threshold = 0.8
        self.target_min_cells = 3
        #: At most this many markers, at least this far apart (metres).
        self.max_targets = 8
        self.target_spacing = 6.0
        self._targets_cache: tuple[Any, list[dict[str, Any]]] = (None, [])
        self.roi: dict[int, _RoiRequest] = {}
        self._region_count = 0
        self._region_sig: tuple[Any, ...] = ()
        self._region_ids: set[int] = set()
        #: A bathymetry receiver whose operator regions (not its automatic gap filling) are
        #: shown even when someone else asked for them (a script, another tool).
        self.region_source: Any = None
        self._zrange: tuple[float, float] | None = None
        # images
        self.images: dict[int, _Image] = {}
        self.progress_info: dict[str, Any] | None = None
        self.image_queries: list[dict[str, Any]] = []
        # series
        self.series: dict[int, dict[str, Any]] = {}
        self.series_requests: list[dict[str, Any]] = []
        # link
        self.links: dict[int, dict[str, Any]] = {}
        self.schedules: dict[int, dict[str, Any]] = {}
        for link, sch in (schedules or {}).items():
            self.set_schedule(link, sch)
        self.bad_frames = 0
        # queues
        self.queue_stamp: float | None = None
        self.streams: dict[int, dict[str, Any]] = {}
        # commands and log
        self.commands: dict[int, _Command] = {}
        self.command_order: deque[int] = deque(maxlen=64)
        self._foreign_acks: dict[int, tuple[str, float]] = {}
        self.log: deque[dict[str, Any]] = deque(maxlen=max_log)

    def _after_restore(self) -> None:
        """A topside store saves the console with its node (:mod:`coex_core.state`); object
        ids are not state: the regions recorded are the ones the requests in ``roi`` hold."""
        self._region_ids = {id(r.region) for r in self.roi.values() if r.region is not None}

    # -------------------------------------------------------------------- bookkeeping
    def _touch(self, *sections: str) -> None:
        for s in sections:
            self.versions[s] += 1

    def _log(self, now: float, text: str, level: str = "info") -> None:
        self.log.append({"t": _num(now, 1), "level": level, "text": text})
        self._touch("log")

    def _advance(self, now: float) -> None:
        if now > self.now:
            self.now = float(now)

    # ------------------------------------------------------------------------ inputs
    def apply_message(self, msg: m.Message, now: float, link: int | None = None) -> set[str]:
        """Take one received message (any type; unknown ones are ignored). Returns the sections
        it changed."""
        self._advance(now)
        before = dict(self.versions)
        handler = _HANDLERS.get(type(msg))
        if handler is not None:
            handler(self, msg, now, link)
        return {s for s in SECTIONS if self.versions[s] != before[s]}

    def apply_messages(self, msgs: Iterable[m.Message], now: float,
                       link: int | None = None) -> set[str]:
        out: set[str] = set()
        for msg in msgs:
            out |= self.apply_message(msg, now, link)
        return out

    def apply_product(self, modality: str, product: Any, now: float) -> set[str]:
        """Take a receiver product (:class:`coex_core.modality.Product`)."""
        self._advance(now)
        before = dict(self.versions)
        kind = str(getattr(product, "kind", ""))
        data = getattr(product, "data", None)
        meta = dict(getattr(product, "meta", {}) or {})
        if kind == "series":
            self._series_product(data, meta)
        elif kind == "image":
            self._image_product(product, data, meta, now)
        elif kind == "image-progress":
            self.progress_info = {"pending": meta.get("pending"), "current": meta.get("current"),
                                  "unacked_fragments": meta.get("unacked_fragments"),
                                  "next": list(meta.get("next_images") or [])}
            self._touch("images")
        elif "target" in kind:
            self._targets_product(data, meta)
        elif kind.startswith("map") and isinstance(data, m.Subgrid):
            self._on_subgrid(data, now, None)
        elif kind == "map-level" and hasattr(data, "shape"):
            self._map_level_product(np.asarray(data, float), meta, now)
        return {s for s in SECTIONS if self.versions[s] != before[s]}

    def apply_event(self, event: Any) -> set[str]:
        """Take a node/channel event (:mod:`coex_core.channel.events`), duck-typed by name."""
        name = type(event).__name__
        now = float(getattr(event, "time", self.now))
        self._advance(now)
        before = dict(self.versions)
        if name == "Received":
            self.apply_message(event.message, now, getattr(event, "link", None))
        elif name == "ProductUpdated":
            self.apply_product(str(event.modality), event.product, now)
        elif name == "CommandResult":
            self._command_result(int(event.command_id), event.status, now,
                                 getattr(event, "command", None))
        elif name == "BadFrame":
            self.bad_frames += 1
            lk = self._link(int(event.link))
            lk["local_bad"] = lk.get("local_bad", 0) + 1
            self._touch("link")
            self._log(now, f"bad frame on link {event.link}: {event.reason}", "warn")
        elif name == "LinkChanged":
            lk = self._link(int(event.link))
            lk["enabled"], lk["muted"] = bool(event.enabled), bool(event.muted)
            self._touch("link")
            state = "enabled" if event.enabled else "disabled"
            self._log(now, f"link {event.link} {state}{' (muted)' if event.muted else ''}")
        elif name == "ScheduleSwitched":
            sch = self.schedules.get(int(event.link))
            if sch is not None:
                sch["active_version"] = int(event.version)
            self._touch("link")
            self._log(now, f"link {event.link} runs schedule v{event.version} ({event.reason})")
        elif name == "Dropped":
            self._log(now, f"stream {event.stream}: {event.count} dropped ({event.reason})", "warn")
        elif name == "Rejected":
            self._log(now, f"rejected {type(event.message).__name__}: {event.reason}", "warn")
        elif name == "SenderFailed":
            self._log(now, f"stream {event.stream} sender failed: {event.error}", "warn")
        return {s for s in SECTIONS if self.versions[s] != before[s]}

    def set_schedule(self, link: int, schedule: Any) -> None:
        """Record the TDMA schedule a link runs (for the timeline)."""
        d = schedule.to_dict() if hasattr(schedule, "to_dict") else dict(schedule)
        slots = [dict(s) for s in d.get("slots", [])]
        self.schedules[int(link)] = {
            "link": int(link), "version": int(d.get("version", 0)),
            "active_version": int(d.get("version", 0)),
            "epoch": float(d.get("epoch", 0.0)), "first_cycle": int(d.get("first_cycle", 0)),
            "cycle": float(sum(float(s["duration"]) for s in slots)),
            "slots": [{"owner": int(s["owner"]), "duration": float(s["duration"]),
                       "guard": float(s.get("guard", 0.0)),
                       "min_priority": int(s.get("min_priority", 0))} for s in slots],
            "proposed": None,
        }
        self._link(int(link))
        self._touch("link")

    def add_targets(self, targets: Iterable[Mapping[str, Any]]) -> None:
        """Add candidate targets (``x``, ``y`` and optionally ``height``, ``level``, ``score``)."""
        for t in targets:
            self.targets.append({k: (_num(v) if isinstance(v, float) else v) for k, v in t.items()})
        self._touch("map")

    # ---------------------------------------------------------------------- vehicle
    def _on_status(self, s: m.VehicleStatus, now: float) -> None:
        t = unwrap(s.stamp, now)
        if self.status_t is not None and t < self.status_t:
            return  # an older status arrived late: keep the newest
        self.status, self.status_t = s, t
        if not self.track or self.track[-1][1:3] != (s.x, s.y):
            self.track.append((t, s.x, s.y, s.depth))
        self._touch("vehicle")

    # -------------------------------------------------------------------------- map
    def _on_meta(self, meta: m.MapMetadata, now: float) -> None:
        self.map_meta = meta
        self._touch("map")

    def _on_subgrid(self, sg: m.Subgrid, now: float, link: int | None) -> None:
        t = unwrap(sg.stamp, now)
        lv = self.levels.get(sg.level)
        cell = float(sg.resolution) * 2 ** sg.level
        if lv is None or lv.side != sg.side or not math.isclose(lv.cell, cell) or not lv.raw:
            lv = self.levels[sg.level] = _Level(sg.level, cell, sg.side, raw=True)
        old = lv.tiles.get((sg.ix, sg.iy))
        if old is not None and old.t >= t:
            return  # duplicate or older
        z = _decode_subgrid(sg)
        lv.tiles[(sg.ix, sg.iy)] = _Tile(sg.stamp, t, now, z)
        lv.version += 1
        if np.isfinite(z).any():
            lo, hi = float(np.nanmin(z)), float(np.nanmax(z))
            if self._zrange is None:
                self._zrange = (lo, hi)
            else:
                self._zrange = (min(self._zrange[0], lo), max(self._zrange[1], hi))
        for req in self.roi.values():
            key = (sg.ix - req.x0, sg.iy - req.y0)
            if (req.level == sg.level and 0 <= key[0] < req.w and 0 <= key[1] < req.h
                    and req.status in ("requested", "queued", "partial")):
                req.received += 1
                expected = req.queued if req.queued else req.w * req.h
                req.status = "received" if req.received >= expected else "partial"
                if req.status == "received":
                    req.done_at = now
                self._touch("commands")
        self._touch("map")

    def _on_roi_reply(self, r: m.MapRoiReply, now: float) -> None:
        req = next((q for q in self.roi.values()
                    if (q.region.request_id if q.region is not None else q.request_id)
                    == r.request_id and q.level == r.level), None)
        if req is None:
            return
        req.queued = r.queued
        if r.queued == 0:
            req.status, req.done_at = "nothing newer", now
        elif req.received >= r.queued:
            req.status, req.done_at = "received", now
        elif req.status == "requested":
            req.status = "queued"
        self._touch("map", "commands")
        self._log(now, f"map request {r.request_id}: {r.queued} subgrids queued")

    def _map_level_product(self, z: FloatArray, meta: dict[str, Any], now: float) -> None:
        """A bathymetry receiver's assembled level, for when its raw subgrids are not tapped
        (every held subgrid gets the level's newest time: ages are approximate)."""
        try:
            level, cell = int(meta["level"]), float(meta["cell_size"])
            x0, y0 = float(meta["x0"]), float(meta["y0"])
        except (KeyError, TypeError, ValueError):
            return
        lv = self.levels.get(level)
        if lv is not None and lv.raw:
            return  # the raw subgrids (with their own stamps) are the better source
        side = self.map_meta.subgrid_side if self.map_meta else (lv.side if lv else 8)
        ny, nx = z.shape[0] // side, z.shape[1] // side
        if ny * nx == 0 or z.shape != (ny * side, nx * side):
            return
        ix0, iy0 = round(x0 / (side * cell)), round(y0 / (side * cell))
        t = float(meta.get("newest") or now)
        blocks = z.reshape(ny, side, nx, side).swapaxes(1, 2)
        held = np.isfinite(blocks).any(axis=(2, 3))
        version = lv.version + 1 if lv is not None else 1
        lv = self.levels[level] = _Level(level, cell, side, version=version)
        for i, j in zip(*np.nonzero(held)):
            lv.tiles[(ix0 + int(j), iy0 + int(i))] = _Tile(to_stamp(t), t, now,
                                                           blocks[i, j].copy())
        if np.isfinite(z).any():
            lo, hi = float(np.nanmin(z)), float(np.nanmax(z))
            zr = self._zrange or (lo, hi)
            self._zrange = (min(zr[0], lo), max(zr[1], hi))
        self._touch("map")

    def held_stamps(self, level: int, x0: int, y0: int, w: int, h: int) -> list[int | None]:
        """Per subgrid of the region, row-major (rows = y): the stamp topside holds, or None."""
        lv = self.levels.get(level)
        out: list[int | None] = []
        for iy in range(y0, y0 + h):
            for ix in range(x0, x0 + w):
                tile = lv.tiles.get((ix, iy)) if lv else None
                out.append(tile.stamp if tile else None)
        return out

    def level_grid(self, level: int) -> tuple[FloatArray, float, float, float] | None:
        """The assembled level: ``(z, x0, y0, cell)`` with row 0 = south, or None if empty."""
        lv = self.levels.get(level)
        if lv is None or not lv.tiles:
            return None
        keys = np.array(list(lv.tiles.keys()), np.int64)
        ixmin, iymin = keys.min(axis=0)
        ixmax, iymax = keys.max(axis=0)
        s = lv.side
        z = np.full(((iymax - iymin + 1) * s, (ixmax - ixmin + 1) * s), np.nan)
        for (ix, iy), tile in lv.tiles.items():
            r, c = (iy - iymin) * s, (ix - ixmin) * s
            z[r:r + s, c:c + s] = tile.z
        return z, float(ixmin * s * lv.cell), float(iymin * s * lv.cell), lv.cell

    def map_png(self, level: int) -> bytes | None:
        """The level as a PNG (colour ramp + hillshade, north up, transparent where empty)."""
        png, job = self.map_png_job(level)
        if job is not None:
            png = job()
        return png

    def map_png_job(self, level: int) -> tuple[bytes | None, Callable[[], bytes] | None]:
        """``(png, None)`` when the picture of the level is current, else ``(None, render)``:
        ``render()`` draws it from a copy of the grid (no need to hold a lock while it runs)
        and keeps it for the next call."""
        lv = self.levels.get(level)
        if lv is None:
            return None, None
        if lv.png is not None and lv.png_version == lv.version:
            return lv.png, None
        grid = self.level_grid(level)
        if grid is None:
            return None, None
        z, _, _, cell = grid
        lo, hi = self._zrange or (0.0, 1.0)
        version = lv.version

        def render() -> bytes:
            png = png_bytes(elevation_rgb(z, lo, hi, cell))
            if lv.png_version < version:
                lv.png, lv.png_version = png, version
            return png

        return None, render

    # ----------------------------------------------------------------------- images
    def _image(self, image_id: int) -> _Image:
        img = self.images.get(image_id)
        if img is None:
            img = self.images[image_id] = _Image(image_id)
        return img

    def _on_announce(self, a: m.ImageAnnounce, now: float) -> None:
        img = self._image(a.image_id)
        if img.announce != a:
            img.announce, img.t = a, unwrap(a.stamp, now)
            img.version += 1
            self._touch("images")

    def _on_fragment(self, f: m.ImageFragment, now: float) -> None:
        img = self._image(f.image_id)
        if img.add_range(f.offset, f.offset + len(f.data)):
            img.version += 1
            self._touch("images")

    def _on_progress(self, p: m.TransferProgress, now: float) -> None:
        self.progress_info = {"pending": p.pending, "current": p.current,
                              "unacked_fragments": p.unacked_fragments,
                              "next": list(p.next_images)}
        self._touch("images")

    def _image_product(self, product: Any, data: Any, meta: dict[str, Any], now: float) -> None:
        iid = meta.get("image_id")
        if iid is None:
            try:
                iid = int(str(getattr(product, "key", "")).rsplit("-", 1)[-1])
            except ValueError:
                return
        img = self._image(int(iid))
        if data is not None and hasattr(data, "shape"):
            img.decoded = data
            img.decoded_version = int(getattr(product, "version", img.decoded_version + 1))
        img.decoded_meta = {k: v for k, v in meta.items()
                            if v is None or isinstance(v, int | float | str | bool)}
        if img.t is None and isinstance(meta.get("time"), int | float):
            img.t = float(meta["time"])
        img.version += 1
        self._touch("images")

    def image_png(self, image_id: int) -> bytes | None:
        """The newest decoded picture of an image, as a thumbnail PNG (None before any)."""
        img = self.images.get(image_id)
        if img is None or img.decoded is None:
            return None
        if img.thumb is None or img.thumb_version != img.decoded_version:
            a = np.asarray(img.decoded)
            if a.ndim == 3 and a.shape[2] >= 3:
                step = max(1, math.ceil(max(a.shape[:2]) / 160))
                rgb = np.ascontiguousarray(a[::step, ::step, :3]).astype(np.uint8)
            else:
                rgb = _grey_thumbnail(a)
            img.thumb, img.thumb_version = png_bytes(rgb), img.decoded_version
        return img.thumb

    # ------------------------------------------------------------------ time series
    def _on_channel(self, c: m.TimeSeriesChannel, now: float) -> None:
        s = self.series.setdefault(c.channel, {"channel": c.channel})
        s.update(name=c.name, unit=c.unit, lo=c.lo, hi=c.hi, resolution=c.resolution)
        self._touch("series")

    def _series_product(self, data: Any, meta: dict[str, Any]) -> None:
        cid = int(meta.get("channel", getattr(data, "channel", -1)))
        if cid < 0:
            return
        s = self.series.setdefault(cid, {"channel": cid})
        for k in ("name", "unit", "lo", "hi", "resolution"):
            if meta.get(k) is not None:
                s[k] = meta[k]
        if data is not None and hasattr(data, "times"):
            s["times"] = np.asarray(data.times, float)
            s["values"] = np.asarray(data.values, float)
            s["bounds"] = np.asarray(data.bounds, float)
        self._touch("series")

    def _targets_product(self, data: Any, meta: dict[str, Any]) -> None:
        rows = data if isinstance(data, list | tuple) else meta.get("targets", [])
        out = []
        for t in rows:
            d = t if isinstance(t, Mapping) else getattr(t, "__dict__", {})
            if "x" in d and "y" in d:
                out.append({k: (_num(v) if isinstance(v, float) else v) for k, v in d.items()
                            if isinstance(v, int | float | str | bool)})
        self.targets = out
        self._touch("map")

    # -------------------------------------------------------------------------- link
    def _link(self, link: int) -> dict[str, Any]:
        lk = self.links.get(link)
        if lk is None:
            lk = self.links[link] = {"link": link, "enabled": True, "muted": False,
                                     "packets": 0, "frames": 0, "bad_frames": 0, "snr": None,
                                     "doppler": None, "last": None, "history": deque(maxlen=120)}
        return lk

    def _on_link_status(self, s: m.LinkStatus, now: float) -> None:
        lk = self._link(s.link)
        t = unwrap(s.stamp, now)
        lk["packets"] += 1
        lk["frames"] += s.frames
        lk["bad_frames"] += s.bad_frames
        lk["snr"], lk["doppler"], lk["last"] = s.snr, s.doppler, t
        lk["history"].append((t, s.snr, s.frames, s.bad_frames))
        self._touch("link")

    # ------------------------------------------------------------------------ queues
    def _on_queue_status(self, q: m.QueueStatus, now: float) -> None:
        self.queue_stamp = unwrap(q.stamp, now)
        for st in q.streams:
            row = self.streams.setdefault(st.stream, {"stream": st.stream, "drops_total": 0})
            row.update(enabled=st.enabled, tier=st.tier, priority=st.priority, depth=st.depth,
                       queued_bytes=st.queued_bytes, oldest_age=st.oldest_age, drops=st.drops)
            row["drops_total"] += st.drops
        self._touch("queues")

    # ---------------------------------------------------------------------- commands
    def record_command(self, msg: m.Message, now: float, summary: str = "") -> None:
        """Remember a command the operator sent (shown as pending until answered)."""
        self._advance(now)
        cid = getattr(msg, "command_id", getattr(msg, "request_id", None))
        if cid is None:
            return
        kind = type(msg).__name__
        key = (0 if isinstance(msg, m.MapRoiRequest) else 256) + int(cid)
        self.commands[key] = _Command(int(cid), kind, summary or kind, now, msg)
        if key in self.command_order:
            self.command_order.remove(key)
        self.command_order.append(key)
        if isinstance(msg, m.MapRoiRequest):
            self.commands[key].roi_key = msg.request_id
            held = dict(zip(((ix, iy) for iy in range(msg.y0, msg.y0 + msg.h)
                             for ix in range(msg.x0, msg.x0 + msg.w)), msg.held or ()))
            self.roi[msg.request_id] = _RoiRequest(msg.request_id, msg.level, msg.x0, msg.y0,
                                                   msg.w, msg.h, now, held)
            self._touch("map")
        elif isinstance(msg, m.ImageGoal):
            self._image(msg.image_id).goal = (msg.kind.name, msg.value)
            self._touch("images")
        elif isinstance(msg, m.ImageByTimeRequest):
            self.image_queries.append({"command_id": msg.command_id, "stamp": msg.stamp,
                                       "direction": msg.direction.name, "sent": _num(now, 1)})
            self._touch("images")
        elif isinstance(msg, m.TimeSeriesRequest):
            self.series_requests.append({"command_id": msg.command_id, "channel": msg.channel,
                                         "start": unwrap(msg.start, now),
                                         "end": unwrap(msg.end, now),
                                         "max_error": msg.max_error, "sent": _num(now, 1)})
            self._touch("series")
        elif isinstance(msg, m.ScheduleUpdate):
            sch = self.schedules.get(msg.link)
            if sch is not None:
                sch["proposed"] = {"version": msg.version, "activate_cycle": msg.activate_cycle,
                                   "command_id": msg.command_id, "status": "sent",
                                   "slots": [{"owner": s.owner, "duration": s.duration,
                                              "guard": s.guard, "min_priority": s.min_priority}
                                             for s in msg.slots]}
                self._touch("link")
        self._touch("commands")
        self._log(now, f"sent {summary or kind}")

    def replace_command(self, built: m.Message, sent: m.Message, now: float) -> None:
        """The node sent ``sent`` for the command recorded as ``built`` (another command id)."""
        old = self.commands.pop(256 + int(getattr(built, "command_id", -1)), None)
        if old is None:
            return
        key = 256 + int(getattr(sent, "command_id", 0))
        old.message, old.command_id = sent, key - 256
        self.commands[key] = old
        self.command_order = deque((key if k == 256 + int(getattr(built, "command_id", -1))
                                    else k for k in self.command_order), maxlen=64)
        if isinstance(sent, m.ScheduleUpdate):
            sch = self.schedules.get(sent.link)
            if sch is not None and sch.get("proposed"):
                sch["proposed"]["command_id"] = sent.command_id
                sch["proposed"]["activate_cycle"] = sent.activate_cycle
        self._touch("commands", "link")

    def record_regions(self, regions: Sequence[Any], now: float, summary: str) -> None:
        """Remember map regions a bathymetry receiver will request (and retry) for us."""
        self._advance(now)
        for r in regions:
            if id(r) in self._region_ids:
                continue
            self._region_ids.add(id(r))
            self._region_count += 1
            key = -self._region_count
            self.roi[key] = _RoiRequest(-1, r.level, r.x0, r.y0, r.w, r.h, now, {}, region=r)
            text = (f"{summary}: subgrids [{r.x0}..{r.x0 + r.w - 1}] x "
                    f"[{r.y0}..{r.y0 + r.h - 1}]")
            ckey = 100000 + self._region_count
            self.commands[ckey] = _Command(-1, "MapRoiRequest", text, now,
                                           m.MapRoiRequest(0, r.level, r.x0, r.y0, r.w, r.h,
                                                           True, (), 0),
                                           status="queued", roi_key=key)
            self.command_order.append(ckey)
            self._log(now, f"requested {text}")
        self._touch("map", "commands")

    def _command_result(self, command_id: int, status: Any, now: float,
                        command: m.Message | None = None) -> None:
        cmd = self.commands.get(256 + command_id)
        name = status.name if hasattr(status, "name") else str(status)
        if cmd is not None and command is not None and cmd.message != command:
            cmd = None  # an id reused by a command sent by someone else
        if cmd is None:
            if command is None:
                last = self._foreign_acks.get(command_id)
                if last is None or last[0] != name or now - last[1] > 600:
                    self._log(now, f"vehicle answered command {command_id}: {name.lower()} "
                                   "(not sent from this console)")
                self._foreign_acks[command_id] = (name, now)
                return
            # a command the topside node sent for someone else (a script, a receiver)
            key = 256 + command_id
            cmd = self.commands[key] = _Command(command_id, type(command).__name__,
                                                f"{type(command).__name__} (by the node)",
                                                now, command)
            if key in self.command_order:
                self.command_order.remove(key)
            self.command_order.append(key)
        cmd.status, cmd.answered = name.lower(), now
        if isinstance(cmd.message, m.ScheduleUpdate):
            sch = self.schedules.get(cmd.message.link)
            if sch is not None and sch.get("proposed"):
                sch["proposed"]["status"] = name.lower()
            self._touch("link")
        self._touch("commands")
        self._log(now, f"{cmd.summary}: {name.lower()}",
                  "info" if name == "ACCEPTED" else "warn")

    def _on_command_ack(self, a: m.CommandAck, now: float) -> None:
        self._command_result(a.command_id, a.status, now)

    # -------------------------------------------------------------------- snapshots
    def changes(self, seen: Mapping[str, int]) -> dict[str, Any]:
        """The sections whose version differs from ``seen`` (section -> version)."""
        return {s: self.section(s) for s in SECTIONS if seen.get(s) != self.versions[s]}

    def snapshot(self) -> dict[str, Any]:
        """The whole state as JSON-able data (plus ``now`` and section ``versions``)."""
        out = {s: self.section(s) for s in SECTIONS}
        out["now"] = self.now
        out["versions"] = dict(self.versions)
        return out

    def section(self, name: str) -> Any:
        return getattr(self, f"_snap_{name}")()

    def _snap_vehicle(self) -> dict[str, Any]:
        s = self.status
        status = None
        if s is not None:
            status = {"t": self.status_t, "age": _num(self.now - (self.status_t or 0), 1),
                      "x": s.x, "y": s.y, "depth": s.depth, "altitude": s.altitude,
                      "heading": s.heading, "speed": s.speed, "battery": s.battery,
                      "mode": s.mode.name, "faults": s.faults}
        track = list(self.track)
        if len(track) > 1500:  # keep the payload small: every k-th point plus the newest
            k = math.ceil(len(track) / 1500)
            track = [*track[::k], track[-1]]
        return {"status": status, "track": [[_num(t, 1), x, y, d] for t, x, y, d in track]}

    def _snap_map(self) -> dict[str, Any]:
        levels = []
        for lv in sorted(self.levels.values(), key=lambda v: -v.level):
            if not lv.tiles:
                continue
            if lv.summary is None or lv.summary[0] != lv.version:
                lv.summary = (lv.version,
                              np.array(list(lv.tiles.keys()), np.int64),
                              np.array([tile.t for tile in lv.tiles.values()]),
                              int(sum(int(np.isfinite(tile.z).sum())
                                      for tile in lv.tiles.values())))
            _, keys, ts, cells = lv.summary
            s, c = lv.side, lv.cell
            levels.append({
                "level": lv.level, "cell": c, "side": s, "subgrids": len(lv.tiles),
                "cells": cells, "coverage_m2": cells * c * c,
                "x0": float(keys[:, 0].min() * s * c), "y0": float(keys[:, 1].min() * s * c),
                "x1": float((keys[:, 0].max() + 1) * s * c),
                "y1": float((keys[:, 1].max() + 1) * s * c),
                "newest_age": _num(self.now - float(ts.max()), 1),
                "oldest_age": _num(self.now - float(ts.min()), 1),
                "version": lv.version, "png": f"/map/{lv.level}.png?v={lv.version}",
                "tiles": np.column_stack([keys, np.round(self.now - ts)]).astype(int).tolist(),
            })
        meta = self.map_meta
        zr = self._zrange
        return {
            "meta": None if meta is None else {
                "resolution": meta.resolution, "vertical_resolution": meta.vertical_resolution,
                "subgrid_side": meta.subgrid_side, "levels": meta.levels,
                "origin_lat": meta.origin_lat, "origin_lon": meta.origin_lon,
                "pending": meta.pending},
            "levels": levels, "zrange": None if zr is None else [zr[0], zr[1]],
            "targets": list(self.targets) + self._auto_targets(),
            "requests": [self._snap_roi(r) for r in sorted(self.roi.values(),
                                                          key=lambda r: r.sent)][-40:],
        }

    def _auto_targets(self) -> list[dict[str, Any]]:
        """Candidate targets flagged on the finest level held at 2 m or better (cells standing
        out from their surroundings, the bathymetry plugin's ``find_targets``)."""
        fine = [lv for lv in self.levels.values() if lv.tiles and lv.cell <= 2.0]
        if not self.auto_targets or not fine:
            return []
        lv = min(fine, key=lambda v: v.level)
        key = (lv.level, lv.version)
        last = self._targets_cache[0]
        # a big map changes with every subgrid: look again once 5% more of it has come in
        stale = (last is None or last[0] != lv.level or lv.version < last[1]
                 or lv.version - last[1] >= max(1, len(lv.tiles) // 20))
        if stale:
            from coex_plugins.bathymetry import find_targets

            grid = self.level_grid(lv.level)
            found: list[dict[str, Any]] = []
            if grid is not None:
                z, x0, y0, cell = grid
                cands = find_targets(z, cell=cell, x0=x0, y0=y0, threshold=self.target_threshold,
                                     min_cells=self.target_min_cells)
                for c in sorted(cands, key=lambda c: -c.height):
                    if len(found) >= self.max_targets:
                        break
                    if any(math.hypot(c.x - f["x"], c.y - f["y"]) < self.target_spacing
                           for f in found):
                        continue  # one marker per object
                    found.append({"x": _num(c.x, 1), "y": _num(c.y, 1),
                                  "height": _num(c.height, 2), "cells": int(c.cells),
                                  "level": lv.level, "auto": True})
            self._targets_cache = (key, found)
        return list(self._targets_cache[1])

    def _snap_roi(self, r: _RoiRequest) -> dict[str, Any]:
        lv = self.levels.get(r.level)
        side = lv.side if lv else (self.map_meta.subgrid_side if self.map_meta else 8)
        res = (lv.cell if lv else (self.map_meta.resolution * 2 ** r.level
                                    if self.map_meta else 2.0 ** r.level))
        span = side * res
        rid = r.request_id
        status = r.status
        if r.region is not None:
            rid = r.region.request_id if r.region.request_id is not None else -1
            if r.region.sends == 0 and status == "requested":
                status = "waiting"
        return {"request_id": rid, "level": r.level, "x0": r.x0, "y0": r.y0,
                "w": r.w, "h": r.h, "status": status, "queued": r.queued,
                "received": r.received, "sent": _num(r.sent, 1),
                "rect": [r.x0 * span, r.y0 * span, (r.x0 + r.w) * span, (r.y0 + r.h) * span]}

    def _snap_images(self) -> dict[str, Any]:
        items = []
        for img in sorted(self.images.values(), key=lambda i: (i.t or 0, i.image_id)):
            a = img.announce
            info = img.decoded_meta
            total = a.total_bytes if a else info.get("total_bytes")
            got = max(img.bytes_received, int(info.get("held_bytes", 0) or 0))
            items.append({
                "image_id": img.image_id, "t": _num(img.t, 1),
                "stamp": a.stamp if a else info.get("stamp"),
                "x": a.x if a else info.get("x"), "y": a.y if a else info.get("y"),
                "width": a.width if a else info.get("width"),
                "height": a.height if a else info.get("height"),
                "total_bytes": total, "bytes_received": got,
                "fraction": _num(got / total, 3) if total else None,
                "goal": None if img.goal is None else {"kind": img.goal[0], "value": img.goal[1]},
                "thumb": (f"/image/{img.image_id}.png?v={img.decoded_version}"
                          if img.decoded is not None else None),
                "meta": img.decoded_meta,
            })
        return {"items": items, "queries": self.image_queries[-10:],
                "progress": self.progress_info}

    def _snap_series(self) -> dict[str, Any]:
        chans = []
        for _cid, s in sorted(self.series.items()):
            d: dict[str, Any] = {k: v for k, v in s.items()
                                 if k not in ("times", "values", "bounds")}
            t = s.get("times")
            if t is not None and t.size:
                v, b = s["values"], s["bounds"]
                if t.size > 2000:  # min/max decimation keeps spikes visible
                    k = math.ceil(t.size / 1000)
                    n = (t.size // k) * k
                    tv = t[:n].reshape(-1, k)
                    vv = v[:n].reshape(-1, k)
                    bb = b[:n].reshape(-1, k)
                    imin, imax = vv.argmin(axis=1), vv.argmax(axis=1)
                    rows = np.arange(vv.shape[0])
                    idx = np.sort(np.stack([imin, imax], axis=1), axis=1)
                    t = tv[rows[:, None], idx].ravel()
                    v = vv[rows[:, None], idx].ravel()
                    b = bb.max(axis=1).repeat(2)
                fin = np.isfinite(b)
                d["t"] = np.round(t, 2).tolist()
                d["v"] = np.round(v, 5).tolist()
                d["err"] = np.where(fin, np.round(b, 5), -1.0).tolist()
                d["max_error"] = _num(float(b[fin].max()), 5) if fin.any() else None
                d["samples"] = int(s["times"].size)
            chans.append(d)
        return {"channels": chans, "requests": self.series_requests[-20:]}

    def _snap_link(self) -> dict[str, Any]:
        links = []
        for lk in sorted(self.links.values(), key=lambda x: x["link"]):
            d = {k: v for k, v in lk.items() if k != "history" and not k.startswith("_")}
            d["history"] = [[_num(t, 1), snr, f, b] for t, snr, f, b in lk["history"]]
            d["age"] = _num(self.now - lk["last"], 1) if lk["last"] is not None else None
            links.append(d)
        schedules = [{k: v for k, v in self.schedules[link].items() if not k.startswith("_")}
                     for link in sorted(self.schedules)]
        return {"links": links, "schedules": schedules,
                "node_id": self.node_id, "vehicle_id": self.vehicle_id,
                "bad_frames": self.bad_frames}

    def _snap_queues(self) -> dict[str, Any]:
        rows = []
        for sid, row in sorted(self.streams.items()):
            d = dict(row)
            d["name"] = self.stream_names.get(sid, f"stream {sid}")
            rows.append(d)
        return {"t": self.queue_stamp,
                "age": _num(self.now - self.queue_stamp, 1) if self.queue_stamp else None,
                "streams": rows}

    def _snap_commands(self) -> list[dict[str, Any]]:
        out = []
        for key in reversed(self.command_order):
            c = self.commands[key]
            status = c.status
            if c.roi_key is not None and c.roi_key in self.roi:
                status = self._snap_roi(self.roi[c.roi_key])["status"]
            out.append({"command_id": c.command_id, "kind": c.kind, "summary": c.summary,
                        "sent": _num(c.sent, 1), "status": status,
                        "answered": _num(c.answered, 1)})
        return out

    def _snap_log(self) -> list[dict[str, Any]]:
        return list(self.log)[-60:]


_HANDLERS: dict[type, Callable[[ConsoleState, Any, float, int | None], None]] = {
    m.VehicleStatus: lambda s, msg, now, link: s._on_status(msg, now),
    m.MapMetadata: lambda s, msg, now, link: s._on_meta(msg, now),
    m.Subgrid: lambda s, msg, now, link: s._on_subgrid(msg, now, link),
    m.MapRoiReply: lambda s, msg, now, link: s._on_roi_reply(msg, now),
    m.ImageAnnounce: lambda s, msg, now, link: s._on_announce(msg, now),
    m.ImageFragment: lambda s, msg, now, link: s._on_fragment(msg, now),
    m.TransferProgress: lambda s, msg, now, link: s._on_progress(msg, now),
    m.TimeSeriesChannel: lambda s, msg, now, link: s._on_channel(msg, now),
    m.LinkStatus: lambda s, msg, now, link: s._on_link_status(msg, now),
    m.QueueStatus: lambda s, msg, now, link: s._on_queue_status(msg, now),
    m.CommandAck: lambda s, msg, now, link: s._on_command_ack(msg, now),
}


def _decode_subgrid(sg: m.Subgrid) -> FloatArray:
    """Elevations of a subgrid (row 0 = south), with the bathymetry plugin's decoder."""
    from coex_plugins.bathymetry import decode_subgrid

    return np.asarray(decode_subgrid(sg), float)




# ----------------------------------------------------------------------------- actions


class ConsoleActions:
    """Operator actions as wire-format commands.

    Each method builds :mod:`coex_core.messages` commands, records them in ``state`` (so the page
    shows what was requested) and hands each one to ``send``. Invalid input raises
    :class:`~coex_core.errors.RequestRejected` and sends nothing. ``clock`` gives ``now``
    (the runner's clock; the actions never read one themselves)."""

    def __init__(self, state: ConsoleState, send: Callable[[m.Message], Any],
                 clock: Callable[[], float], *, first_command_id: int = 0,
                 map_receiver: Any = None) -> None:
        self.state = state
        #: A bathymetry receiver (``request_area``): when set, map regions are asked through it
        #: (it knows what topside holds, numbers the requests and retries them).
        self.map_receiver = map_receiver
        self.send = send
        self.clock = clock
        self._next_id = first_command_id % 256
        self._next_request = first_command_id % 256

    def _cid(self) -> int:
        source = getattr(self.send, "next_command_id", None)
        if callable(source):
            return int(source()) % 256
        cid = self._next_id
        self._next_id = (cid + 1) % 256
        return cid

    def _emit(self, msgs: Sequence[m.Message], summaries: Sequence[str]) -> list[m.Message]:
        now = self.clock()
        out: list[m.Message] = []
        for msg, text in zip(msgs, summaries):
            sent = self.send(msg)
            actual = sent if isinstance(sent, m.Message) else msg
            self.state.record_command(actual, now, text)
            out.append(actual)
        return out

    # -------------------------------------------------------------------------- map
    def request_region(self, level: int, x_min: float, y_min: float, x_max: float,
                       y_max: float, *, fill_gaps: bool = False) -> list[Any]:
        """Request the map at ``level`` over the rectangle ``[x_min, x_max] x [y_min, y_max]``
        (metres). The rectangle is cut into requests of at most 8 x 8 subgrids (16 x 16 with
        ``fill_gaps``), each listing what topside holds, so the vehicle sends only what is newer
        or missing."""
        level = int(level)
        if not 0 <= level <= 15:
            raise RequestRejected(f"level {level} outside 0..15")
        vals = [float(v) for v in (x_min, y_min, x_max, y_max)]
        if not all(math.isfinite(v) for v in vals):
            raise RequestRejected("region corners must be finite numbers")
        x_min, x_max = sorted(vals[0::2])
        y_min, y_max = sorted(vals[1::2])
        if self.map_receiver is not None:
            regions = list(self.map_receiver.request_area(level, x_min, y_min, x_max, y_max,
                                                          fill_gaps=bool(fill_gaps)))
            self.state.record_regions(regions, self.clock(), f"map level {level}"
                                      + (" (gaps)" if fill_gaps else ""))
            return regions
        lv = self.state.levels.get(level)
        meta = self.state.map_meta
        if lv is not None:
            side, cell = lv.side, lv.cell
        elif meta is not None:
            side, cell = meta.subgrid_side, meta.resolution * 2 ** level
        else:
            other = next(iter(self.state.levels.values()), None)
            if other is None:
                raise RequestRejected("no map geometry yet (no MapMetadata or subgrid received)")
            side, cell = other.side, other.cell / 2 ** other.level * 2 ** level
        span = side * cell
        ix0, iy0 = math.floor(x_min / span), math.floor(y_min / span)
        ix1, iy1 = math.floor(x_max / span), math.floor(y_max / span)
        nx, ny = ix1 - ix0 + 1, iy1 - iy0 + 1
        if nx * ny > MAX_ROI_SUBGRIDS:
            raise RequestRejected(f"region of {nx} x {ny} subgrids at level {level} is too large")
        if not (-8192 <= ix0 and ix1 < 8192 and -8192 <= iy0 and iy1 < 8192):
            raise RequestRejected("region outside the map's index range")
        step = MAX_ROI_SIDE if fill_gaps else 8
        msgs: list[m.MapRoiRequest] = []
        texts: list[str] = []
        for y in range(iy0, iy1 + 1, step):
            for x in range(ix0, ix1 + 1, step):
                w, h = min(step, ix1 + 1 - x), min(step, iy1 + 1 - y)
                held = self.state.held_stamps(level, x, y, w, h)
                rid = self._next_request
                self._next_request = (rid + 1) % 256
                if fill_gaps:
                    have = 0
                    for k, st in enumerate(held):
                        if st is not None:
                            have |= 1 << (w * h - 1 - k)
                    msg = m.MapRoiRequest(rid, level, x, y, w, h, True, (), have)
                else:
                    msg = m.MapRoiRequest(rid, level, x, y, w, h, False, tuple(held))
                msgs.append(msg)
                texts.append(f"map level {level} subgrids [{x}..{x + w - 1}] x "
                             f"[{y}..{y + h - 1}]{' (gaps)' if fill_gaps else ''}")
        return self._emit(msgs, texts)

    # ----------------------------------------------------------------------- images
    def set_image_goal(self, image_id: int, kind: str, value: int = 0) -> m.ImageGoal:
        """Transfer an image up to a goal: ``skip``, ``fraction`` (value in %), ``layer``, ``full``."""
        try:
            gk = m.GoalKind[str(kind).upper()]
        except KeyError:
            raise RequestRejected(f"unknown goal kind {kind!r}") from None
        value = int(value)
        if gk == m.GoalKind.FRACTION and not 1 <= value <= 100:
            raise RequestRejected("a fraction goal is 1..100 (%)")
        if gk == m.GoalKind.LAYER and not 0 <= value <= 255:
            raise RequestRejected("a layer goal is 0..255")
        if gk in (m.GoalKind.SKIP, m.GoalKind.FULL):
            value = 0
        msg = m.ImageGoal(self._cid(), int(image_id), gk, value)
        text = f"image {image_id} goal {gk.name.lower()}" + (f" {value}" if value else "")
        self._emit([msg], [text])
        return msg

    def image_by_time(self, t: float, direction: str = "nearest") -> m.ImageByTimeRequest:
        """Ask for the image nearest time ``t`` (absolute seconds), or the one before/after it."""
        try:
            d = {"nearest": m.TimeDirection.NEAREST, "previous": m.TimeDirection.BEFORE,
                 "before": m.TimeDirection.BEFORE, "next": m.TimeDirection.AFTER,
                 "after": m.TimeDirection.AFTER}[str(direction).lower()]
        except KeyError:
            raise RequestRejected(f"unknown direction {direction!r}") from None
        if not math.isfinite(float(t)):
            raise RequestRejected("time must be finite")
        msg = m.ImageByTimeRequest(self._cid(), to_stamp(float(t)), d)
        self._emit([msg], [f"image {d.name.lower()} t={float(t):.0f}"])
        return msg

    # ------------------------------------------------------------------ time series
    def refine_series(self, channel: int, start: float, end: float,
                      max_error: float | None = None) -> m.TimeSeriesRequest:
        """Refine a channel over ``[start, end]`` (absolute seconds) down to ``max_error``
        (default: a quarter of the worst bound held in the window)."""
        start, end = sorted((float(start), float(end)))
        if not (math.isfinite(start) and math.isfinite(end)):
            raise RequestRejected("window must be finite")
        s = self.state.series.get(int(channel))
        if s is None:
            raise RequestRejected(f"unknown channel {channel}")
        if max_error is None:
            t, b = s.get("times"), s.get("bounds")
            if t is None or b is None:
                raise RequestRejected("no data in that window to refine; give max_error")
            sel = (t >= start) & (t <= end) & np.isfinite(b)
            if not sel.any():
                raise RequestRejected("no data in that window to refine; give max_error")
            max_error = float(b[sel].max()) / 4
            if s.get("resolution"):
                max_error = max(max_error, float(s["resolution"]) / 2)
        if not (math.isfinite(max_error) and max_error > 0):
            raise RequestRejected("max_error must be positive")
        msg = m.TimeSeriesRequest(self._cid(), int(channel), to_stamp(start), to_stamp(end),
                                  float(np.float32(max_error)))
        name = s.get("name", f"channel {channel}")
        self._emit([msg], [f"refine {name} {start:.0f}..{end:.0f} s to ±{max_error:.3g}"])
        return msg

    # ------------------------------------------------------------------------ queues
    def queue_config(self, stream: int, *, flush: bool = False, enabled: bool | None = None,
                     priority: int | None = None, ttl: int | None = None,
                     max_depth: int | None = None,
                     newest_first: bool | None = None) -> m.QueueConfig:
        """Change one stream's settings (``None`` leaves a setting unchanged) or flush it."""
        stream = int(stream)
        if not 0 <= stream <= 31:
            raise RequestRejected(f"stream {stream} outside 0..31")
        if priority is not None and not 0 <= int(priority) <= 127:
            raise RequestRejected("priority is 0..127")
        if ttl is not None and not 0 <= int(ttl) <= 16383:
            raise RequestRejected("ttl is 0..16383 s")
        if max_depth is not None and not 0 <= int(max_depth) <= 1023:
            raise RequestRejected("max_depth is 0..1023")
        msg = m.QueueConfig(self._cid(), stream, bool(flush), enabled,
                            None if priority is None else int(priority),
                            None if ttl is None else int(ttl),
                            None if max_depth is None else int(max_depth), newest_first)
        parts = [f"stream {stream}:"]
        if flush:
            parts.append("flush")
        if enabled is not None:
            parts.append("enable" if enabled else "disable")
        if priority is not None:
            parts.append(f"priority {priority}")
        for k, v in (("ttl", ttl), ("max depth", max_depth), ("newest first", newest_first)):
            if v is not None:
                parts.append(f"{k} {v}")
        self._emit([msg], [" ".join(parts)])
        return msg

    # -------------------------------------------------------------------------- link
    def link_control(self, link: int, enabled: bool, mute: bool = False) -> m.LinkControl:
        """Enable or disable one modem link (or mute it)."""
        link = int(link)
        if not 0 <= link <= 7:
            raise RequestRejected(f"link {link} outside 0..7")
        msg = m.LinkControl(self._cid(), link, bool(enabled), bool(mute))
        self._emit([msg], [f"link {link} {'enable' if enabled else 'disable'}"
                           + (" mute" if mute else "")])
        return msg

    def propose_schedule(self, link: int, slots: Sequence[Mapping[str, Any]],
                         activate_cycle: int | None = None,
                         version: int | None = None) -> m.ScheduleUpdate:
        """Propose a new TDMA schedule for ``link``: ``slots`` of ``owner``, ``duration``,
        ``guard``, ``min_priority``; active from ``activate_cycle`` (default: two cycles after
        the current one) with ``version`` (default: the running one plus 1, mod 16)."""
        link = int(link)
        if not 0 <= link <= 7:
            raise RequestRejected(f"link {link} outside 0..7")
        if not 1 <= len(slots) <= 32:
            raise RequestRejected("a schedule has 1..32 slots")
        out = []
        for s in slots:
            try:
                owner, dur = int(s["owner"]), float(s["duration"])
                guard, minp = float(s.get("guard", 0.0)), int(s.get("min_priority", 0))
            except (KeyError, TypeError, ValueError) as exc:
                raise RequestRejected(f"bad slot {s!r}: {exc}") from None
            if not (0 <= owner <= 15 and 0.1 <= dur <= 600 and 0 <= guard <= 25.5
                    and guard < dur and 0 <= minp <= 127):
                raise RequestRejected(f"slot {s!r} out of range")
            out.append(m.Slot(owner, round(dur, 1), round(guard, 1), minp))
        cur = self.state.schedules.get(link)
        now = self.clock()
        if version is None:
            version = ((cur["active_version"] if cur else 0) + 1) % 16
        if activate_cycle is None:
            if cur and cur["cycle"] > 0:
                activate_cycle = (cur["first_cycle"]
                                  + int((now - cur["epoch"]) // cur["cycle"]) + 2)
            else:
                activate_cycle = 0
        msg = m.ScheduleUpdate(self._cid(), link, int(version) % 16, int(activate_cycle) % 65536,
                               tuple(out))
        self._emit([msg], [f"schedule v{msg.version} for link {link} "
                           f"({len(out)} slots, cycle {msg.activate_cycle})"])
        return msg

    # ------------------------------------------------------------------- dispatcher
    def dispatch(self, action: str, args: Mapping[str, Any]) -> list[m.Message]:
        """Run an action named by the page (``request_region``, ``set_image_goal``,
        ``image_by_time``, ``refine_series``, ``queue_config``, ``link_control``,
        ``propose_schedule``) with keyword ``args``; returns the messages sent."""
        fn = {
            "request_region": self.request_region, "set_image_goal": self.set_image_goal,
            "image_by_time": self.image_by_time, "refine_series": self.refine_series,
            "queue_config": self.queue_config, "link_control": self.link_control,
            "propose_schedule": self.propose_schedule,
        }.get(action)
        if fn is None:
            raise RequestRejected(f"unknown action {action!r}")
        try:
            result = fn(**dict(args))  # type: ignore[operator]
        except TypeError as exc:
            raise RequestRejected(f"bad arguments for {action}: {exc}") from None
        except (ValueError, OverflowError) as exc:
            raise RequestRejected(f"bad value for {action}: {exc}") from None
        return list(result) if isinstance(result, list) else [result]
