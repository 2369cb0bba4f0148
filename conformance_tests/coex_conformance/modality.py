"""Abstract tests every modality plugin must pass (use with :class:`ModalityFixtures`)."""

from __future__ import annotations

import random
from collections.abc import Callable, Sequence
from typing import Any

import pytest

from coex_core import state, wire
from coex_core.errors import DecodeError, RequestRejected
from coex_core.messages import Message, VehicleMode, VehicleStatus
from coex_core.modality import Modality, ModalityReceiver, ModalitySender

from .harness import LinkedPair, ingest_all, run_until


def _foreign_message(modality: Modality) -> Message:
    status = VehicleStatus(0, 0.0, 0.0, 0.0, None, 0.0, 0.0, 0, VehicleMode.IDLE, 0)
    assert not modality.handles(status), "VehicleStatus must not belong to a modality"
    return status


class ModalityTests:
    """Round trip over a lossy link, byte-budget compliance, invalid input rejection."""

    def _pair(self, modality: Modality, sender_config: Any, receiver_config: Any, **kw: Any) -> LinkedPair:
        return LinkedPair(modality.sender(sender_config), modality.receiver(receiver_config), **kw)

    def test_declares_messages(self, modality: Modality) -> None:
        assert modality.name and isinstance(modality.name, str)
        assert modality.messages, "a modality declares the message types it sends"
        for cls in (*modality.messages, *modality.requests):
            assert issubclass(cls, Message)

    @pytest.mark.parametrize("budget", [0, 1, 5, 17, 32, 64, 100, 251])
    def test_fill_honours_budget(
        self, modality: Modality, sender_config: Any, sample_inputs: Sequence[tuple[float, Any]], budget: int
    ) -> None:
        sender = modality.sender(sender_config)
        now = ingest_all(sender, sample_inputs)
        for i in range(50):
            out = sender.fill(budget, now + 30.0 * (i + 1))
            sizes = [wire.encoded_size(m) for m in out]
            assert sum(sizes) <= budget, f"fill({budget}) returned {sum(sizes)} B"
            for m in out:
                assert isinstance(m, modality.messages), f"{type(m).__name__} not in Modality.messages"
            if not out and budget >= 64:
                break

    @pytest.mark.parametrize("budget", [0, 1, 17, 64, 251])
    def test_spare_honours_budget_and_fill_s_contract(
        self, modality: Modality, sender_config: Any, sample_inputs: Sequence[tuple[float, Any]], budget: int
    ) -> None:
        """Spare work (``ModalitySender.spare``, optional) returns a list of the modality's own
        messages within the budget, before and after the sender has sent everything, and its
        estimates (``spare_bytes``, ``ready_bytes``) are non-negative integers."""
        sender = modality.sender(sender_config)
        now = ingest_all(sender, sample_inputs)
        for i in range(30):
            t = now + 30.0 * (i + 1)
            sender.fill(240, t)
            out = sender.spare(budget, t)
            assert isinstance(out, list), f"spare returned {type(out).__name__}"
            sizes = [wire.encoded_size(m) for m in out]
            assert sum(sizes) <= budget, f"spare({budget}) returned {sum(sizes)} B"
            for m in out:
                assert isinstance(m, modality.messages), f"{type(m).__name__} not in Modality.messages"
            for n in (sender.spare_bytes(), sender.ready_bytes(t)):
                assert isinstance(n, int) and n >= 0

    def test_delivery_hooks_accept_every_own_message(
        self, modality: Modality, sender_config: Any, sample_inputs: Sequence[tuple[float, Any]]
    ) -> None:
        """The channel tells a sender which of its messages arrived (``acked``) and which were
        lost (``lost``); both take any message the sender produced, in any order, more than
        once, without raising, and the sender keeps working."""
        sender = modality.sender(sender_config)
        now = ingest_all(sender, sample_inputs)
        sent: list[Message] = []
        for i in range(20):
            t = now + 30.0 * (i + 1)
            sent += sender.fill(240, t) + sender.spare(240, t)
        assert sent, "the sender produced nothing from the sample inputs"
        rng = random.Random(3)
        t = now + 700.0
        for m in rng.sample(sent, len(sent)):
            (sender.lost if rng.random() < 0.5 else sender.acked)(m, t)
            sender.lost(m, t)
        for m in sent[: len(sent) // 2]:
            sender.acked(m, t + 1.0)
        out = sender.fill(240, t + 30.0) + sender.spare(240, t + 30.0)
        assert sum(wire.encoded_size(m) for m in out) <= 480

    def test_messages_roundtrip_on_the_wire(
        self, modality: Modality, sender_config: Any, sample_inputs: Sequence[tuple[float, Any]]
    ) -> None:
        sender = modality.sender(sender_config)
        now = ingest_all(sender, sample_inputs)
        seen = 0
        for i in range(200):
            for m in sender.fill(240, now + 30.0 * (i + 1)):
                assert wire.decode(wire.encode(m)) == m
                seen += 1
        assert seen, "the sender produced nothing from the sample inputs"

    def test_converges_over_lossy_link(
        self,
        modality: Modality,
        sender_config: Any,
        receiver_config: Any,
        sample_inputs: Sequence[tuple[float, Any]],
        converged: Callable[[ModalitySender, ModalityReceiver], bool],
        start_requests: Callable[[ModalityReceiver, float], None] | None,
        loss: float,
        frame_budget: int,
        max_rounds: int,
        round_seconds: float,
    ) -> None:
        pair = self._pair(modality, sender_config, receiver_config, loss=loss, frame_budget=frame_budget,
                          round_seconds=round_seconds, seed=7)
        pair.now = ingest_all(pair.sender, sample_inputs)
        if start_requests is not None:
            start_requests(pair.receiver, pair.now)
        run_until(pair, lambda: converged(pair.sender, pair.receiver), max_rounds)
        assert pair.receiver.products(), "a converged receiver has products"

    def test_state_survives_a_restart(
        self,
        modality: Modality,
        sender_config: Any,
        receiver_config: Any,
        sample_inputs: Sequence[tuple[float, Any]],
        converged: Callable[[ModalitySender, ModalityReceiver], bool],
        start_requests: Callable[[ModalityReceiver, float], None] | None,
        loss: float,
        frame_budget: int,
        max_rounds: int,
        round_seconds: float,
    ) -> None:
        """A node store saves the sender and the receiver mid-transfer with
        :mod:`coex_core.state` (every class they keep must be registered with
        ``coex_core.state.persistent``) and journals the inputs; restored, they hold the same
        products, and the transfer still converges."""
        pair = self._pair(modality, sender_config, receiver_config, loss=loss, frame_budget=frame_budget,
                          round_seconds=round_seconds, seed=9)
        # the inputs as a store journals them and replays them: saved, loaded, then ingested
        journaled = [(now, state.loads(state.dumps(pair.sender.journal_form(data))))
                     for now, data in sample_inputs]
        pair.now = ingest_all(pair.sender, journaled)
        if start_requests is not None:
            start_requests(pair.receiver, pair.now)
        for _ in range(3):
            pair.step()
        before = [(p.kind, p.key, p.version) for p in pair.receiver.products()]
        pair.sender = state.loads(state.dumps(pair.sender))
        pair.receiver = state.loads(state.dumps(pair.receiver))
        assert [(p.kind, p.key, p.version) for p in pair.receiver.products()] == before
        run_until(pair, lambda: converged(pair.sender, pair.receiver), max_rounds)

    def test_receiver_tolerates_duplicates_and_reordering(
        self,
        modality: Modality,
        sender_config: Any,
        receiver_config: Any,
        sample_inputs: Sequence[tuple[float, Any]],
    ) -> None:
        sender = modality.sender(sender_config)
        now = ingest_all(sender, sample_inputs)
        produced: list[Message] = []
        for i in range(100):
            produced.extend(sender.fill(240, now + 30.0 * (i + 1)))
        receiver = modality.receiver(receiver_config)
        shuffled = produced + produced[::-1]
        random.Random(3).shuffle(shuffled)
        for m in shuffled:
            receiver.receive(m, now + 4000.0)
        receiver.poll(now + 4000.0)
        receiver.products()

    def test_sender_rejects_foreign_request(
        self, modality: Modality, sender_config: Any, sample_inputs: Sequence[tuple[float, Any]]
    ) -> None:
        sender = modality.sender(sender_config)
        now = ingest_all(sender, sample_inputs)
        with pytest.raises(RequestRejected):
            sender.handle(_foreign_message(modality), now)

    def test_corrupted_messages_raise_decode_error(
        self, modality: Modality, sender_config: Any, sample_inputs: Sequence[tuple[float, Any]]
    ) -> None:
        sender = modality.sender(sender_config)
        now = ingest_all(sender, sample_inputs)
        rng = random.Random(11)
        samples = [wire.encode(m) for i in range(20) for m in sender.fill(240, now + 30.0 * (i + 1))]
        assert samples
        for data in samples:
            variants = [data[:k] for k in range(len(data))]
            for _ in range(20):
                b = bytearray(data)
                b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
                variants.append(bytes(b))
            for v in variants:
                try:
                    wire.decode(v)
                except DecodeError:
                    pass
