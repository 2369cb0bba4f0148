"""Fragmentation of CoEx frames into MAVLink ``TUNNEL`` payloads, and their reassembly.

Pure logic: bytes and ``now`` (float seconds, any monotonic origin) in, bytes out. Nothing here
reads a clock or touches a socket. The layout is normative in ``spec/bindings/mavlink.md``:

====== ===== ==================================================================
offset bytes field
====== ===== ==================================================================
0      1     ``version`` (high nibble, = 1) and ``reserved`` (low nibble, = 0)
1      1     ``frame_id``: per-sender frame counter, modulo 256
2      1     ``index``: 0-based fragment index, ``index < count``
3      1     ``count``: fragments in the frame, 1..255
4      n     chunk: exactly 124 bytes unless last; the last carries 0..124 bytes
====== ===== ==================================================================

A frame of ``L`` bytes is sent as ``max(1, ceil(L / 124))`` fragments. A partial frame is never
delivered: it is dropped when it expires, when a conflicting fragment replaces it, or when the
memory bound evicts it.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Hashable
from dataclasses import dataclass, field

from coex_core.errors import ConfigError, DecodeError, EncodeError

__all__ = [
    "CHUNK_BYTES",
    "FRAGMENT_HEADER_BYTES",
    "FRAGMENT_VERSION",
    "MAX_FRAGMENTS",
    "MAX_FRAME_BYTES",
    "TUNNEL_PAYLOAD_BYTES",
    "Fragment",
    "Reassembler",
    "fragments_needed",
    "parse_fragment",
    "split_frame",
]

#: Size of the ``payload`` array of the MAVLink ``TUNNEL`` message.
TUNNEL_PAYLOAD_BYTES = 128
#: Bytes of fragmentation header at the start of every ``TUNNEL`` payload.
FRAGMENT_HEADER_BYTES = 4
#: Bytes of CoEx frame carried by every fragment but the last.
CHUNK_BYTES = TUNNEL_PAYLOAD_BYTES - FRAGMENT_HEADER_BYTES
#: Version nibble of the fragment header.
FRAGMENT_VERSION = 1
#: Most fragments one frame may have (the ``count`` field is one byte).
MAX_FRAGMENTS = 255
#: Largest CoEx frame the binding can carry (255 x 124 bytes).
MAX_FRAME_BYTES = MAX_FRAGMENTS * CHUNK_BYTES


@dataclass(frozen=True, slots=True)
class Fragment:
    """One parsed ``TUNNEL`` payload of the CoEx binding."""

    frame_id: int
    index: int
    count: int
    chunk: bytes


def fragments_needed(size: int) -> int:
    """Fragments used for a frame of ``size`` bytes (at least one, even for an empty frame)."""
    return max(1, -(-size // CHUNK_BYTES))


def split_frame(frame: bytes, frame_id: int) -> list[bytes]:
    """Split one CoEx frame into ``TUNNEL`` payloads (each at most 128 bytes, header included)."""
    if not 0 <= frame_id <= 255:
        raise EncodeError(f"frame_id must be 0..255, got {frame_id}")
    size = len(frame)
    if size > MAX_FRAME_BYTES:
        raise EncodeError(f"frame of {size} B exceeds the {MAX_FRAME_BYTES} B the MAVLink binding carries")
    count = fragments_needed(size)
    first = FRAGMENT_VERSION << 4
    return [
        bytes((first, frame_id, index, count)) + bytes(frame[index * CHUNK_BYTES:(index + 1) * CHUNK_BYTES])
        for index in range(count)
    ]


def parse_fragment(payload: bytes) -> Fragment:
    """Parse the significant ``payload_length`` bytes of a ``TUNNEL`` payload.

    Raises :class:`~coex_core.errors.DecodeError` (and nothing else) for any payload that is not a
    well-formed fragment: too short or too long, wrong version, reserved bits set, ``index`` not
    below ``count``, a non-last fragment whose chunk is not exactly 124 bytes, or an empty last
    fragment of a multi-fragment frame."""
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise DecodeError(f"expected bytes, got {type(payload).__name__}")
    data = bytes(payload)
    n = len(data)
    if n > TUNNEL_PAYLOAD_BYTES:
        raise DecodeError(f"payload_length {n} exceeds the {TUNNEL_PAYLOAD_BYTES}-byte TUNNEL payload")
    if n < FRAGMENT_HEADER_BYTES:
        raise DecodeError(f"truncated: {n} B is shorter than the {FRAGMENT_HEADER_BYTES}-byte fragment header")
    head, frame_id, index, count = data[0], data[1], data[2], data[3]
    if head >> 4 != FRAGMENT_VERSION:
        raise DecodeError(f"unsupported fragment version {head >> 4} (expected {FRAGMENT_VERSION})")
    if head & 0x0F:
        raise DecodeError(f"reserved fragment header bits set (0x{head & 0x0F:x})")
    if count == 0:
        raise DecodeError("fragment count is 0")
    if index >= count:
        raise DecodeError(f"fragment index {index} is not below its count {count}")
    chunk = data[FRAGMENT_HEADER_BYTES:]
    if index < count - 1 and len(chunk) != CHUNK_BYTES:
        raise DecodeError(
            f"non-last fragment {index}/{count} carries {len(chunk)} B, expected exactly {CHUNK_BYTES}"
        )
    if count > 1 and index == count - 1 and not chunk:
        raise DecodeError(f"last fragment of a {count}-fragment frame is empty")
    return Fragment(frame_id, index, count, chunk)


@dataclass
class _Partial:
    count: int
    started: float
    chunks: list[bytes | None]
    received: int = 0
    nbytes: int = 0
    key: Hashable = field(default=None)


class Reassembler:
    """Bounded reassembly of fragments into frames, driven by ``now``.

    * At most ``max_partial`` incomplete frames are held (the oldest is evicted beyond that), so
      memory stays below ``max_partial * max_frame`` bytes of chunks.
    * A partial frame older than ``timeout`` seconds (since its first fragment) is dropped.
    * A fragment that disagrees with the partial frame of the same key (another ``count``, or
      different bytes at an index already held) means the frame id was reused: the old partial is
      dropped and a new one starts with the fragment. An identical duplicate is ignored.
    * A fragment whose ``count`` implies a frame larger than ``max_frame`` is rejected.

    Counters: ``completed``, ``expired``, ``evicted``, ``conflicts``, ``duplicates``, ``oversize``.
    """

    def __init__(self, *, timeout: float = 5.0, max_partial: int = 8, max_frame: int = 2048) -> None:
        if not timeout > 0:
            raise ConfigError(f"reassembly timeout must be positive, got {timeout}")
        if max_partial < 1:
            raise ConfigError(f"max_partial must be at least 1, got {max_partial}")
        if not 0 <= max_frame <= MAX_FRAME_BYTES:
            raise ConfigError(f"max_frame must be 0..{MAX_FRAME_BYTES}, got {max_frame}")
        self.timeout = float(timeout)
        self.max_partial = max_partial
        self.max_frame = max_frame
        self.max_fragments = fragments_needed(max_frame)
        self._partials: OrderedDict[Hashable, _Partial] = OrderedDict()
        self.completed = 0
        self.expired = 0
        self.evicted = 0
        self.conflicts = 0
        self.duplicates = 0
        self.oversize = 0

    def __len__(self) -> int:
        return len(self._partials)

    @property
    def buffered_bytes(self) -> int:
        """Bytes of chunks currently held for incomplete frames."""
        return sum(p.nbytes for p in self._partials.values())

    def expire(self, now: float) -> int:
        """Drop partial frames older than the timeout; return how many were dropped."""
        stale = [k for k, p in self._partials.items() if now - p.started > self.timeout]
        for k in stale:
            del self._partials[k]
        self.expired += len(stale)
        return len(stale)

    def add(self, source: Hashable, fragment: Fragment, now: float) -> bytes | None:
        """Add one fragment from ``source``; return the whole frame when it completes.

        Raises :class:`~coex_core.errors.DecodeError` for a fragment of a frame larger than
        ``max_frame``; the partial frames already held are unaffected."""
        self.expire(now)
        count = fragment.count
        if count > self.max_fragments or (
            fragment.index == count - 1 and (count - 1) * CHUNK_BYTES + len(fragment.chunk) > self.max_frame
        ):
            self.oversize += 1
            raise DecodeError(
                f"fragment {fragment.index}/{count} belongs to a frame above the {self.max_frame} B MTU"
            )
        if count == 1:
            self.completed += 1
            return fragment.chunk
        key = (source, fragment.frame_id)
        partial = self._partials.get(key)
        if partial is not None:
            held = partial.chunks[fragment.index] if partial.count == count else None
            if partial.count != count or (held is not None and held != fragment.chunk):
                self.conflicts += 1
                del self._partials[key]
                partial = None
            elif held is not None:
                self.duplicates += 1
                return None
        if partial is None:
            while len(self._partials) >= self.max_partial:
                self._partials.popitem(last=False)
                self.evicted += 1
            partial = _Partial(count=count, started=now, chunks=[None] * count, key=key)
            self._partials[key] = partial
        partial.chunks[fragment.index] = fragment.chunk
        partial.received += 1
        partial.nbytes += len(fragment.chunk)
        if partial.received < count:
            return None
        del self._partials[key]
        self.completed += 1
        return b"".join(c for c in partial.chunks if c is not None)

    def stats(self) -> dict[str, int]:
        return {
            "partial": len(self._partials),
            "buffered_bytes": self.buffered_bytes,
            "completed": self.completed,
            "expired": self.expired,
            "evicted": self.evicted,
            "conflicts": self.conflicts,
            "duplicates": self.duplicates,
            "oversize": self.oversize,
        }
