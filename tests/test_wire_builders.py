"""The codec's one-step body builder (issue 55's speed) gives construct's own bytes for every
message: the golden vectors' and any the schemas allow."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

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


def _streams(con: Any) -> list[Any]:
    """The ``Restreamed`` streams in a construct."""
    import construct as cs

    found: list[Any] = []
    seen: set[int] = set()

    def walk(c: Any) -> None:
        if id(c) in seen:
            return
        seen.add(id(c))
        if isinstance(c, cs.Restreamed):
            found.append(c)
        for value in vars(c).values():
            for sub in (value.values() if isinstance(value, dict) else
                        value if isinstance(value, list | tuple) else (value,)):
                if isinstance(sub, cs.Construct):
                    walk(sub)
    walk(con)
    return found


@contextlib.contextmanager
def _constructs_conversions(con: Any) -> Iterator[None]:
    """Within: ``con``'s streams convert bits with construct's own functions again."""
    back = {fast: slow for slow, fast in _codec._FAST.items()}
    streams = _streams(con)
    saved = [(r.decoder, r.encoder) for r in streams]
    try:
        for r in streams:
            r.decoder, r.encoder = back.get(r.decoder, r.decoder), back.get(r.encoder, r.encoder)
        yield
    finally:
        for r, (dec, enc) in zip(streams, saved, strict=True):
            r.decoder, r.encoder = dec, enc


def _outcome(f: Any, arg: Any) -> tuple[str, Any]:
    try:
        return "value", f(arg)
    except Exception as exc:
        return type(exc).__name__, str(exc)


@settings(max_examples=300, deadline=None)
@given(any_message, st.binary(max_size=300), st.integers(0, 40))
def test_bit_lookups_parse_and_build_as_construct_does(message: Message, noise: bytes, cut: int) -> None:
    """The bodies' streams convert bits by lookups (``_codec._fast_conversions``): every body
    builds and parses (a message's own bytes, cut short, or noise) to what construct's own
    conversions give, errors included."""
    con = _BODIES[spec_for(message).type_id]
    container = _to_container(message)

    def run() -> list[tuple[str, Any]]:
        built = _outcome(con.build, container)
        data = built[1] if built[0] == "value" else b""
        return [built] + [_outcome(con.parse, raw) for raw in
                          (data, data[:max(len(data) - cut, 0)], noise, data + noise[:3])]
    fast = run()
    with _constructs_conversions(con):
        slow = run()
    assert fast == slow


def test_bit_lookups_are_constructs_conversions() -> None:
    """One byte or 8 bits by lookup, anything else by construct's own functions."""
    import construct as cs

    for i in range(256):
        b = bytes([i])
        assert _codec._bytes2bits(b) == cs.lib.bytes2bits(b)
        assert _codec._bits2bytes(cs.lib.bytes2bits(b)) == b
    for data in (b"", b"ab", bytearray(b"\x07")):
        assert _codec._bytes2bits(data) == cs.lib.bytes2bits(data)
    for bits in (b"", b"\x01" * 16, b"\x00\x01\x02\x00\x00\x00\x00\x00"):
        assert _outcome(_codec._bits2bytes, bits) == _outcome(cs.lib.bits2bytes, bits)
    with pytest.raises(ValueError):
        _codec._bits2bytes(b"\x01" * 7)
    streams = [r for con in _BODIES.values() for r in _streams(con)]  # every body's use the lookups
    assert streams and not [r for r in streams if r.decoder in _codec._FAST or r.encoder in _codec._FAST]
