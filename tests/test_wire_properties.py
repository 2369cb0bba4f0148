"""Property tests of the codec: round trips, and only DecodeError for any input whatsoever."""

from __future__ import annotations

import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from coex_core import wire
from coex_core.errors import DecodeError, EncodeError
from coex_core.messages import FrameHeader, Opaque

from .strategies import ALL_SPECS, any_message, message_strategy


def _encodable(m: object) -> bytes:
    try:
        return wire.encode(m)  # type: ignore[arg-type]
    except EncodeError:
        assume(False)
        raise


@pytest.mark.parametrize("spec", ALL_SPECS, ids=[s.name for s in ALL_SPECS])
def test_roundtrip_every_type(spec) -> None:  # type: ignore[no-untyped-def]
    @given(message_strategy(spec))
    def check(m):  # type: ignore[no-untyped-def]
        data = _encodable(m)
        assert len(data) <= wire.MAX_SIZES[spec.name] <= wire.MAX_MESSAGE_BYTES
        assert wire.decode(data) == m

    check()


@given(st.lists(any_message, max_size=5), st.integers(0, 15), st.integers(0, 15), st.integers(0, 255),
       st.integers(0, 15), st.booleans())
def test_frame_roundtrip(messages, src, dst, seq, schedule, crc) -> None:  # type: ignore[no-untyped-def]
    for m in messages:
        _encodable(m)
    header = FrameHeader(src=src, dst=dst, seq=seq, schedule=schedule, crc=crc)
    budget = wire.header_size(header) + sum(wire.encoded_size(m) for m in messages)
    frame = wire.pack(messages, budget, header)
    got = wire.unpack_frame(frame + bytes(7))  # zero padding after the messages is allowed
    assert got.header == header and list(got.messages) == messages
    with pytest.raises(EncodeError):
        wire.pack([*messages, Opaque(96, b"x")], budget, header)


@given(st.integers(96, 32767), st.binary(max_size=200))
def test_opaque_roundtrip(type_id, body) -> None:  # type: ignore[no-untyped-def]
    m = Opaque(type_id, body)
    assert wire.decode(wire.encode(m)) == m


def _only_decode_error(data: bytes) -> None:
    for fn in (wire.decode, wire.unpack, wire.unpack_frame):
        try:
            fn(data)
        except DecodeError:
            pass


@given(st.binary(max_size=300))
def test_random_bytes_raise_only_decode_error(data) -> None:  # type: ignore[no-untyped-def]
    _only_decode_error(data)


@given(any_message, st.data())
def test_truncated_and_mutated_raise_only_decode_error(m, data) -> None:  # type: ignore[no-untyped-def]
    encoded = _encodable(m)
    cut = data.draw(st.integers(0, len(encoded) - 1))
    with pytest.raises(DecodeError):
        wire.decode(encoded[:cut])
    mutated = bytearray(encoded)
    for _ in range(data.draw(st.integers(1, 4))):
        i = data.draw(st.integers(0, len(mutated) - 1))
        mutated[i] = data.draw(st.integers(0, 255))
    _only_decode_error(bytes(mutated))
    _only_decode_error(b"\x40\x00\x00" + bytes(mutated))


@given(any_message)
def test_decoded_bytes_are_canonical(m) -> None:  # type: ignore[no-untyped-def]
    """Whatever decodes re-encodes to the same bytes: one encoding per message."""
    data = _encodable(m)
    assert wire.encode(wire.decode(data)) == data


def test_non_bytes_input_is_a_decode_error() -> None:
    for bad in (None, "text", 5, [1, 2]):
        with pytest.raises(DecodeError):
            wire.decode(bad)  # type: ignore[arg-type]
        with pytest.raises(DecodeError):
            wire.unpack(bad)  # type: ignore[arg-type]


def test_encode_rejects_out_of_range_and_wrong_types() -> None:
    from coex_core.messages import CommandAck, VehicleMode, VehicleStatus

    with pytest.raises(EncodeError):
        wire.encode(VehicleStatus(0, 0.0, 0.0, 6000.1, None, 0.0, 0.0, 0, VehicleMode.IDLE, 0))
    with pytest.raises(EncodeError):
        wire.encode(CommandAck(256, 0))  # type: ignore[arg-type]
    with pytest.raises(EncodeError):
        wire.encode(Opaque(50, b""))  # not a third-party id
    with pytest.raises(EncodeError):
        wire.encode(object())  # type: ignore[arg-type]
