"""Pure functions between CoEx frames and the LCM type ``coex.frame_t`` (no LCM instance, no I/O).

``encode_frame`` wraps one CoEx frame in a ``frame_t``; ``decode_frame`` checks and unwraps one,
raising only :class:`~coex_core.errors.DecodeError` whatever bytes it is given;
``unpack_event`` is the whole receive path of an LCM message (``frame_t`` decode, then
:func:`coex_core.wire.unpack_frame`).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from coex_core.errors import DecodeError, EncodeError
from coex_core.messages import Frame

from ._types import frame_t

__all__ = [
    "FRAME_T_FINGERPRINT",
    "FRAME_T_OVERHEAD",
    "MAX_FRAME_T_DATA",
    "LcmFrame",
    "decode_frame",
    "encode_frame",
    "is_frame_t",
    "unpack_event",
]

#: The 8-byte fingerprint that starts every encoded ``coex.frame_t``.
FRAME_T_FINGERPRINT: bytes = frame_t._get_packed_fingerprint()
#: Bytes a ``frame_t`` adds around a frame: fingerprint, utime, origin, length.
FRAME_T_OVERHEAD = 8 + 8 + 8 + 4
#: Largest frame ``data`` a ``frame_t`` can carry (``length`` is an int32).
MAX_FRAME_T_DATA = 2**31 - 1

_INT64 = (-(2**63), 2**63 - 1)


@dataclass(frozen=True, slots=True)
class LcmFrame:
    """A decoded ``coex.frame_t``: publisher time (µs since 1970, 0 = unknown), origin, frame."""

    utime: int
    origin: int
    data: bytes


def is_frame_t(data: bytes) -> bool:
    """Whether ``data`` starts with the ``coex.frame_t`` fingerprint (cheap; no validation)."""
    return bytes(data[:8]) == FRAME_T_FINGERPRINT


def encode_frame(frame: bytes, *, utime: int = 0, origin: int = 0) -> bytes:
    """Encode one CoEx frame as a ``coex.frame_t`` LCM message (fingerprint included)."""
    if not isinstance(frame, bytes | bytearray | memoryview):
        raise TypeError("a frame is bytes")
    if len(frame) > MAX_FRAME_T_DATA:
        raise EncodeError(f"frame of {len(frame)} B does not fit a frame_t")
    for name, value in (("utime", utime), ("origin", origin)):
        if not _INT64[0] <= value <= _INT64[1]:
            raise EncodeError(f"{name}={value} is not an int64")
    msg = frame_t()
    msg.utime = int(utime)
    msg.origin = int(origin)
    msg.length = len(frame)
    msg.data = bytes(frame)
    return bytes(msg.encode())


def decode_frame(data: bytes) -> LcmFrame:
    """Decode one ``coex.frame_t`` LCM message; raises only :class:`DecodeError`.

    Stricter than the generated ``frame_t.decode``: a negative or inconsistent ``length``, a
    short message and trailing bytes are all refused."""
    if not isinstance(data, bytes | bytearray | memoryview):
        raise DecodeError(f"an LCM message is bytes, not {type(data).__name__}")
    raw = bytes(data)
    if len(raw) < FRAME_T_OVERHEAD:
        raise DecodeError(f"{len(raw)} B is shorter than a frame_t ({FRAME_T_OVERHEAD} B at least)")
    if raw[:8] != FRAME_T_FINGERPRINT:
        raise DecodeError(
            f"not a coex.frame_t: fingerprint {raw[:8].hex()} != {FRAME_T_FINGERPRINT.hex()}"
        )
    length = struct.unpack_from(">i", raw, 24)[0]
    if length < 0:
        raise DecodeError(f"frame_t length {length} is negative")
    if FRAME_T_OVERHEAD + length != len(raw):
        raise DecodeError(
            f"frame_t length {length} disagrees with the {len(raw) - FRAME_T_OVERHEAD} B of data"
        )
    try:
        msg = frame_t.decode(raw)
    except (ValueError, struct.error) as exc:  # pragma: no cover - excluded by the checks above
        raise DecodeError(f"bad frame_t: {exc}") from None
    return LcmFrame(utime=int(msg.utime), origin=int(msg.origin), data=bytes(msg.data))


def unpack_event(data: bytes) -> tuple[LcmFrame, Frame]:
    """The LCM receive path: decode a ``frame_t`` and unpack the CoEx frame it carries.

    Raises only :class:`DecodeError`."""
    lcm_frame = decode_frame(data)
    from coex_core.wire import unpack_frame

    return lcm_frame, unpack_frame(lcm_frame.data)
