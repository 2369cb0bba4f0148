"""Command authentication: signed commands pass; forged, replayed, unauthenticated ones are rejected."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from coex_core import wire
from coex_core.auth import TRAILER_BYTES, CommandSigner, CommandVerifier
from coex_core.errors import AuthenticationError, ConfigError, DecodeError
from coex_core.messages import (
    AckStatus,
    CommandAck,
    FrameHeader,
    GoalKind,
    ImageGoal,
    MapRoiRequest,
    QueueConfig,
    VehicleMode,
    VehicleStatus,
)

KEY = b"0123456789abcdef-coex-test-key"
GOAL = ImageGoal(1, 17, GoalKind.FULL, 0)
ROI = MapRoiRequest(2, 0, 0, 0, 2, 1, False, (None, 100))


def test_signed_commands_are_accepted_once() -> None:
    signer, verifier = CommandSigner(KEY), CommandVerifier(KEY)
    frame = signer.pack([GOAL, ROI], 256, FrameHeader(src=1, dst=2, seq=4))
    assert wire.encoded_size(wire.unpack(frame)[-1]) == TRAILER_BYTES
    assert verifier.unpack(frame) == [GOAL, ROI]
    assert verifier.counter == 1
    with pytest.raises(AuthenticationError, match="replayed"):
        verifier.unpack(frame)
    assert verifier.rejected == 1
    assert verifier.unpack(signer.pack([GOAL], 64)) == [GOAL]


def test_crc_frames_are_signed_too() -> None:
    frame = CommandSigner(KEY).pack([GOAL], 64, FrameHeader(src=1, dst=2, crc=True))
    assert CommandVerifier(KEY).unpack(frame) == [GOAL]


def test_wrong_key_and_tampering_rejected() -> None:
    frame = CommandSigner(KEY).pack([QueueConfig(3, 4, True, None, None, None, None, None)], 64)
    with pytest.raises(AuthenticationError, match="tag"):
        CommandVerifier(b"another-key-of-16-bytes!").unpack(frame)
    # change the command (stream 4 -> 5) and keep the old tag: rejected
    forged = wire.pack([QueueConfig(3, 5, True, None, None, None, None, None), wire.unpack(frame)[-1]], 64)
    with pytest.raises(AuthenticationError):
        CommandVerifier(KEY).unpack(forged)


def test_unauthenticated_commands_rejected_but_status_passes() -> None:
    verifier = CommandVerifier(KEY)
    with pytest.raises(AuthenticationError, match="unauthenticated"):
        verifier.unpack(wire.pack([GOAL], 64))
    status = VehicleStatus(0, 0.0, 0.0, 10.0, None, 0.0, 0.0, 90, VehicleMode.SURVEY, 0)
    assert verifier.unpack(wire.pack([status, CommandAck(1, AckStatus.ACCEPTED)], 64)) == [
        status, CommandAck(1, AckStatus.ACCEPTED)]


def test_trailer_must_be_last() -> None:
    frame = CommandSigner(KEY).pack([GOAL], 64)
    msgs = wire.unpack(frame)
    with pytest.raises(AuthenticationError, match="last"):
        CommandVerifier(KEY).unpack(wire.pack([msgs[1], msgs[0]], 64))


def test_restart_keeps_counter() -> None:
    signer = CommandSigner(KEY)
    old = signer.pack([GOAL], 64)
    verifier = CommandVerifier(KEY)
    verifier.unpack(signer.pack([GOAL], 64))
    restarted = CommandVerifier(KEY, counter=verifier.counter)
    with pytest.raises(AuthenticationError):
        restarted.unpack(old)


def test_short_key_is_a_config_error() -> None:
    with pytest.raises(ConfigError):
        CommandSigner(b"short")


@given(st.binary(max_size=80))
def test_garbage_gives_only_typed_errors(data: bytes) -> None:
    try:
        CommandVerifier(KEY).unpack(data)
    except (DecodeError, AuthenticationError):
        pass


@given(st.integers(0, 40), st.integers(0, 7))
def test_any_bit_flip_is_detected(byte: int, bit: int) -> None:
    frame = bytearray(CommandSigner(KEY).pack([GOAL, ROI], 256, FrameHeader(src=1, dst=2)))
    byte %= len(frame)
    frame[byte] ^= 1 << bit
    with pytest.raises((DecodeError, AuthenticationError)):
        CommandVerifier(KEY).unpack(bytes(frame))
