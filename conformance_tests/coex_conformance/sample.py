"""The conformance suite's sample third-party plugin: a counter modality that speaks only
third-party ids from the experimental block (spec/third-party-ids.md), as an out-of-tree plugin
would. The suite runs it beside the plugin under test to prove that routing keeps them apart.

Wire (its own bodies, big-endian):

* ``SAMPLE_DATA`` (32700): ``seq`` u16, ``n`` u8, then ``n`` u16 values (body length 3 + 2n).
* ``SAMPLE_ACK`` (32701, routine): ``n`` u8, then ``n`` u16 sequence numbers held.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from typing import Any, ClassVar

from coex import (
    DecodeError,
    EncodeError,
    Message,
    Modality,
    ModalityReceiver,
    ModalitySender,
    Product,
    RequestRejected,
    persistent,
)
from coex.messages import Opaque
from coex.wire import encoded_size

SAMPLE_DATA, SAMPLE_ACK = 32700, 32701
#: values per data message
CHUNK = 8


def decode_data(body: bytes) -> tuple[int, tuple[int, ...]]:
    """``(seq, values)`` of a data body; :class:`DecodeError` unless it is exactly well formed."""
    if len(body) < 3:
        raise DecodeError(f"sample data body of {len(body)} B is shorter than its 3-byte head")
    seq, n = struct.unpack(">HB", body[:3])
    if len(body) != 3 + 2 * n:
        raise DecodeError(f"sample data says {n} values but carries {len(body) - 3} B")
    return seq, struct.unpack(f">{n}H", body[3:])


def encode_data(seq: int, values: tuple[int, ...]) -> bytes:
    return struct.pack(f">HB{len(values)}H", seq, len(values), *values)


def decode_ack(body: bytes) -> tuple[int, ...]:
    if len(body) < 1 or len(body) != 1 + 2 * body[0]:
        raise DecodeError(f"sample ack body of {len(body)} B does not match its count")
    return struct.unpack(f">{body[0]}H", body[1:])


def encode_ack(seqs: tuple[int, ...]) -> bytes:
    return struct.pack(f">B{len(seqs)}H", len(seqs), *seqs)


@persistent("conformance-sample.Sender")
class SampleSender(ModalitySender):
    """Ingests lists of integers; sends them in chunks until each chunk is acked."""

    def __init__(self) -> None:
        self.chunks: dict[int, tuple[int, ...]] = {}
        self.acked_seqs: set[int] = set()
        self.sent_at: dict[int, float] = {}
        self._buffer: list[int] = []
        self.rto = 120.0

    def ingest(self, data: Any, now: float) -> None:
        self._buffer.extend(int(v) & 0xFFFF for v in data)
        while len(self._buffer) >= CHUNK:
            self.chunks[len(self.chunks)] = tuple(self._buffer[:CHUNK])
            del self._buffer[:CHUNK]

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        out: list[Message] = []
        for seq, values in self.chunks.items():
            if seq in self.acked_seqs or now - self.sent_at.get(seq, -1e18) < self.rto:
                continue
            msg = Opaque(SAMPLE_DATA, encode_data(seq, values))
            size = encoded_size(msg)
            if size > max_bytes:
                break
            out.append(msg)
            self.sent_at[seq] = now
            max_bytes -= size
        return out

    def handle(self, message: Message, now: float) -> list[Message]:
        if not (isinstance(message, Opaque) and message.type_id == SAMPLE_ACK):
            raise RequestRejected(f"the sample sender does not handle {type(message).__name__}")
        self.acked_seqs.update(s for s in decode_ack(message.body) if s in self.chunks)
        return []

    def pending_bytes(self) -> int:
        return sum(3 + 2 * len(v) for s, v in self.chunks.items() if s not in self.acked_seqs)


@persistent("conformance-sample.Receiver")
class SampleReceiver(ModalityReceiver):
    def __init__(self) -> None:
        self.values: dict[int, tuple[int, ...]] = {}
        self._to_ack: list[int] = []

    def receive(self, message: Message, now: float) -> list[Product]:
        if not (isinstance(message, Opaque) and message.type_id == SAMPLE_DATA):
            return []
        seq, values = decode_data(message.body)
        self.values[seq] = values
        self._to_ack.append(seq)
        return [Product("chunk", str(seq), 1, values)]

    def poll(self, now: float) -> list[Message]:
        out: list[Message] = []
        while self._to_ack:
            batch, self._to_ack = tuple(self._to_ack[:20]), self._to_ack[20:]
            out.append(Opaque(SAMPLE_ACK, encode_ack(batch)))
        return out

    def products(self) -> list[Product]:
        return [Product("chunk", str(s), 1, v) for s, v in sorted(self.values.items())]


class SampleModality(Modality):
    """Counts, in chunks of eight, acked by sequence number."""

    name: ClassVar[str] = "conformance-sample"
    message_ids: ClassVar[tuple[int, ...]] = (SAMPLE_DATA,)
    request_ids: ClassVar[tuple[int, ...]] = (SAMPLE_ACK,)
    routine: ClassVar[tuple[type[Message] | int, ...]] = (SAMPLE_ACK,)

    def sender(self, config: Mapping[str, Any] | None = None) -> ModalitySender:
        return SampleSender()

    def receiver(self, config: Mapping[str, Any] | None = None) -> ModalityReceiver:
        return SampleReceiver()

    @classmethod
    def decode_body(cls, type_id: int, body: bytes) -> Any:
        if type_id == SAMPLE_DATA:
            return decode_data(body)
        if type_id == SAMPLE_ACK:
            return decode_ack(body)
        raise DecodeError(f"the conformance sample declares no type id {type_id}")

    @classmethod
    def encode_body(cls, type_id: int, value: Any) -> bytes:
        if type_id == SAMPLE_DATA:
            return encode_data(*value)
        if type_id == SAMPLE_ACK:
            return encode_ack(value)
        raise EncodeError(f"the conformance sample declares no type id {type_id}")


def sample_inputs() -> list[tuple[float, Any]]:
    return [(5.0 * (i + 1), list(range(40 * i, 40 * i + 40))) for i in range(4)]


def sample_converged(sender: ModalitySender, receiver: ModalityReceiver) -> bool:
    assert isinstance(sender, SampleSender) and isinstance(receiver, SampleReceiver)
    return bool(sender.chunks) and receiver.values == sender.chunks and sender.acked_seqs == set(sender.chunks)
