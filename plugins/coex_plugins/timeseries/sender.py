"""The subsea side of the time-series modality."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from coex import (
    STAMP_MODULUS,
    CoexError,
    ConfigError,
    ModalitySender,
    RequestRejected,
    merged_config,
    persistent,
    unwrap,
    wire,
)
from coex.messages import (
    Message,
    TimeSeriesAck,
    TimeSeriesChannel,
    TimeSeriesChunk,
    TimeSeriesRequest,
)

from . import codec

__all__ = ["InvalidSamples", "Samples", "TimeSeriesSender", "ChannelConfig", "WAVELETS"]

WAVELETS = {name: w for w, name in codec.WAVELET_NAMES.items()}
MAX_CHANNELS = 32
MAX_PASSES = 16
MAX_CHUNK_DATA = 232
# priority classes of queued chunks (lower is sent first)
_REQUESTED, _ALERT, _OVERVIEW = 0, 1, 2
#: refinement passes made for spare capacity: sent only by ``spare``
_SPARE = 3
#: what a done block keeps of its samples, reconstruction and pass codes
_NOTHING = np.zeros(0)
_NO_CODES = np.zeros(0, np.int64)


class InvalidSamples(CoexError, ValueError):
    """Sensor samples that cannot be ingested (unknown channel, bad times, out of range)."""


@persistent("timeseries.Samples")
@dataclass(frozen=True)
class Samples:
    """Samples of one channel: ``times`` (absolute seconds, non-decreasing) and ``values``
    (NaN marks a missing value)."""

    channel: str
    times: Any
    values: Any


@persistent("timeseries.ChannelConfig")
@dataclass(frozen=True)
class ChannelConfig:
    """A channel's registration and coding settings."""

    name: str
    unit: str
    lo: float
    hi: float
    resolution: float
    period: float | None = None
    overview_error: float | None = None

    @classmethod
    def from_mapping(cls, m: Mapping[str, Any]) -> ChannelConfig:
        try:
            cfg = cls(
                name=str(m["name"]), unit=str(m.get("unit", "")), lo=float(m["lo"]), hi=float(m["hi"]),
                resolution=float(m["resolution"]),
                period=None if m.get("period") is None else float(m["period"]),
                overview_error=None if m.get("overview_error") is None else float(m["overview_error"]),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"invalid channel {dict(m)!r}: {exc}") from exc
        if not cfg.name or len(cfg.name.encode()) > 32 or len(cfg.unit.encode()) > 16:
            raise ConfigError(f"channel name must be 1..32 bytes and unit at most 16: {cfg.name!r}")
        if not (math.isfinite(cfg.lo) and math.isfinite(cfg.hi) and cfg.lo < cfg.hi):
            raise ConfigError(f"channel {cfg.name}: need finite lo < hi")
        if not (math.isfinite(cfg.resolution) and cfg.resolution > 0):
            raise ConfigError(f"channel {cfg.name}: resolution must be positive")
        if cfg.period is not None and not 0.01 <= cfg.period <= 655.35:
            raise ConfigError(f"channel {cfg.name}: period must be in 0.01..655.35 s")
        if cfg.overview_error is not None and not cfg.overview_error > 0:
            raise ConfigError(f"channel {cfg.name}: overview_error must be positive")
        return cfg


@persistent("timeseries.Chunk")
@dataclass
class _Chunk:
    message: TimeSeriesChunk
    size: int
    key: tuple[int, float, int, int]
    klass: int
    order: int
    t0: float  # absolute start of the chunk's block
    sent_at: float | None = None
    acked: bool = False


