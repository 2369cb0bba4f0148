"""Encoding and decoding of messages and frames; the only Container <-> dataclass boundary."""

from __future__ import annotations

import binascii
import dataclasses
import enum
import functools
import io
import types
import typing
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import construct as cs

from ..errors import DecodeError, EncodeError
from ..messages import Frame, FrameHeader, Message, Opaque
from . import bathymetry, core, detections, imagery, navigation, survey, timeseries  # noqa: F401  (they register their messages)
from ._primitives import Bool, Bounded, OutOfRange, UInt
from ._registry import (
    MAX_MESSAGE_BYTES,
    RESERVED_RANGE,
    SPECS_BY_CLASS,
    SPECS_BY_ID,
    THIRD_PARTY_RANGES,
    MessageSpec,
)

FRAME_VERSION = 1
FRAME_HEADER_BYTES = 3
CRC_BYTES = 2
END_MARKER = 0x00


class TypeIdCon(cs.Construct):  # type: ignore[misc]
    """Message type id: one byte ``0xxxxxxx`` (0..127) or two bytes ``1xxxxxxx xxxxxxxx`` (128..32767).

    The two-byte form of an id below 128 is invalid (every id has exactly one encoding)."""

    def _parse(self, stream: Any, context: Any, path: str) -> int:
        b0 = cs.stream_read(stream, 1, path)[0]
        if not b0 & 0x80:
            return b0
        value = ((b0 & 0x7F) << 8) | cs.stream_read(stream, 1, path)[0]
        if value < 128:
            raise OutOfRange(f"over-long type id {value} (two bytes for an id below 128)", path=path,
                             reason="over-long")
        return value

    def _build(self, obj: Any, stream: Any, context: Any, path: str) -> int:
        v = int(obj)
        if 0 <= v < 128:
            cs.stream_write(stream, bytes([v]), 1, path)
        elif v < 32768:
            cs.stream_write(stream, bytes([0x80 | (v >> 8), v & 0xFF]), 2, path)
        else:
            raise cs.ValidationError(f"type id {v} out of range", path=path)
        return v

    def _sizeof(self, context: Any, path: str) -> int:
        raise cs.SizeofError(path=path)


TYPE_ID = TypeIdCon()
OPAQUE_BODY = cs.Prefixed(cs.VarInt, cs.GreedyBytes)

FRAME_HEADER = cs.Struct(
    "bits" / cs.Bitwise(cs.Struct(
        "version" / cs.Const(FRAME_VERSION, UInt(2)) * "Format version, 1 for this document",
        "crc" / Bool() * "A CRC-16 follows the header",
        "reserved" / cs.Const(0, UInt(1)) * "Reserved, 0",
        "schedule" / Bounded(0, 15) * "TDMA schedule version of the sender",
        "src" / Bounded(0, 15) * "Source node id",
        "dst" / Bounded(0, 15) * "Destination node id (0 = broadcast)",
        "seq" / Bounded(0, 255) * "Transmission sequence number (mod 256)",
    )),
    "checksum" / cs.If(cs.this.bits.crc, cs.Int16ub) * "CRC-16/CCITT-FALSE (see Integrity)",
)


def _body(spec: MessageSpec) -> cs.Construct:
    return cs.Prefixed(cs.VarInt, spec.body) if spec.prefixed else spec.body


_BODIES: dict[int, cs.Construct] = {tid: _body(spec) for tid, spec in SPECS_BY_ID.items()}

_TO_ASCII = bytes.maketrans(b"\x00\x01", b"01")


