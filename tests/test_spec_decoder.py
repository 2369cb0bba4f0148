"""A decoder written from spec/wire-format.md alone: the field tables (read from the document,
not from the construct definitions), sections 2, 5 and 6, the JSON form of section 13.1 and
the Rice code of spec/payloads.md 1.3. Its decoding uses nothing of coex_core (no codec, no
jsonfmt); only its answers go through `coex spec vectors`' comparison (section 13.3), and they
must agree with every valid vector, frames and third-party messages included. When the text
leaves out something a second implementer needs, this fails."""

from __future__ import annotations

import json
import re
import struct
from pathlib import Path
from typing import Any

import pytest

from coex_core._wire import spec as specgen  # only the comparison of section 13.3

ROOT = Path(__file__).resolve().parents[1]
TEXT = (ROOT / "spec" / "wire-format.md").read_text()
VECTORS = ROOT / "spec" / "vectors"

Row = dict[str, str]


def _table(lines: list[str]) -> list[Row]:
    keys = ["field", "bits", "range", "resolution", "unit", "coding", "present", "description"]
    rows = []
    for line in lines:
        cells = [c.strip() for c in re.split(r"(?<!\\)\|", line)[1:-1]]
        rows.append(dict(zip(keys, cells, strict=True)))
    return rows


def _tables(block: str) -> tuple[list[Row], dict[str, list[Row]]]:
    """The message's table and its entry tables (``Each entry of `x`:``)."""
    parts = re.split(r"\nEach entry of `(\w+)`:\n", block)
    def rows_of(text: str) -> list[Row]:
        return _table([ln for ln in text.splitlines() if ln.startswith("| `") or ln.startswith("| (padding)")])
    return rows_of(parts[0]), {parts[i]: rows_of(parts[i + 1]) for i in range(1, len(parts), 2)}


def messages_of_the_document() -> dict[int, dict[str, Any]]:
    out = {}
    for m in re.finditer(r"^### (\d+): (\w+) \(\w+\)\n(.*?)(?=^### |^<!-- END)", TEXT, re.S | re.M):
        tid, name, block = int(m[1]), m[2], m[3]
        rows, entries = _tables(block)
        out[tid] = {"name": name, "prefixed": "VarInt byte length, then the body" in block, "rows": rows,
                    "entries": entries}
    return out


MESSAGES = messages_of_the_document()
HEADER = _table([ln for ln in TEXT.split("<!-- BEGIN GENERATED FRAME HEADER TABLE -->", 1)[1]
                 .split("<!-- END", 1)[0].splitlines() if ln.startswith("| `")])


