"""The golden vectors, the spec document and the construct definitions agree."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from coex_conformance import WireVectorTests, vectors_dir
from coex_core._wire import spec as specgen
from coex_core._wire._primitives import Rule
from coex_core._wire._registry import SPECS_BY_ID

ROOT = Path(__file__).resolve().parent.parent


class TestCoreCodecVectors(WireVectorTests):
    """The reference codec passes the suite that any codec implementation runs."""


def test_vectors_are_current() -> None:
    """Regenerating the vectors from the schemas gives exactly the committed files."""
    d = ROOT / "spec" / "vectors"
    files = specgen.all_vector_files()
    assert sorted(p.name for p in d.glob("*.json")) == sorted(files)
    for name, doc in files.items():
        assert json.loads((d / name).read_text()) == doc, f"{name} is stale: run coex spec --write-vectors spec/vectors"


def test_spec_document_tables_are_current() -> None:
    assert not specgen.check_document(ROOT / "spec" / "wire-format.md"), "run: coex spec --write"


def test_every_message_type_has_three_vectors_and_is_in_the_spec() -> None:
    text = (ROOT / "spec" / "wire-format.md").read_text()
    for tid, spec in SPECS_BY_ID.items():
        doc = json.loads((vectors_dir() / f"{spec.name}.json").read_text())
        assert doc["type_id"] == tid
        assert len(doc["vectors"]) >= 3, spec.name
        assert f"### {tid}: {spec.name} " in text


def test_required_message_types_exist() -> None:
    names = {spec.name for spec in SPECS_BY_ID.values()}
    required = {
        "MapMetadata", "Subgrid", "MapRoiRequest", "ImageAnnounce", "ImageFragment", "ImageAck",
        "ImageGoal", "ImageByTimeRequest", "TransferProgress", "TimeSeriesChunk", "TimeSeriesRequest",
        "VehicleStatus", "QueueStatus", "QueueConfig", "ScheduleUpdate", "AuthTrailer",
    }
    assert required <= names


def test_invalid_vectors_cover_each_kind() -> None:
    reasons = {v["reason"] for v in json.loads((vectors_dir() / "invalid.json").read_text())["vectors"]}
    for kind in ("truncated", "unknown message type", "above maximum", "crc mismatch", "padding"):
        assert kind in reasons


def error_words() -> list[str]:
    """The error words of spec section 13.2, in the order of its table (one word a row)."""
    text = (ROOT / "spec" / "wire-format.md").read_text()
    table = text.split("### 13.2 Invalid inputs and their error words", 1)[1].split("### 13.3", 1)[0]
    return [row.split("|")[1].strip().strip("`") for row in table.splitlines() if row.startswith("| `")]


def _rules() -> list[tuple[str, Rule]]:
    out = []
    for spec in SPECS_BY_ID.values():
        stack = [spec.body]
        while stack:
            con = stack.pop()
            if isinstance(con, Rule):
                out.append((spec.name, con))
            stack += [c for c in (getattr(con, "subcons", None) or []) if c is not None]
            sub = getattr(con, "subcon", None)
            if sub is not None:
                stack.append(sub)
    return out


def test_every_error_word_of_the_vectors_is_defined_in_section_13() -> None:
    """Each invalid vector names its rule with a word section 13.2 defines (one word per row, no
    word twice); every word of the table has a vector; every decoding rule under a table has its
    word in section 13.2 and a vector that breaks it."""
    words = error_words()
    assert len(words) == len(set(words)), "a word twice in section 13.2"
    assert all("/" not in w for w in words), "one error word per row"
    vectors = json.loads((vectors_dir() / "invalid.json").read_text())["vectors"]
    used = {v["reason"] for v in vectors}
    # `context` is the answer to a cells line (13.3), not a rule of the wire: its vectors are cells'
    used |= {v["error"] for v in json.loads((vectors_dir() / "cells.json").read_text())["vectors"] if "error" in v}
    assert used <= set(words), sorted(used - set(words))
    assert set(words) <= used, f"error words without an invalid vector: {sorted(set(words) - used)}"
    rules = _rules()
    assert len(rules) >= 10
    for name, rule in rules:
        if rule.encode_only:
            assert rule.reason is None
            continue
        assert rule.reason in words, f"{name}: rule {rule.violation!r} has no error word of section 13.2"


def test_every_rule_under_a_table_states_the_violation() -> None:
    """Rules are listed under "A decoder MUST reject the message ... when:": each states the
    broken state, never the requirement (no "needs", "must", "exactly when", "not both")."""
    text = (ROOT / "spec" / "wire-format.md").read_text()
    for name, rule in _rules():
        low = rule.violation.lower()
        for requirement in ("needs", " must ", "exactly when", "not both", "only a "):
            assert requirement not in low, f"{name}: {rule.violation!r} reads as a requirement"
        line = f"- {rule.violation}" + ("" if rule.encode_only else f" — `{rule.reason}`")
        assert line in text, f"{name}: rule not in the spec as {line!r}"
    frag = text.split("### 33: ImageFragment", 1)[1].split("### 34", 1)[0]
    decoding, encoding = frag.split("An encoder MUST refuse a value when", 1)
    assert "`packet` is given without packet marks" in encoding and "`packet`" not in decoding.split(
        "A decoder MUST reject", 1)[1], "the packet rule is an encoder's rule, not a decoder's"


def test_a_valid_marked_fragment_meets_every_decoding_rule() -> None:
    """Read as a rejection rule, the old "`packet` is given exactly when there are packet marks"
    rejected every marked fragment: the marked vectors decode, and their packet is given."""
    marked = [v for v in json.loads((vectors_dir() / "ImageFragment.json").read_text())["vectors"]
              if v["fields"]["packets"]]
    assert len(marked) >= 3
    for v in marked:
        assert v["fields"]["packet"] is not None
        assert specgen.decode_line(f"message {v['hex']}")["fields"] == v["fields"]


def test_the_unassigned_builtin_ids_the_spec_lists_are_the_registrys() -> None:
    """Section 5 and section 13.2 list the built-in ids no message has; both lists are the
    registry's gaps, and an invalid vector rejects an id of each domain's gap."""
    from coex_core._wire._registry import BUILTIN_RANGE

    gaps = sorted(set(BUILTIN_RANGE) - set(SPECS_BY_ID))
    listed = "21..31, 40..47 and 52..63"  # 15: PositionFix (issue 56), 20: PredictedSubgrid (issue 54)
    expanded: set[int] = set()
    for part in listed.replace(" and ", ", ").split(", "):
        lo, _, hi = part.partition("..")
        expanded.update(range(int(lo), int(hi or lo) + 1))
    assert sorted(expanded) == gaps
    text = " ".join((ROOT / "spec" / "wire-format.md").read_text().split())
    assert f"today {listed}" in text.split("## 6.", 1)[0]
    assert "(21..31, 40..47, 52..63)" in text.split("### 13.2", 1)[1]
    rejected = {bytes.fromhex(v["hex"])[0] for v in json.loads((vectors_dir() / "invalid.json").read_text())["vectors"]
                if v["reason"] == "unknown message type"}
    for lo, hi in ((21, 31), (40, 47), (52, 63), (64, 95)):
        assert rejected & set(range(lo, hi + 1)), f"no invalid vector with an id in {lo}..{hi}"


def test_the_spec_says_which_messages_carry_a_length() -> None:
    """Section 5: a built-in message carries a VarInt length exactly when its table's framing
    line says so, and the section names those messages: the registry's length-prefixed types."""
    text = (ROOT / "spec" / "wire-format.md").read_text()
    section5 = " ".join(text.split("## 5.", 1)[1].split("## 6.", 1)[0].split())
    prefixed = sorted((s.type_id, s.name) for s in SPECS_BY_ID.values() if s.prefixed)
    assert prefixed == [(48, "TimeSeriesChannel"), (49, "TimeSeriesChunk")]
    for tid, name in prefixed:
        assert f"`{name}` ({tid})" in section5
        assert f"### {tid}: {name} " in text
    for spec in SPECS_BY_ID.values():
        head = text.split(f"### {spec.type_id}: {spec.name} ", 1)[1].split("| field |", 1)[0]
        framing = "VarInt byte length, then the body" if spec.prefixed else "self-delimiting bit-packed body"
        assert framing in head, spec.name
    # ImageFragment ends in raw bytes sized by a count, with no length
    assert not SPECS_BY_ID[33].prefixed and "`n_data`, not by a length" in section5


