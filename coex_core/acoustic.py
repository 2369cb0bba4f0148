"""A simulated acoustic channel between modem nodes (sans-I/O, simulated time only).

The model, in order of what happens to a transmission:

1. **Rate table** (:data:`RATES`): the WHOI Micromodem packet types (frame size x frame count)
   and an airtime model ``airtime(n) = preamble + 8 n / bit_rate``. Every frame on air occupies its
   full ``frame_bytes`` (the modem pads short frames), so a packet of ``k`` frames lasts
   ``airtime(k * frame_bytes)``. The numbers for rates 1, 3 and 5 are fitted through the two packet
   durations ros_acomms' ``mac_utils.py`` gives for each PSK FDP rate (72 B mini-packet and the full
   data packet): rate 1 0.675 s + 641 bit/s (72 B: 1.57 s, 192 B: 3.07 s), rate 3 0.376 s +
   1519 bit/s (512 B: 3.07 s), rate 5 0.187 s + 5830 bit/s (72 B: 0.29 s, 2048 B: 3.0 s). Rates 0
   (FH-FSK, 80 bit/s), 2, 4 and 6 are not in that table; their numbers are estimates from the
   Micromodem's nominal rates and are marked so in :attr:`RateInfo.note`.
2. **Propagation**: nodes have positions (metres); a packet sent at ``t`` by ``src`` occupies
   ``[t + d/c, end + d/c]`` at a node at distance ``d`` (``c = sound_speed``).
3. **Half duplex and collisions**: a node that transmits during any part of an arrival does not
   receive it; two arrivals that overlap at one node destroy each other. Such arrivals are still
   reported (every frame ``None``) with :attr:`Arrival.cause` saying why.
4. **Frame loss**: each frame is lost independently with probability ``loss``, and/or by a
   :class:`GilbertElliott` two-state burst model stepped once per frame (one state per
   sender-receiver path), and/or by
   ``range_loss(distance)``; all drawn from one ``random.Random(seed)`` at transmit time, so a seed
   always gives the same losses whatever the polling pattern.
5. **Bit errors**: with ``bit_error_rate`` every bit of a surviving frame flips independently
   (drawn with a numpy generator seeded from the same seed, vectorised per frame). The receiving
   modem then checks its per-frame CRC-16 (CCITT, as the Micromodem reports ``CRC bad`` per frame):
   a frame whose CRC no longer matches is reported as ``None``; the rare corrupted frame whose CRC
   still matches (probability about 2^-16) is delivered corrupted, as a real modem would.

Only :meth:`AcousticChannel.transmit` and :meth:`AcousticChannel.poll` move things; nothing reads a
clock. Every delivered or lost packet also produces a link-log record (:meth:`AcousticChannel.log`).
"""

from __future__ import annotations

import binascii
import math
import random
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from .errors import ConfigError, FrameTooLarge

__all__ = ["RATES", "Arrival", "AcousticChannel", "GilbertElliott", "RateInfo", "rate_info"]


@dataclass(frozen=True, slots=True)
class RateInfo:
    """One Micromodem packet type: ``frames`` frames of ``frame_bytes`` bytes each."""

    rate: int
    frame_bytes: int
    frames: int
    #: Fixed time of a packet on air before its data: probe/preamble, header mini-packet.
    preamble: float
    #: Effective data bit rate (bits per second) after coding.
    bit_rate: float
    note: str = ""

    @property
    def max_bytes(self) -> int:
        """Bytes of a full packet (all frames)."""
        return self.frame_bytes * self.frames

    def airtime(self, nbytes: int | None = None) -> float:
        """Seconds on air to send ``nbytes`` (default: a full packet)."""
        n = self.max_bytes if nbytes is None else int(nbytes)
        if n < 0:
            raise ConfigError(f"cannot send {n} bytes")
        return self.preamble + 8.0 * n / self.bit_rate

    def packet_airtime(self, n_frames: int | None = None) -> float:
        """Seconds on air of a packet of ``n_frames`` frames (each padded to ``frame_bytes``)."""
        k = self.frames if n_frames is None else int(n_frames)
        return self.airtime(k * self.frame_bytes)


_FIT = "fitted to ros_acomms mac_utils packet durations"
_EST = "estimated from the Micromodem nominal rate"

