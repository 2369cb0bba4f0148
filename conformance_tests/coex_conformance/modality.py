"""Abstract tests every modality plugin must pass (use with :class:`ModalityFixtures`)."""

from __future__ import annotations

import random
from collections.abc import Callable, Sequence
from typing import Any

import pytest

from coex import (
    ConfigError,
    DecodeError,
    EncodeError,
    Message,
    Modality,
    ModalityReceiver,
    ModalitySender,
    RequestRejected,
    state,
    wire,
)
from coex.messages import Opaque, VehicleMode, VehicleStatus
from coex.routing import declared_ids, routine_ids, type_id

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
        """A modality has a name and declares what it sends: built-in types (``messages``) or
        third-party ids (``message_ids``), and its requests; the ids are third-party ids, and
        ``routine`` names only its own requests."""
        cls = type(modality)
        assert modality.name and isinstance(modality.name, str), "rule: a modality has a name (a string)"
        try:
            sends = declared_ids(cls, "messages")
            asks = declared_ids(cls, "requests")
            routine = routine_ids(cls)
        except ConfigError as exc:
            raise AssertionError(f"rule: declared ids are third-party type ids (96..32767); {exc}") from exc
        assert sends, (
            "rule: a modality declares the messages it sends (messages or message_ids)")
        for t in (*modality.messages, *modality.requests):
            assert isinstance(t, type) and issubclass(t, Message), f"rule: messages and requests are Message types; {t!r}"
        assert routine <= asks, (f"rule: routine names the modality's own requests; "
                                 f"{sorted(routine - asks)} are not among its requests")

    @staticmethod
    def _sends_own(modality: Modality, m: Message) -> bool:
        tid = type_id(m)
        cls = type(modality)
        return tid is not None and tid in declared_ids(cls, "messages")

    @pytest.mark.parametrize("budget", [0, 1, 5, 17, 32, 64, 100, 251])
    def test_fill_honours_budget(
        self, modality: Modality, sender_config: Any, sample_inputs: Sequence[tuple[float, Any]], budget: int
    ) -> None:
        """``fill(max_bytes)`` never returns more than ``max_bytes`` encoded bytes (0, 1 and
        tiny budgets included), and only the modality's own messages."""
        sender = modality.sender(sender_config)
        now = ingest_all(sender, sample_inputs)
        for i in range(50):
            out = sender.fill(budget, now + 30.0 * (i + 1))
            sizes = [wire.encoded_size(m) for m in out]
            assert sum(sizes) <= budget, f"rule: fill honours its byte budget; fill({budget}) returned {sum(sizes)} B"
            for m in out:
                assert self._sends_own(modality, m), (
                    f"rule: a sender sends only the messages its modality declares; {m!r:.120}")
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
            assert isinstance(out, list), f"rule: spare returns a list; it returned {type(out).__name__}"
            sizes = [wire.encoded_size(m) for m in out]
            assert sum(sizes) <= budget, f"rule: spare honours its byte budget; spare({budget}) returned {sum(sizes)} B"
            for m in out:
                assert self._sends_own(modality, m), (
                    f"rule: a sender sends only the messages its modality declares; {m!r:.120}")
            for n in (sender.spare_bytes(), sender.ready_bytes(t)):
                assert isinstance(n, int) and n >= 0, f"rule: spare_bytes and ready_bytes are integers >= 0; got {n!r}"

    def test_delivery_hooks_accept_every_own_message(
        self, modality: Modality, sender_config: Any, sample_inputs: Sequence[tuple[float, Any]]
    ) -> None:
        """The channel tells a sender which of its messages arrived (``acked``) and which were
        lost (``lost``); both take any message the sender produced, in any order, more than
        once, without raising, and the sender keeps working."""
        sender = modality.sender(sender_config)
        for hook in ("acked", "lost", "spare", "spare_bytes", "ready_bytes", "pending_bytes", "focus", "throughput",
                     "bind_peers", "peer", "detector_view"):
            assert callable(getattr(sender, hook, None)), (
                f"rule: the channel calls the sender's {hook}(); an attribute of that name hides it")
        now = ingest_all(sender, sample_inputs)
        sent: list[Message] = []
        for i in range(20):
            t = now + 30.0 * (i + 1)
            sent += sender.fill(240, t) + sender.spare(240, t)
        assert sent, "rule: the sender produces messages from the sample inputs; it produced none"
        rng = random.Random(3)
        t = now + 700.0
        for m in rng.sample(sent, len(sent)):
            (sender.lost if rng.random() < 0.5 else sender.acked)(m, t)
            sender.lost(m, t)
        for m in sent[: len(sent) // 2]:
            sender.acked(m, t + 1.0)
        out = sender.fill(240, t + 30.0) + sender.spare(240, t + 30.0)
        assert sum(wire.encoded_size(m) for m in out) <= 480, (
            "rule: after any acked/lost notifications the sender still honours its budgets")

    def test_messages_roundtrip_on_the_wire(
        self, modality: Modality, sender_config: Any, sample_inputs: Sequence[tuple[float, Any]]
    ) -> None:
        """Every message the sender produces encodes and decodes back to an equal message."""
        sender = modality.sender(sender_config)
        now = ingest_all(sender, sample_inputs)
        seen = 0
        for i in range(200):
            for m in sender.fill(240, now + 30.0 * (i + 1)):
                assert wire.decode(wire.encode(m)) == m, f"rule: a message survives the wire; {m!r:.160} did not"
                seen += 1
        assert seen, "rule: the sender produces messages from the sample inputs; it produced none"

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
        """A sender and a receiver joined by a lossy link (``loss``, 30 % by default, both
        directions; one ``frame_budget`` frame each way per round) converge within
        ``max_rounds``, and the receiver then has products."""
        pair = self._pair(modality, sender_config, receiver_config, loss=loss, frame_budget=frame_budget,
                          round_seconds=round_seconds, seed=7)
        pair.now = ingest_all(pair.sender, sample_inputs)
        if start_requests is not None:
            start_requests(pair.receiver, pair.now)
        run_until(pair, lambda: converged(pair.sender, pair.receiver), max_rounds)
        assert pair.receiver.products(), "rule: a converged receiver has products; it has none"

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
        :mod:`coex.state` (every class they keep must be registered with
        ``coex.persistent``) and journals the inputs; restored, they hold the same
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
        """The receiver takes its messages twice and in random order without raising."""
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
        """A request that is not the modality's is refused with RequestRejected."""
        sender = modality.sender(sender_config)
        now = ingest_all(sender, sample_inputs)
        try:
            sender.handle(_foreign_message(modality), now)
        except RequestRejected:
            return
        raise AssertionError("rule: a sender refuses a foreign request with RequestRejected; it took a VehicleStatus")

    def test_corrupted_messages_raise_decode_error(
        self, modality: Modality, sender_config: Any, sample_inputs: Sequence[tuple[float, Any]]
    ) -> None:
        """Truncated and bit-flipped encodings of the sender's messages raise DecodeError from
        ``coex.wire.decode``, nothing else."""
        sender = modality.sender(sender_config)
        now = ingest_all(sender, sample_inputs)
        rng = random.Random(11)
        samples = [wire.encode(m) for i in range(20) for m in sender.fill(240, now + 30.0 * (i + 1))]
        assert samples, "rule: the sender produces messages from the sample inputs; it produced none"
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
                except Exception as exc:
                    raise AssertionError(f"rule: wire.decode raises DecodeError only; {type(exc).__name__} "
                                         f"on {v.hex()}") from exc

    # ------------------------------------------------------------------ in a real node
    def _node_run(self, modality: Modality, sender_config: Any, receiver_config: Any,
                  sample_inputs: Sequence[tuple[float, Any]], converged: Any, start_requests: Any,
                  loss: float, node_converge_seconds: float, other_plugins: Sequence[Any] = ()) -> Any:
        from .noderun import NodeRun

        run = NodeRun(modality, sender_config, receiver_config, sample_inputs, converged, start_requests, loss,
                      others=other_plugins)
        run.run_until_converged(node_converge_seconds)
        late = [p.name for p in run.parts if p.converged_at is None]
        assert not late, (f"rule: every plugin converges in a node beside the others; not converged after "
                          f"{node_converge_seconds:.0f} s at {loss:.0%} loss: {', '.join(late)}")
        return run

    def test_works_in_a_node_beside_every_other_plugin(
        self, modality: Modality, sender_config: Any, receiver_config: Any,
        sample_inputs: Sequence[tuple[float, Any]], converged: Any, start_requests: Any, loss: float,
        node_converge_seconds: float, other_plugins: Sequence[Any],
    ) -> None:
        """The plugin under test, the sample third-party plugin and every built-in modality run
        in two real nodes (vehicle senders, topside receivers) over a lossy simulated acoustic
        link with a TDMA schedule: all of them converge, every message reaches the modality that
        declared it and no other, none is left unrouted, and neither node rejects anything."""
        run = self._node_run(modality, sender_config, receiver_config, sample_inputs, converged,
                             start_requests, loss, node_converge_seconds, other_plugins)
        misrouted = [m for p in run.parts for m in p.misrouted]
        assert not misrouted, ("rule: a node hands a modality only the messages it declares "
                               "(messages, requests, message_ids, request_ids); " + "; ".join(misrouted[:5]))
        assert not run.unrouted, ("rule: every message a modality declares reaches it; " + "; ".join(run.unrouted[:5]))
        for node in (run.vehicle, run.topside):
            assert node.stats["rejected"] == 0, (
                f"rule: nothing is rejected between conforming plugins; node {node.node_id} rejected "
                f"{node.stats['rejected']} message(s)")

    def test_sender_goes_quiet_once_everything_is_acknowledged(
        self, modality: Modality, sender_config: Any, receiver_config: Any,
        sample_inputs: Sequence[tuple[float, Any]], converged: Any, start_requests: Any, loss: float,
        node_converge_seconds: float, settle_seconds: float, other_plugins: Sequence[Any],
    ) -> None:
        """After convergence and the acks that follow it (``settle_seconds``), the sender of the
        plugin under test sends at most its declared ``keepalive_bytes_per_hour`` over the next
        hour (spare traffic on): it never resends what topside holds."""
        run = self._node_run(modality, sender_config, receiver_config, sample_inputs, converged,
                             start_requests, loss, node_converge_seconds, other_plugins)
        run.run(settle_seconds)
        mark = run.now
        run.run(3600.0)
        part = run.part(modality.name)
        sent = sum(n for t, n in part.sent if t >= mark)
        allowed = int(type(modality).keepalive_bytes_per_hour)
        assert sent <= allowed, (
            f"rule: a converged sender goes quiet (at most keepalive_bytes_per_hour = {allowed} B); "
            f"{modality.name} sent {sent} B in the hour after it converged and settled")

    # ------------------------------------------------------------------ damaged input, encoding
    def _own_messages(self, modality: Modality, sender_config: Any, receiver_config: Any,
                      sample_inputs: Sequence[tuple[float, Any]], start_requests: Any) -> list[Message]:
        """What the sender sends and the receiver asks for, over a short lossless exchange."""
        pair = self._pair(modality, sender_config, receiver_config, loss=0.0, seed=2)
        pair.now = ingest_all(pair.sender, sample_inputs)
        if start_requests is not None:
            start_requests(pair.receiver, pair.now)
        for _ in range(60):
            pair.step()
        return pair.sent_messages + pair.requests

    def test_receiver_raises_only_decode_error_on_damaged_messages(
        self, modality: Modality, sender_config: Any, receiver_config: Any,
        sample_inputs: Sequence[tuple[float, Any]], start_requests: Any,
    ) -> None:
        """Truncated and bit-flipped copies of the plugin's own messages: the wire layer rejects
        them with DecodeError, or the plugin takes them: the receiver raises nothing but
        DecodeError, the sender (for its requests) nothing but DecodeError or RequestRejected
        (a damaged request is one it refuses). A third-party body the modality's own codec
        (``decode_body``) rejects must be rejected by the receiver too: a lenient receiver
        would show damaged data as good."""
        own = [m for m in self._own_messages(modality, sender_config, receiver_config, sample_inputs,
                                             start_requests) if modality.handles(m)]
        assert own, "the plugin produced no messages of its own from the sample inputs"
        receiver = modality.receiver(receiver_config)
        sender = modality.sender(sender_config)
        now = ingest_all(sender, sample_inputs) + 10.0
        codec = type(modality).decode_body
        rng = random.Random(13)
        tried = 0
        for m in own[:40]:
            data = wire.encode(m)
            variants = [data[:k] for k in range(1, len(data))]
            for _ in range(12):
                b = bytearray(data)
                b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
                variants.append(bytes(b))
            if isinstance(m, Opaque):  # the body alone damaged: the wire layer cannot see it
                variants += [wire.encode(Opaque(m.type_id, m.body[:k])) for k in range(len(m.body))]
            for v in variants:
                try:
                    d = wire.decode(v)
                except DecodeError:
                    continue
                if not modality.handles(d):
                    continue
                tried += 1
                is_request = type(d) in tuple(modality.requests) or (
                    isinstance(d, Opaque) and d.type_id in type(modality).request_ids)
                side = "sender" if is_request else "receiver"
                rejected_by_codec = False
                if isinstance(d, Opaque):
                    try:
                        codec(d.type_id, d.body)
                    except DecodeError:
                        rejected_by_codec = True
                allowed: tuple[type[Exception], ...] = (DecodeError, RequestRejected) if is_request else (DecodeError,)
                try:
                    if is_request:
                        sender.handle(d, now)
                    else:
                        receiver.receive(d, now)
                except allowed:
                    continue
                except Exception as exc:
                    what = "DecodeError or RequestRejected" if is_request else "DecodeError"
                    raise AssertionError(
                        f"rule: a damaged message raises {what} only; the {side} raised "
                        f"{type(exc).__name__}: {exc} on {d!r:.160}") from exc
                assert not rejected_by_codec, (
                    f"rule: the {side} rejects what the modality's decode_body rejects; it accepted "
                    f"{d!r:.160}")
        assert tried or own, "no damaged variant reached the plugin"

    def test_body_codec_refuses_ids_it_does_not_declare(
        self, modality: Modality, sender_config: Any, receiver_config: Any,
        sample_inputs: Sequence[tuple[float, Any]], start_requests: Any,
    ) -> None:
        """``decode_body(type_id, body)`` decodes the bodies of the ids the modality declares
        (``message_ids``, ``request_ids``) and raises DecodeError for any other id, whatever the
        body: given one of its own bodies under an id it does not declare, it refuses."""
        cls = type(modality)
        dec = cls.decode_body
        own_ids = set(cls.message_ids) | set(cls.request_ids)
        if not own_ids:
            return
        by_id: dict[int, list[bytes]] = {}
        for m in self._own_messages(modality, sender_config, receiver_config, sample_inputs, start_requests):
            if isinstance(m, Opaque) and len(by_id.setdefault(m.type_id, [])) < 5:
                by_id[m.type_id].append(m.body)  # a few bodies of each of its ids
        bodies = [b for bs in by_id.values() for b in bs] or [b""]
        others = [i for i in (96, 127, 128, 4242, 29999, 32767, *(i + 1 for i in own_ids))
                  if i not in own_ids and 96 <= i <= 32767]
        for tid in others:
            for body in bodies:
                try:
                    value = dec(tid, body)
                except DecodeError:
                    continue
                raise AssertionError(
                    f"rule: decode_body raises DecodeError for an id the modality does not declare; "
                    f"decode_body({tid}, {body.hex()[:40]}) gave {value!r:.80}")

    def test_bodies_re_encode_to_the_same_bytes(
        self, modality: Modality, sender_config: Any, receiver_config: Any,
        sample_inputs: Sequence[tuple[float, Any]], start_requests: Any,
    ) -> None:
        """Every message the plugin sends or asks for decodes and re-encodes to the same bytes;
        a third-party body re-encodes the same through the modality's ``decode_body`` and
        ``encode_body``, which a modality that declares third-party ids must provide."""
        cls = type(modality)
        own = self._own_messages(modality, sender_config, receiver_config, sample_inputs, start_requests)
        assert own, "the plugin produced no messages from the sample inputs"
        dec, enc = cls.decode_body, cls.encode_body
        for m in own:
            data = wire.encode(m)
            again = wire.encode(wire.decode(data))
            assert again == data, f"rule: a message re-encodes to the same bytes; {m!r:.160} did not"
            if isinstance(m, Opaque):
                try:
                    body = enc(m.type_id, dec(m.type_id, m.body))
                except (DecodeError, EncodeError) as exc:
                    raise AssertionError(
                        "rule: a modality that declares third-party ids gives their body codec "
                        "(classmethods decode_body(type_id, body) and encode_body(type_id, value)), "
                        f"which takes its own bodies; type id {m.type_id}: {exc}") from exc
                assert body == m.body, (f"rule: a third-party body re-encodes to the same bytes; type id "
                                        f"{m.type_id}: {m.body.hex()} became {bytes(body).hex()}")
