"""Command authentication (spec section 10): truncated HMAC-SHA256 tags and monotonic counters.

Topside signs every frame of commands with :class:`CommandSigner`; the vehicle checks them with
:class:`CommandVerifier`, which rejects forged, replayed and unauthenticated commands with
:class:`~coex_core.errors.AuthenticationError` (the caller logs the rejection and answers
``CommandAck(status=UNAUTHENTICATED)`` where it can). Both are sans-I/O: the verifier's counter is
state the caller persists (``verifier.counter``) so that a restart cannot reopen old counters.

The tag is ``HMAC-SHA256(key, header[0:3] || messages before the trailer || 0x07 || counter)[:8]``
(the trailer's type id byte and its 4 counter bytes, big-endian). Cost: 13 bytes per frame.
"""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import Callable, Sequence

from . import wire
from .errors import AuthenticationError, ConfigError, DecodeError
from .messages import (
    AuthTrailer,
    FrameHeader,
    ImageAck,
    ImageByTimeRequest,
    ImageGoal,
    ImageRegionRequest,
    LinkControl,
    MapRoiRequest,
    Message,
    QueueConfig,
    ScheduleUpdate,
    SpareConfig,
    SurveyCommand,
    TimeSeriesAck,
    TimeSeriesRequest,
)

__all__ = ["COMMAND_TYPES", "TAG_BYTES", "TRAILER_BYTES", "CommandSigner", "CommandVerifier", "ReplayError",
           "is_command", "parse_key"]

TAG_BYTES = 8
TRAILER_BYTES = 13
MAX_COUNTER = 2**32 - 1
#: Topside-to-vehicle messages that change what the vehicle does: they must be authenticated.
COMMAND_TYPES: tuple[type[Message], ...] = (
    QueueConfig, ScheduleUpdate, LinkControl, ImageGoal, ImageByTimeRequest, MapRoiRequest,
    TimeSeriesRequest, ImageAck, TimeSeriesAck, SpareConfig, SurveyCommand, ImageRegionRequest,
)
_TRAILER_TYPE = wire.type_id(AuthTrailer)


class ReplayError(AuthenticationError):
    """A correctly signed frame whose counter is not newer than the last accepted one."""


def is_command(message: Message) -> bool:
    return isinstance(message, COMMAND_TYPES)


def parse_key(text: bytes) -> bytes:
    """The key of a key file's contents: hexadecimal (at least 32 hex digits, surrounding
    whitespace ignored) or else the raw bytes (at least 16). Raises :class:`ConfigError`."""
    stripped = text.strip()
    try:
        key = bytes.fromhex(stripped.decode("ascii"))
    except (UnicodeDecodeError, ValueError):
        key = text
    return _check_key(key)


def _check_key(key: bytes) -> bytes:
    if not isinstance(key, bytes) or len(key) < 16:
        raise ConfigError("the command key must be at least 16 bytes")
    return key


def _tag(key: bytes, signed: bytes, counter: int) -> bytes:
    data = signed + bytes([_TRAILER_TYPE]) + counter.to_bytes(4, "big")
    return hmac.new(key, data, hashlib.sha256).digest()[:TAG_BYTES]


class CommandSigner:
    """Topside: appends an :class:`AuthTrailer` to frames of commands."""

    def __init__(self, key: bytes, counter: int = 0) -> None:
        self._key = _check_key(key)
        if not 0 <= counter < MAX_COUNTER:
            raise ConfigError("counter out of range")
        self.counter = counter

    def pack(self, messages: Sequence[Message], budget: int, header: FrameHeader | None = None) -> bytes:
        """Like :func:`coex_core.wire.pack`, with the trailer (13 bytes of the budget) added."""
        header = header or FrameHeader()
        if self.counter >= MAX_COUNTER:
            raise ConfigError("command counter exhausted: configure a new key")
        self.counter += 1
        plain = wire.pack(list(messages), budget - TRAILER_BYTES, header)
        signed = plain[: wire.FRAME_HEADER_BYTES] + plain[wire.header_size(header):]
        trailer = AuthTrailer(self.counter, _tag(self._key, signed, self.counter))
        return wire.pack([*messages, trailer], budget, header)


class CommandVerifier:
    """Vehicle: checks frames and returns their messages, or raises :class:`AuthenticationError`.

    Frames without commands pass unchanged (status, acks of vehicle data are not commands).
    ``counter`` is the last accepted counter: persist it and pass it back after a restart."""

    def __init__(self, key: bytes, counter: int = 0) -> None:
        self._key = _check_key(key)
        self.counter = counter
        self.rejected = 0

    def unpack(self, frame: bytes) -> list[Message]:
        try:
            return self._unpack(frame)
        except AuthenticationError:
            self.rejected += 1
            raise

    def _unpack(self, frame: bytes) -> list[Message]:
        decoded = wire.unpack_frame(frame)  # DecodeError for corrupt frames
        return self._verify(frame, decoded.header, decoded.messages, is_command)

    def verify(self, frame: bytes, header: FrameHeader, messages: Sequence[Message],
               command: Callable[[Message], bool] = is_command) -> list[Message]:
        """Check an already decoded frame (``messages`` as :func:`coex_core.wire.unpack_frame`
        returned them); ``command`` says which messages need authentication (default:
        :func:`is_command`). Returns the messages without the trailer."""
        try:
            return self._verify(frame, header, messages, command)
        except AuthenticationError:
            self.rejected += 1
            raise

    def _verify(self, frame: bytes, header: FrameHeader, messages_in: Sequence[Message],
                command: Callable[[Message], bool]) -> list[Message]:
        messages = list(messages_in)
        trailers = [i for i, m in enumerate(messages) if isinstance(m, AuthTrailer)]
        if not trailers:
            if any(command(m) for m in messages):
                raise AuthenticationError("unauthenticated command rejected")
            return messages
        if trailers != [len(messages) - 1]:
            raise AuthenticationError("the AuthTrailer must be the last message and appear once")
        trailer = messages.pop()
        assert isinstance(trailer, AuthTrailer)
        signed = self._signed_bytes(frame, header, messages)
        expected = _tag(self._key, signed, trailer.counter)
        if not hmac.compare_digest(expected, trailer.tag):
            raise AuthenticationError("bad authentication tag (forged or corrupted command)")
        if trailer.counter <= self.counter:
            raise ReplayError(
                f"replayed command: counter {trailer.counter} <= last accepted {self.counter}")
        self.counter = trailer.counter
        return messages

    @staticmethod
    def _signed_bytes(frame: bytes, header: FrameHeader, messages: list[Message]) -> bytes:
        start = wire.header_size(header)
        body = b"".join(wire.encode(m) for m in messages)
        if frame[start:start + len(body)] != body:  # canonical decoding makes this hold
            raise DecodeError("frame body does not match its messages")
        return frame[: wire.FRAME_HEADER_BYTES] + body