#: The Micromodem rate table (frame size, frame count, airtime model); see the module docstring.
RATES: dict[int, RateInfo] = {
    0: RateInfo(0, 32, 1, 1.0, 80.0, _EST + " (FH-FSK 80 bit/s)"),
    1: RateInfo(1, 64, 3, 0.675, 641.0, _FIT),
    2: RateInfo(2, 64, 3, 0.5, 1200.0, _EST),
    3: RateInfo(3, 256, 2, 0.376, 1519.0, _FIT),
    4: RateInfo(4, 256, 2, 0.3, 2600.0, _EST),
    5: RateInfo(5, 256, 8, 0.187, 5830.0, _FIT),
    6: RateInfo(6, 32, 6, 0.5, 2400.0, _EST),
}


def rate_info(rate: int) -> RateInfo:
    """The :class:`RateInfo` of ``rate``; :class:`ConfigError` for an unknown rate."""
    try:
        return RATES[int(rate)]
    except (KeyError, ValueError, TypeError):
        raise ConfigError(f"unknown Micromodem rate {rate!r}; known: {sorted(RATES)}") from None


@dataclass
class GilbertElliott:
    """Two-state burst-loss model, stepped once per frame.

    In the good state a frame is lost with ``loss_good``, in the bad state with ``loss_bad``;
    after each frame the state flips good->bad with ``p_good_bad`` and bad->good with
    ``p_bad_good``. Mean burst length is ``1 / p_bad_good`` frames; the stationary loss rate is
    ``(p_bad_good * loss_good + p_good_bad * loss_bad) / (p_good_bad + p_bad_good)``.
    """

    p_good_bad: float = 0.05
    p_bad_good: float = 0.3
    loss_good: float = 0.0
    loss_bad: float = 1.0
    bad: bool = False

    def __post_init__(self) -> None:
        for name in ("p_good_bad", "p_bad_good", "loss_good", "loss_bad"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ConfigError(f"GilbertElliott.{name} must be in [0, 1], got {v}")

    @property
    def mean_loss(self) -> float:
        total = self.p_good_bad + self.p_bad_good
        if total == 0:
            return self.loss_bad if self.bad else self.loss_good
        return (self.p_bad_good * self.loss_good + self.p_good_bad * self.loss_bad) / total

    def step(self, rng: random.Random) -> bool:
        """Whether the next frame is lost; then move the state."""
        lost = rng.random() < (self.loss_bad if self.bad else self.loss_good)
        flip = rng.random()
        self.bad = flip >= self.p_bad_good if self.bad else flip < self.p_good_bad
        return lost


@dataclass(frozen=True, slots=True)
class Arrival:
    """A packet as one receiving node saw it.

    ``frames[i]`` is the i-th frame's bytes, or ``None`` when it was lost or failed its CRC.
    ``start``/``end`` are the times its first/last bit arrived at ``dst``. ``cause`` is ``""``
    for a normal reception, ``"collision"`` or ``"half-duplex"`` when the whole packet was
    destroyed at the receiver."""

    dst: int
    src: int
    rate: int
    frames: list[bytes | None]
    start: float
    end: float
    cause: str = ""
    link: int = 0
    slot: int | None = None

    @property
    def ok_frames(self) -> int:
        return sum(1 for f in self.frames if f is not None)


@dataclass
class _Tx:
    src: int
    start: float
    end: float


@dataclass
class _Pending:
    arrival: Arrival
    sent_at: float
    capacity: int
    used: int
    lost_reasons: list[str] = field(default_factory=list)


def crc16(data: bytes) -> int:
    """The per-frame modem CRC: CRC-16/CCITT-FALSE."""
    return binascii.crc_hqx(data, 0xFFFF)


class AcousticChannel:
    """A shared underwater acoustic channel between nodes (see the module docstring)."""

    def __init__(
        self,
        *,
        loss: float = 0.0,
        burst: GilbertElliott | None = None,
        bit_error_rate: float = 0.0,
        sound_speed: float = 1500.0,
        seed: int = 0,
        range_loss: Callable[[float], float] | None = None,
        link: int = 0,
    ) -> None:
        if not 0.0 <= loss <= 1.0:
            raise ConfigError(f"loss must be in [0, 1], got {loss}")
        if not 0.0 <= bit_error_rate < 1.0:
            raise ConfigError(f"bit_error_rate must be in [0, 1), got {bit_error_rate}")
        if not sound_speed > 0:
            raise ConfigError(f"sound_speed must be positive, got {sound_speed}")
        self.loss = float(loss)
        self.burst = burst
        self.bit_error_rate = float(bit_error_rate)
        self.sound_speed = float(sound_speed)
        self.range_loss = range_loss
        self.link = int(link)
        self._rng = random.Random(seed)
        self._np = np.random.default_rng(seed)
        self._pos: dict[int, tuple[float, float, float]] = {}
        self._busy: dict[int, float] = {}
        self._txs: list[_Tx] = []
        self._pending: list[_Pending] = []
        self._burst: dict[tuple[int, int], GilbertElliott] = {}
        self._log: list[dict[str, Any]] = []
        self.sent_packets = 0
        self.sent_frames = 0

    # ----------------------------------------------------------------------------- nodes
    def set_position(self, node: int, xyz: Sequence[float]) -> None:
        """Place (or move) ``node`` at ``xyz`` metres (x, y, z; z down or up, only distances matter)."""
        if len(xyz) != 3 or not all(math.isfinite(float(v)) for v in xyz):
            raise ConfigError(f"position must be three finite numbers, got {xyz!r}")
        self._pos[int(node)] = (float(xyz[0]), float(xyz[1]), float(xyz[2]))

    @property
    def nodes(self) -> list[int]:
        return sorted(self._pos)

    def distance(self, a: int, b: int) -> float:
        pa, pb = self._position(a), self._position(b)
        return math.dist(pa, pb)

    def delay(self, a: int, b: int) -> float:
        """One-way propagation delay between two nodes (seconds)."""
        return self.distance(a, b) / self.sound_speed

    def _position(self, node: int) -> tuple[float, float, float]:
        try:
            return self._pos[node]
        except KeyError:
            raise ConfigError(f"node {node} has no position; call set_position first") from None

    def busy_until(self, node: int) -> float:
        """End of ``node``'s last transmission (0 if it never transmitted)."""
        return self._busy.get(node, 0.0)

    # -------------------------------------------------------------------------- transmit
    def transmit(
        self, src: int, frames: list[bytes], rate: int, now: float, *, slot: int | None = None
    ) -> float:
        """Send a packet of ``frames`` at ``rate`` from ``src``, starting at ``now`` (or when
        ``src``'s previous transmission ends, if later). Returns the end time of the transmission.

        Raises :class:`FrameTooLarge` for too many frames or a frame above the rate's frame size."""
        info = rate_info(rate)
        self._position(src)
        if not all(isinstance(f, bytes | bytearray | memoryview) for f in frames):
            raise ConfigError("frames must be bytes")
        frames = [bytes(f) for f in frames]
        if not frames:
            raise ConfigError("a packet needs at least one frame")
        if len(frames) > info.frames:
            raise FrameTooLarge(f"{len(frames)} frames exceed rate {rate}'s {info.frames}")
        for f in frames:
            if len(f) > info.frame_bytes:
                raise FrameTooLarge(f"frame of {len(f)} B exceeds rate {rate}'s {info.frame_bytes} B")
        start = max(float(now), self._busy.get(src, 0.0))
        end = start + info.packet_airtime(len(frames))
        self._busy[src] = end
        self._txs.append(_Tx(src, start, end))
        self.sent_packets += 1
        self.sent_frames += len(frames)
        capacity = len(frames) * info.frame_bytes
        used = sum(len(f) for f in frames)
        for dst in sorted(self._pos):
            if dst == src:
                continue
            d = self.distance(src, dst)
            delay = d / self.sound_speed
            extra = 0.0
            if self.range_loss is not None:
                extra = min(max(float(self.range_loss(d)), 0.0), 1.0)
            out: list[bytes | None] = []
            reasons: list[str] = []
            for f in frames:
                lost = self._rng.random() < self.loss
                if self.burst is not None and self._burst_state(src, dst).step(self._rng):
                    lost = True
                if extra and self._rng.random() < extra:
                    lost = True
                if lost:
                    out.append(None)
                    reasons.append("lost")
                    continue
                got = self._bit_errors(f)
                if got is None:
                    reasons.append("crc")
                else:
                    reasons.append("")
                out.append(got)
            arrival = Arrival(dst, src, rate, out, start + delay, end + delay, "", self.link, slot)
            self._pending.append(_Pending(arrival, start, capacity, used, reasons))
        return end

    def _burst_state(self, src: int, dst: int) -> GilbertElliott:
        """Each (sender, receiver) path has its own burst state (a copy of ``burst``)."""
        key = (src, dst)
        state = self._burst.get(key)
        if state is None:
            assert self.burst is not None
            state = self._burst[key] = replace(self.burst)
        return state

    def _bit_errors(self, frame: bytes) -> bytes | None:
        if self.bit_error_rate <= 0.0 or not frame:
            return frame
        bits = np.unpackbits(np.frombuffer(frame, dtype=np.uint8))
        flips = self._np.random(bits.size) < self.bit_error_rate
        if not flips.any():
            return frame
        corrupted = np.packbits(bits ^ flips.astype(np.uint8)).tobytes()
        if crc16(corrupted) != crc16(frame):
            return None  # the modem's per-frame CRC fails: reported as a bad frame
        return corrupted

    # ------------------------------------------------------------------------------ poll
    def next_arrival(self) -> float | None:
        """Time the earliest pending arrival completes (``None`` when nothing is in flight)."""
        if not self._pending:
            return None
        return min(p.arrival.end for p in self._pending)

    def poll(self, now: float) -> list[Arrival]:
        """Arrivals completed by ``now``, in order of completion.

        Collisions and half duplex are judged against every transmission registered so far, so
        callers must register transmissions in time order (as a simulation does)."""
        done = sorted((p for p in self._pending if p.arrival.end <= now),
                      key=lambda p: (p.arrival.end, p.arrival.dst, p.arrival.src))
        if not done:
            return []
        self._pending = [p for p in self._pending if p.arrival.end > now]
        out: list[Arrival] = []
        for p in done:
            a = p.arrival
            cause = self._interference(p)
            if cause:
                a = Arrival(a.dst, a.src, a.rate, [None] * len(a.frames), a.start, a.end, cause,
                            a.link, a.slot)
            out.append(a)
            self._log.append({
                "time": round(p.sent_at, 6),
                "arrival": round(a.end, 6),
                "link": a.link,
                "slot": a.slot,
                "src": a.src,
                "dst": a.dst,
                "rate": a.rate,
                "frames": len(a.frames),
                "capacity_bytes": p.capacity,
                "used_bytes": p.used,
                "delivered": [f is not None for f in a.frames],
                "delivered_bytes": sum(len(f) for f in a.frames if f is not None),
                "lost": sum(1 for f in a.frames if f is None),
                "cause": cause or ",".join(sorted({r for r in p.lost_reasons if r})),
            })
        self._prune(now)
        return out

    def _interference(self, p: _Pending) -> str:
        a = p.arrival
        # half duplex: the receiver itself transmitted while this packet was arriving
        for tx in self._txs:
            if tx.src == a.dst and tx.start < a.end and tx.end > a.start:
                return "half-duplex"
        # collision: another packet from a third node overlapped at this receiver
        for tx in self._txs:
            if tx.src in (a.src, a.dst) or tx.src not in self._pos:
                continue
            d = self.delay(tx.src, a.dst)
            if tx.start + d < a.end and tx.end + d > a.start:
                return "collision"
        return ""

    def _prune(self, now: float) -> None:
        if not self._txs:
            return
        horizon = max((math.dist(a, b) for a in self._pos.values() for b in self._pos.values()),
                      default=0.0) / self.sound_speed
        oldest = min((p.arrival.start for p in self._pending), default=now)
        keep_after = min(oldest, now) - 2 * horizon - 1.0
        self._txs = [t for t in self._txs if t.end >= keep_after]

    # ------------------------------------------------------------------------------- log
    def log(self) -> list[dict[str, Any]]:
        """Take the link-log records produced since the last call (one per packet and receiver):
        ``time, arrival, link, slot, src, dst, rate, frames, capacity_bytes, used_bytes,
        delivered (per frame), delivered_bytes, lost, cause``."""
        out, self._log = self._log, []
        return out