def test_the_json_form_has_exactly_the_tables_fields() -> None:
    """Section 13.1: a message's JSON keys are its table's fields without padding and derived
    rows (entries likewise), for every vector of every type."""
    for spec in SPECS_BY_ID.values():
        rows = specgen._rows(specgen._struct_of(spec.body))
        names = {n for n, fs, _, _ in rows if not n.startswith("(") and "(derived)" not in fs.presence}
        entries = {n: sub for n, fs, _, sub in rows if sub is not None}
        doc = json.loads((vectors_dir() / f"{spec.name}.json").read_text())
        for v in doc["vectors"]:
            assert set(v["fields"]) == names, f"{spec.name}/{v['name']}: {sorted(v['fields'])} != {sorted(names)}"
            for key, sub in entries.items():
                sub_names = {n for n, fs, _, _ in specgen._rows(sub) if "(derived)" not in fs.presence}
                for entry in v["fields"][key]:
                    assert set(entry) == sub_names, f"{spec.name}/{v['name']}.{key}"


def test_the_json_form_of_masks_absent_fields_and_third_party_messages() -> None:
    """Section 13.1 by example: bit masks are integers with the first wire bit most significant;
    absent fields are null and absent arrays []; a third-party message is Opaque, type_id, body."""
    sub = {v["name"]: v for v in json.loads((vectors_dir() / "Subgrid.json").read_text())["vectors"]}
    sparse = sub["sparse_mask"]
    assert sparse["fields"]["mask"] == 0b1011 << 60 and "partial" not in sparse["fields"]
    # the mask's first bit on the wire (cell 0) is the integer's most significant of side^2 bits
    data = bytes.fromhex(sparse["hex"])
    bits = "".join(format(b, "08b") for b in data[1:])
    start = 4 + 14 + 14 + 18 + 3 + 3 + 4 + 2 + 20 + 5 + 1  # up to and with `partial` (OFFSET: no slopes)
    assert int(bits[start:start + 64], 2) == sparse["fields"]["mask"]
    roi = {v["name"]: v["fields"] for v in json.loads((vectors_dir() / "MapRoiRequest.json").read_text())["vectors"]}
    assert roi["fill_gaps_holds_nothing"]["held"] == [] and roi["fill_gaps_holds_nothing"]["have"] == 0
    assert roi["single_missing"]["held"] == [None] and roi["single_missing"]["have"] is None
    frag = {v["name"]: v["fields"] for v in json.loads((vectors_dir() / "ImageFragment.json").read_text())["vectors"]}
    assert frag["inside_packet"]["packet"] is None and frag["inside_packet"]["packets"] == []
    opaque = json.loads((vectors_dir() / "Opaque.json").read_text())
    assert opaque["type"] == "Opaque" and opaque["type_id"] is None
    for v in opaque["vectors"]:
        assert set(v["fields"]) == {"type_id", "body"}
        assert specgen.decode_line(f"message {v['hex']}") == {"type": "Opaque", "fields": v["fields"]}
    assert {v["fields"]["type_id"] for v in opaque["vectors"]} >= {96, 127, 128, 32767}