class Bits:
    """Section 2: most significant bit first."""

    def __init__(self, data: bytes) -> None:
        self.data, self.pos = data, 0

    def read(self, n: int) -> int:
        if self.pos + n > 8 * len(self.data):
            raise ValueError("truncated")
        v = 0
        for _ in range(n):
            v = (v << 1) | (self.data[self.pos // 8] >> (7 - self.pos % 8) & 1)
            self.pos += 1
        return v

    def align(self) -> None:
        pad = -self.pos % 8
        if self.read(pad):
            raise ValueError("padding")


def _range(row: Row) -> tuple[float, float]:
    lo, _, hi = row["range"].partition("..")
    return float(lo), float(eval(hi.replace("^", "**"))) if hi else float(lo)


def _expr(text: str, ctx: dict[str, Any]) -> int:
    """``side^2``, ``w*h``: widths and counts in the tables' words."""
    return int(eval(text.replace("^", "**"), {}, dict(ctx)))


def _scalar(row: Row, bits: Bits, ctx: dict[str, Any]) -> Any:
    coding, desc, width_text = row["coding"], row["description"], row["bits"]
    if coding == "zero bits":
        raise AssertionError("padding is not a value")
    if " or " in width_text:  # 12 or 20: "(12 bits when `far` = 0, 20 bits when `far` = 1)"
        near, far = (int(w) for w in width_text.split(" or "))
        flag = re.search(r"bits when `(\w+)` = 0", desc)[1]  # type: ignore[index]
        width = far if ctx[flag] else near
    elif width_text in ("side^2", "w*h"):
        width = _expr(width_text, ctx)
    elif coding == "UTF-8":
        n = bits.read(8)
        raw = bytes(bits.read(8) for _ in range(n))
        return raw.decode("utf-8")
    elif coding == "bytes":
        if width_text.isdigit():
            n = int(width_text) // 8
        else:
            counted = re.search(r"\(`(\w+)` bytes\)", desc)
            n = ctx[counted[1]] if counted else (len(bits.data) * 8 - bits.pos) // 8  # the rest of the body
        return bytes(bits.read(8) for _ in range(n)).hex()
    else:
        width = int(re.sub(r"^n x ", "", width_text))
    code = bits.read(width)
    if coding == "boolean":
        return bool(code)
    if coding == "optional boolean":
        return [None, False, True][code]
    if coding == "enum":
        members = dict(re.findall(r"(\d+) (\w+)", desc.split("(enum: ", 1)[1].split(";")[0]))
        return members[str(code)]
    if coding == "table index":
        table = dict(re.findall(r"(\d+) = ([\d.]+)", desc.split("(table: ", 1)[1]))
        return float(table[str(code)])
    if coding.startswith("IEEE 754"):
        return struct.unpack(">f", code.to_bytes(4, "big"))[0]
    if coding == "two's complement":
        return code - (1 << width) if code >> (width - 1) else code
    if coding.startswith("bit mask"):
        return code
    # unsigned / bounded: lo + code * res, an optional one with code 0 absent (section 13.1)
    if "optional: code 0 = absent" in desc:
        if code == 0:
            return None
        code -= 1
    if row["resolution"] == "" or ".." not in row["range"] or "2^" in row["range"]:
        return code
    lo, _ = _range(row)
    res = float(row["resolution"])
    if lo.is_integer() and res.is_integer():
        return int(lo) + code * int(res)
    return lo + code * res  # binary64 arithmetic: within the tolerance of section 13.3


def _rice(bits: Bits, k: int) -> int:
    """spec/payloads.md 1.3."""
    q = 0
    while bits.read(1):
        q += 1
        if q == 16:
            return bits.read(bits.read(5))
    return (q << k) | bits.read(k)


def _present(row: Row, ctx: dict[str, Any]) -> bool:
    when = re.match(r"when `(\w+)` = (\w+)", row["present"])
    if not when:
        return True
    value = ctx[when[1]]
    return str(int(value) if isinstance(value, bool) else value) == when[2]


def _count(row: Row, ctx: dict[str, Any]) -> int:
    present = row["present"]
    if present.startswith("none when `encoding` = OFFSET and `width` = 0"):  # Subgrid.values
        if ctx["encoding"] == "OFFSET" and ctx["width"] == 0:
            return 0
        return bin(ctx["mask"]).count("1") if ctx.get("mask") is not None else ctx["side"] ** 2
    m = re.match(r"(\S+) entries when `(\w+)` = (\d); none when it is \d", present)
    if m:
        return _expr(m[1], ctx) if int(ctx[m[2]]) == int(m[3]) else 0
    m = re.match(r"`(\w+)` entries", present)
    assert m, present
    return int(ctx.get(m[1]) or 0)


def _arithmetic_cells(bits: Bits, ctx: dict[str, Any]) -> dict[str, Any]:
    """The coded cells of payloads.md 1.7, with the coder of the decoder written from that
    section (tests/spec_decoder/subgrids.py, itself from the document alone)."""
    from .spec_decoder import subgrids

    reader = subgrids.Bits(bits.data)
    coder = subgrids.Coder(reader, bits.pos)
    table = min(ctx["level"], 2) if ctx["context"] == "PARENT" else 3
    mask, residuals = subgrids.cells_code(int(ctx["side"]), bool(ctx["partial"]), int(ctx["shift"]), table, coder)
    bits.read(coder.shifts + 2)
    return {"mask": mask, "residuals": residuals}


def _fields(rows: list[Row], bits: Bits, entries: dict[str, list[Row]]) -> tuple[dict[str, Any], dict[str, Any]]:
    """(the JSON fields of section 13.1, every decoded field)."""
    ctx: dict[str, Any] = {}
    out: dict[str, Any] = {}
    for row in rows:
        if row["field"] == "(padding)":
            bits.align()
            continue
        name = row["field"].strip("`")
        derived = "(derived)" in row["present"]
        if row["coding"] == "entries" or row["bits"].startswith("n x"):
            n = _count(row, ctx)
            if row["coding"] == "entries":
                value = [_fields(entries[name], bits, {})[0] for _ in range(n)]
            elif row["coding"].startswith("OFFSET"):
                value = [bits.read(ctx["width"]) if ctx["encoding"] == "OFFSET" else _rice(bits, ctx["width"])
                         for _ in range(n)]
            else:
                value = [_scalar(row, bits, ctx) for _ in range(n)]
        elif row["coding"] == "arithmetic code":  # PredictedSubgrid.cells: spec/payloads.md 1.7
            value = _arithmetic_cells(bits, ctx)
        elif _present(row, ctx):
            value = _scalar(row, bits, ctx)
        else:
            value = None  # absent by its present column: null (an array: [] above)
        ctx[name] = value
        if not derived:
            out[name] = value
    return out, ctx


def _varint(data: bytes, pos: int) -> tuple[int, int]:
    v = shift = 0
    while True:
        b = data[pos]
        v |= (b & 0x7F) << shift
        pos, shift = pos + 1, shift + 7
        if not b & 0x80:
            return v, pos


def decode_message(data: bytes, pos: int = 0) -> tuple[dict[str, Any], int]:
    """One message at ``pos``: (``{"type", "fields"}``, the position after it) (section 5)."""
    tid = data[pos]
    pos += 1
    if tid & 0x80:
        tid = (tid & 0x7F) << 8 | data[pos]
        pos += 1
    if tid >= 96:  # third party: a VarInt length and the body (13.1: Opaque)
        n, pos = _varint(data, pos)
        return {"type": "Opaque", "fields": {"type_id": tid, "body": data[pos:pos + n].hex()}}, pos + n
    msg = MESSAGES[tid]
    if msg["prefixed"]:
        n, pos = _varint(data, pos)
        body, end = data[pos:pos + n], pos + n
    else:
        body, end = data[pos:], None
    bits = Bits(body)
    fields, _ = _fields(msg["rows"], bits, msg["entries"])
    return {"type": msg["name"], "fields": fields}, end if end is not None else pos + bits.pos // 8


def decode_frame(data: bytes) -> dict[str, Any]:
    bits = Bits(data)
    header, _ = _fields(HEADER[:-1], bits, {})
    pos = 3 + (2 if header["crc"] else 0)
    messages = []
    while pos < len(data) and data[pos] != 0:
        m, pos = decode_message(data, pos)
        messages.append({"type": m["type"], **m["fields"]})
    return {"header": {k: header[k] for k in ("src", "dst", "seq", "schedule", "crc")}, "messages": messages}


def test_the_document_has_every_message_the_vectors_have() -> None:
    names = {json.loads(p.read_text())["type"] for p in VECTORS.glob("*.json")
             if p.stem not in ("frames", "invalid", "cells")}
    assert names - {"Opaque"} == {m["name"] for m in MESSAGES.values()}


@pytest.mark.parametrize("path", sorted(p.name for p in VECTORS.glob("*.json") if p.stem not in ("invalid", "cells")))
def test_a_decoder_from_the_document_alone_agrees_with_the_vectors(path: str) -> None:
    cases = [c for c in specgen.vector_cases(VECTORS) if c[0].startswith(json.loads(
        (VECTORS / path).read_text()).get("type", "frames") + "/")]
    assert cases
    answers = []
    for _, scope, hx, _ in cases:
        data = bytes.fromhex(hx)
        if scope == "frame":
            answers.append(json.dumps(decode_frame(data)))
        else:
            message, end = decode_message(data)
            assert end == len(data), f"{hx}: {end} of {len(data)} bytes read"
            answers.append(json.dumps(message))
    assert specgen.compare_answers(cases, "\n".join(answers)) == []
