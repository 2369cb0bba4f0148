"""The topside side of the time-series modality: reconstruction, error bounds, requests, CSV."""

from __future__ import annotations

import csv
import io
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from coex import (
    ConfigError,
    ModalityReceiver,
    Options,
    Product,
    RequestRejected,
    RequestTracker,
    merged_config,
    persistent,
    to_stamp,
    unwrap,
)
from coex.messages import (
    Message,
    TimeSeriesAck,
    TimeSeriesChannel,
    TimeSeriesChunk,
    TimeSeriesPart,
    TimeSeriesRequest,
    Wavelet,
)
from coex.options import anything, integer, number

from . import codec
from .product import SeriesProduct

__all__ = ["Series", "TimeSeriesReceiver", "sample_series"]

log = logging.getLogger(__name__)
MAX_ACK_PARTS = 40


@persistent("timeseries.Series")
@dataclass(frozen=True)
class Series:
    """A channel's reconstruction: sample times, values and the error bound of each value
    (``inf`` where the bound is unknown because a pass is incomplete)."""

    channel: int
    name: str
    unit: str
    times: np.ndarray
    values: np.ndarray
    bounds: np.ndarray

    @property
    def max_bound(self) -> float:
        return float(self.bounds.max()) if self.bounds.size else math.inf


def _narrow(codes: np.ndarray) -> np.ndarray:
    """Integer codes in the narrowest integer type that holds them: topside keeps every pass of
    the dive's blocks (and saves them in every snapshot), mostly small codes."""
    if not codes.size:
        return codes
    lo, hi = int(codes.min()), int(codes.max())
    for t in (np.int8, np.int16, np.int32):
        info = np.iinfo(t)
        if info.min <= lo and hi <= info.max:
            return codes.astype(t)
    return codes


@persistent("timeseries.Part")
@dataclass
class _Part:
    end: int
    step: int
    error: int
    codes: np.ndarray
    samples: bool


@persistent("timeseries.RBlock")
@dataclass
class _RBlock:
    start: float
    period: float
    count: int
    wavelet: Wavelet
    passes: dict[int, dict[int, _Part]] = field(default_factory=dict)
    cache: tuple[np.ndarray, float] | None = None

    @property
    def end(self) -> float:
        return self.start + (self.count - 1) * self.period

    def complete(self, level: int) -> bool:
        parts = self.passes.get(level)
        if not parts:
            return False
        total = self.total(next(iter(parts.values())).samples)
        pos = 0
        for first in sorted(parts):
            if first > pos:
                return False
            pos = max(pos, parts[first].end)
        return pos >= total

    def total(self, samples: bool) -> int:
        return self.count if samples else codec.layout(self.count, self.wavelet).total

    def reconstruct(self) -> tuple[np.ndarray, float] | None:
        """Values and bound from the complete passes ``0..P`` (or partial pass 0, bound inf)."""
        if self.cache is not None:
            return self.cache
        total = codec.layout(self.count, self.wavelet).total
        top = -1
        while self.complete(top + 1):
            top += 1
        levels = list(range(top + 1)) if top >= 0 else ([0] if 0 in self.passes else [])
        if not levels:
            return None
        flat = np.zeros(total)
        direct = np.zeros(self.count)
        error = 255
        for level in levels:
            for first, part in self.passes[level].items():
                target = direct if part.samples else flat
                target[first:part.end] += part.codes * codec.code_value(part.step)
                error = part.error
        bound = codec.code_value(error) if top >= 0 else math.inf
        self.cache = (codec.synthesise(flat, self.count, self.wavelet) + direct, bound)
        return self.cache

    def bound(self) -> float:
        r = self.reconstruct()
        return math.inf if r is None else r[1]


@persistent("timeseries.RChannel")
@dataclass
class _RChannel:
    cid: int
    registration: TimeSeriesChannel | None = None
    ack_registration: bool = False
    blocks: dict[int, _RBlock] = field(default_factory=dict)  # by start in centiseconds
    to_ack: list[TimeSeriesPart] = field(default_factory=list)
    version: int = 0

    @property
    def name(self) -> str:
        return self.registration.name if self.registration else f"channel{self.cid}"


