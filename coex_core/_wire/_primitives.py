"""Bit-level building blocks: DCCL-style bounded numbers, enums, stamps, byte alignment.

Every field constructor here records its specification (bits, range, resolution, unit) on the
construct object so that ``spec/wire-format.md`` field tables are generated from the very objects
that encode and decode (see :mod:`coex_core._wire.spec`).

Rules (normative, see the spec):

* Bits are written most-significant first; multi-bit integers are big-endian.
* A bounded value ``v`` in ``[lo, hi]`` at resolution ``res`` is sent as the unsigned integer
  ``round((v - lo) / res)`` in ``ceil(log2((hi - lo) / res + 1 + optional))`` bits (the ``+1``
  counts both end points; *round*, not floor). An optional field reserves code 0 for "absent"
  and shifts every value up by one.
* Encoding a value outside ``[lo, hi]`` raises :class:`~coex_core.errors.EncodeError` (strict
  mode) unless the field is documented as *saturating*, in which case it is clamped.
* Decoding a code that maps outside ``[lo, hi]`` raises :class:`~coex_core.errors.DecodeError`.
"""

from __future__ import annotations

import enum
import math
import struct
from collections.abc import Callable, Sequence
from typing import Any

import construct as cs

__all__ = [
    "Align8",
    "Count",
    "Float32",
    "RawBytes",
    "Text",
    "Bits",
    "Body",
    "Bool",
    "Bounded",
    "Choice",
    "Enum",
    "FieldSpec",
    "Flag",
    "FarFlag",
    "NearFar",
    "OptBool",
    "SInt",
    "Stamp",
    "STAMP_BITS",
    "STAMP_MODULUS",
    "UInt",
    "nbits",
    "spec_of",
]

STAMP_BITS = 18
STAMP_MODULUS = 1 << STAMP_BITS


class OutOfRange(cs.ConstructError):
    """Raised inside construct for a value or code outside its field's range, or a broken rule;
    ``reason`` is the spec's error word for it (``spec/wire-format.md`` section 13)."""

    def __init__(self, message: str, path: str | None = None, reason: str | None = None) -> None:
        super().__init__(message, path=path)
        self.reason = reason


def nbits(lo: float, hi: float, res: float = 1.0, optional: bool = False) -> int:
    """Bits needed for ``[lo, hi]`` at ``res`` (DCCL formula, with the +1, and +1 value if optional)."""
    steps = round((hi - lo) / res)
    values = steps + 1 + (1 if optional else 0)
    return max(1, math.ceil(math.log2(values)))


def _decimals(res: float) -> int:
    if float(res).is_integer():
        return 0
    return max(0, -math.floor(math.log10(res) + 1e-9)) + 1


class FieldSpec:
    """What the spec generator needs to know about one field: its width in bits, range,
    resolution, unit, how its code maps to a value (``coding``: "unsigned", "offset from lo",
    "two's complement", "IEEE 754 binary32", "bytes" ...), a note, and when it is present
    (``presence``, filled in by the generator)."""

    def __init__(
        self,
        bits: str,
        range_: str = "",
        resolution: str = "",
        unit: str = "",
        note: str = "",
        coding: str = "unsigned",
        presence: str = "always",
    ) -> None:
        self.bits = bits
        self.range = range_
        self.resolution = resolution
        self.unit = unit
        self.note = note
        self.coding = coding
        self.presence = presence

    def but(self, **changes: Any) -> FieldSpec:
        out = FieldSpec(self.bits, self.range, self.resolution, self.unit, self.note, self.coding, self.presence)
        for k, v in changes.items():
            setattr(out, k, v)
        return out


def spec_of(con: Any) -> FieldSpec | None:
    """The :class:`FieldSpec` attached to a construct, looking through renames and constants
    (a constant's row shows its width and its one value)."""
    const = None
    while con is not None:
        spec = getattr(con, "coex_spec", None)
        if spec is not None:
            return spec.but(range=str(const.value), note="constant") if const is not None else spec  # type: ignore[no-any-return]
        if isinstance(con, cs.Const):
            const = con
        if isinstance(con, UInt) and not callable(con.width):
            return FieldSpec(str(con.width), f"0..{(1 << con.width) - 1}" if const is None else str(const.value),
                             note="constant" if const is not None else "")
        con = getattr(con, "subcon", None)
    return None


