"""Generate the field tables of ``spec/wire-format.md`` and the golden vectors from the construct
definitions, so that the document, the vectors and the code cannot drift apart.

``coex spec --write`` rewrites the tables between the GENERATED markers of the document;
``coex spec --check`` fails when they are stale (a test runs it); ``coex spec --write-vectors DIR``
regenerates ``DIR/*.json``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import construct as cs

from .. import jsonfmt
from ..errors import DecodeError
from ..messages import (
    AckStatus,
    AuthTrailer,
    CommandAck,
    FrameHeader,
    ImageFragment,
    Message,
    Opaque,
    VehicleMode,
    VehicleStatus,
)
from . import _codec
from ._primitives import Align8, FieldSpec, Rule, spec_of
from ._registry import SPECS_BY_ID, MessageSpec

BEGIN = "<!-- BEGIN GENERATED MESSAGE TABLES (coex spec --write) -->"
END = "<!-- END GENERATED MESSAGE TABLES -->"
FRAME_BEGIN = "<!-- BEGIN GENERATED FRAME HEADER TABLE -->"
FRAME_END = "<!-- END GENERATED FRAME HEADER TABLE -->"


def _struct_of(con: Any) -> Any:
    while con is not None and not isinstance(con, cs.Struct):
        con = getattr(con, "subcon", None)
    return con


def _is_derived(con: Any) -> bool:
    while con is not None:
        if isinstance(con, cs.Rebuild):
            return True
        con = getattr(con, "subcon", None)
    return False


def _count_text(arr: Any) -> str:
    """How many entries an array has, in the spec's words."""
    told = getattr(arr, "coex_count", None)
    if told:
        return str(told)
    count = arr.count
    if isinstance(count, int):
        return f"{count} entries"
    text = str(count)  # a construct expression such as this['n_packets']
    if text.startswith("this['") and text.endswith("']"):
        return f"`{text[6:-2]}` entries"
    raise ValueError(f"array {arr!r}: say how many entries it has (coex_primitives.Entries)")


def _rows(struct: Any, prefix: str = "") -> list[tuple[str, FieldSpec, str, Any]]:
    rows = []
    for sc in struct.subcons:
        name = getattr(sc, "name", None)
        if not name:
            if isinstance(sc, Align8):
                rows.append(("(padding)", FieldSpec("0..7", "0", coding="zero bits",
                                                    presence="always"), "Zero bits up to the next byte boundary", None))
            continue
        doc = getattr(sc, "docs", "") or ""
        inner = sc
        while isinstance(inner, cs.Renamed):
            doc = doc or (getattr(inner, "docs", "") or "")
            inner = inner.subcon
        if isinstance(inner, cs.IfThenElse):
            presence = getattr(inner, "coex_presence", None)
            if presence is None:
                raise ValueError(f"field {name}: say when it is present (coex_primitives.When)")
            spec = spec_of(inner.thensubcon)
            if spec is None:
                raise ValueError(f"field {name}: no FieldSpec")
            derived = " (derived)" if _is_derived(inner.thensubcon) else ""
            rows.append((prefix + name, spec.but(presence=f"when {presence}{derived}"), doc, None))
            continue
        if isinstance(inner, cs.Array):
            count = _count_text(inner)
            sub = _struct_of(inner.subcon)
            if sub is not None:
                rows.append((prefix + name, FieldSpec("n x entry", note="array of entries below", coding="entries",
                                                      presence=count), doc, sub))
            else:
                el = spec_of(inner.subcon)
                if el is None:
                    raise ValueError(f"field {name}: no FieldSpec")
                rows.append((prefix + name, el.but(bits=f"n x {el.bits}", presence=count), doc, None))
            continue
        spec = spec_of(inner)
        if spec is None:
            raise ValueError(f"field {name}: no FieldSpec")
        if _is_derived(inner):
            spec = spec.but(presence="always (derived)")
        rows.append((prefix + name, spec, doc, None))
    return rows


def _table(struct: Any) -> list[str]:
    lines = [
        "| field | bits | range | resolution | unit | coding | present | description |",
        "|---|---|---|---|---|---|---|---|",
    ]
    subs = []
    for name, spec, doc, sub in _rows(struct):
        desc = doc.strip().replace("|", "\\|")
        if spec.note:
            desc = f"{desc} ({spec.note})" if desc else spec.note
        field = name if name.startswith("(") else f"`{name}`"
        lines.append(f"| {field} | {spec.bits} | {spec.range} | {spec.resolution} | {spec.unit} | {spec.coding} "
                     f"| {spec.presence} | {desc} |")
        if sub is not None:
            subs.append((name, sub))
    rules = [sc for sc in struct.subcons if isinstance(sc, Rule)]
    decoding = [r for r in rules if not r.encode_only]
    if decoding:
        lines += ["", "A decoder MUST reject the message (and an encoder refuse it) when one of these holds "
                  "(after the dash: its error word, section 13.2):", ""]
        lines += [f"- {r.violation} — `{r.reason}`" for r in decoding]
    encoding = [r for r in rules if r.encode_only]
    if encoding:
        lines += ["", "An encoder MUST refuse a value when (decoded bytes never break this: the layout "
                  "above rules it out):", ""]
        lines += [f"- {r.violation}" for r in encoding]
    for name, sub in subs:
        lines += ["", f"Each entry of `{name}`:", ""]
        lines += _table(sub)
    return lines


