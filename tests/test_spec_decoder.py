"""A decoder written from spec/wire-format.md alone: the field tables (read from the document,
not from the construct definitions), sections 2, 4, 5 and 6, the JSON form of section 13.1,
the Rice code of spec/payloads.md 1.3 and the coded cells of its 1.7 (tests/spec_decoder/
subgrids.py, from payloads.md alone). Its decoding uses nothing of coex_core (no codec, no
jsonfmt); only its answers go through `coex spec vectors`' comparison (section 13.3), and they
must agree with every valid vector, frames and third-party messages included, and reject every
invalid one for its error word (section 13.2): the rules it checks are those of sections 2 to 6,
12 and 13.2, and the rules listed under each message's table (read from the document, each
with its error word; the conditions, English in the document, are written out here once each).
When the text leaves out something a second implementer needs, this fails."""

from __future__ import annotations

import binascii
import json
import math
import re
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from coex_core._wire import spec as specgen  # only the comparison of section 13.3

ROOT = Path(__file__).resolve().parents[1]
TEXT = (ROOT / "spec" / "wire-format.md").read_text()
VECTORS = ROOT / "spec" / "vectors"

Row = dict[str, str]


class DecodeError(Exception):
    """The input breaks a rule of the document; ``args[0]`` is the rule's error word (13.2)."""


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


def _rules(block: str) -> list[tuple[str, str]]:
    """(condition, error word) of each rule listed after "A decoder MUST reject the message"."""
    if "A decoder MUST reject the message" not in block:
        return []
    listed = block.split("A decoder MUST reject the message", 1)[1].split("\n\n", 2)[1]
    return [(m[1], m[2]) for m in re.finditer(r"^- (.*) — `([^`]+)`$", listed, re.M)]


