"""Property tests of the codec: round trips, and only DecodeError for any input whatsoever."""

from __future__ import annotations

from pathlib import Path

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


def _error_words() -> set[str]:
    text = (Path(__file__).resolve().parents[1] / "spec" / "wire-format.md").read_text()
    table = text.split("### 13.2 Invalid inputs and their error words", 1)[1].split("### 13.3", 1)[0]
    return {row.split("|")[1].strip().strip("`") for row in table.splitlines() if row.startswith("| `")}


#: the error words of spec section 13.2
WORDS = _error_words()


def _only_decode_error(data: bytes) -> None:
    """Whatever the bytes, the codec raises only DecodeError, and it names the rule broken with
    an error word of section 13.2 (``DecodeError.reason``, also in its text)."""
    for fn in (wire.decode, wire.unpack, wire.unpack_frame):
        try:
            fn(data)
        except DecodeError as exc:
            assert exc.reason in WORDS, f"{fn.__name__}({data.hex()}): {exc} has reason {exc.reason!r}"
            assert exc.reason.lower() in str(exc).lower() or exc.reason == "truncated", str(exc)


@given(st.binary(max_size=300))
def test_random_bytes_raise_only_decode_error(data) -> None:  # type: ignore[no-untyped-def]
    _only_decode_error(data)


@given(any_message, st.data())
def test_truncated_and_mutated_raise_only_decode_error(m, data) -> None:  # type: ignore[no-untyped-def]
    encoded = _encodable(m)
    cut = data.draw(st.integers(0, len(encoded) - 1))
    with pytest.raises(DecodeError) as info:
        wire.decode(encoded[:cut])
    assert info.value.reason in WORDS, str(info.value)
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


def test_negative_zero_is_rejected_in_every_float32_whatever_was_decoded_before() -> None:
    """Zero has one encoding, +0.0 (spec section 6): the bits of -0.0 are rejected in every
    Float32 field (`canonical`), also after an equal message with +0.0 was encoded or decoded
    (the encoder's cache once made the verdict depend on that); an encoder writes +0.0 for -0.0
    and for a value that rounds to zero in binary32."""
    import struct

    from coex_core.messages import TimeSeriesChannel, TimeSeriesRequest

    def channel(lo: float, hi: float, res: float) -> bytes:
        body = bytes([0x08]) + struct.pack(">fff", lo, hi, res) + b"\x00\x00"
        return bytes([0x30, len(body)]) + body

    plus = channel(0.0, 0.0, 0.0)
    assert wire.decode(plus) == TimeSeriesChannel(1, "", "", 0.0, 0.0, 0.0)
    for args in ((-0.0, 0.0, 0.0), (0.0, -0.0, 0.0), (0.0, 0.0, -0.0), (-0.0, 1.0, 0.5)):
        for _ in range(2):  # the second time, +0.0's encoding is cached
            with pytest.raises(DecodeError) as info:
                wire.decode(channel(*args))
            assert info.value.reason == "canonical"
    request = wire.encode(TimeSeriesRequest(1, 0, 0, 0, 0.0))
    with pytest.raises(DecodeError, match="canonical"):
        wire.decode(request[:-4] + struct.pack(">f", -0.0))
    for zero in (-0.0, -1e-50, 1e-50):
        assert wire.encode(TimeSeriesRequest(1, 0, 0, 0, zero)) == request
        assert wire.encode(TimeSeriesChannel(1, "", "", zero, zero, zero)) == plus
    # every other finite value is valid, whatever it means: lo above hi, a negative resolution
    assert wire.decode(channel(5.0, 1.0, -0.5)) == TimeSeriesChannel(1, "", "", 5.0, 1.0, -0.5)