def _bits_to_bytes(bits: bytes) -> bytes:
    """construct's ``bits2bytes`` in one step: a bit stream (one byte, 0 or 1, per bit, MSB
    first) as bytes."""
    if len(bits) % 8:
        raise ValueError(f"{len(bits)} bits are not whole bytes")
    return int(bits.translate(_TO_ASCII), 2).to_bytes(len(bits) // 8, "big") if bits else b""


def _builder(con: cs.Construct) -> Any:
    """``con.build``, faster for a bit-packed body (``Body``: ``Bitwise`` of a variable-length
    struct, optionally ``Prefixed``): the struct is built into one bit stream, converted to
    bytes at once, instead of construct's ``Restreamed`` stream converting it eight bits at a
    time as it is written. The same bytes from the same definitions (the struct sees the same
    context, path and stream positions); anything else builds as construct does."""
    prefixed = isinstance(con, cs.Prefixed) and not con.includelength
    inner = con.subcon if prefixed else con
    if not (isinstance(inner, cs.Restreamed) and inner.encoder is cs.lib.bits2bytes and inner.encoderunit == 8):
        return con.build
    struct, length = inner.subcon, con.lengthfield if prefixed else None

    def build(obj: Any) -> bytes:
        data = _bits_to_bytes(struct.build(obj))
        return data if length is None else length.build(len(data)) + data
    return build


_BUILDERS: dict[int, Any] = {tid: _builder(con) for tid, con in _BODIES.items()}

# construct's bit conversions, one byte (8 bits) at a time: what a bit-packed body's
# ``Restreamed`` streams call for every byte they read or write (``Bitwise`` reads one byte at a
# time, ``Bytewise`` data fields 8 bits at a time), through a generator each call
_BYTE_BITS: dict[bytes, bytes] = {bytes([i]): cs.lib.bytes2bits(bytes([i])) for i in range(256)}
_BITS_BYTE: dict[bytes, bytes] = {bits: byte for byte, bits in _BYTE_BITS.items()}


def _by_lookup(table: dict[bytes, bytes], construct_fn: Callable[[Any], bytes], what: str) -> Callable[[Any], bytes]:
    """construct's ``construct_fn`` (the same value, the same errors), one byte or 8 bits by a
    lookup in ``table``; anything else by construct's own function."""
    def convert(data: Any) -> bytes:
        if type(data) is bytes:
            out = table.get(data)
            if out is not None:
                return out
        return construct_fn(data)
    convert.__doc__ = f"construct's {what} (the same value, the same errors), by a lookup where it can."
    return convert


_bytes2bits = _by_lookup(_BYTE_BITS, cs.lib.bytes2bits, "bytes2bits")
_bits2bytes = _by_lookup(_BITS_BYTE, cs.lib.bits2bytes, "bits2bytes")


_FAST = {cs.lib.bytes2bits: _bytes2bits, cs.lib.bits2bytes: _bits2bytes}


def _fast_conversions(con: Any, seen: set[int]) -> None:
    """Every ``Restreamed`` stream in ``con`` (``Bitwise``, ``Bytewise`` of a variable size)
    converts with the lookups above instead of construct's functions: the same bytes and
    bits, the same errors (anything but one byte or 8 bits goes to construct's own)."""
    if id(con) in seen:
        return
    seen.add(id(con))
    if isinstance(con, cs.Restreamed):
        con.decoder = _FAST.get(con.decoder, con.decoder)
        con.encoder = _FAST.get(con.encoder, con.encoder)
    for value in vars(con).values():
        for sub in (value.values() if isinstance(value, dict) else
                    value if isinstance(value, list | tuple) else (value,)):
            if isinstance(sub, cs.Construct):
                _fast_conversions(sub, seen)


_seen: set[int] = set()
for _con in _BODIES.values():  # after _BUILDERS: _builder recognises construct's bits2bytes
    _fast_conversions(_con, _seen)
del _seen, _con


# ------------------------------------------------------------------ Container <-> dataclass

_HINTS: dict[type[Any], dict[str, Any]] = {}


def _hints(cls: type[Any]) -> dict[str, Any]:
    h = _HINTS.get(cls)
    if h is None:
        import coex_core.messages as m

        h = typing.get_type_hints(cls, vars(m))
        _HINTS[cls] = h
    return h


def _from_container(tp: Any, value: Any) -> Any:
    """Turn a parsed construct value into the Python type ``tp`` names."""
    if value is None:
        return None
    origin = typing.get_origin(tp)
    if origin is typing.Union or origin is types.UnionType:
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return _from_container(args[0], value)
    if origin is tuple:
        inner = typing.get_args(tp)[0]
        return tuple(_from_container(inner, v) for v in value)
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        hints = _hints(tp)
        return tp(**{f.name: _from_container(hints[f.name], value[f.name]) for f in dataclasses.fields(tp)})
    if tp is bytes:
        return bytes(value)
    return value


def _to_container(value: Any) -> Any:
    """Turn a dataclass (or a value inside one) into what construct builds from."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _to_container(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, tuple | list):
        return [_to_container(v) for v in value]
    return value


# ------------------------------------------------------------------------------- messages


def spec_for(message: Message) -> MessageSpec:
    try:
        return SPECS_BY_CLASS[type(message)]
    except KeyError:
        raise EncodeError(f"{type(message).__name__} is not a wire message") from None


def encode(message: Message) -> bytes:
    """Encode one message (type id, length where specified, body)."""
    if isinstance(message, Opaque):
        return _encode_opaque(message)
    try:
        return _encode_cached(message)
    except TypeError:  # unhashable field values (a list given where a tuple is expected)
        return _encode(message)


@functools.lru_cache(maxsize=8192)
def _encode_cached(message: Message) -> bytes:
    # messages are frozen dataclasses: equal messages have equal encodings, so packing (which asks
    # for sizes repeatedly) and the canonical-form check of decoding do not re-run construct
    return _encode(message)


def _encode(message: Message) -> bytes:
    spec = spec_for(message)
    try:
        data = TYPE_ID.build(spec.type_id) + _BUILDERS[spec.type_id](_to_container(message))
    except Exception as exc:  # construct raises many types; all mean "this value cannot be sent"
        raise EncodeError(f"cannot encode {spec.name}: {_reason(exc)}") from exc
    if len(data) > MAX_MESSAGE_BYTES:
        raise EncodeError(f"{spec.name} encodes to {len(data)} B, above the {MAX_MESSAGE_BYTES} B maximum")
    return data


def _encode_opaque(message: Opaque) -> bytes:
    tid = message.type_id
    if not any(tid in r for r in THIRD_PARTY_RANGES):
        raise EncodeError(f"Opaque type id {tid} is not in a third-party range (96..32767)")
    if not isinstance(message.body, bytes):
        raise EncodeError("Opaque body must be bytes")
    data = TYPE_ID.build(tid) + OPAQUE_BODY.build(message.body)
    if len(data) > MAX_MESSAGE_BYTES:
        raise EncodeError(f"Opaque message of {len(data)} B exceeds {MAX_MESSAGE_BYTES} B")
    return data


def encoded_size(message: Message) -> int:
    """Bytes the message takes on the wire."""
    return len(encode(message))


def _reason(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[-1] if text else type(exc).__name__


def _decode_at(data: bytes, stream: io.BytesIO) -> Message:
    start = stream.tell()
    tid = TYPE_ID.parse_stream(stream)
    if tid in SPECS_BY_ID:
        spec = SPECS_BY_ID[tid]
        container = _BODIES[tid].parse_stream(stream)
        message: Message = _from_container(spec.cls, container)
    elif any(tid in r for r in THIRD_PARTY_RANGES):
        message = Opaque(tid, bytes(OPAQUE_BODY.parse_stream(stream)))
    elif tid == 0:
        raise DecodeError("unknown message type 0 (the end marker, never a message)",
                          reason="unknown message type")
    elif tid in RESERVED_RANGE:
        raise DecodeError(f"unknown message type {tid} (reserved for future built-in messages)",
                          reason="unknown message type")
    else:
        raise DecodeError(f"unknown message type {tid} (a built-in id no message is assigned)",
                          reason="unknown message type")
    end = stream.tell()
    if end - start > MAX_MESSAGE_BYTES:
        raise DecodeError(f"{type(message).__name__} of {end - start} B is above 251 bytes",
                          reason="above 251 bytes")
    # Canonical form: the bytes must be exactly what encoding the message gives. This rejects bad
    # lengths, trailing bytes inside a length-prefixed body and over-long encodings.
    if encode(message) != data[start:end]:
        raise DecodeError(f"{type(message).__name__} is not in canonical form (the bytes are not those "
                          "that encoding its value gives)", reason="canonical")
    return message


def _decode_guarded(data: bytes, stream: io.BytesIO) -> Message:
    try:
        return _decode_at(data, stream)
    except DecodeError:
        raise
    except EncodeError as exc:  # re-encoding a decoded value failed: it is not a valid value
        raise DecodeError(f"invalid field value: {exc}", reason="canonical") from exc
    except Exception as exc:  # any other failure on received bytes is the peer's (or the channel's) fault
        raise DecodeError(_describe(exc), reason=_reason_word(exc)) from exc


def _describe(exc: BaseException) -> str:
    if isinstance(exc, cs.StreamError):
        return f"truncated: {_reason(exc)}"
    return f"{type(exc).__name__}: {_reason(exc)}"


def _reason_word(exc: BaseException) -> str | None:
    """The spec's error word (section 13) for an exception raised while parsing."""
    if isinstance(exc, cs.StreamError):
        return "truncated"
    return getattr(exc, "reason", None)


def decode(data: bytes) -> Message:
    """Decode exactly one message. Raises :class:`DecodeError` (only) for any invalid input."""
    if not isinstance(data, bytes | bytearray | memoryview):
        raise DecodeError(f"expected bytes, got {type(data).__name__}")
    data = bytes(data)
    if not data:
        raise DecodeError("empty input", reason="empty")
    stream = io.BytesIO(data)
    message = _decode_guarded(data, stream)
    if stream.tell() != len(data):
        raise DecodeError(f"{len(data) - stream.tell()} bytes after the message", reason="after the message")
    return message


# --------------------------------------------------------------------------------- frames


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor)."""
    return binascii.crc_hqx(data, 0xFFFF)


def header_size(header: FrameHeader | None = None) -> int:
    """Bytes of frame overhead for this header (3, or 5 with a CRC)."""
    return FRAME_HEADER_BYTES + (CRC_BYTES if header is not None and header.crc else 0)


def _build_header(header: FrameHeader, checksum: int | None) -> bytes:
    try:
        return FRAME_HEADER.build(dict(
            bits=dict(crc=header.crc, schedule=header.schedule, src=header.src, dst=header.dst,
                      seq=header.seq),
            checksum=checksum,
        ))
    except Exception as exc:
        raise EncodeError(f"invalid frame header {header}: {_reason(exc)}") from exc


def pack(messages: Iterable[Message], budget: int, header: FrameHeader | None = None) -> bytes:
    """Pack messages into one frame of at most ``budget`` bytes (header and CRC included).

    Raises :class:`EncodeError` if they do not fit: choosing what to send is the channel
    manager's job, not this function's."""
    header = header or FrameHeader()
    body = b"".join(encode(m) for m in messages)
    size = header_size(header) + len(body)
    if size > budget:
        raise EncodeError(f"messages need {size} B, above the frame budget of {budget} B")
    if header.crc:
        plain = _build_header(header, 0)[:FRAME_HEADER_BYTES]
        checksum = crc16(plain + body)
        return _build_header(header, checksum) + body
    return _build_header(header, None) + body


def unpack_frame(packet: bytes) -> Frame:
    """Decode a frame: header, messages, optional end marker and zero padding, CRC check."""
    if not isinstance(packet, bytes | bytearray | memoryview):
        raise DecodeError(f"expected bytes, got {type(packet).__name__}")
    data = bytes(packet)
    if len(data) < FRAME_HEADER_BYTES:
        raise DecodeError(f"truncated: frame of {len(data)} B is shorter than its header", reason="truncated")
    stream = io.BytesIO(data)
    try:
        parsed = FRAME_HEADER.parse_stream(stream)
    except cs.StreamError as exc:  # the CRC flag is set and the two CRC bytes are missing
        raise DecodeError(f"truncated: the frame ends inside its header ({_reason(exc)})",
                          reason="truncated") from exc
    except Exception as exc:
        raise DecodeError(f"bad frame header: {_describe(exc)}", reason="bad frame header") from exc
    bits = parsed.bits
    header = FrameHeader(src=bits.src, dst=bits.dst, seq=bits.seq, schedule=bits.schedule, crc=bits.crc)
    body_start = stream.tell()
    messages: list[Message] = []
    while stream.tell() < len(data):
        if data[stream.tell()] == END_MARKER:
            rest = data[stream.tell():]
            if any(rest):
                raise DecodeError("non-zero bytes after the end marker", reason="after the end marker")
            break
        messages.append(_decode_guarded(data, stream))
    end = stream.tell()
    if header.crc:
        expected = crc16(data[:FRAME_HEADER_BYTES] + data[body_start:end])
        if expected != parsed.checksum:
            raise DecodeError(f"CRC mismatch: frame says {parsed.checksum:#06x}, computed {expected:#06x}",
                              reason="crc mismatch")
    return Frame(header, tuple(messages))


def unpack(packet: bytes) -> list[Message]:
    """Decode a frame and return its messages."""
    return list(unpack_frame(packet).messages)


def check_sizes(specs: Sequence[MessageSpec]) -> dict[str, int]:
    """Encode each type's largest message; return the sizes. Raises if one exceeds the maximum."""
    sizes = {}
    for spec in specs:
        size = len(encode(spec.largest()))
        sizes[spec.name] = size
    return sizes


def _enum_or_value(v: Any) -> Any:
    return v.name if isinstance(v, enum.Enum) else v


# The import-time check of every message type's maximum encoded size (DCCL's max_bytes rule).
MAX_SIZES: dict[str, int] = check_sizes(list(SPECS_BY_ID.values()))