def When(condition: str, predicate: Callable[[Any], bool], subcon: cs.Construct) -> cs.Construct:
    """A field present only when ``predicate(context)`` holds; ``condition`` says so in the
    spec's words (e.g. "`encoding` = PLANE")."""
    c = cs.If(predicate, subcon)
    c.coex_presence = condition
    return c


def Entries(count: str, length: Callable[[Any], int], subcon: cs.Construct) -> cs.Construct:
    """An array whose length follows from earlier fields; ``count`` says how, in the spec's words."""
    c = cs.Array(length, subcon)
    c.coex_count = count
    return c


class UInt(cs.Construct):  # type: ignore[misc]
    """Unsigned integer of ``width`` bits (an int or a context lambda); width 0 is legal and reads 0."""

    def __init__(self, width: int | Callable[[Any], int]) -> None:
        super().__init__()
        self.width = width

    def _width(self, context: Any) -> int:
        w = self.width(context) if callable(self.width) else self.width
        return int(w)

    def _parse(self, stream: Any, context: Any, path: str) -> int:
        w = self._width(context)
        if w == 0:
            return 0
        return _bits_to_int(cs.stream_read(stream, w, path))

    def _build(self, obj: Any, stream: Any, context: Any, path: str) -> int:
        w = self._width(context)
        value = int(obj)
        if value < 0 or (value >= (1 << w) and not (w == 0 and value == 0)):
            raise OutOfRange(f"{value} does not fit in {w} bits", path=path)
        if w:
            cs.stream_write(stream, _int_to_bits(value, w), w, path)
        return value

    def _sizeof(self, context: Any, path: str) -> int:
        raise cs.SizeofError("bit field", path=path)


_TO_ASCII = bytes.maketrans(b"\x00\x01", b"01")
_FROM_ASCII = bytes.maketrans(b"01", b"\x00\x01")


def _bits_to_int(data: bytes) -> int:
    """construct's bit streams hold one bit per byte (0 or 1)."""
    return int(bytes(data).translate(_TO_ASCII), 2)


def _int_to_bits(value: int, width: int) -> bytes:
    return format(value, f"0{width}b").encode().translate(_FROM_ASCII)


def Bits(width: int | Callable[[Any], int], note: str = "") -> cs.Construct:
    """A raw unsigned bit field (flags, masks, codes)."""
    c = UInt(width)
    w = f"{width}" if isinstance(width, int) else "variable"
    c.coex_spec = FieldSpec(w, f"0..2^{width}-1" if isinstance(width, int) else "", note=note)
    return c


class SInt(cs.Adapter):  # type: ignore[misc]
    """Two's-complement signed integer of ``width`` bits."""

    def __init__(self, width: int, unit: str = "") -> None:
        super().__init__(UInt(width))
        self.bits = width
        self.coex_spec = FieldSpec(
            str(width), f"{-(1 << (width - 1))}..{(1 << (width - 1)) - 1}", "1", unit, "",
            coding="two's complement"
        )

    def _decode(self, obj: int, context: Any, path: str) -> int:
        return obj - (1 << self.bits) if obj >= 1 << (self.bits - 1) else obj

    def _encode(self, obj: Any, context: Any, path: str) -> int:
        v = int(obj)
        if not -(1 << (self.bits - 1)) <= v < (1 << (self.bits - 1)):
            raise OutOfRange(f"{v} outside signed {self.bits}-bit range", path=path)
        return v & ((1 << self.bits) - 1)


