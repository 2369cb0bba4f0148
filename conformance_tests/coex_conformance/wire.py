"""Golden-vector checks any codec implementation can run.

The vectors are JSON files (``spec/vectors/*.json``, shipped in this package as ``vectors/``):

* one file per message type: ``{"type": NAME, "type_id": N, "vectors": [{"name", "fields", "hex"}]}``
  (``fields`` as :func:`coex.to_json` writes them, minus ``type``);
* ``frames.json``: ``{"vectors": [{"name", "header", "messages", "budget", "hex"}]}``;
* ``Opaque.json``: third-party messages in the same form, ``type_id`` null (the fields carry it);
* ``invalid.json``: ``{"vectors": [{"name", "scope", "hex", "error", "reason"}]}``: bytes every
  decoder must reject (``error`` is ``DecodeError``; ``reason`` the error word of spec section
  13.2, which the reference's ``DecodeError.reason`` is and its message contains);
* ``cells.json``: ``{"vectors": [{"name", "hex", "parent", "cells" | "error"}]}``: the elevations a
  receiver holding ``parent`` rebuilds from a subgrid (spec/payloads.md section 1), or ``error``
  ``context`` when it cannot.

Another implementation can read the JSON directly; a Python codec can subclass
:class:`WireVectorTests` and override the ``encode_message``/``decode_message`` fixtures.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from coex import (
    ContextMismatch,
    DecodeError,
    FrameHeader,
    from_json,
    parent_from_rows,
    subgrid_units,
    to_json,
    units_rows,
    wire,
)
from coex.messages import SubgridMessage


def vectors_dir() -> Path:
    """Where the golden vectors are: inside the installed package, or ``spec/vectors`` in a checkout."""
    here = Path(__file__).resolve().parent
    for candidate in (here / "vectors", here.parent.parent / "spec" / "vectors"):
        if (candidate / "invalid.json").exists():
            return candidate
    raise FileNotFoundError("CoEx golden vectors not found")


def load_vectors(kind: str = "messages") -> list[dict[str, Any]]:
    """``messages`` (every valid message vector, with its ``type``), ``frames``, ``invalid`` or
    ``cells``."""
    d = vectors_dir()
    if kind in ("frames", "invalid", "cells"):
        return list(json.loads((d / f"{kind}.json").read_text())["vectors"])
    out = []
    for path in sorted(d.glob("*.json")):
        if path.stem in ("frames", "invalid", "cells"):
            continue
        doc = json.loads(path.read_text())
        for v in doc["vectors"]:
            out.append({"type": doc["type"], "type_id": doc["type_id"], **v})
    return out


def _ids(vectors: list[dict[str, Any]]) -> list[str]:
    return [f"{v.get('type', 'frame')}-{v['name']}" for v in vectors]


MESSAGE_VECTORS = load_vectors("messages")
FRAME_VECTORS = load_vectors("frames")
INVALID_VECTORS = load_vectors("invalid")
CELLS_VECTORS = load_vectors("cells")


class WireVectorTests:
    """Every valid vector encodes to its hex and decodes to its fields; every invalid one is rejected."""

    @pytest.fixture
    def encode_message(self) -> Callable[[dict[str, Any]], bytes]:
        """Optional: encode a JSON message (``{"type": ..., fields}``) to bytes."""
        return lambda obj: wire.encode(from_json(obj))

    @pytest.fixture
    def decode_message(self) -> Callable[[bytes], dict[str, Any]]:
        """Optional: decode bytes to a JSON message; must raise for invalid input."""
        return lambda data: to_json(wire.decode(data))

    @pytest.fixture
    def rebuild_cells(self) -> Callable[[bytes, list[list[int | None]] | None], dict[str, Any]]:
        """Optional: the elevations (vertical units, rows south first, None where absent) a
        receiver holding the parent cells ``parent`` rebuilds from a subgrid's bytes, as
        ``{"cells": rows}``, or ``{"error": "context"}`` when it cannot (spec section 13.3)."""
        def rebuild(data: bytes, parent: list[list[int | None]] | None) -> dict[str, Any]:
            message = wire.decode(data)
            assert isinstance(message, SubgridMessage)
            try:
                return {"cells": units_rows(subgrid_units(message, None if parent is None else parent_from_rows(parent)))}
            except ContextMismatch:
                return {"error": "context"}

        return rebuild

    @pytest.fixture
    def decode_error(self) -> type[BaseException]:
        """Optional: the exception the decoder raises for invalid input. When it has a ``reason``
        attribute, that must be the vector's error word; otherwise its text must contain it."""
        return DecodeError

    @pytest.mark.parametrize("vector", MESSAGE_VECTORS, ids=_ids(MESSAGE_VECTORS))
    def test_encode_matches_vector(self, vector: dict[str, Any], encode_message: Callable[[dict[str, Any]], bytes]) -> None:
        """A valid vector's fields encode to exactly its bytes."""
        got = encode_message({"type": vector["type"], **vector["fields"]}).hex()
        assert got == vector["hex"], f"rule: fields encode to the vector's bytes; {vector['type']}/{vector['name']} gave {got}"

    @pytest.mark.parametrize("vector", MESSAGE_VECTORS, ids=_ids(MESSAGE_VECTORS))
    def test_decode_matches_vector(self, vector: dict[str, Any], decode_message: Callable[[bytes], dict[str, Any]]) -> None:
        """A valid vector's bytes decode to exactly its fields."""
        got = decode_message(bytes.fromhex(vector["hex"]))
        assert got == {"type": vector["type"], **vector["fields"]}, (
            f"rule: bytes decode to the vector's fields; {vector['type']}/{vector['name']} gave {got}")

    @pytest.mark.parametrize("vector", CELLS_VECTORS, ids=[v["name"] for v in CELLS_VECTORS])
    def test_cells_rebuilt_from_what_the_receiver_holds(
            self, vector: dict[str, Any],
            rebuild_cells: Callable[[bytes, list[list[int | None]] | None], dict[str, Any]]) -> None:
        """A subgrid rebuilds to the vector's elevations with the parent cells the receiver holds,
        or cannot be rebuilt with them (``context``: another parent than it was predicted from)."""
        got = rebuild_cells(bytes.fromhex(vector["hex"]), vector["parent"])
        if "error" in vector:
            assert got.get("error") == vector["error"], (
                f"rule: {vector['name']} cannot be rebuilt with that parent ({vector['error']}); got {got}")
        else:
            assert got.get("cells") == vector["cells"], f"rule: {vector['name']} rebuilds to the vector's cells"

    @pytest.mark.parametrize("vector", FRAME_VECTORS, ids=_ids(FRAME_VECTORS))
    def test_frames(self, vector: dict[str, Any]) -> None:
        """A frame vector's header and messages pack to its bytes, and unpack back."""
        header = FrameHeader(**vector["header"])
        messages = [from_json(m) for m in vector["messages"]]
        assert wire.pack(messages, vector["budget"], header).hex() == vector["hex"], (
            f"rule: a frame packs to the vector's bytes ({vector['name']})")
        frame = wire.unpack_frame(bytes.fromhex(vector["hex"]))
        assert frame.header == header and list(frame.messages) == messages, (
            f"rule: a frame unpacks to the vector's header and messages ({vector['name']})")

    @pytest.mark.parametrize("vector", INVALID_VECTORS, ids=_ids(INVALID_VECTORS))
    def test_invalid_rejected(
        self,
        vector: dict[str, Any],
        decode_message: Callable[[bytes], dict[str, Any]],
        decode_error: type[BaseException],
    ) -> None:
        """Every invalid vector is rejected with the decoder's error, for its stated reason
        (the error words of spec section 13)."""
        data = bytes.fromhex(vector["hex"])
        decoder = decode_message if vector.get("scope", "message") == "message" else (
            lambda d: wire.unpack_frame(d)
        )
        with pytest.raises(decode_error) as info:
            decoder(data)
        reason = getattr(info.value, "reason", None)
        if reason is not None:  # the error word itself (coex.DecodeError.reason)
            assert reason == vector["reason"], (
                f"rule: {vector['name']} is rejected for '{vector['reason']}'; the error's reason is "
                f"'{reason}': {info.value}")
        else:
            assert vector["reason"].lower() in str(info.value).lower(), (
                f"rule: {vector['name']} is rejected for '{vector['reason']}'; the error said: {info.value}")
