"""The codec's one-step body builder (issue 55's speed) gives construct's own bytes for every
message: the golden vectors' and any the schemas allow."""

from __future__ import annotations

from typing import Any

from hypothesis import given, settings

from coex_core._wire import _codec
from coex_core._wire._codec import _BODIES, _BUILDERS, _to_container, spec_for
from coex_core.messages import Message

from .strategies import any_message


@settings(max_examples=300, deadline=None)
@given(any_message)
def test_body_builder_gives_constructs_bytes(message: Message) -> None:
    """The same bytes, or the same error for a value the schema refuses."""
    tid = spec_for(message).type_id
    container = _to_container(message)

    def run(build: Any) -> tuple[str, Any]:
        try:
            return "bytes", build(container)
        except Exception as exc:
            return type(exc).__name__, str(exc)
    assert run(_BUILDERS[tid]) == run(_BODIES[tid].build)


def test_every_body_has_the_fast_builder() -> None:
    """Every message body is a bit-packed one (else the fast path would quietly fall back)."""
    assert all(_BUILDERS[tid] != con.build for tid, con in _BODIES.items())
    assert _codec._bits_to_bytes(b"") == b"" and _codec._bits_to_bytes(b"\x00\x01" * 8) == b"\x55\x55"
