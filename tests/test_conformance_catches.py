"""The conformance suite fails, with a message naming the rule, on each broken plugin the
plugin-interoperability issue names: a receiver that raises IndexError on its own truncated
message, a sender that resends forever after everything was acknowledged, a lenient receiver
that accepts a body whose count disagrees with its length, a plugin that routes another's
messages, a receiver that refuses damaged input with RequestRejected, a body codec that decodes
ids its modality does not declare."""

from __future__ import annotations

import struct
from typing import Any, ClassVar

import pytest

from coex_conformance import ModalityTests
from coex_conformance.sample import (
    SAMPLE_DATA,
    SampleModality,
    SampleReceiver,
    SampleSender,
    sample_converged,
    sample_inputs,
)
from coex_core.errors import DecodeError, RequestRejected
from coex_core.messages import Message, Opaque
from coex_core.modality import ModalityReceiver, ModalitySender, Product

SUITE = ModalityTests()


class IndexErrorReceiver(SampleReceiver):
    """Reads the count and then indexes the values without checking the length."""

    def receive(self, message: Message, now: float) -> list[Product]:
        if not (isinstance(message, Opaque) and message.type_id == SAMPLE_DATA):
            return []
        body = message.body
        seq = body[0] << 8 | body[1]
        values = tuple(body[3 + 2 * i] << 8 | body[4 + 2 * i] for i in range(body[2]))
        self.values[seq] = values
        self._to_ack.append(seq)
        return []


class LenientReceiver(SampleReceiver):
    """Takes as many values as the body holds, whatever its count says."""

    def receive(self, message: Message, now: float) -> list[Product]:
        if not (isinstance(message, Opaque) and message.type_id == SAMPLE_DATA) or len(message.body) < 3:
            return []
        seq = struct.unpack(">H", message.body[:2])[0]
        n = (len(message.body) - 3) // 2
        self.values[seq] = struct.unpack(f">{n}H", message.body[3:3 + 2 * n])
        self._to_ack.append(seq)
        return []


class ChattySender(SampleSender):
    """Keeps resending every chunk each ``rto``, acknowledged or not."""

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        acked, self.acked_seqs = self.acked_seqs, set()
        try:
            return super().fill(max_bytes, now)
        finally:
            self.acked_seqs = acked


def variant(name: str, sender: type[SampleSender] = SampleSender,
            receiver: type[SampleReceiver] = SampleReceiver) -> SampleModality:
    class Broken(SampleModality):
        def sender(self, config: Any = None) -> ModalitySender:
            return sender()

        def receiver(self, config: Any = None) -> ModalityReceiver:
            return receiver()

    Broken.name = name
    return Broken()


def test_a_receiver_raising_index_error_on_a_truncated_message_fails_the_suite() -> None:
    m = variant("broken-index", receiver=IndexErrorReceiver)
    with pytest.raises(AssertionError, match=r"rule: a damaged message raises DecodeError only; the receiver "
                                             r"raised IndexError"):
        SUITE.test_receiver_raises_only_decode_error_on_damaged_messages(m, None, None, sample_inputs(), None)


def test_a_lenient_receiver_fails_the_suite() -> None:
    m = variant("broken-lenient", receiver=LenientReceiver)
    with pytest.raises(AssertionError, match="rule: the receiver rejects what the modality's decode_body rejects"):
        SUITE.test_receiver_raises_only_decode_error_on_damaged_messages(m, None, None, sample_inputs(), None)


def test_a_sender_that_never_goes_quiet_fails_the_suite() -> None:
    m = variant("broken-chatty", sender=ChattySender)
    with pytest.raises(AssertionError, match=r"rule: a converged sender goes quiet .* broken-chatty sent \d+ B"):
        SUITE.test_sender_goes_quiet_once_everything_is_acknowledged(
            m, None, None, sample_inputs(), sample_converged, None, 0.3, 4 * 3600.0, 1800.0, ())