def messages_of_the_document() -> dict[int, dict[str, Any]]:
    out = {}
    for m in re.finditer(r"^### (\d+): (\w+) \(\w+\)\n(.*?)(?=^### |^<!-- END)", TEXT, re.S | re.M):
        tid, name, block = int(m[1]), m[2], m[3]
        rows, entries = _tables(block)
        out[tid] = {"name": name, "prefixed": "VarInt byte length, then the body" in block, "rows": rows,
                    "entries": entries, "rules": _rules(block)}
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
            raise DecodeError("truncated")
        v = 0
        for _ in range(n):
            v = (v << 1) | (self.data[self.pos // 8] >> (7 - self.pos % 8) & 1)
            self.pos += 1
        return v

    def align(self) -> None:
        pad = -self.pos % 8
        if self.read(pad):
            raise DecodeError("padding")


def _range(row: Row) -> tuple[float, float]:
    lo, _, hi = row["range"].partition("..")
    return float(lo), float(eval(hi.replace("^", "**"))) if hi else float(lo)


def _max_bytes(row: Row) -> int:
    """The most bytes a text or raw-bytes field holds: its range, ``0..32 bytes``."""
    m = re.fullmatch(r"0\.\.(\d+) bytes", row["range"])
    assert m, row
    return int(m[1])


def _max_code(row: Row) -> int | None:
    """The largest code a number's range allows (section 6), None when its bits are the limit."""
    if ".." not in row["range"]:
        return None  # a constant of the frame header: section 4's rules
    lo, hi = _range(row)
    res = float(row["resolution"] or 1)
    top = round((hi - lo) / res)
    return top + 1 if "optional: code 0 = absent" in row["description"] else top


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
        if n > _max_bytes(row):
            raise DecodeError("exceed")
        raw = bytes(bits.read(8) for _ in range(n))
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise DecodeError("utf-8") from None
    elif coding == "bytes":
        if width_text.isdigit():
            n = int(width_text) // 8
        else:
            counted = re.search(r"\(`(\w+)` bytes\)", desc)
            n = ctx[counted[1]] if counted else (len(bits.data) * 8 - bits.pos) // 8  # the rest of the body
            if n > _max_bytes(row):  # a count above it is its count's own range (above maximum)
                raise DecodeError("exceed")
        return bytes(bits.read(8) for _ in range(n)).hex()
    else:
        width = int(re.sub(r"^n x ", "", width_text))
    code = bits.read(width)
    if coding == "boolean":
        return bool(code)
    if coding == "optional boolean":
        if code == 3:
            raise DecodeError("optional boolean")
        return [None, False, True][code]
    if coding == "enum":
        members = dict(re.findall(r"(\d+) (\w+)", desc.split("(enum: ", 1)[1].split(";")[0]))
        if str(code) not in members:
            raise DecodeError("not a valid")
        return members[str(code)]
    if coding == "table index":
        table = dict(re.findall(r"(\d+) = ([\d.]+)", desc.split("(table: ", 1)[1]))
        return float(table[str(code)])
    if coding.startswith("IEEE 754"):
        value = struct.unpack(">f", code.to_bytes(4, "big"))[0]
        if not math.isfinite(value):
            raise DecodeError("non-finite")
        if code == 0x80000000:  # -0.0: zero has one encoding (section 6)
            raise DecodeError("canonical")
        return value
    if coding == "two's complement":
        return code - (1 << width) if code >> (width - 1) else code
    if coding.startswith("bit mask"):
        return code
    # unsigned / bounded: lo + code * res, an optional one with code 0 absent (section 13.1)
    top = _max_code(row)
    if top is not None and code > top:
        raise DecodeError("above maximum")
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
    """spec/payloads.md 1.3, with its canonical form: an escape only where the plain form does
    not fit, its length ``m`` the value's bit length."""
    q = 0
    while bits.read(1):
        q += 1
        if q == 16:
            m = bits.read(5)
            v = bits.read(m)
            if v >> k <= 15 or m != v.bit_length():
                raise DecodeError("canonical")
            return v
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
    """The coded cells of payloads.md 1.7, with the coder and the checks of the decoder written
    from that section (tests/spec_decoder/subgrids.py, itself from the document alone)."""
    from .spec_decoder import subgrids

    reader = subgrids.Bits(bits.data)
    reader.pos = bits.pos
    table = min(ctx["level"], 2) if ctx["context"] == "PARENT" else 3
    try:
        mask, residuals = subgrids.coded_cells(reader, int(ctx["side"]), bool(ctx["partial"]), int(ctx["shift"]),
                                               table)
    except subgrids.Invalid as exc:
        raise DecodeError(exc.args[0]) from None
    bits.pos = reader.pos
    return {"mask": mask, "residuals": residuals}


#: The conditions of the rules listed under the tables of section 11, as the document words them
#: (each checked once the fields it names in backquotes are decoded; the error word is the
#: document's). ``_bits`` holds how many bits each array took.
CONDITIONS: dict[str, Callable[[dict[str, Any]], bool]] = {
    "`kind` is LINE and `heading` or `length` is absent, or `kind` is LAWNMOWER and one of `heading`, "
    "`length`, `width`, `spacing` is absent":
        lambda f: (f["kind"] == "LINE" and None in (f["heading"], f["length"]))
        or (f["kind"] == "LAWNMOWER" and None in (f["heading"], f["length"], f["width"], f["spacing"])),
    "`points` has entries and `kind` is not WAYPOINTS": lambda f: bool(f["points"]) and f["kind"] != "WAYPOINTS",
    "`altitude` and `depth` are both given": lambda f: f["altitude"] is not None and f["depth"] is not None,
    "`has_detail` is 1 and `detail` has no bytes (no detail is `has_detail` = 0)":
        lambda f: f["has_detail"] == 1 and f["detail"] == "",
    "`width` is above `length`, both given (the length is the long axis; either alone is valid)":
        lambda f: f["width"] is not None and f["length"] is not None and f["width"] > f["length"],
    "the `values` take more than 1536 bits in all": lambda f: f["_bits"]["values"] > 1536,
    "`encoding` is GRADIENT and `partial` is 1 (a GRADIENT subgrid has no mask)":
        lambda f: f["encoding"] == "GRADIENT" and f["partial"] == 1,
    "`fill_gaps` is 0 and w*h is above 64": lambda f: not f["fill_gaps"] and f["w"] * f["h"] > 64,
    "`far` is 1 while `offset` is below 4096 (the long form of a short offset: one encoding per offset)":
        lambda f: f["far"] == 1 and f["offset"] < 4096,
    "the `packets` entries are not strictly increasing, or one is above the number of `data` bytes":
        lambda f: any(a >= b for a, b in zip(f["packets"], f["packets"][1:]))
        or any(p > f["n_data"] for p in f["packets"]),
    "`x0` >= `x1` or `y0` >= `y1` (no pixel in the region)": lambda f: f["x0"] >= f["x1"] or f["y0"] >= f["y1"],
    "`x0` >= `x1` or `y0` >= `y1` (no pixel in the crop)": lambda f: f["x0"] >= f["x1"] or f["y0"] >= f["y1"],
}


def _checks_after(rows: list[Row], rules: list[tuple[str, str]]) -> dict[str, list[tuple[str, str]]]:
    """Each rule under the field after which it is checked: the last row its condition names."""
    names = [r["field"].strip("`") for r in rows]
    out: dict[str, list[tuple[str, str]]] = {}
    for condition, word in rules:
        named = [n for n in re.findall(r"`(\w+)`", condition) if n in names]
        assert named, condition
        out.setdefault(max(named, key=names.index), []).append((condition, word))
    return out


def _fields(rows: list[Row], bits: Bits, entries: dict[str, list[Row]],
            rules: list[tuple[str, str]] | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """(the JSON fields of section 13.1, every decoded field)."""
    ctx: dict[str, Any] = {"_bits": {}}
    out: dict[str, Any] = {}
    checks = _checks_after(rows, rules or [])
    for row in rows:
        if row["field"] == "(padding)":
            bits.align()
            continue
        name = row["field"].strip("`")
        derived = "(derived)" in row["present"]
        start = bits.pos
        value: Any
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
        ctx["_bits"][name] = bits.pos - start
        if not derived:
            out[name] = value
        for condition, word in checks.get(name, []):
            if CONDITIONS[condition](ctx):
                raise DecodeError(word)
    return out, ctx


def _byte(data: bytes, pos: int) -> int:
    """The byte at ``pos``: an input that ends before it is truncated (section 13.2)."""
    if pos >= len(data):
        raise DecodeError("truncated")
    return data[pos]


def _varint(data: bytes, pos: int) -> tuple[int, int]:
    """Section 5: unsigned LEB128, its minimal encoding only."""
    v = shift = 0
    while True:
        b = _byte(data, pos)
        v |= (b & 0x7F) << shift
        pos, shift = pos + 1, shift + 7
        if not b & 0x80:
            if b == 0 and shift > 7:  # a last group of zeros: not the minimal encoding
                raise DecodeError("canonical")
            return v, pos


def decode_message(data: bytes, pos: int = 0) -> tuple[dict[str, Any], int]:
    """One message at ``pos``: (``{"type", "fields"}``, the position after it) (section 5)."""
    first = pos
    if pos >= len(data):
        raise DecodeError("empty")
    tid = data[pos]
    pos += 1
    if tid == 0:
        raise DecodeError("unknown message type")  # the end marker is never a message
    if tid & 0x80:
        tid = (tid & 0x7F) << 8 | _byte(data, pos)
        pos += 1
        if tid < 128:
            raise DecodeError("over-long")
    if tid >= 96:  # third party: a VarInt length and the body (13.1: Opaque)
        n, pos = _varint(data, pos)
        if pos + n - first > 251:
            raise DecodeError("above 251 bytes")
        if pos + n > len(data):
            raise DecodeError("truncated")
        return {"type": "Opaque", "fields": {"type_id": tid, "body": data[pos:pos + n].hex()}}, pos + n
    if tid not in MESSAGES:
        raise DecodeError("unknown message type")
    msg = MESSAGES[tid]
    if msg["prefixed"]:
        n, pos = _varint(data, pos)
        if pos + n - first > 251:
            raise DecodeError("above 251 bytes")
        if pos + n > len(data):
            raise DecodeError("truncated")
        body, end = data[pos:pos + n], pos + n
    else:
        body, end = data[pos:], None
    bits = Bits(body)
    fields, _ = _fields(msg["rows"], bits, msg["entries"], msg["rules"])
    if end is None:
        end = pos + bits.pos // 8
    elif bits.pos // 8 != n:
        raise DecodeError("canonical")  # bytes left over inside the length
    if end - first > 251:
        raise DecodeError("above 251 bytes")
    return {"type": msg["name"], "fields": fields}, end


def decode_one(data: bytes) -> dict[str, Any]:
    """An input checked as one message (section 13): nothing may follow it."""
    message, end = decode_message(data)
    if end != len(data):
        raise DecodeError("after the message")
    return message


def decode_frame(data: bytes) -> dict[str, Any]:
    """Sections 4 and 12."""
    if len(data) < 3:
        raise DecodeError("truncated")
    bits = Bits(data[:3])
    header, _ = _fields(HEADER[:-1], bits, {})
    if header["version"] != 1 or header["reserved"] != 0:
        raise DecodeError("bad frame header")
    pos = 3
    if header["crc"]:
        if len(data) < 5:
            raise DecodeError("truncated")
        checksum, pos = int.from_bytes(data[3:5], "big"), 5
    messages = []
    while pos < len(data) and data[pos] != 0:
        m, pos = decode_message(data, pos)
        messages.append({"type": m["type"], **m["fields"]})
    if any(data[pos:]):
        raise DecodeError("after the end marker")
    if header["crc"] and binascii.crc_hqx(data[:3] + data[5:pos], 0xFFFF) != checksum:
        raise DecodeError("crc mismatch")
    return {"header": {k: header[k] for k in ("src", "dst", "seq", "schedule", "crc")}, "messages": messages}


def answer(scope: str, hx: str) -> str:
    """One answer line of section 13.3: the JSON form, or ``{"error": WORD}``."""
    data = bytes.fromhex(hx)
    try:
        return json.dumps(decode_frame(data) if scope == "frame" else decode_one(data))
    except DecodeError as exc:
        return json.dumps({"error": exc.args[0]})


def test_the_document_has_every_message_the_vectors_have() -> None:
    names = {json.loads(p.read_text())["type"] for p in VECTORS.glob("*.json")
             if p.stem not in ("frames", "invalid", "cells")}
    assert names - {"Opaque"} == {m["name"] for m in MESSAGES.values()}


@pytest.mark.parametrize("path", sorted(p.name for p in VECTORS.glob("*.json") if p.stem not in ("invalid", "cells")))
def test_a_decoder_from_the_document_alone_agrees_with_the_vectors(path: str) -> None:
    cases = [c for c in specgen.vector_cases(VECTORS) if c[0].startswith(json.loads(
        (VECTORS / path).read_text()).get("type", "frames") + "/")]
    assert cases
    assert specgen.compare_answers(cases, "\n".join(answer(scope, hx) for _, scope, hx, _ in cases)) == []


INVALID = [c for c in specgen.vector_cases(VECTORS) if c[0].startswith("invalid/")]


def test_every_invalid_vector_is_checked() -> None:
    assert len(INVALID) == len(json.loads((VECTORS / "invalid.json").read_text())["vectors"]) >= 88


@pytest.mark.parametrize("case", INVALID, ids=[c[0] for c in INVALID])
def test_a_decoder_from_the_document_alone_rejects_the_invalid_vectors(
        case: tuple[str, str, str, dict[str, Any]]) -> None:
    """Each invalid vector (13.2) is rejected for its error word, by the document's rules alone."""
    _, scope, hx, _ = case
    assert specgen.compare_answers([case], answer(scope, hx)) == []


def test_the_rules_under_the_tables_are_the_ones_this_decoder_checks() -> None:
    """Every rule the document lists under a table has its condition here, and no other: a rule
    added to the document fails this until a second implementer could check it too."""
    listed = {condition for m in MESSAGES.values() for condition, _ in m["rules"]}
    assert listed == set(CONDITIONS)


def test_a_decoder_that_skips_a_rule_fails_its_vector(monkeypatch: pytest.MonkeyPatch) -> None:
    """The invalid vectors check the rules: without the empty-region rule, its vectors decode."""
    for condition in [c for c in CONDITIONS if c.startswith("`x0` >= `x1`")]:
        monkeypatch.setitem(CONDITIONS, condition, lambda f: False)
    region = [c for c in INVALID if c[0] == "invalid/region_empty_columns"]
    assert region
    assert specgen.compare_answers(region, answer(region[0][1], region[0][2])) != []