def render_message(spec: MessageSpec) -> str:
    body = _struct_of(spec.body)
    framing = "VarInt byte length, then the body" if spec.prefixed else "self-delimiting bit-packed body"
    lines = [
        f"### {spec.type_id}: {spec.name} ({spec.domain})",
        "",
        spec.doc,
        "",
        f"Type id {spec.type_id} (`{spec.type_id:02x}`); {framing}; at most "
        f"{_codec.MAX_SIZES[spec.name]} bytes including the type id.",
        "",
    ]
    lines += _table(body)
    return "\n".join(lines)


def render_tables() -> str:
    parts = [render_message(spec) for _, spec in sorted(SPECS_BY_ID.items())]
    return "\n\n".join(parts) + "\n"


def render_frame_header() -> str:
    struct = _codec.FRAME_HEADER.subcons[0].subcon.subcon  # Renamed(bits) -> Bitwise -> Struct
    lines = _table(_struct_of(struct))
    lines.append("| `checksum` | 16 | 0..65535 | 1 |  | unsigned, big-endian | when `crc` = 1 | "
                 "CRC-16/CCITT-FALSE (section 9) |")
    return "\n".join(lines) + "\n"


def _replace(text: str, begin: str, end: str, content: str) -> str:
    if begin not in text or end not in text:
        raise ValueError(f"markers {begin!r} / {end!r} missing from the document")
    head, rest = text.split(begin, 1)
    _, tail = rest.split(end, 1)
    return f"{head}{begin}\n{content}{end}{tail}"


def updated_document(text: str) -> str:
    text = _replace(text, BEGIN, END, render_tables())
    return _replace(text, FRAME_BEGIN, FRAME_END, render_frame_header())


def write_document(path: str | Path) -> None:
    p = Path(path)
    p.write_text(updated_document(p.read_text()))


def check_document(path: str | Path) -> bool:
    """True when the document's generated tables are stale."""
    text = Path(path).read_text()
    return updated_document(text) != text


# ------------------------------------------------------------------------------ vectors


def message_vectors(spec: MessageSpec) -> dict[str, Any]:
    vectors = []
    for name, message in spec.cases():
        data = _codec.encode(message)
        assert _codec.decode(data) == message, f"{spec.name}/{name} does not round-trip"
        fields = jsonfmt.to_json(message)
        fields.pop("type")
        vectors.append({"name": name, "fields": fields, "hex": data.hex()})
    return {"type": spec.name, "type_id": spec.type_id, "vectors": vectors}


def _status() -> VehicleStatus:
    return VehicleStatus(3600, 12.5, -7.2, 45.0, 3.1, 90.0, 1.0, 80, VehicleMode.SURVEY, 0)


FRAME_CASES: list[tuple[str, FrameHeader, list[Message], int]] = [
    ("empty", FrameHeader(), [], 3),
    ("status_and_ack", FrameHeader(src=2, dst=1, seq=17, schedule=3),
     [_status(), CommandAck(4, AckStatus.ACCEPTED)], 64),
    ("with_crc", FrameHeader(src=1, dst=2, seq=255, schedule=15, crc=True),
     [CommandAck(255, AckStatus.REJECTED)], 8),
    ("third_party", FrameHeader(src=15, dst=0, seq=0),
     [Opaque(96, b"\x01\x02"), Opaque(32767, b""), Opaque(200, bytes(range(16)))], 256),
    ("fragment_fills_subframe", FrameHeader(src=2, dst=1, seq=3, crc=True),
     [ImageFragment(9, 640, 12, (0,), bytes(241))], 256),
    # valid frames, whatever command authentication makes of them (spec section 10): a decoder
    # accepts a trailer anywhere, and two of them
    ("trailer_not_last", FrameHeader(src=1, dst=2, seq=4),
     [AuthTrailer(7, bytes(range(8))), CommandAck(3, AckStatus.ACCEPTED)], 64),
    ("two_trailers", FrameHeader(src=1, dst=2, seq=5),
     [AuthTrailer(8, bytes(8)), AuthTrailer(9, b"\xff" * 8)], 64),
]

#: Third-party messages (any id 96..32767, spec section 5): the type name ``Opaque``, the id and
#: the body in the fields.
OPAQUE_CASES: list[tuple[str, Opaque]] = [
    ("one_byte_id_min_empty", Opaque(96, b"")),
    ("one_byte_id_max", Opaque(127, bytes(range(10)))),
    ("two_byte_id_min", Opaque(128, b"\x01")),
    ("assigned_range_top", Opaque(29999, b"ctd")),
    ("experimental_max_largest", Opaque(32767, b"\xff" * 247)),
]


def opaque_vectors() -> dict[str, Any]:
    """``Opaque.json``: ``type_id`` is null (each vector's fields carry the id)."""
    vectors = []
    for name, message in OPAQUE_CASES:
        data = _codec.encode(message)
        assert _codec.decode(data) == message, f"Opaque/{name} does not round-trip"
        fields = jsonfmt.to_json(message)
        fields.pop("type")
        vectors.append({"name": name, "fields": fields, "hex": data.hex()})
    return {"type": "Opaque", "type_id": None, "vectors": vectors}