#: the time-series receiver's options: the one declaration of their types, ranges and units
RECEIVER_OPTIONS = Options(
    request_retry=number(120.0, "an unsatisfied request is sent again after", unit="s", above=0),
    request_tries=integer(10, "sends of a request before it is dropped", lo=1),
    keep=number(None, "blocks older than this leave memory for out_dir (None: all stay)", unit="s", above=0,
                none=True),
    out_dir=anything(None, "a folder: series_<name>.csv, the whole dive (needed by keep)"),
)
#: their defaults (a name kept for 0.x code)
RECEIVER_DEFAULTS: dict[str, Any] = RECEIVER_OPTIONS.defaults()
#: archived block starts remembered one by one (per channel); older ones count as archived
MAX_ARCHIVED_KEYS = 1024
#: the archive's columns (``series_<name>.csv``)
ARCHIVE_COLUMNS = ("time", "value", "bound", "block_start")


def _upgrade_receiver(fields: dict[str, Any], saved: int) -> dict[str, Any]:
    """Version 1 kept every block in memory (no ``keep``, no archive)."""
    if saved < 2:
        fields.setdefault("keep", None)
        fields.setdefault("out_dir", None)
        fields.setdefault("_archived", {})
        fields.setdefault("_archived_floor", {})
        fields.setdefault("archived_late", 0)
    return fields