@persistent("timeseries.Block")
@dataclass
class _Block:
    start: float  # absolute time of sample 0 (on a 0.01 s grid)
    stamp: int
    offset: float
    period: float
    x: np.ndarray
    recon: np.ndarray
    passes: list[codec.Pass] = field(default_factory=list)
    chunks: list[list[_Chunk]] = field(default_factory=list)
    #: a done block's sample count (-1 while it is not done: ``x`` holds the samples). A block
    #: is done when no pass is left to make and topside acknowledged all its chunks: its
    #: samples, reconstruction, pass codes and chunks are dropped (nothing can need them), so
    #: the sender's saved state does not grow with the length of the dive.
    samples: int = -1

    @property
    def count(self) -> int:
        return self.samples if self.samples >= 0 else int(self.x.size)

    @property
    def done(self) -> bool:
        return self.samples >= 0

    @property
    def end(self) -> float:
        return self.start + (self.count - 1) * self.period

    def bound(self) -> float:
        return codec.code_value(self.passes[-1].error) if self.passes else math.inf


@persistent("timeseries.Channel")
@dataclass
class _Channel:
    cid: int
    cfg: ChannelConfig
    registration: TimeSeriesChannel
    reg_size: int
    reg_sent_at: float | None = None
    reg_acked: bool = False
    period: float | None = None
    times: np.ndarray = field(default_factory=lambda: np.zeros(0))
    values: np.ndarray = field(default_factory=lambda: np.zeros(0))
    last_time: float = -math.inf
    blocks: list[_Block] = field(default_factory=list)
    by_key: dict[tuple[int, float, int, int], _Chunk] = field(default_factory=dict)


def _positive(config: Mapping[str, Any], key: str, default: float) -> float:
    v = config.get(key, default)
    try:
        f = float(v)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{key} must be a number, got {v!r}") from exc
    if not (math.isfinite(f) and f > 0):
        raise ConfigError(f"{key} must be positive, got {v!r}")
    return f


#: the time-series sender's options (None: the default documented below)
SENDER_OPTIONS: dict[str, Any] = dict.fromkeys((
    "channels", "wavelet", "block_samples", "max_latency", "overview_factor", "alert_fraction",
    "retry_after", "spike_close"))


