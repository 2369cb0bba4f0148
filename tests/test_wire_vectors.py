"""The golden vectors, the spec document and the construct definitions agree."""

from __future__ import annotations

import json
from pathlib import Path

from coex_conformance import WireVectorTests, vectors_dir
from coex_core._wire import spec as specgen
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


def test_every_error_word_of_the_vectors_is_defined_in_section_13() -> None:
    """Each invalid vector names its rule with a word section 13 defines; each rule the tables
    state under a message has a vector (the reference rejects everything the spec calls invalid)."""
    text = (ROOT / "spec" / "wire-format.md").read_text()
    table = text.split("## 13. Golden vectors", 1)[1].split("### Checking another implementation", 1)[0]
    defined = {w for row in table.splitlines() if row.startswith("| `")
               for w in row.split("|")[1].replace("`", "").split(" / ")}
    defined = {w.strip() for w in defined}
    vectors = json.loads((vectors_dir() / "invalid.json").read_text())["vectors"]
    assert {v["reason"] for v in vectors} <= defined
    for word in ("canonical", "out of order", "non-finite", "utf-8", "too large", "too many", "GRADIENT"):
        assert word in {v["reason"] for v in vectors}, word


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