class Bounded(cs.Adapter):  # type: ignore[misc]
    """A DCCL-style bounded number: clamp-or-reject, round (not floor), offset by ``lo``.

    ``saturating=True`` clamps out-of-range values on encode (documented in the spec);
    otherwise they raise. Integers are returned when ``lo`` and ``res`` are integral.
    """

    def __init__(
        self,
        lo: float,
        hi: float,
        res: float = 1,
        *,
        optional: bool = False,
        unit: str = "",
        saturating: bool = False,
    ) -> None:
        self.lo, self.hi, self.res = lo, hi, res
        self.optional = optional
        self.saturating = saturating
        self.steps = round((hi - lo) / res)
        self.bits = nbits(lo, hi, res, optional)
        self.integral = float(lo).is_integer() and float(res).is_integer()
        self.ndigits = _decimals(res)
        super().__init__(UInt(self.bits))
        note = []
        if optional:
            note.append("optional: code 0 = absent")
        if saturating:
            note.append("saturating")
        self.coex_spec = FieldSpec(str(self.bits), f"{_fmt(lo)}..{_fmt(hi)}", _fmt(res), unit, "; ".join(note),
                                   coding="unsigned" if lo == 0 and res == 1 and not optional else "bounded")

    def _decode(self, obj: int, context: Any, path: str) -> Any:
        if self.optional:
            if obj == 0:
                return None
            obj -= 1
        if obj > self.steps:
            raise OutOfRange(f"code {obj} above maximum {self.steps}", path=path, reason="above maximum")
        if self.integral:
            return int(self.lo) + obj * int(self.res)
        return round(self.lo + obj * self.res, self.ndigits)

    def _encode(self, obj: Any, context: Any, path: str) -> int:
        if obj is None:
            if self.optional:
                return 0
            raise OutOfRange("value is required", path=path)
        if isinstance(obj, bool) or not isinstance(obj, int | float):
            raise OutOfRange(f"expected a number, got {type(obj).__name__}", path=path)
        v = float(obj)
        if not math.isfinite(v):
            raise OutOfRange(f"{obj} is not finite", path=path)
        tol = self.res * 1e-6
        if v < self.lo - tol or v > self.hi + tol:
            if not self.saturating:
                raise OutOfRange(f"{obj} outside [{self.lo}, {self.hi}]", path=path)
            v = min(max(v, self.lo), self.hi)
        code = min(max(round((v - self.lo) / self.res), 0), self.steps)
        return code + (1 if self.optional else 0)