def test_the_generated_tables_state_coding_presence_and_padding() -> None:
    """No '?' widths; signedness (coding), presence conditions and padding rows are generated."""
    text = (ROOT / "spec" / "wire-format.md").read_text()
    assert "| ? |" not in text and "only when the preceding flag is set" not in text
    assert "| `slope_x` | 12 | -2048..2047 | 1 |  | two's complement | when `encoding` = PLANE |" in text
    assert "| `have` | w*h |" in text and "| when `fill_gaps` = 1 |" in text
    assert "| `version` | 2 | 1 |" in text  # the frame header's constant, with its width
    frag = text.split("### 33: ImageFragment", 1)[1].split("### 34", 1)[0]
    rows = [r.split("|")[1].strip() for r in frag.splitlines() if r.startswith("| ")][2:]
    assert rows[-2:] == ["`data`", "(padding)"]  # data follows the packets without alignment


def test_spec_check_fails_when_a_generated_table_drifts(tmp_path: Path) -> None:
    doc = tmp_path / "wire-format.md"
    text = (ROOT / "spec" / "wire-format.md").read_text()
    doc.write_text(text.replace("| two's complement | when `encoding` = PLANE |", "| unsigned | always |", 1))
    assert specgen.check_document(doc)


def test_the_vector_checker_passes_the_reference_and_reports_a_wrong_decoder(tmp_path: Path) -> None:
    """`coex spec vectors --check-command CMD` against the reference decoder (what CI runs):
    every vector agrees; against a decoder that gets one field wrong and accepts one invalid
    input, both are reported and the exit code is 1."""
    import subprocess
    import sys

    ok = subprocess.run([sys.executable, "-m", "coex_core.cli", "spec", "vectors", "--vectors",
                         str(ROOT / "spec" / "vectors"), "--check-command",
                         f"{sys.executable} -m coex_core.cli spec decode"],
                        capture_output=True, text=True, timeout=300)
    assert ok.returncode == 0, ok.stdout + ok.stderr
    assert " 0 difference(s)" in ok.stdout
    wrong = tmp_path / "wrong.py"
    wrong.write_text(
        "import json, sys\n"
        "from coex_core._wire.spec import decode_line\n"
        "for line in sys.stdin:\n"
        "    out = decode_line(line)\n"
        "    if out.get('type') == 'CommandAck':\n"
        "        out['fields']['command_id'] += 1\n"
        "    if 'error' in out and 'GRADIENT' in out['error']:\n"
        "        out = {'type': 'Subgrid', 'fields': {}}\n"
        "    print(json.dumps(out))\n")
    bad = subprocess.run([sys.executable, "-m", "coex_core.cli", "spec", "vectors", "--vectors",
                          str(ROOT / "spec" / "vectors"), "--check-command", f"{sys.executable} {wrong}"],
                         capture_output=True, text=True, timeout=300)
    assert bad.returncode == 1
    assert "CommandAck/" in bad.stdout and "decoded" in bad.stdout
    assert "invalid/gradient_with_mask: accepted an invalid input (GRADIENT)" in bad.stdout