def test_a_plugin_claiming_another_plugins_ids_fails_the_suite() -> None:
    """A plugin that declares the sample plugin's id as its own is refused by the node the
    suite builds, with the message naming both."""
    from coex_core.errors import ConfigError
    from coex_core.modality import Modality

    class Squatter(Modality):  # its own plugin, which took the sample's ids
        name: ClassVar[str] = "squatter"
        message_ids = SampleModality.message_ids
        request_ids = SampleModality.request_ids

        def sender(self, config: Any = None) -> ModalitySender:
            return SampleSender()

        def receiver(self, config: Any = None) -> ModalityReceiver:
            return SampleReceiver()

    with pytest.raises(ConfigError, match="'squatter' and 'conformance-sample' both claim"):
        SUITE.test_works_in_a_node_beside_every_other_plugin(
            Squatter(), None, None, sample_inputs(), sample_converged, None, 0.3, 4 * 3600.0, ())


def test_a_body_codec_that_does_not_round_trip_fails_the_suite() -> None:
    class Sloppy(SampleModality):
        name: ClassVar[str] = "sloppy"

        @classmethod
        def encode_body(cls, type_id: int, value: Any) -> bytes:
            return super().encode_body(type_id, value) + b"\0"

    with pytest.raises(AssertionError, match="rule: a third-party body re-encodes to the same bytes"):
        SUITE.test_bodies_re_encode_to_the_same_bytes(Sloppy(), None, None, sample_inputs(), None)


class RefusingReceiver(SampleReceiver):
    """Refuses a damaged chunk with RequestRejected (a sender's error), not DecodeError."""

    def receive(self, message: Message, now: float) -> list[Product]:
        try:
            return super().receive(message, now)
        except DecodeError as exc:
            raise RequestRejected(str(exc)) from exc


def test_a_receiver_raising_request_rejected_on_damaged_input_fails_the_suite() -> None:
    """docs/plugins.md: a receiver raises nothing but DecodeError on damaged input (only a
    sender may refuse a damaged request with RequestRejected)."""
    m = variant("broken-refusing", receiver=RefusingReceiver)
    with pytest.raises(AssertionError, match=r"rule: a damaged message raises DecodeError only; the receiver "
                                             r"raised RequestRejected"):
        SUITE.test_receiver_raises_only_decode_error_on_damaged_messages(m, None, None, sample_inputs(), None)


def test_a_body_codec_that_decodes_ids_it_does_not_declare_fails_the_suite() -> None:
    """decode_body takes any id it does not know for its ack (as the guide's codec once did)."""
    from coex_conformance.sample import decode_ack, decode_data

    class Careless(SampleModality):
        name: ClassVar[str] = "careless"

        @classmethod
        def decode_body(cls, type_id: int, body: bytes) -> Any:
            return decode_data(body) if type_id == SAMPLE_DATA else decode_ack(body)

    with pytest.raises(AssertionError, match="rule: decode_body raises DecodeError for an id the modality does "
                                             "not declare"):
        SUITE.test_body_codec_refuses_ids_it_does_not_declare(Careless(), None, None, sample_inputs(), None)


def test_the_unbroken_sample_passes_the_same_checks() -> None:
    m = SampleModality()
    SUITE.test_receiver_raises_only_decode_error_on_damaged_messages(m, None, None, sample_inputs(), None)
    SUITE.test_bodies_re_encode_to_the_same_bytes(m, None, None, sample_inputs(), None)
    SUITE.test_body_codec_refuses_ids_it_does_not_declare(m, None, None, sample_inputs(), None)


def test_every_suite_test_says_what_it_checks() -> None:
    """Every test of the conformance suite has a docstring (what a plugin author reads when it
    fails), and its assertions name the rule broken ("rule: ...")."""
    import inspect

    from coex_conformance import TransportTests, WireVectorTests

    for cls in (ModalityTests, TransportTests, WireVectorTests):
        for name, fn in inspect.getmembers(cls, inspect.isfunction):
            if name.startswith("test"):
                assert (fn.__doc__ or "").strip(), f"{cls.__name__}.{name} has no docstring"
                src = inspect.getsource(fn)
                if "assert " in src:
                    assert "rule:" in src or "self._" in src, f"{cls.__name__}.{name}: no rule message"