def frame_vectors() -> dict[str, Any]:
    out = []
    for name, header, messages, budget in FRAME_CASES:
        data = _codec.pack(messages, budget, header)
        out.append({
            "name": name,
            "header": {"src": header.src, "dst": header.dst, "seq": header.seq,
                       "schedule": header.schedule, "crc": header.crc},
            "messages": [jsonfmt.to_json(m) for m in messages],
            "budget": budget,
            "hex": data.hex(),
        })
    return {"vectors": out}


def _bits(*fields: tuple[int | str, int]) -> bytes:
    """Bytes from ``(value, width)`` fields (or ``(bit string, 0)``), zero-padded to a byte:
    hand-made inputs that the encoder would refuse to produce."""
    s = "".join(format(v, f"0{w}b") if isinstance(v, int) else v for v, w in fields)
    s += "0" * (-len(s) % 8)
    return int(s, 2).to_bytes(len(s) // 8, "big") if s else b""


def _f32(x: float) -> str:
    import struct

    return format(struct.unpack(">I", struct.pack(">f", x))[0], "032b")


def _subgrid_head(encoding: int, width: int, side: int = 2, partial: int = 0) -> list[tuple[int | str, int]]:
    """Subgrid 17 up to `partial`: level 0, ix 0, iy 0, stamp 0, 1 m, 0.1 m, side, encoding,
    z_base 0, width (no slopes: not PLANE)."""
    return [(17, 8), (0, 4), (0, 14), (0, 14), (0, 18), (3, 3), (3, 3), (side - 2, 4), (encoding, 2),
            (0, 20), (width, 5), (partial, 1)]


def _longer_length(message: Message) -> bytes:
    """A length-prefixed message (type id and length one byte each) with its length in two bytes."""
    data = _codec.encode(message)
    return data[:1] + bytes([0x80 | data[1], 0x00]) + data[2:]


def _survey(kind: int, *, heading: int = 0, length: int = 0, width: int = 0, spacing: int = 0,
            altitude: int = 0, depth: int = 0, points: int = 0) -> bytes:
    """A SurveyCommand (type 11) from its codes: command 1, survey 2, at (0, 0), the optional
    fields' codes (0 = absent), no speed, append 0, ``points`` waypoints at (0, 0)."""
    centre = 500000  # x = y = 0.0 m: (0 - -50000) / 0.1
    return _bits((11, 8), (1, 8), (2, 10), (kind, 3), (centre, 20), (centre, 20), (heading, 12), (length, 15),
                 (width, 15), (spacing, 10), (altitude, 13), (depth, 16), (0, 7), (0, 1), (points, 5),
                 *[(centre, 20)] * (2 * points))


def _region(x0: int, y0: int, x1: int, y1: int) -> bytes:
    """An ImageRegionRequest (type 38): command 1, image 2, the box (``x1``, ``y1`` sent minus 1),
    QUALITY 30 dB."""
    return _bits((38, 8), (1, 8), (2, 10), (x0, 12), (y0, 12), (x1 - 1, 12), (y1 - 1, 12), (0, 2), (300, 16))


def _crop(x0: int, y0: int, x1: int, y1: int) -> bytes:
    """An ImageCrop (type 39): crop 3 of image 2 for command 1, the box (``x1``, ``y1`` sent minus
    1), 100 bytes, params 0x302, base 0, cover 0."""
    return _bits((39, 8), (3, 10), (2, 10), (1, 8), (x0, 12), (y0, 12), (x1 - 1, 12), (y1 - 1, 12), (100, 20),
                 (0x302, 15), (0, 11), (0, 6))


def _channel(name: bytes = b"t", lo: float = 0.0, hi: float = 1.0, resolution: float = 0.1) -> bytes:
    """A TimeSeriesChannel (type 48, VarInt length) from raw parts: channel 1, unit ''."""
    body = _bits((1, 5), (0, 3), (_f32(lo), 0), (_f32(hi), 0), (_f32(resolution), 0), (len(name), 8)) + name + b"\x00"
    return bytes([0x30, len(body)]) + body


def _predicted_head(shift: int = 0, partial: int = 0) -> list[tuple[int | str, int]]:
    """PredictedSubgrid 20 up to `partial`: level 0, ix 0, iy 0, stamp 0, side 8 (code 2),
    PARENT, check 0, predictor 0, ``shift``, ``partial``."""
    return [(20, 8), (0, 4), (0, 14), (0, 14), (0, 18), (2, 2), (1, 1), (0, 8), (0, 2), (shift, 2), (partial, 1)]


def _first_escape(ones: int, low: int, tail: int = 64) -> str:
    """The coded cells (table 0, full block, shift 0) of a first residual that escapes with an
    Exp-Golomb prefix of ``ones`` ones and the low bits ``low`` (``ones`` bits), then ``tail``
    raw zeros (so that the decoder's register never reaches past the input where it stops):
    bits no encoder writes for residuals it can send."""
    from ._arith import HALF_P, ArithEncoder
    from ._subgrid_code import INITIAL

    t = INITIAL[0]
    z, u = list(t.z), [list(r) for r in t.u]
    enc = ArithEncoder()
    enc.adaptive(1, z, 1)  # the first cell has no neighbour: class 1; u > 0
    for k in range(15):  # u > 1 .. u > 15: an escape
        enc.adaptive(1, u[1], min(k, 3))
    for _ in range(ones):
        enc.encode(1, HALF_P)
    enc.encode(0, HALF_P)
    for bit in range(ones - 1, -1, -1):
        enc.encode((low >> bit) & 1, HALF_P)
    for _ in range(tail):
        enc.encode(0, HALF_P)
    return "".join(str(b) for b in enc.finish())


def _long_cells() -> str:
    """Coded cells (table 0, full block, shift 0) longer than 1536 bits, the message still within
    251 bytes: what the encoder refuses to send."""
    from ._subgrid_code import CodedCells, encode_cells

    for m in range(200, 5000, 50):
        bits = encode_cells(8, CodedCells(None, tuple(m if i % 2 else -m for i in range(64))), 0, 0)
        if 1600 <= len(bits) <= 1800:
            return "".join(str(b) for b in bits)
    raise AssertionError("no long coded cells found")


def _noncanonical_cells() -> bytes:
    """A PredictedSubgrid whose last code bit is flipped where its residuals decode the same:
    valid bits of the coder, but not those the encoder writes (``canonical``)."""
    from ..messages import PredictedSubgrid, SubgridCells, SubgridContext

    for k in range(64):
        msg = PredictedSubgrid(level=0, ix=k, iy=0, stamp=0, side=8, context=SubgridContext.PARENT, predictor=0,
                               shift=0, cells=SubgridCells(None, tuple((i * (k + 3)) % 5 - 2 for i in range(64))),
                               check=0)
        data = bytearray(_codec.encode(msg))
        for pos in range(8 * len(data) - 1, 8 * 11, -1):
            bad = bytearray(data)
            bad[pos // 8] ^= 0x80 >> (pos % 8)
            try:
                _codec.decode(bytes(bad))
            except DecodeError as exc:
                if exc.reason == "canonical":
                    return bytes(bad)
    raise AssertionError("no non-canonical PredictedSubgrid found")


def _spec_rule_cases() -> list[tuple[str, str, bytes, str]]:
    """Inputs each invalid by one rule of the document that the encoder never produces."""
    zeros3 = [("0", 0)] * 3  # three more DELTA codes of 0 (Rice, k = 0)
    # type 33, image 1, marked, near, offset 0, 2 marks (code 1), first packet 0, the marks,
    # 10 data bytes
    frag = _bits((33, 8), (1, 10), (1, 1), (0, 1), (0, 12), (1, 5), (0, 10), (5, 8), (3, 8), (10, 8),
                 ("0" * 80, 0))
    frag_above = _bits((33, 8), (1, 10), (1, 1), (0, 1), (0, 12), (1, 5), (0, 10), (3, 8), (11, 8), (10, 8),
                       ("0" * 80, 0))
    # image 1, not marked, far, offset 4095 (fits the near form), 0 data bytes
    frag_far = _bits((33, 8), (1, 10), (0, 1), (1, 1), (4095, 20), (0, 8))
    # a TimeSeriesChunk (type 49) with no data, then 233 data bytes (one above its 232)
    chunk = _codec.encode(SPECS_BY_ID[49].cases()[0][1])[2:] + bytes(233)
    return [
        ("rice_escape_not_needed", "message",
         _bits(*_subgrid_head(1, 0), ("1" * 16 + "00001" + "1", 0), *zeros3), "canonical"),
        ("rice_escape_length_not_minimal", "message",
         _bits(*_subgrid_head(1, 0), ("1" * 16 + "00110" + "010100", 0), *zeros3), "canonical"),
        ("varint_length_not_minimal", "message", _longer_length(SPECS_BY_ID[48].cases()[0][1]), "canonical"),
        ("gradient_with_mask", "message", _bits(*_subgrid_head(3, 0, partial=1), (0b1111, 4), ("0000", 0)),
         "GRADIENT"),
        ("subgrid_values_too_large", "message", _bits(*_subgrid_head(0, 7, side=16), ("0" * 256 * 7, 0)),
         "too large"),
        ("roi_held_too_many", "message",
         _bits((18, 8), (0, 8), (0, 4), (0, 14), (0, 14), (8, 4), (7, 4), (0, 1), ("0" * 19 * 72, 0)),
         "too many"),
        ("fragment_packets_decreasing", "message", frag, "out of order"),
        ("fragment_packet_beyond_data", "message", frag_above, "out of order"),
        ("fragment_far_offset_not_canonical", "message", frag_far, "canonical"),
        ("float_nan", "message", _bits((50, 8), (1, 8), (0, 5), (0, 18), (0, 18), (0, 7), (_f32(float("nan")), 0)),
         "non-finite"),
        # zero has one encoding, +0.0 (spec section 6): -0.0 anywhere a Float32 is
        ("float_negative_zero", "message",
         _bits((50, 8), (1, 8), (0, 5), (0, 18), (0, 18), (0, 7), (_f32(-0.0), 0)), "canonical"),
        ("channel_resolution_negative_zero", "message", _channel(resolution=-0.0), "canonical"),
        ("text_not_utf8", "message", _channel(name=b"\xff"), "utf-8"),
        ("text_too_long", "message", _channel(name=b"n" * 33), "exceed"),
        ("chunk_data_too_long", "message", bytes([0x31]) + bytes([0x80 | len(chunk) & 0x7F, len(chunk) >> 7]) + chunk,
         "exceed"),
        # survey 1 REJECTED AUTONOMY_REFUSED at 0, no index, no value, has_detail 1 with 0 bytes
        ("survey_detail_empty", "message",
         _bits((12, 8), (1, 10), (1, 3), (6, 4), (0, 18), (0, 9), (0, 17), (1, 1), (0, 8)), "empty detail"),
        ("survey_line_without_length", "message", _survey(1, heading=1), "incomplete survey"),
        ("survey_lawnmower_without_spacing", "message", _survey(2, heading=1, length=2, width=2),
         "incomplete survey"),
        ("survey_points_not_waypoints", "message", _survey(0, points=1), "points without WAYPOINTS"),
        ("survey_altitude_and_depth", "message", _survey(0, altitude=1, depth=1), "altitude and depth"),
        ("survey_kind_unassigned", "message", _survey(4), "not a valid"),
        # detection 1 from the MAP at 0, x = y = 0, score 0.5, no height, length 2.0 (code 11),
        # width 2.2 (code 12), no orientation or footprint
        ("detection_width_above_length", "message",
         _bits((14, 8), (1, 10), (0, 2), (0, 18), (500000, 20), (500000, 20), (50, 7), (0, 8), (11, 8), (12, 8),
               (0, 8), (0, 10)), "width above length"),
        ("detection_source_unassigned", "message",
         _bits((14, 8), (1, 10), (3, 2), (0, 18), (500000, 20), (500000, 20), (50, 7), (0, 8), (0, 8), (0, 8),
               (0, 8), (0, 10)), "not a valid"),
        ("region_empty_columns", "message", _region(10, 0, 10, 10), "empty region"),
        ("region_empty_rows", "message", _region(0, 20, 10, 5), "empty region"),
        ("crop_empty_columns", "message", _crop(64, 0, 64, 48), "empty region"),
        ("crop_empty_rows", "message", _crop(0, 48, 64, 16), "empty region"),
        ("predicted_escape_too_long", "message", _bits(*_predicted_head(), (_first_escape(22, 5), 0)),
         "above maximum"),
        ("predicted_residual_too_large", "message",
         _bits(*_predicted_head(), (_first_escape(21, (1 << 21) - 1 - (1 << 20)), 0)), "above maximum"),
        ("predicted_cells_too_large", "message", _bits(*_predicted_head(), (_long_cells(), 0)), "too large"),
        ("predicted_cells_not_canonical", "message", _noncanonical_cells(), "canonical"),
    ]


def _invalid_cases() -> list[tuple[str, str, bytes, str]]:
    """(name, scope, bytes, reason): reason is the error word (section 13) of the rule the input
    breaks; the reference's DecodeError has it as ``reason`` and in its text."""
    cases: list[tuple[str, str, bytes, str]] = []
    for spec in sorted(SPECS_BY_ID.values(), key=lambda s: s.type_id):
        _, message = spec.cases()[-1]
        data = _codec.encode(message)
        cases.append((f"{spec.name}_truncated", "message", data[:-1], "truncated"))
    cases += [
        ("empty_input", "message", b"", "empty"),
        ("end_marker_alone", "message", b"\x00", "unknown message type"),
        ("unassigned_builtin_id", "message", b"\x3f\x00", "unknown message type"),
        ("unassigned_bathymetry_id", "message", b"\x15\x00", "unknown message type"),
        ("unassigned_imagery_id", "message", b"\x28\x00", "unknown message type"),
        ("unassigned_timeseries_id", "message", b"\x34\x00", "unknown message type"),
        ("reserved_id", "message", b"\x40\x00", "unknown message type"),
        ("overlong_type_id", "message", b"\x80\x06\x00\x00", "over-long"),
        ("nonzero_padding_bits", "message", bytes.fromhex("060001"), "padding"),
        ("enum_out_of_range", "message", bytes.fromhex("2400000030"), "not a valid"),
        ("optional_bool_code_3", "message", bytes.fromhex("03000300000000"), "optional boolean"),
        ("bounded_code_above_max", "message",
         bytes.fromhex("08000000007f8000"), "above maximum"),
        # image 0, near offset 0, n_data 10 but only 2 data bytes
        ("fragment_data_truncated", "message", bytes.fromhex("210000000a") + bytes(2), "truncated"),
        # n_data 245: above the 244 a fragment may carry
        ("fragment_data_too_large", "message", bytes.fromhex("21000000f5") + bytes(245), "above maximum"),
        ("fragment_above_251_bytes", "message", _codec.TYPE_ID.build(33) + _codec._BODIES[33].build(
            _codec._to_container(ImageFragment(0, 0, 0, tuple(range(31)), bytes(214)))), "above 251 bytes"),
        # type 96, a VarInt length of 250 (fa 01) and 250 bytes: 253 bytes
        ("opaque_above_251_bytes", "message", bytes.fromhex("60fa01") + bytes(250), "above 251 bytes"),
        ("trailing_bytes", "message", _codec.encode(CommandAck(1, AckStatus.ACCEPTED)) + b"\x01", "after the message"),
        ("frame_too_short", "frame", b"\x40\x00", "truncated"),
        # the crc flag set and one CRC byte
        ("frame_crc_truncated", "frame", bytes.fromhex("60210900"), "truncated"),
        ("frame_bad_version", "frame", bytes.fromhex("800000"), "bad frame header"),
        ("frame_reserved_bit", "frame", bytes.fromhex("500000"), "bad frame header"),
        ("frame_crc_mismatch", "frame",
         bytes.fromhex("6021095b51") + _codec.encode(CommandAck(1, AckStatus.ACCEPTED)), "crc mismatch"),
        ("frame_garbage_after_end", "frame", bytes.fromhex("40000000000001"), "after the end marker"),
        ("frame_truncated_message", "frame", bytes.fromhex("40000001"), "truncated"),
        *_spec_rule_cases(),
    ]
    return cases


def invalid_vectors() -> dict[str, Any]:
    out = []
    names = set()
    for name, scope, data, reason in _invalid_cases():
        assert name not in names, f"invalid vector {name} twice"
        names.add(name)
        decoder = _codec.decode if scope == "message" else _codec.unpack_frame
        try:
            decoder(data)
        except DecodeError as exc:
            if exc.reason != reason or reason.lower() not in str(exc).lower():
                raise AssertionError(f"invalid vector {name}: {exc!s} (reason {exc.reason!r}) is not "
                                     f"{reason!r}") from exc
        else:
            raise AssertionError(f"invalid vector {name} decoded without error")
        out.append({"name": name, "scope": scope, "hex": data.hex(), "error": "DecodeError", "reason": reason})
    return {"vectors": out}


# -------------------------------------------------------------- cells (payloads.md section 1)


def rebuild_cells(message: Message, parent: list[list[int | None]] | None) -> dict[str, Any]:
    """The answer to a ``cells`` line (section 13.3): the elevations a receiver holding ``parent``
    (the parent subgrid's cells, vertical units, rows south first, null where absent) rebuilds
    from ``message``, or ``{"error": "context"}`` when it cannot (payloads.md 1.9)."""
    from ..messages import SubgridMessage
    from ..predicted import ContextMismatch, parent_from_rows, subgrid_units, units_rows

    if not isinstance(message, SubgridMessage):
        return {"error": "bad input", "detail": f"{type(message).__name__} has no cells"}
    try:
        return {"cells": units_rows(subgrid_units(message, None if parent is None else parent_from_rows(parent)))}
    except ContextMismatch as exc:
        return {"error": "context", "detail": str(exc)}


def _cells_cases() -> list[tuple[str, Message, list[list[int | None]] | None]]:
    """Subgrids with the parent cells a receiver holds (payloads.md 1.1 to 1.10): every
    PredictedSubgrid predictor and context, quarters of negative indices, parent cells missing
    (the fallback and the mirror taps), a check that fails, a parent that differs only outside
    the check region, and a Subgrid of each encoding."""
    import numpy as np

    from ..messages import SubgridContext, SubgridEncoding
    from ..predicted import SubgridParent, encode_predicted
    from ..subgrid import encode_subgrid

    a, b = np.indices((8, 8))
    smooth = -5000 + 7 * a - 4 * b + (a * b) % 5 + (a * a) // 3
    full = np.ones((8, 8), bool)
    parent = SubgridParent(smooth, full)
    holes = full.copy()
    holes[[1, 2, 3, 5], [2, 0, 3, 6]] = False
    holed = SubgridParent(smooth, holes)

    def rows(p: SubgridParent) -> list[list[int | None]]:
        return [[int(z) if ok else None for z, ok in zip(zr, pr, strict=True)]
                for zr, pr in zip(p.z.tolist(), p.present.tolist(), strict=True)]

    def child(p: SubgridParent, qx: int, qy: int, wiggle: int = 3) -> Any:
        i, j = np.indices((8, 8))
        base = p.z[qy * 4 + i // 2, qx * 4 + j // 2]
        return base + ((i * 5 + j * 3) % (2 * wiggle + 1)) - wiggle + (i + j) // 3

    out: list[tuple[str, Message, list[list[int | None]] | None]] = []

    def pred(name: str, q: Any, present: Any, level: int, ix: int, iy: int, p: SubgridParent | None,
             only: tuple[SubgridContext, int, int], given: SubgridParent | None = None, vres: float = 0.1) -> None:
        got = encode_predicted(q, present, level=level, ix=ix, iy=iy, stamp=4000 + len(out), resolution=1.0,
                               vertical_resolution=vres, parent=p, only=only)
        assert got is not None, name
        held = p if given is None else given
        out.append((name, got[0], None if held is None else rows(held)))

    P = SubgridContext.PARENT
    pred("parent_nearest", child(parent, 0, 0), full, 0, 0, 0, parent, (P, 0, 0))
    pred("parent_bilinear_east_negative_ix", child(parent, 1, 0), full, 0, -3, 2, parent, (P, 1, 0))
    pred("parent_cubic_north_negative_iy", child(parent, 0, 1), full, 1, 4, -1, parent, (P, 2, 0))
    pred("parent_cubic_half_shift_2", child(parent, 1, 1, 30), full, 2, 7, 5, parent, (P, 3, 2))
    partial = np.ones((8, 8), bool)
    partial[:, 5:] = False
    partial[0, :3] = False
    pred("parent_partial_holes_bilinear", child(holed, 0, 0), partial, 0, 6, 8, holed, (P, 1, 0))
    pred("parent_holes_cubic_mirror", child(holed, 1, 0), full, 0, 1, 0, holed, (P, 3, 0))
    pred("parent_holes_nearest_fallback", child(holed, 0, 0), full, 0, 0, 0, holed, (P, 0, 1))
    other = smooth.copy()
    other[7, 7] += 9  # outside the check region of quarter (0, 0): rows and columns 0..5
    pred("parent_differs_outside_the_check", child(parent, 0, 0), full, 0, 2, 2, parent, (P, 2, 0),
         given=SubgridParent(other, full))
    inside = smooth.copy()
    inside[5, 5] += 1  # inside it
    pred("parent_differs_inside_the_check", child(parent, 0, 0), full, 0, 2, 2, parent, (P, 2, 0),
         given=SubgridParent(inside, full))
    name, msg, _ = ("parent_not_held", *out[0][1:])
    out.append((name, msg, None))
    small = SubgridParent(smooth[:4, :4], full[:4, :4])
    out.append(("parent_of_another_side", out[0][1], rows(small)))
    q4 = np.repeat(np.repeat(small.z[2:4, 2:4], 2, 0), 2, 1) + np.arange(16).reshape(4, 4) % 3 - 1
    pred("side_4_parent_bilinear", q4, np.ones((4, 4), bool), 3, 3, 3, small, (P, 1, 0))
    N = SubgridContext.NONE
    qn = child(parent, 0, 0, 6)
    for k in range(4):
        pred(f"none_predictor_{k}", qn, full if k != 2 else partial, 4, -1, -1, None, (N, k, k % 2))
    pred("none_side_4_shift_3", (q4 - 5000) * 9, np.ones((4, 4), bool), 0, 0, 0, None, (N, 1, 3))
    for enc in SubgridEncoding:
        present = full if enc == SubgridEncoding.GRADIENT else partial
        sg = encode_subgrid(qn, present, level=1, ix=-2, iy=3, stamp=77, resolution=1.0, vertical_resolution=0.1,
                            encodings=(enc,))
        out.append((f"subgrid_{enc.name.lower()}", sg, None))
    return out


def cells_vectors() -> dict[str, Any]:
    """``cells.json``: per vector the message's bytes, the parent cells a receiver holds (null:
    none) and the elevations it rebuilds (``cells``) or ``error`` (section 13.3)."""
    out = []
    for name, message, parent in _cells_cases():
        data = _codec.encode(message)
        answer = rebuild_cells(_codec.decode(data), parent)
        vec: dict[str, Any] = {"name": name, "hex": data.hex(), "parent": parent}
        if "error" in answer:
            vec["error"] = answer["error"]
        else:
            vec["cells"] = answer["cells"]
        out.append(vec)
    return {"vectors": out}


def all_vector_files() -> dict[str, dict[str, Any]]:
    files = {f"{spec.name}.json": message_vectors(spec) for spec in SPECS_BY_ID.values()}
    files["Opaque.json"] = opaque_vectors()
    files["frames.json"] = frame_vectors()
    files["invalid.json"] = invalid_vectors()
    files["cells.json"] = cells_vectors()
    return files


def dumps(doc: dict[str, Any]) -> str:
    return json.dumps(doc, indent=1, sort_keys=False) + "\n"


def write_vectors(directory: str | Path) -> None:
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    for name, doc in all_vector_files().items():
        (d / name).write_text(dumps(doc))


# ------------------------------------------------------------------ other implementations
#
# ``coex spec vectors --check-command CMD`` runs CMD once and writes one line per vector to its
# standard input: ``message <hex>`` or ``frame <hex>``. CMD answers with one JSON object per
# line, in order: ``{"type": NAME, "fields": {...}}`` for a message, ``{"header": {...},
# "messages": [{"type": NAME, ...fields}, ...]}`` for a frame (fields in the JSON form of the
# vectors, spec section 13.1), or ``{"error": WORD}`` when the input is invalid, WORD the error
# word of the rule it breaks (section 13.2; other keys, such as the reference's ``detail``, are
# ignored). ``coex spec decode`` is the reference implementation of that protocol.


def decode_line(line: str) -> dict[str, Any]:
    """The reference answer to one line of the vector-checking protocol."""
    scope, _, hexdata = line.strip().partition(" ")
    if scope == "cells":
        try:
            query = json.loads(hexdata)
            data = bytes.fromhex(query["hex"])
            parent = query.get("parent")
        except (ValueError, KeyError, TypeError) as exc:
            return {"error": "bad input", "detail": f"not a cells query: {exc}"}
        try:
            return rebuild_cells(_codec.decode(data), parent)
        except DecodeError as exc:
            return {"error": exc.reason or "invalid", "detail": str(exc)}
    try:
        data = bytes.fromhex(hexdata.strip())
    except ValueError:
        return {"error": "bad input", "detail": f"not hexadecimal: {hexdata.strip()[:40]!r}"}
    try:
        if scope == "message":
            m = _codec.decode(data)
            fields = jsonfmt.to_json(m)
            name = fields.pop("type")
            return {"type": name, "fields": fields}
        if scope == "frame":
            frame = _codec.unpack_frame(data)
            h = frame.header
            return {"header": {"src": h.src, "dst": h.dst, "seq": h.seq, "schedule": h.schedule, "crc": h.crc},
                    "messages": [jsonfmt.to_json(m) for m in frame.messages]}
        return {"error": "bad input", "detail": f"unknown scope {scope!r} (message or frame)"}
    except DecodeError as exc:
        return {"error": exc.reason or "invalid", "detail": str(exc)}


def serve_decoder(stdin: Any, stdout: Any) -> int:
    """``coex spec decode``: answer every line of ``stdin`` (the protocol above)."""
    for line in stdin:
        if line.strip():
            stdout.write(json.dumps(decode_line(line), separators=(",", ":")) + "\n")
            stdout.flush()
    return 0


def vector_cases(directory: str | Path) -> list[tuple[str, str, str, dict[str, Any]]]:
    """``(name, scope, hex, expected)`` of every vector in ``directory``; ``expected`` is what a
    conformant decoder answers (``{"error": reason}`` for an invalid one)."""
    d = Path(directory)
    out: list[tuple[str, str, str, dict[str, Any]]] = []
    for path in sorted(d.glob("*.json")):
        doc = json.loads(path.read_text())
        if path.name == "invalid.json":
            out += [(f"invalid/{v['name']}", v["scope"], v["hex"], {"error": v["reason"]}) for v in doc["vectors"]]
        elif path.name == "cells.json":
            for v in doc["vectors"]:
                query = json.dumps({"hex": v["hex"], "parent": v["parent"]}, separators=(",", ":"))
                want = {"error": v["error"]} if "error" in v else {"cells": v["cells"]}
                out.append((f"cells/{v['name']}", "cells", query, want))
        elif path.name == "frames.json":
            out += [(f"frames/{v['name']}", "frame", v["hex"], {"header": v["header"], "messages": v["messages"]})
                    for v in doc["vectors"]]
        else:
            out += [(f"{doc['type']}/{v['name']}", "message", v["hex"], {"type": doc["type"], "fields": v["fields"]})
                    for v in doc["vectors"]]
    return out


#: numbers agree when |a - b| <= TOLERANCE * max(1, |a|, |b|) (spec section 13.1)
TOLERANCE = 1e-9


def _same(a: Any, b: Any) -> bool:
    """``a`` (an answer) agrees with ``b`` (the vector): booleans are booleans, an integer of the
    vector is met exactly (masks, counts, codes: no tolerance), other numbers within
    :data:`TOLERANCE`."""
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b
    if isinstance(a, int | float) and isinstance(b, int):
        return a == b
    if isinstance(a, int | float) and isinstance(b, int | float):
        return a == b or abs(float(a) - float(b)) <= TOLERANCE * max(1.0, abs(float(a)), abs(float(b)))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return bool(a == b)


def vector_input(cases: list[tuple[str, str, str, dict[str, Any]]]) -> str:
    """The standard input of the protocol for ``cases`` (:func:`vector_cases`)."""
    return "".join(f"{scope} {hx}\n" for _, scope, hx, _ in cases)


def compare_answers(cases: list[tuple[str, str, str, dict[str, Any]]], stdout: str) -> list[str]:
    """The differences between another implementation's answers (its standard output) and what
    the vectors say (empty: conformant). The front end (``coex spec vectors``) runs it."""
    answers = [ln for ln in stdout.splitlines() if ln.strip()]
    problems: list[str] = []
    if len(answers) != len(cases):
        problems.append(f"{len(cases)} vectors sent, {len(answers)} answers received")
    for (name, _, hx, want), line in zip(cases, answers):
        try:
            got = json.loads(line)
        except ValueError:
            problems.append(f"{name}: not JSON: {line[:120]}")
            continue
        if not isinstance(got, dict):
            problems.append(f"{name}: not a JSON object: {line[:120]}")
            continue
        if "error" in want:
            if "error" not in got:
                problems.append(f"{name}: accepted an invalid input ({want['error']}): {hx}")
            elif got["error"] != want["error"]:
                problems.append(f"{name}: rejected for {str(got['error'])[:80]!r}, but the input breaks the "
                                f"rule of {want['error']!r} (section 13.2): {hx}")
        elif "error" in got:
            detail = f" ({str(got['detail'])[:120]})" if got.get("detail") else ""
            problems.append(f"{name}: rejected a valid input: {got['error']}{detail}")
        elif not _same(got, want):
            problems.append(f"{name}: decoded {json.dumps(got)[:200]}, expected {json.dumps(want)[:200]}")
    return problems