def _run_checker(tmp_path: Path, script: str) -> subprocess.CompletedProcess[str]:
    decoder = tmp_path / "decoder.py"
    decoder.write_text(script)
    return subprocess.run([sys.executable, "-m", "coex_core.cli", "spec", "vectors", "--vectors",
                           str(ROOT / "spec" / "vectors"), "--check-command", f"{sys.executable} {decoder}"],
                          capture_output=True, text=True, timeout=300)


def test_a_decoder_that_ignores_the_rejection_reasons_fails_coex_spec_vectors(tmp_path: Path) -> None:
    """A decoder that decodes every valid vector right but answers {"error": "xyz"} to every
    invalid one fails, with one difference per invalid vector; so does one that always answers a
    real error word (truncated)."""
    invalid = json.loads((vectors_dir() / "invalid.json").read_text())["vectors"]
    for word in ("xyz", "truncated"):
        r = _run_checker(tmp_path, (
            "import json, sys\n"
            "from coex_core._wire.spec import decode_line\n"
            "for line in sys.stdin:\n"
            "    out = decode_line(line)\n"
            f"    print(json.dumps({{'error': {word!r}}} if 'error' in out else out))\n"))
        assert r.returncode == 1, r.stdout[-2000:]
        wrong = [v for v in invalid if v["reason"] != word]
        cells = [v for v in json.loads((vectors_dir() / "cells.json").read_text())["vectors"]
                 if v.get("error", word) != word]
        assert f" {len(wrong) + len(cells)} difference(s)" in r.stdout, r.stdout[-500:]
        for v in wrong:
            assert f"invalid/{v['name']}: rejected for '{word}', but the input breaks the rule of '{v['reason']}'" \
                in r.stdout or len(wrong) > 50
    assert "rejected a valid input" not in r.stdout


def test_the_checker_compares_integers_exactly_and_other_numbers_within_the_tolerance() -> None:
    """Section 13.3: a 256-bit mask one off is a difference (binary64 would not see it); a number
    within 1e-9 * max(1, |a|, |b|) of a non-integer field agrees; booleans are not numbers."""
    cases = [c for c in specgen.vector_cases(vectors_dir())
             if c[0] in ("Subgrid/largest", "VehicleStatus/" + json.loads(
                 (vectors_dir() / "VehicleStatus.json").read_text())["vectors"][1]["name"])]
    assert len(cases) == 2
    sub, status = (c[3] for c in cases)
    mask_off = json.loads(json.dumps(sub))
    mask_off["fields"]["mask"] -= 1
    assert float(mask_off["fields"]["mask"]) == float(sub["fields"]["mask"])  # binary64 cannot tell
    near = json.loads(json.dumps(status))
    near["fields"]["x"] = status["fields"]["x"] * (1 + 5e-10) if status["fields"]["x"] else 5e-10
    far = json.loads(json.dumps(status))
    far["fields"]["x"] = status["fields"]["x"] + 1e-3  # 50000.001: beyond 5e-5
    answers = [json.dumps(a) for a in (mask_off, near)]
    problems = specgen.compare_answers(cases, "\n".join(answers))
    assert len(problems) == 1 and problems[0].startswith("Subgrid/largest: decoded"), problems
    assert len(specgen.compare_answers(cases, "\n".join([json.dumps(sub), json.dumps(far)]))) == 1
    assert specgen._same(True, True) and not specgen._same(1, True) and not specgen._same(True, 1)
    assert specgen._same(5.0, 5) and specgen._same(5, 5.0) and not specgen._same(5.5, 5)