def _fmt(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else f"{x:g}"


def Stamp(optional: bool = False) -> cs.Construct:
    """A compact timestamp: whole seconds modulo 2^18 (about 72.8 h); see the rollover rule."""
    c = Bounded(0, STAMP_MODULUS - 1, 1, optional=optional, unit="s mod 2^18")
    c.coex_spec.note = ("optional: code 0 = absent; " if optional else "") + "stamp (see 'Time')"
    return c


class Bool(cs.Adapter):  # type: ignore[misc]
    """One bit, 1 = true."""

    def __init__(self) -> None:
        super().__init__(UInt(1))
        self.coex_spec = FieldSpec("1", "0..1", coding="boolean")

    def _decode(self, obj: int, context: Any, path: str) -> bool:
        return bool(obj)

    def _encode(self, obj: Any, context: Any, path: str) -> int:
        if not isinstance(obj, bool):
            raise OutOfRange(f"expected a bool, got {obj!r}", path=path)
        return int(obj)


class OptBool(cs.Adapter):  # type: ignore[misc]
    """Two bits: 0 = absent (no change), 1 = false, 2 = true; 3 is invalid."""

    def __init__(self) -> None:
        super().__init__(UInt(2))
        self.coex_spec = FieldSpec("2", "0..2", note="0 absent, 1 false, 2 true", coding="optional boolean")

    def _decode(self, obj: int, context: Any, path: str) -> bool | None:
        if obj == 3:
            raise OutOfRange("code 3 is not a valid optional boolean", path=path, reason="optional boolean")
        return None if obj == 0 else obj == 2

    def _encode(self, obj: Any, context: Any, path: str) -> int:
        if obj is None:
            return 0
        if not isinstance(obj, bool):
            raise OutOfRange(f"expected a bool or None, got {obj!r}", path=path)
        return 2 if obj else 1


class Enum(cs.Adapter):  # type: ignore[misc]
    """An IntEnum in the fewest bits that hold its largest member, or in ``bits`` (more, leaving
    room for members to come: the table shows the width); codes that name no member are invalid."""

    def __init__(self, enum_cls: type[enum.IntEnum], bits: int | None = None) -> None:
        top = max(int(m) for m in enum_cls)
        fewest = max(1, top.bit_length())
        self.bits = bits or fewest
        if self.bits < fewest:
            raise ValueError(f"{enum_cls.__name__} needs {fewest} bits, not {self.bits}")
        self.enum_cls = enum_cls
        super().__init__(UInt(self.bits))
        members = ", ".join(f"{int(m)} {m.name}" for m in enum_cls)
        note = f"enum: {members}"
        if self.bits > fewest:  # room for members to come (spec section 6: the table's width rules)
            note += f"; {self.bits} bits, wider than the {fewest} its members need"
        self.coex_spec = FieldSpec(str(self.bits), f"0..{top}", note=note, coding="enum")

    def _decode(self, obj: int, context: Any, path: str) -> enum.IntEnum:
        try:
            return self.enum_cls(obj)
        except ValueError:
            raise OutOfRange(f"{obj} is not a valid {self.enum_cls.__name__}", path=path,
                             reason="not a valid") from None

    def _encode(self, obj: Any, context: Any, path: str) -> int:
        try:
            return int(self.enum_cls(obj))
        except (ValueError, TypeError):
            raise OutOfRange(f"{obj!r} is not a valid {self.enum_cls.__name__}", path=path) from None


class Choice(cs.Adapter):  # type: ignore[misc]
    """A value from a fixed table, sent as its index."""

    def __init__(self, table: Sequence[float], unit: str = "") -> None:
        self.table = tuple(table)
        self.bits = max(1, (len(self.table) - 1).bit_length())
        super().__init__(UInt(self.bits))
        values = ", ".join(f"{i} = {_fmt(v)}" for i, v in enumerate(self.table))
        self.coex_spec = FieldSpec(str(self.bits), f"0..{len(self.table) - 1}", "", unit, f"table: {values}",
                                   coding="table index")

    def _decode(self, obj: int, context: Any, path: str) -> float:
        if obj >= len(self.table):
            raise OutOfRange(f"table index {obj} above maximum {len(self.table) - 1}", path=path,
                             reason="above maximum")
        return self.table[obj]

    def _encode(self, obj: Any, context: Any, path: str) -> int:
        for i, v in enumerate(self.table):
            if isinstance(obj, int | float) and not isinstance(obj, bool) and abs(float(obj) - v) < 1e-9:
                return i
        raise OutOfRange(f"{obj!r} is not one of {self.table}", path=path)


class Align8(cs.Construct):  # type: ignore[misc]
    """Zero bits up to the next byte boundary (must be zero when parsed)."""

    def __init__(self) -> None:
        super().__init__()
        self.flagbuildnone = True

    def _parse(self, stream: Any, context: Any, path: str) -> None:
        pad = -cs.stream_tell(stream, path) % 8
        if any(cs.stream_read(stream, pad, path)):
            raise OutOfRange("non-zero padding bits", path=path, reason="padding")
        return None

    def _build(self, obj: Any, stream: Any, context: Any, path: str) -> None:
        pad = -cs.stream_tell(stream, path) % 8
        cs.stream_write(stream, bytes(pad), pad, path)
        return None

    def _sizeof(self, context: Any, path: str) -> int:
        raise cs.SizeofError("alignment", path=path)


class Rule(cs.Construct):  # type: ignore[misc]
    """A rule on the fields before it (no bits): ``predicate(context)`` must hold when parsing
    and building; otherwise :class:`OutOfRange`.

    ``violation`` says, in the spec's words, what breaks the rule (the spec lists it under "A
    decoder MUST reject the message when:", so it names the broken state, never the
    requirement); ``reason`` is its error word (section 13), which the error text contains.
    ``encode_only``: a rule that decoded bytes always meet (the layout implies it); it guards
    the encoder against values the layout cannot carry, and the spec lists it apart."""

    def __init__(self, predicate: Callable[[Any], bool], violation: str, reason: str | None = None, *,
                 encode_only: bool = False) -> None:
        super().__init__()
        if (reason is None) != encode_only:
            raise ValueError(f"rule {violation!r}: a decoding rule has an error word, an encode-only one none")
        self.predicate, self.violation, self.reason = predicate, violation, reason
        self.encode_only = encode_only
        self.flagbuildnone = True

    @property
    def message(self) -> str:
        """The error text: the violation and its error word."""
        return self.violation if self.reason is None else f"{self.violation} ({self.reason})"

    def _check(self, context: Any, path: str) -> None:
        if not self.predicate(context):
            raise OutOfRange(self.message, path=path, reason=self.reason)

    def _parse(self, stream: Any, context: Any, path: str) -> None:
        self._check(context, path)

    def _build(self, obj: Any, stream: Any, context: Any, path: str) -> None:
        self._check(context, path)

    def _sizeof(self, context: Any, path: str) -> int:
        return 0


class _MaxLen(cs.Adapter):  # type: ignore[misc]
    def __init__(self, subcon: cs.Construct, max_len: int) -> None:
        super().__init__(subcon)
        self.max_len = max_len

    def _decode(self, obj: Any, context: Any, path: str) -> Any:
        if len(obj) > self.max_len:
            raise OutOfRange(f"{len(obj)} bytes exceed the maximum {self.max_len}", path=path, reason="exceed")
        return obj

    def _encode(self, obj: Any, context: Any, path: str) -> Any:
        if len(obj) > self.max_len:
            raise OutOfRange(f"{len(obj)} bytes exceed the maximum {self.max_len}", path=path)
        return obj


def RawBytes(max_len: int | None = None, fixed: int | None = None, count: str = "") -> cs.Construct:
    """Raw bytes, 8 bits each, continuing the bit stream (not aligned): a fixed count, as many as
    an earlier count field says (``count``: its name, at most ``max_len``), or the rest of a
    length-prefixed body (at most ``max_len``)."""
    if fixed is not None:
        c = cs.Bytewise(cs.Bytes(fixed))
        c.coex_spec = FieldSpec(str(8 * fixed), f"{fixed} bytes", unit="bytes", coding="bytes")
        return c
    assert max_len is not None
    if count:
        c = cs.Bytewise(_MaxLen(cs.Bytes(lambda ctx: ctx[count]), max_len))
        c.coex_spec = FieldSpec("8 x n", f"0..{max_len} bytes", unit="bytes", note=f"`{count}` bytes",
                                coding="bytes")
        return c
    c = cs.Bytewise(_MaxLen(cs.GreedyBytes, max_len))
    c.coex_spec = FieldSpec("8 x n", f"0..{max_len} bytes", unit="bytes", note="rest of the body",
                            coding="bytes")
    return c


class _Text(cs.Adapter):  # type: ignore[misc]
    def __init__(self, max_len: int) -> None:
        self.max_len = max_len
        super().__init__(cs.Bytewise(cs.Prefixed(cs.Int8ub, cs.GreedyBytes)))

    def _decode(self, obj: bytes, context: Any, path: str) -> str:
        if len(obj) > self.max_len:
            raise OutOfRange(f"text of {len(obj)} bytes exceeds {self.max_len}", path=path, reason="exceed")
        try:
            return obj.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise OutOfRange(f"text is not valid utf-8: {exc}", path=path, reason="utf-8") from None

    def _encode(self, obj: Any, context: Any, path: str) -> bytes:
        if not isinstance(obj, str):
            raise OutOfRange(f"expected a str, got {obj!r}", path=path)
        data = obj.encode("utf-8")
        if len(data) > self.max_len:
            raise OutOfRange(f"text of {len(data)} bytes exceeds {self.max_len}", path=path)
        return data


def Text(max_len: int) -> cs.Construct:
    """UTF-8 text with a one-byte length (at most ``max_len`` bytes), continuing the bit stream."""
    c = _Text(max_len)
    c.coex_spec = FieldSpec("8 + 8 x n", f"0..{max_len} bytes", note="one-byte length first",
                            coding="UTF-8")
    return c


_F32 = struct.Struct(">f")


class _Float32(cs.Adapter):  # type: ignore[misc]
    def __init__(self) -> None:
        super().__init__(cs.Bytewise(cs.Float32b))

    def _decode(self, obj: float, context: Any, path: str) -> float:
        if not math.isfinite(obj):
            raise OutOfRange("non-finite float", path=path, reason="non-finite")
        if obj == 0 and math.copysign(1.0, obj) < 0:
            # zero has one encoding, +0.0 (what the encoder writes for -0.0 too)
            raise OutOfRange("-0.0 is not the canonical zero (+0.0)", path=path, reason="canonical")
        return float(obj)

    def _encode(self, obj: Any, context: Any, path: str) -> float:
        if isinstance(obj, bool) or not isinstance(obj, int | float) or not math.isfinite(obj):
            raise OutOfRange(f"expected a finite number, got {obj!r}", path=path)
        v = float(obj)
        try:
            if _F32.unpack(_F32.pack(v))[0] == 0:
                return 0.0  # -0.0 (or a tiny negative rounding to it) is sent as +0.0: one zero
        except (OverflowError, struct.error):
            pass  # too large for binary32: construct refuses it
        return v


def Float32(unit: str = "") -> cs.Construct:
    """IEEE 754 binary32, big-endian, continuing the bit stream; NaN and infinities are invalid,
    and so is -0.0 (zero is sent as +0.0: one encoding per value)."""
    c = _Float32()
    c.coex_spec = FieldSpec("32", "finite", unit=unit, coding="IEEE 754 binary32, big-endian")
    return c


def Count(lo: int, hi: int, of: str) -> cs.Construct:
    """A derived element count: built from ``len(<of>)``, checked against ``[lo, hi]``."""
    c = cs.Rebuild(Bounded(lo, hi), lambda ctx: len(ctx[of]))
    c.coex_spec = FieldSpec(str(nbits(lo, hi)), f"{lo}..{hi}", "1",
                            note=f"number of entries in `{of}`" + (f"; the code is the number minus {lo}" if lo else ""),
                            coding="bounded" if lo else "unsigned", presence="always (derived)")
    c.coex_derived = True
    return c


def Flag(of: str) -> cs.Construct:
    """A derived bit: 1 when ``<of>`` has entries (the fields that depend on it are then present)."""
    c = cs.Rebuild(Bool(), lambda ctx: len(ctx[of]) > 0)
    c.coex_spec = FieldSpec("1", "0..1", "1", note=f"1 when `{of}` has entries", coding="unsigned",
                            presence="always (derived)")
    c.coex_derived = True
    return c


def Given(of: str) -> cs.Construct:
    """A derived bit: 1 when the optional field ``<of>`` is given (it is then present)."""
    c = cs.Rebuild(Bool(), lambda ctx: ctx[of] is not None)
    c.coex_spec = FieldSpec("1", "0..1", "1", note=f"1 when `{of}` is given", coding="unsigned",
                            presence="always (derived)")
    c.coex_derived = True
    return c


class NearFar(UInt):
    """An unsigned number in ``near`` bits when an earlier derived bit ``flag`` is 0 (the number is
    below ``2**near``), else in ``far`` bits. Build the flag with :func:`FarFlag`, and add a
    :class:`Rule` that rejects the long form of a number below ``2**near`` (one encoding each)."""

    def __init__(self, near: int, far: int, flag: str, unit: str = "") -> None:
        super().__init__(lambda ctx: far if ctx[flag] else near)
        self.near, self.far, self.flag = near, far, flag
        self.coex_spec = FieldSpec(f"{near} or {far}", f"0..{(1 << far) - 1}", "1", unit,
                                   note=f"{near} bits when `{flag}` = 0, {far} bits when `{flag}` = 1",
                                   coding="unsigned")


def FarFlag(of: str, near: int) -> cs.Construct:
    """The derived bit that says a :class:`NearFar` number ``of`` takes its long form: 1 exactly
    when it is at least ``2**near``."""
    c = cs.Rebuild(Bool(), lambda ctx: int(ctx[of]) >= (1 << near))
    c.coex_spec = FieldSpec("1", "0..1", "1", note=f"1 when `{of}` >= {1 << near}", coding="unsigned",
                            presence="always (derived)")
    c.coex_derived = True
    return c


def Body(*fields: cs.Construct) -> cs.Construct:
    """A message body: the fields, bit-packed MSB first, zero-padded to a whole byte."""
    return cs.Bitwise(cs.Struct(*fields, Align8()))
