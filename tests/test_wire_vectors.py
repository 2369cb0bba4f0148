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