@persistent("timeseries.Sender")
class TimeSeriesSender(ModalitySender):
    """Blocks samples per channel, codes each block progressively and serves the link.

    Configuration (all optional except ``channels``):

    * ``channels``: list of ``{name, unit, lo, hi, resolution[, period][, overview_error]}``;
      channel ids are list positions (at most 32).
    * ``wavelet`` (``"bior4.4"``), ``block_samples`` (4096, at most 4096), ``max_latency``
      (120 s: a block closes when full or this long after its first sample, so a series shows
      topside within a minute or two; longer blocks code better: an archive may set 1200),
      ``overview_factor`` (12: the overview's error target is this many noise sigmas, at least
      half the resolution, unless the channel sets ``overview_error``), ``alert_fraction``
      (0.4: when a block holds spikes, i.e. short excursions from its running median, higher than
      ``2 * overview / alert_fraction``, a cheaper first pass with error ``alert_fraction * h``
      (``h`` the smallest such spike) goes ahead of every overview, so that spikes show
      early; 0 disables it), ``retry_after``
      (90 s: an unacknowledged chunk is sent again after this long), ``spike_close`` (60 s: a
      block closes early, so its alert goes out at once, when it holds a spike that ended this
      long before its newest sample; 0 disables it).
    """

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        config = {k: v for k, v in merged_config(config, SENDER_OPTIONS, "time-series sender").items()
                  if v is not None}
        name = str(config.get("wavelet", "bior4.4"))
        if name not in WAVELETS:
            raise ConfigError(f"wavelet must be one of {sorted(WAVELETS)}, got {name!r}")
        self.wavelet = WAVELETS[name]
        bs = config.get("block_samples", 4096)
        if not isinstance(bs, int) or isinstance(bs, bool) or not 16 <= bs <= 4096:
            raise ConfigError(f"block_samples must be an integer in 16..4096, got {bs!r}")
        self.block_samples = bs
        self.max_latency = _positive(config, "max_latency", 120.0)
        self.overview_factor = _positive(config, "overview_factor", 12.0)
        self.retry_after = _positive(config, "retry_after", 90.0)
        af = config.get("alert_fraction", 0.4)
        if isinstance(af, bool) or not isinstance(af, int | float) or not 0 <= af < 1:
            raise ConfigError(f"alert_fraction must be in [0, 1), got {af!r}")
        self.alert_fraction = float(af)
        sc = config.get("spike_close", 60.0)
        if isinstance(sc, bool) or not isinstance(sc, int | float) or not 0 <= sc < math.inf:
            raise ConfigError(f"spike_close must be a non-negative number of seconds, got {sc!r}")
        self.spike_close = float(sc)
        self._channels: list[_Channel] = []
        self._by_name: dict[str, _Channel] = {}
        self._order = 0
        for entry in config.get("channels", ()) or ():
            cfg = entry if isinstance(entry, ChannelConfig) else ChannelConfig.from_mapping(entry)
            self.register(cfg)

    # ------------------------------------------------------------------ channels

    def register(self, cfg: ChannelConfig) -> int:
        """Register a channel; returns its id."""
        if cfg.name in self._by_name:
            raise ConfigError(f"channel {cfg.name!r} registered twice")
        if len(self._channels) >= MAX_CHANNELS:
            raise ConfigError(f"at most {MAX_CHANNELS} channels")
        cid = len(self._channels)
        reg = TimeSeriesChannel(cid, cfg.name, cfg.unit, float(np.float32(cfg.lo)),
                                float(np.float32(cfg.hi)), float(np.float32(cfg.resolution)))
        ch = _Channel(cid, cfg, reg, wire.encoded_size(reg), period=cfg.period)
        self._channels.append(ch)
        self._by_name[cfg.name] = ch
        return cid

    @property
    def channels(self) -> list[ChannelConfig]:
        return [c.cfg for c in self._channels]

    # -------------------------------------------------------------------- ingest

    def ingest(self, data: Any, now: float) -> None:
        """Take samples: a :class:`Samples`, a ``(name, times, values)`` tuple, a mapping
        ``{name: (times, values)}`` or a sequence of these. Everything is checked before
        anything is taken: a bad batch raises :class:`InvalidSamples` and changes nothing."""
        batches = self._normalise(data)
        checked = [self._check(ch, t, v) for ch, t, v in batches]
        for ch, t, v in checked:
            ch.times = np.concatenate([ch.times, t])
            ch.values = np.concatenate([ch.values, v])
            ch.last_time = float(t[-1]) if t.size else ch.last_time
            self._close_full(ch)
            if t.size:
                self._close_on_spike(ch)
        self._close_late(now)

    def _close_on_spike(self, ch: _Channel) -> None:
        """Close the open block early when it holds a spike worth an alert that has ended
        ``spike_close`` seconds before the newest sample, so that the alert need not wait for
        the block to fill."""
        if not (self.spike_close and self.alert_fraction) or ch.times.size < 64:
            return
        ok = ~np.isnan(ch.values)
        t, v = ch.times[ok], ch.values[ok]
        if v.size < 64:
            return
        d = np.diff(v)
        sigma = float(np.median(np.abs(d - np.median(d)))) / 0.6745 / math.sqrt(2)
        target = ch.cfg.overview_error if ch.cfg.overview_error is not None else self.overview_factor * sigma
        target = max(target, ch.cfg.resolution / 2)
        e = _excursions(v)
        sig = np.flatnonzero(e > 2 * target / self.alert_fraction)
        # alert-worthy: the alert pass would aim at least twice as coarse as the overview
        if sig.size and self.alert_fraction * float(e[sig].max()) > 2 * target \
                and t[-1] - t[sig[-1]] >= self.spike_close:
            self._close(ch, ch.times.size)

    def _normalise(self, data: Any) -> list[tuple[_Channel, Any, Any]]:
        if isinstance(data, Samples):
            return [(self._channel(data.channel), data.times, data.values)]
        if isinstance(data, Mapping):
            out = []
            for name, pair in data.items():
                if not (isinstance(pair, Sequence) and len(pair) == 2):
                    raise InvalidSamples(f"channel {name!r}: expected (times, values)")
                out.append((self._channel(name), pair[0], pair[1]))
            return out
        if isinstance(data, tuple) and len(data) == 3 and isinstance(data[0], str | int):
            return [(self._channel(data[0]), data[1], data[2])]
        if isinstance(data, list | tuple):
            out = []
            for item in data:
                out.extend(self._normalise(item))
            return out
        raise InvalidSamples(f"cannot ingest {type(data).__name__}; give Samples or {{name: (times, values)}}")

    def _channel(self, key: Any) -> _Channel:
        if isinstance(key, int) and not isinstance(key, bool) and 0 <= key < len(self._channels):
            return self._channels[key]
        if isinstance(key, str) and key in self._by_name:
            return self._by_name[key]
        raise InvalidSamples(f"unknown channel {key!r}")

    def _check(self, ch: _Channel, times: Any, values: Any) -> tuple[_Channel, np.ndarray, np.ndarray]:
        try:
            t = np.atleast_1d(np.asarray(times, dtype=np.float64))
            v = np.atleast_1d(np.asarray(values, dtype=np.float64))
        except (TypeError, ValueError) as exc:
            raise InvalidSamples(f"channel {ch.cfg.name}: times and values must be numbers: {exc}") from exc
        if t.ndim != 1 or t.shape != v.shape:
            raise InvalidSamples(f"channel {ch.cfg.name}: {t.shape} times for {v.shape} values")
        if not np.isfinite(t).all():
            raise InvalidSamples(f"channel {ch.cfg.name}: non-finite sample times")
        if t.size and (np.any(np.diff(t) < 0) or t[0] < ch.last_time):
            raise InvalidSamples(f"channel {ch.cfg.name}: sample times go backwards")
        if np.isinf(v).any():
            raise InvalidSamples(f"channel {ch.cfg.name}: infinite values")
        tol = ch.cfg.resolution / 2
        good = v[~np.isnan(v)]
        if good.size and (good.min() < ch.cfg.lo - tol or good.max() > ch.cfg.hi + tol):
            raise InvalidSamples(
                f"channel {ch.cfg.name}: values outside [{ch.cfg.lo}, {ch.cfg.hi}] "
                f"({good.min():g}..{good.max():g})")
        return ch, t, v

    # ------------------------------------------------------------------- blocks

    def _period(self, ch: _Channel) -> float:
        if ch.period is not None:
            return ch.period
        if ch.times.size >= 2:
            d = np.diff(ch.times)
            d = d[d > 0]
            if d.size:
                return float(min(max(round(float(np.median(d)), 2), 0.01), 655.35))
        return 1.0

    def _close_full(self, ch: _Channel) -> None:
        while ch.times.size:
            p = self._period(ch)
            start = math.floor(ch.times[0] * 100 + 1e-6) / 100
            g = np.rint((ch.times - start) / p)
            over = np.flatnonzero(g >= self.block_samples)
            if not over.size:
                return
            self._close(ch, int(over[0]))

    def _close_late(self, now: float) -> None:
        for ch in self._channels:
            if ch.times.size and now - ch.times[0] >= self.max_latency:
                self._close(ch, ch.times.size)

    def flush(self, now: float) -> None:
        """Close every open block now (end of data, or before a request for recent data)."""
        for ch in self._channels:
            if ch.times.size:
                self._close(ch, ch.times.size)

    def _close(self, ch: _Channel, n: int) -> None:
        """Close the first ``n`` open samples into one or more blocks (never more than
        ``block_samples`` grid points each)."""
        while n > 0:
            p = self._period(ch)
            cs = math.floor(float(ch.times[0]) * 100 + 1e-6)
            g = np.rint((ch.times[:n] - cs / 100) / p).astype(np.int64)
            m = max(1, int(np.searchsorted(g, self.block_samples, side="left")))
            self._close_block(ch, m, p, cs)
            n -= m

    def _close_block(self, ch: _Channel, n: int, p: float, cs: int) -> None:
        t, v = ch.times[:n], ch.values[:n]
        ch.times, ch.values = ch.times[n:], ch.values[n:]
        if ch.period is None and t.size >= 16:
            ch.period = p
        keep = ~np.isnan(v)
        if not keep.any():
            return
        start = cs / 100
        g = np.rint((t - start) / p).astype(np.int64)
        g, v = g[keep], v[keep]
        count = int(g.max()) + 1
        # one value per grid cell: where several samples share a cell keep the one farthest from
        # the block median (so a one-sample spike survives), and interpolate empty cells
        med = float(np.median(v))
        order = np.lexsort((-np.abs(v - med), g))
        cells, first = np.unique(g[order], return_index=True)
        vals = v[order][first]
        x = np.interp(np.arange(count, dtype=np.float64), cells.astype(np.float64), vals)
        block = _Block(start, (cs // 100) % (1 << 18), (cs % 100) / 100, p, x, np.zeros(count))
        ch.blocks.append(block)
        target = ch.cfg.overview_error
        if target is None:
            target = self.overview_factor * codec.noise_sigma(x, self.wavelet)
        target = max(target, ch.cfg.resolution / 2)
        alert = self.alert_fraction * _smallest_spike(x, 2 * target / self.alert_fraction) \
            if self.alert_fraction else 0.0
        if alert > 2 * target:
            self._add_pass(ch, block, alert, _ALERT)
        self._add_pass(ch, block, target, _OVERVIEW)

    def _add_pass(self, ch: _Channel, block: _Block, target: float, klass: int) -> None:
        level = len(block.passes)
        if level == MAX_PASSES - 1:
            target = min(target, ch.cfg.resolution / 2)
        goal = codec.code_value(codec.floor_code(target))
        p, block.recon = codec.make_pass(block.x, block.recon, goal, self.wavelet)
        block.passes.append(p)
        n_approx = 0 if p.samples else codec.layout(block.count, self.wavelet).n_approx
        pieces = codec.split_pass(p.codes, n_approx, MAX_CHUNK_DATA, p.samples)
        whole = len(pieces) == 1
        chunks = []
        for first, end, data in pieces:
            msg = TimeSeriesChunk(
                ch.cid, block.stamp, block.offset, block.period, block.count, self.wavelet, level,
                p.samples, p.step, p.error, None if whole else first, None if whole else end, data)
            chunk = _Chunk(msg, wire.encoded_size(msg), (block.stamp, block.offset, level, first),
                           klass, self._next_order(), block.start)
            ch.by_key[chunk.key] = chunk
            chunks.append(chunk)
        block.chunks.append(chunks)

    def _next_order(self) -> int:
        self._order += 1
        return self._order

    # ---------------------------------------------------------------------- link

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        self._close_late(now)
        out: list[Message] = []
        left = max_bytes
        for ch in self._channels:
            if not ch.reg_acked and ch.reg_size <= left and self._due(ch.reg_sent_at, now):
                out.append(ch.registration)
                ch.reg_sent_at = now
                left -= ch.reg_size
        self._send(self._candidates(now), left, out, now)
        return out

    @staticmethod
    def _send(chunks: list[_Chunk], left: int, out: list[Message], now: float) -> int:
        """Append the chunks that fit in ``left`` bytes to ``out`` (marked sent now); returns
        the bytes left."""
        for chunk in chunks:
            if left < 13:
                break
            if chunk.size <= left:
                out.append(chunk.message)
                chunk.sent_at = now
                left -= chunk.size
        return left

    def _due(self, sent_at: float | None, now: float) -> bool:
        return sent_at is None or now - sent_at >= self.retry_after or now < sent_at

    def spare(self, max_bytes: int, now: float) -> list[Message]:
        """Refinements: further passes of the closed blocks, newest block first, each quartering
        the block's error bound down to half the resolution; one pass is made at a time, when
        the spare chunks made before are all sent. A topside request turns them into requested
        chunks (:class:`TimeSeriesRequest`)."""
        out: list[Message] = []
        left = max_bytes
        for _ in range(2):
            left = self._send(self._candidates(now, spare=True), left, out, now)
            if left < 13 or any(not c.acked and c.sent_at is None
                                for ch in self._channels for c in ch.by_key.values() if c.klass == _SPARE):
                break
            if not self._refine_spare():
                break
        return out

    def _refinable(self) -> list[tuple[_Channel, _Block]]:
        return [(ch, b) for ch in self._channels for b in ch.blocks if self._can_refine(ch, b)]

    @staticmethod
    def _can_refine(ch: _Channel, b: _Block) -> bool:
        return not b.done and len(b.passes) < MAX_PASSES and b.bound() > ch.cfg.resolution / 2 * (1 + 1e-9)

    def _retire(self, ch: _Channel) -> None:
        """Drop what the channel's done blocks no longer need (see :attr:`_Block.samples`):
        every pass made, none left to make, no chunk waiting for its acknowledgement."""
        waiting = {c.key[:2] for c in ch.by_key.values()}  # (stamp, offset) of blocks with chunks out
        for b in ch.blocks:
            if b.done or not b.passes or (b.stamp, b.offset) in waiting or self._can_refine(ch, b):
                continue
            b.samples = b.count
            b.x = b.recon = _NOTHING
            b.passes = [dataclasses.replace(b.passes[-1], codes=_NO_CODES)]  # its bound
            b.chunks = []

    def _refine_spare(self) -> bool:
        """Make the next spare refinement pass (newest block first); False when none is left."""
        blocks = self._refinable()
        if not blocks:
            return False
        ch, block = max(blocks, key=lambda cb: cb[1].start)
        self._add_pass(ch, block, max(block.bound() / 4, ch.cfg.resolution / 2), _SPARE)
        return True

    def ready_bytes(self, now: float) -> int:
        """Registrations and chunks (background and spare) due now, and refinements to make."""
        regs = sum(ch.reg_size for ch in self._channels if not ch.reg_acked and self._due(ch.reg_sent_at, now))
        chunks = sum(c.size for ch in self._channels for c in ch.by_key.values()
                     if not c.acked and self._due(c.sent_at, now))
        return regs + chunks + 64 * len(self._refinable())

    def spare_bytes(self) -> int:
        held = sum(c.size for ch in self._channels for c in ch.by_key.values()
                   if c.klass == _SPARE and not c.acked)
        return held + 64 * len(self._refinable())

    def _candidates(self, now: float, spare: bool = False) -> list[_Chunk]:
        # a stamp is unambiguous for half its period: older chunks would be misplaced, drop them
        horizon = now - STAMP_MODULUS / 2 + 3600.0
        for ch in self._channels:
            for key in [k for k, c in ch.by_key.items() if c.t0 < horizon]:
                del ch.by_key[key]
        cands = [c for ch in self._channels for c in ch.by_key.values()
                 if not c.acked and (c.klass == _SPARE) == spare and self._due(c.sent_at, now)]
        cands.sort(key=lambda c: (c.klass, c.order))
        return cands

    def pending_bytes(self) -> int:
        total = sum(ch.reg_size for ch in self._channels if not ch.reg_acked)
        return total + sum(c.size for ch in self._channels for c in ch.by_key.values()
                           if not c.acked and c.klass != _SPARE)

    def handle(self, message: Message, now: float) -> list[Message]:
        if isinstance(message, TimeSeriesAck):
            ch = self._request_channel(message.channel)
            if message.registered:
                ch.reg_acked = True
            for part in message.parts:
                chunk = ch.by_key.get((part.start, part.offset, part.level, part.first))
                if chunk is not None:
                    chunk.acked = True
            for key in [k for k, c in ch.by_key.items() if c.acked]:
                del ch.by_key[key]
            self._retire(ch)
            return []
        if isinstance(message, TimeSeriesRequest):
            self._refine(message, now)
            return []
        raise RequestRejected(f"the time-series sender does not handle {type(message).__name__}")

    def _request_channel(self, cid: int) -> _Channel:
        if not 0 <= cid < len(self._channels):
            raise RequestRejected(f"unknown time-series channel {cid}")
        return self._channels[cid]

    def _refine(self, req: TimeSeriesRequest, now: float) -> None:
        ch = self._request_channel(req.channel)
        if not (math.isfinite(req.max_error) and req.max_error >= ch.cfg.resolution / 2 * (1 - 1e-6)):
            raise RequestRejected(
                f"max_error {req.max_error:g} is below half the resolution of {ch.cfg.name} "
                f"({ch.cfg.resolution / 2:g})")
        t0, t1 = unwrap(req.start, now), unwrap(req.end, now) + 1.0
        if t1 < t0:
            raise RequestRejected(f"window end {req.end} is before its start {req.start}")
        if ch.times.size and ch.times[0] <= t1:
            self._close(ch, ch.times.size)
        for block in ch.blocks:
            if block.end < t0 or block.start > t1 or block.done:  # a done block is held as well as it can be
                continue
            while block.bound() > req.max_error and len(block.passes) < MAX_PASSES:
                self._add_pass(ch, block, max(req.max_error, ch.cfg.resolution / 2), _REQUESTED)
            # what topside lacks of the passes up to the first one that meets the bound
            for p, chunks in zip(block.passes, block.chunks):
                for c in chunks:
                    if not c.acked:
                        c.klass = _REQUESTED
                        c.order = self._next_order()
                        c.sent_at = None
                if codec.code_value(p.error) <= req.max_error:
                    break

    # ---------------------------------------------------------------- inspection

    def bound(self, channel: str | int) -> list[tuple[float, float, float]]:
        """``(start, end, error bound)`` of every closed block of a channel, as the vehicle
        sees them (every chunk created so far delivered)."""
        ch = self._channel(channel)
        return [(b.start, b.end, b.bound()) for b in ch.blocks]

    def blocks(self, channel: str | int) -> list[tuple[float, int, float]]:
        """``(start, count, period)`` of every closed block of a channel."""
        ch = self._channel(channel)
        return [(b.start, b.count, b.period) for b in ch.blocks]

    def unacked(self) -> int:
        """Chunks and registrations not yet acknowledged by topside."""
        return sum(not ch.reg_acked for ch in self._channels) + sum(
            len(ch.by_key) for ch in self._channels)



def _excursions(x: np.ndarray, window: int = 61) -> np.ndarray:
    """Distance of each sample from a running median of ``window`` samples (spikes up to about
    half as long do not pull the median)."""
    if x.size < 3:
        return np.zeros(x.size)
    w = min(window, x.size - (1 - x.size % 2))
    half = w // 2
    trend = np.median(np.lib.stride_tricks.sliding_window_view(np.pad(x, half, mode="edge"), w), axis=1)
    e: np.ndarray = np.abs(x - trend)
    return e


def _smallest_spike(x: np.ndarray, threshold: float) -> float:
    """Height of the smallest spike above ``threshold``: spikes are runs of samples whose
    distance from the block's running median exceeds the threshold; 0 when there is none."""
    e = _excursions(x)
    sig = e > threshold
    if not sig.any():
        return 0.0
    edges = np.flatnonzero(np.diff(np.concatenate(([0], sig.astype(np.int8), [0]))))
    heights = np.maximum.reduceat(e, edges[0::2])
    return float(heights.min())
