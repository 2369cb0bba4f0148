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
    CommandAck,
    FrameHeader,
    ImageFragment,
    Message,
    Opaque,
    VehicleMode,
    VehicleStatus,
)
from . import _codec
from ._primitives import FieldSpec, spec_of
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


def _rows(struct: Any, prefix: str = "") -> list[tuple[str, FieldSpec, str, Any]]:
    rows = []
    for sc in struct.subcons:
        name = getattr(sc, "name", None)
        if not name:
            continue
        doc = getattr(sc, "docs", "") or ""
        inner = sc
        while isinstance(inner, cs.Renamed):
            doc = doc or (getattr(inner, "docs", "") or "")
            inner = inner.subcon
        if isinstance(inner, cs.IfThenElse):
            spec = spec_of(inner.thensubcon) or FieldSpec("?")
            spec = FieldSpec(spec.bits, spec.range, spec.resolution, spec.unit,
                             "only when the preceding flag is set")
            rows.append((prefix + name, spec, doc, None))
            continue
        if isinstance(inner, cs.Array):
            sub = _struct_of(inner.subcon)
            if sub is not None:
                rows.append((prefix + name, FieldSpec("n x entry", note="array of entries below"), doc, sub))
            else:
                el = spec_of(inner.subcon) or FieldSpec("?")
                rows.append((prefix + name, FieldSpec(f"n x {el.bits}", el.range, el.resolution, el.unit,
                                                      el.note), doc, None))
            continue
        spec = spec_of(inner) or FieldSpec("?")
        if _is_derived(inner):
            spec = FieldSpec(spec.bits, spec.range, spec.resolution, spec.unit, spec.note or "derived")
        rows.append((prefix + name, spec, doc, None))
    return rows


def _table(struct: Any) -> list[str]:
    lines = [
        "| field | bits | range | resolution | unit | description |",
        "|---|---|---|---|---|---|",
    ]
    subs = []
    for name, spec, doc, sub in _rows(struct):
        desc = doc.strip().replace("|", "\\|")
        if spec.note:
            desc = f"{desc} ({spec.note})" if desc else spec.note
        lines.append(f"| `{name}` | {spec.bits} | {spec.range} | {spec.resolution} | {spec.unit} | {desc} |")
        if sub is not None:
            subs.append((name, sub))
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
    lines.append("")
    lines.append("The body is padded with zero bits to a whole byte.")
    return "\n".join(lines)


def render_tables() -> str:
    parts = [render_message(spec) for _, spec in sorted(SPECS_BY_ID.items())]
    return "\n\n".join(parts) + "\n"


def render_frame_header() -> str:
    struct = _codec.FRAME_HEADER.subcons[0].subcon.subcon  # Renamed(bits) -> Bitwise -> Struct
    lines = _table(_struct_of(struct))
    lines.append("| `checksum` | 16 | 0..65535 | | | CRC-16/CCITT-FALSE, only when `crc` is 1 |")
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
     [ImageFragment(9, 640, 12, (0,), bytes(224))], 256),
]


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


def _invalid_cases() -> list[tuple[str, str, bytes, str]]:
    """(name, scope, bytes, reason): reason is a word the DecodeError message must contain."""
    cases: list[tuple[str, str, bytes, str]] = []
    for spec in sorted(SPECS_BY_ID.values(), key=lambda s: s.type_id):
        _, message = spec.cases()[-1]
        data = _codec.encode(message)
        cases.append((f"{spec.name}_truncated", "message", data[:-1], "truncated"))
    status = _codec.encode(_status())
    heading_max = bytearray(status)
    cases += [
        ("empty_input", "message", b"", "empty"),
        ("end_marker_alone", "message", b"\x00", "unknown message type"),
        ("unassigned_builtin_id", "message", b"\x3f\x00", "unknown message type"),
        ("reserved_id", "message", b"\x40\x00", "unknown message type"),
        ("overlong_type_id", "message", b"\x80\x06\x00\x00", "over-long"),
        ("nonzero_padding_bits", "message", bytes.fromhex("060001"), "padding"),
        ("enum_out_of_range", "message", bytes.fromhex("2400000030"), "not a valid"),
        ("optional_bool_code_3", "message", bytes.fromhex("03000300000000"), "optional boolean"),
        ("bounded_code_above_max", "message",
         bytes.fromhex("08000000007f8000"), "above maximum"),
        ("fragment_length_too_long", "message", bytes.fromhex("21ff0100"), "truncated"),
        ("fragment_length_short", "message", bytes.fromhex("2102000000"), "truncated"),
        ("fragment_data_too_large", "message",
         bytes.fromhex("21f901") + bytes(6) + bytes(243), "exceed"),
        ("fragment_above_251_bytes", "message", _codec.TYPE_ID.build(33) + _codec._BODIES[33].build(
            _codec._to_container(ImageFragment(0, 0, 0, tuple(range(16)), bytes(227)))), "above"),
        ("trailing_bytes", "message", _codec.encode(CommandAck(1, AckStatus.ACCEPTED)) + b"\x01", "after"),
        ("frame_too_short", "frame", b"\x40\x00", "truncated"),
        ("frame_bad_version", "frame", bytes.fromhex("800000"), "bad frame header"),
        ("frame_reserved_bit", "frame", bytes.fromhex("500000"), "bad frame header"),
        ("frame_crc_mismatch", "frame",
         bytes.fromhex("6021095b51") + _codec.encode(CommandAck(1, AckStatus.ACCEPTED)), "crc mismatch"),
        ("frame_garbage_after_end", "frame", bytes.fromhex("40000000000001"), "after the end marker"),
        ("frame_truncated_message", "frame", bytes.fromhex("40000001"), "truncated"),
    ]
    _ = heading_max
    return cases


def invalid_vectors() -> dict[str, Any]:
    out = []
    for name, scope, data, reason in _invalid_cases():
        decoder = _codec.decode if scope == "message" else _codec.unpack_frame
        try:
            decoder(data)
        except DecodeError as exc:
            if reason.lower() not in str(exc).lower():
                raise AssertionError(f"invalid vector {name}: {exc!s} lacks {reason!r}") from exc
        else:
            raise AssertionError(f"invalid vector {name} decoded without error")
        out.append({"name": name, "scope": scope, "hex": data.hex(), "error": "DecodeError", "reason": reason})
    return {"vectors": out}


def all_vector_files() -> dict[str, dict[str, Any]]:
    files = {f"{spec.name}.json": message_vectors(spec) for spec in SPECS_BY_ID.values()}
    files["frames.json"] = frame_vectors()
    files["invalid.json"] = invalid_vectors()
    return files


def dumps(doc: dict[str, Any]) -> str:
    return json.dumps(doc, indent=1, sort_keys=False) + "\n"


def write_vectors(directory: str | Path) -> None:
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    for name, doc in all_vector_files().items():
        (d / name).write_text(dumps(doc))
