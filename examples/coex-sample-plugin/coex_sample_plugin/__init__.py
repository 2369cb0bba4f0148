"""A sample third-party CoEx modality: echo-sounder "pings" (time, range) sent as Opaque messages.

It shows everything a plugin author needs: a type id from the third-party range, a sender that
honours the byte budget, acks (the receiver acks the highest contiguous sequence number it holds),
retransmission of what is not acked, and the two-line conformance test in ``tests/``.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from typing import Any

from coex import (
    ConfigError,
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

PING_TYPE = 100  # third-party, one-byte form
ACK_TYPE = 101
RECORD = struct.Struct(">HIH")  # seq, time (s), range (cm)
MAX_RECORDS = 20

__all__ = ["PingModality", "PING_TYPE", "ACK_TYPE"]


def decode_pings(body: bytes) -> list[tuple[int, int, int]]:
    """The records of a ping body; :class:`DecodeError` unless it is whole records (1..20)."""
    if not body or len(body) % RECORD.size or len(body) > MAX_RECORDS * RECORD.size:
        raise DecodeError(f"a ping body is 1..{MAX_RECORDS} records of {RECORD.size} B, not {len(body)} B")
    return [RECORD.unpack_from(body, i) for i in range(0, len(body), RECORD.size)]


def sample_inputs() -> list[tuple[float, Any]]:
    """A minute of pings, one a second: ``(now, (time, range))``."""
    return [(10.0 + i, (10.0 + i, 20.0 + i / 10)) for i in range(60)]


def converged(sender: ModalitySender, receiver: ModalityReceiver) -> bool:
    """Topside holds every ping the vehicle took."""
    assert isinstance(sender, PingSender) and isinstance(receiver, PingReceiver)
    return len(receiver.records) == len(sender.records)


def conformance() -> Any:
    """Entry point ``coex.conformance: pings``: what ``coex plugins check pings`` runs it on."""
    from coex_conformance.companions import Companion

    return Companion("pings", PingModality, sample_inputs, converged)


@persistent("pings.Sender")  # saved with the node by a store (stable name, not module path)
class PingSender(ModalitySender):
    def __init__(self, resend_after: float = 30.0) -> None:
        self.records: dict[int, tuple[int, int]] = {}  # seq -> (time, range_cm)
        self.acked_below = 0
        self.sent_at: dict[int, float] = {}
        self.resend_after = resend_after

    def ingest(self, data: Any, now: float) -> None:
        t, rng = data
        if not (0 <= rng < 655.36):
            raise ConfigError(f"range {rng} m outside 0..655.35 m")
        seq = len(self.records)
        if seq >= 65536:
            raise ConfigError("sequence space exhausted")
        self.records[seq] = (int(t), round(rng * 100))

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        due = [s for s in sorted(self.records) if s >= self.acked_below
               and now - self.sent_at.get(s, -1e9) >= self.resend_after]
        out: list[Message] = []
        used = 0
        while due:
            n = min(len(due), MAX_RECORDS)
            while n:
                body = b"".join(RECORD.pack(s, *self.records[s]) for s in due[:n])
                msg = Opaque(PING_TYPE, body)
                if used + encoded_size(msg) <= max_bytes:
                    break
                n -= 1
            if not n:
                break
            out.append(msg)
            used += encoded_size(msg)
            for s in due[:n]:
                self.sent_at[s] = now
            due = due[n:]
        return out

    def handle(self, message: Message, now: float) -> list[Message]:
        if not (isinstance(message, Opaque) and message.type_id == ACK_TYPE and len(message.body) == 2):
            raise RequestRejected(f"pings sender does not handle {type(message).__name__}")
        (below,) = struct.unpack(">H", message.body)
        self.acked_below = max(self.acked_below, min(below, len(self.records)))
        return []

    def pending_bytes(self) -> int:
        return RECORD.size * max(0, len(self.records) - self.acked_below)


@persistent("pings.Receiver")
class PingReceiver(ModalityReceiver):
    def __init__(self) -> None:
        self.records: dict[int, tuple[int, int]] = {}
        self.version = 0

    def receive(self, message: Message, now: float) -> list[Product]:
        if not (isinstance(message, Opaque) and message.type_id == PING_TYPE):
            return []
        changed = False
        for seq, t, rng in decode_pings(message.body):  # DecodeError on a damaged body
            if seq not in self.records:
                self.records[seq] = (t, rng)
                changed = True
        if changed:
            self.version += 1
            return [self._product()]
        return []

    def contiguous(self) -> int:
        n = 0
        while n in self.records:
            n += 1
        return n

    def poll(self, now: float) -> list[Message]:
        return [Opaque(ACK_TYPE, struct.pack(">H", self.contiguous()))]

    def _product(self) -> Product:
        rows = [(seq, t, r / 100) for seq, (t, r) in sorted(self.records.items())]
        return Product("pings", "pings", self.version, rows, {"count": len(rows)})

    def products(self) -> list[Product]:
        return [self._product()] if self.records else []


class PingModality(Modality):
    name = "pings"
    version = "0.3.1"
    # the third-party ids it owns (spec/third-party-ids.md): a node routes these, and only
    # these, to it; the ack is routine (it does not hurry the sender's stream)
    message_ids = (PING_TYPE,)
    request_ids = (ACK_TYPE,)
    routine = (ACK_TYPE,)

    @classmethod
    def decode_body(cls, type_id: int, body: bytes) -> Any:
        """The body codec the conformance suite checks: strict, canonical, and only for the ids
        this modality declares (DecodeError for any other)."""
        if type_id == PING_TYPE:
            return decode_pings(body)
        if type_id != ACK_TYPE:
            raise DecodeError(f"pings declares no type id {type_id}")
        if len(body) != 2:
            raise DecodeError(f"a ping ack is 2 bytes, not {len(body)}")
        return struct.unpack(">H", body)[0]

    @classmethod
    def encode_body(cls, type_id: int, value: Any) -> bytes:
        if type_id == PING_TYPE:
            return b"".join(RECORD.pack(*r) for r in value)
        if type_id != ACK_TYPE:
            raise EncodeError(f"pings declares no type id {type_id}")
        return struct.pack(">H", value)

    def sender(self, config: Mapping[str, Any] | None = None) -> PingSender:
        return PingSender(**dict(config or {}))

    def receiver(self, config: Mapping[str, Any] | None = None) -> PingReceiver:
        return PingReceiver()