@persistent("timeseries.Receiver", version=2, upgrade=_upgrade_receiver)
class TimeSeriesReceiver(ModalityReceiver):
    """Takes channel registrations and chunks, acks them, tracks requests, reconstructs.

    Configuration: ``request_retry`` (120 s: an unsatisfied request is sent again after this
    long), ``request_tries`` (10: then it is dropped); ``keep`` (seconds, default None: every
    block of the dive stays in memory) with ``out_dir`` (a directory): a block that ends more
    than ``keep`` seconds before the newest block of its channel is appended to
    ``out_dir/series_<name>.csv`` (:data:`ARCHIVE_COLUMNS`) and leaves memory, so memory and
    the saved state hold a window of the series while the file holds the whole dive
    (``docs/timeseries.md``, "Archive").
    """

    options = RECEIVER_OPTIONS

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        config = merged_config(config, self.options, "time-series receiver")
        self.request_retry = float(config["request_retry"])
        self.request_tries = int(config["request_tries"])
        self.keep: float | None = config["keep"]
        out_dir = config.get("out_dir")
        self.out_dir: str | None = None if out_dir in (None, "") else str(out_dir)
        if self.keep is not None and self.out_dir is None:
            raise ConfigError("keep needs out_dir: the blocks leaving memory are written there")
        #: channel -> block starts (centiseconds) archived, the newest; older than the floor too
        self._archived: dict[int, list[int]] = {}
        self._archived_floor: dict[int, int] = {}
        #: chunks of blocks already archived (acked, not taken)
        self.archived_late = 0
        self._channels: dict[int, _RChannel] = {}
        self._pending: RequestTracker[TimeSeriesRequest] = RequestTracker(
            self.request_retry, self.request_tries)
        #: command id -> the window (start, end) of a tracked request, in seconds
        self._windows: dict[int, tuple[float, float]] = {}
        self.ignored = 0  # chunks that were well-formed on the wire but inconsistent

    # ------------------------------------------------------------------- receive

    def _ch(self, cid: int) -> _RChannel:
        ch = self._channels.get(cid)
        if ch is None:
            ch = self._channels[cid] = _RChannel(cid)
        return ch

    def receive(self, message: Message, now: float) -> list[Product]:
        if isinstance(message, TimeSeriesChannel):
            ch = self._ch(message.channel)
            ch.ack_registration = True
            if ch.registration != message:
                ch.registration = message
                ch.version += 1
                return [self._product(ch)]
            return []
        if isinstance(message, TimeSeriesChunk):
            return self._chunk(message, now)
        return []

    def _chunk(self, m: TimeSeriesChunk, now: float) -> list[Product]:
        ch = self._ch(m.channel)
        start = unwrap(m.start, now) + m.offset
        key = round(start * 100)  # absolute: stamps repeat every 2^18 s
        lay = codec.layout(m.count, m.wavelet)
        total = m.count if m.samples else lay.total
        n_approx = 0 if m.samples else lay.n_approx
        first, end = (0, total) if m.first is None else (m.first, m.end or 0)
        if not first < end <= total:
            self.ignored += 1
            log.warning("chunk of channel %d covers [%d, %d) outside 0..%d", m.channel, first, end, total)
            return []
        block = ch.blocks.get(key)
        if block is None and self._was_archived(m.channel, key):
            # its block is in the archive already: acked (the vehicle stops sending it), not taken
            ch.to_ack.append(TimeSeriesPart(m.start, m.offset, m.level, 0 if m.first is None else m.first))
            self.archived_late += 1
            return []
        if block is not None and (block.count, block.period, block.wavelet) != (m.count, m.period, m.wavelet):
            self.ignored += 1
            log.warning("chunk of channel %d disagrees with its block's geometry", m.channel)
            return []
        try:
            if m.samples:  # every code of a samples chunk may be difference-coded
                codes = codec.decode_codes(m.data, end - first, end - first)
            else:
                codes = codec.decode_codes(m.data, end - first, n_approx, allow_dpcm=first == 0)
        except codec.CodeError as exc:
            self.ignored += 1
            log.warning("undecodable chunk of channel %d: %s", m.channel, exc)
            return []
        if block is None:
            block = ch.blocks[key] = _RBlock(start, m.period, m.count, m.wavelet)
        parts = block.passes.setdefault(m.level, {})
        if parts and next(iter(parts.values())).samples != m.samples:
            self.ignored += 1
            log.warning("chunk of channel %d disagrees with its pass's other chunks", m.channel)
            return []
        ch.to_ack.append(TimeSeriesPart(m.start, m.offset, m.level, first))
        if first in parts:
            return []  # duplicate: acked again, nothing new
        if any(f < end and first < p.end for f, p in parts.items()):
            # coefficients [first, end) overlap a chunk already held: adding both would count
            # them twice (spec/payloads.md 2.4); the chunk is refused, not acked
            ch.to_ack.pop()
            self.ignored += 1
            log.warning("chunk [%d, %d) of channel %d overlaps a chunk of its pass already held", first, end,
                        m.channel)
            return []
        parts[first] = _Part(end, m.step, m.error, _narrow(codes), m.samples)
        block.cache = None
        ch.version += 1
        self._archive_old(ch)
        return [self._product(ch)]

    # ------------------------------------------------------------------ archive

    def _was_archived(self, cid: int, key: int) -> bool:
        return key in self._archived.get(cid, ()) or key <= self._archived_floor.get(cid, -(2**62))

    def archive_path(self, channel: str | int) -> Path | None:
        """The channel's archive file (None without ``out_dir``)."""
        if self.out_dir is None:
            return None
        name = self._find(channel).name
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in name)
        return Path(self.out_dir) / f"series_{safe}.csv"

    def _archive_old(self, ch: _RChannel) -> None:
        """Blocks that end more than ``keep`` before the channel's newest go to the archive."""
        if self.keep is None or not ch.blocks:
            return
        newest = max(b.end for b in ch.blocks.values())
        old = sorted((k for k, b in ch.blocks.items() if b.end < newest - self.keep))
        if not old:
            return
        path = self.archive_path(ch.cid)
        assert path is not None
        path.parent.mkdir(parents=True, exist_ok=True)
        rows = []
        for k in old:
            block = ch.blocks[k]
            r = block.reconstruct()
            if r is not None:
                t = block.start + block.period * np.arange(block.count)
                rows.append(np.stack([np.char.mod("%.3f", t), np.char.mod("%.10g", r[0]),
                                      np.full(block.count, f"{r[1]:.10g}"),
                                      np.full(block.count, f"{block.start:.3f}")], axis=1))
        new_file = not path.exists()
        with path.open("a", newline="") as fh:  # appended and flushed before the blocks leave memory
            w = csv.writer(fh, lineterminator="\n")
            if new_file:
                w.writerow(ARCHIVE_COLUMNS)
            for table in rows:
                w.writerows(table.tolist())
        keys = self._archived.setdefault(ch.cid, [])
        for k in old:
            del ch.blocks[k]
            keys.append(k)
        keys.sort()
        if len(keys) > MAX_ARCHIVED_KEYS:
            floor = keys[-MAX_ARCHIVED_KEYS - 1]
            self._archived_floor[ch.cid] = max(self._archived_floor.get(ch.cid, floor), floor)
            del keys[:-MAX_ARCHIVED_KEYS]
        ch.version += 1

    def archived(self, channel: str | int) -> tuple[Series, list[tuple[float, float, float]]]:
        """What the archive file holds of a channel: its samples (a :class:`Series`) and
        ``(start, end, bound)`` of each block, as :meth:`series` and :meth:`bounds` give them
        (a block written twice, after a crash between its writing and the next snapshot:
        the last)."""
        ch = self._find(channel)
        unit = ch.registration.unit if ch.registration else ""
        path = self.archive_path(channel)
        empty = Series(ch.cid, ch.name, unit, np.zeros(0), np.zeros(0), np.zeros(0))
        if path is None or not path.exists():
            return empty, []
        table = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
        if not table.size:
            return empty, []
        t, v, b, blk = table.T
        keep = np.zeros(t.size, bool)
        starts, idx = np.unique(blk, return_inverse=True)
        blocks = []
        for j, s0 in enumerate(starts.tolist()):
            rows = np.flatnonzero(idx == j)
            # one writing of a block is a run of consecutive rows: the last run wins
            cut = np.flatnonzero(np.diff(rows) != 1)
            rows = rows[cut[-1] + 1:] if cut.size else rows
            keep[rows] = True
            blocks.append((float(s0), float(t[rows].max()), float(b[rows].max())))
        sel = np.flatnonzero(keep)
        sel = sel[np.argsort(t[sel], kind="stable")]
        return Series(ch.cid, ch.name, unit, t[sel], v[sel], b[sel]), blocks

    def held(self, channel: str | int) -> Series:
        """Every sample held topside: the archive's and memory's (time order)."""
        arch, _ = self.archived(channel)
        live = self.series(channel)
        return Series(live.channel, live.name, live.unit, np.concatenate([arch.times, live.times]),
                      np.concatenate([arch.values, live.values]), np.concatenate([arch.bounds, live.bounds]))

    # ----------------------------------------------------------------- requests

    def request(self, channel: str | int, start: float, end: float,
                max_error: float | None = None) -> TimeSeriesRequest:
        """Ask for the window ``[start, end]`` (absolute seconds) of a channel down to
        ``max_error`` or, when it is ``None``, four times finer than the worst bound held there.
        The request is sent by :meth:`poll` and repeated until the bound is met."""
        ch = self._find(channel)
        if not (math.isfinite(start) and math.isfinite(end) and start <= end):
            raise RequestRejected(f"invalid window [{start}, {end}]")
        if max_error is None:
            held = [b.bound() for b in ch.blocks.values() if b.end >= start and b.start <= end]
            finite = [h for h in held if math.isfinite(h)]
            if not finite:
                raise RequestRejected("no decoded data in that window to refine; give max_error")
            max_error = max(finite) / 4
            if ch.registration is not None:
                max_error = max(max_error, ch.registration.resolution / 2)
        if not (math.isfinite(max_error) and max_error > 0):
            raise RequestRejected(f"max_error must be positive, got {max_error}")
        if ch.registration is not None and max_error < ch.registration.resolution / 2 * (1 - 1e-6):
            raise RequestRejected(
                f"max_error {max_error:g} is below half the resolution ({ch.registration.resolution / 2:g})")
        req = TimeSeriesRequest(self.next_command_id(), ch.cid, to_stamp(start), to_stamp(end),
                                float(np.float32(max_error)))
        self._windows[req.command_id] = (start, end)
        self._pending.add(req.command_id, req)
        return req

    def _find(self, channel: str | int) -> _RChannel:
        if isinstance(channel, int) and not isinstance(channel, bool):
            if not 0 <= channel < 32:
                raise RequestRejected(f"channel id {channel} out of range")
            return self._ch(channel)
        for ch in self._channels.values():
            if ch.registration is not None and ch.registration.name == channel:
                return ch
        raise RequestRejected(f"unknown channel {channel!r}")

    def _satisfied(self, req: TimeSeriesRequest) -> bool:
        t0, t1 = self._windows[req.command_id]
        ch = self._ch(req.channel)
        blocks = [b for b in ch.blocks.values() if b.end >= t0 and b.start <= t1 + 1]
        return bool(blocks) and all(b.bound() <= req.max_error for b in blocks)

    def poll(self, now: float) -> list[Message]:
        out: list[Message] = []
        for ch in self._channels.values():
            parts, ch.to_ack = ch.to_ack, []
            if ch.ack_registration or parts:
                for i in range(0, max(len(parts), 1), MAX_ACK_PARTS):
                    out.append(TimeSeriesAck(ch.cid, ch.ack_registration, tuple(parts[i:i + MAX_ACK_PARTS])))
                ch.ack_registration = False
        out += self._pending.due(now, done=self._satisfied)
        self._windows = {cid: w for cid, w in self._windows.items() if cid in self._pending}
        return out

    def pending_requests(self) -> list[TimeSeriesRequest]:
        """Requests not yet satisfied."""
        return self._pending.pending(done=self._satisfied)

    # ----------------------------------------------------------------- products

    def series(self, channel: str | int) -> Series:
        """The reconstruction of one channel (blocks in time order)."""
        ch = self._find(channel)
        return self._series(ch)

    def _series(self, ch: _RChannel) -> Series:
        ts, vs, bs = [], [], []
        for block in sorted(ch.blocks.values(), key=lambda b: b.start):
            r = block.reconstruct()
            if r is None:
                continue
            ts.append(block.start + block.period * np.arange(block.count))
            vs.append(r[0])
            bs.append(np.full(block.count, r[1]))
        unit = ch.registration.unit if ch.registration else ""
        return Series(ch.cid, ch.name, unit, _cat(ts), _cat(vs), _cat(bs))

    def _product(self, ch: _RChannel) -> SeriesProduct:
        s = self._series(ch)
        reg = ch.registration
        return SeriesProduct(
            "series", ch.name, ch.version, s, channel=ch.cid, name=ch.name, unit=s.unit,
            samples=int(s.times.size), blocks=len(ch.blocks),
            # JSON-safe: None while nothing is held or a bound is unknown (incomplete pass)
            max_bound=s.max_bound if s.times.size and math.isfinite(s.max_bound) else None,
            lo=None if reg is None else reg.lo, hi=None if reg is None else reg.hi,
            resolution=None if reg is None else reg.resolution)

    def products(self) -> list[Product]:
        return [self._product(ch) for _, ch in sorted(self._channels.items())]

    def bounds(self, channel: str | int) -> list[tuple[float, float, float]]:
        """``(start, end, bound)`` of every block held for a channel (``inf``: incomplete), in
        memory and, with ``keep``, in the archive."""
        ch = self._find(channel)
        live = [(b.start, b.end, b.bound()) for b in sorted(ch.blocks.values(), key=lambda b: b.start)]
        return (self.archived(channel)[1] if self.keep is not None else []) + live

    # ---------------------------------------------------------------------- CSV

    def to_csv(self, target: str | Path | io.TextIOBase | None = None,
               times: Sequence[float] | np.ndarray | None = None,
               channels: Sequence[str | int] | None = None,
               names: Sequence[str] | None = None) -> str:
        """Export ``time``, one column per channel, then one ``<name>_bound`` column each.

        Values are given at ``times`` (linear interpolation of each block's grid; empty where
        no block covers the time), or at the union of the channels' grid times. ``channels``
        (names or ids) picks and orders the channels, ``names`` renames their columns. Returns
        the text and writes it to ``target`` when given."""
        chans = [self._find(c) for c in channels] if channels is not None else [
            ch for _, ch in sorted(self._channels.items())]
        series = [self._series(ch) for ch in chans]
        if times is None:
            grid = np.unique(np.concatenate([s.times for s in series])) if series else np.zeros(0)
        else:
            grid = np.asarray(times, dtype=np.float64)
        cols_v, cols_b = [], []
        for s in series:
            v, b = sample_series(s, grid)
            cols_v.append(v)
            cols_b.append(b)
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        labels = list(names) if names is not None else [s.name for s in series]
        if len(labels) != len(series):
            raise ConfigError(f"{len(labels)} names for {len(series)} channels")
        w.writerow(["time", *labels, *(f"{n}_bound" for n in labels)])
        table = [np.char.mod("%.3f", grid)]
        table += [np.where(np.isnan(c), "", np.char.mod("%.10g", c)) for c in cols_v + cols_b]
        if grid.size:
            w.writerows(np.stack(table, axis=1).tolist())
        text = buf.getvalue()
        if isinstance(target, str | Path):
            Path(target).write_text(text)
        elif target is not None:
            target.write(text)
        return text


def _cat(arrays: list[np.ndarray]) -> np.ndarray:
    return np.concatenate(arrays) if arrays else np.zeros(0)


def sample_series(s: Series, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Values and bounds of a series at ``grid`` times (NaN where no block covers them)."""
    v = np.full(grid.size, np.nan)
    b = np.full(grid.size, np.nan)
    if not s.times.size or not grid.size:
        return v, b
    # blocks are contiguous runs of the grid; interpolate inside each block only
    gaps = np.zeros(0, dtype=np.int64)
    if s.times.size > 1:
        d = np.diff(s.times)
        gaps = np.flatnonzero(d > 1.5 * np.median(d))
    bounds = np.split(np.arange(s.times.size), gaps + 1)
    for idx in bounds:
        t = s.times[idx]
        half = 0.5 * (t[1] - t[0]) if t.size > 1 else 0.5
        inside = (grid >= t[0] - half) & (grid <= t[-1] + half)
        v[inside] = np.interp(grid[inside], t, s.values[idx])
        b[inside] = np.interp(grid[inside], t, s.bounds[idx])
    return v, b
