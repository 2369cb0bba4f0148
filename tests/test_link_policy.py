"""Priorities that follow the link (issue 41): the channel manager's measured throughput, its
low / normal policy with hysteresis, and what every sender is told before each packet; the
node's peer lookup between the senders of one vehicle."""

from __future__ import annotations

from typing import Any

import pytest

from coex_core.channel import ChannelManager, LinkConfig, Schedule, StreamConfig
from coex_core.errors import ConfigError
from coex_core.messages import FrameAck, FrameAckEntry, Message, Opaque
from coex_core.modality import Modality, ModalityReceiver, ModalitySender, Product
from coex_core.node import Node

VEHICLE, TOPSIDE = 2, 1


def nui() -> Schedule:
    return Schedule.simple([TOPSIDE, VEHICLE, VEHICLE, TOPSIDE, VEHICLE, VEHICLE], 20.0, 2.0)


class Listener(ModalitySender):
    """Always has a 40-byte piece; remembers what the channel told it."""

    def __init__(self) -> None:
        self.told: list[tuple[float, bool, float]] = []

    def ingest(self, data: Any, now: float) -> None:
        pass

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        return [Opaque(200, bytes(37))] if max_bytes >= 40 else []

    def handle(self, message: Message, now: float) -> list[Message]:
        return []

    def throughput(self, bytes_per_second: float, low: bool, now: float) -> None:
        self.told.append((bytes_per_second, low, now))


class Thing(Modality):
    name = "thing"
    message_ids = (200,)

    def sender(self, config: Any = None) -> ModalitySender:
        return Listener()

    def receiver(self, config: Any = None) -> ModalityReceiver:
        return Rx()  # the tests use the sender side only


def vehicle(rate: int) -> tuple[ChannelManager, Listener]:
    mgr = ChannelManager(VEHICLE, [LinkConfig(0, nui(), rate=rate, dst=TOPSIDE)])
    s = Listener()
    mgr.add_stream(StreamConfig(3, "thing"), s)
    return mgr, s


def test_capacity_counts_the_full_packets_of_the_nodes_slots() -> None:
    """Rate 1 (3 x 64 B, 3.07 s): 5 packets in each 20 s vehicle slot less its 2 s guard, 4
    slots a 120 s cycle: 32 B/s. Rate 5 (8 x 256 B, 3.0 s): 6 a slot, 409.6 B/s. Topside owns 2
    slots: half of that."""
    assert vehicle(1)[0].capacity(0) == pytest.approx(4 * 5 * 192 / 120)
    assert vehicle(5)[0].capacity(0) == pytest.approx(4 * 6 * 2048 / 120)
    top = ChannelManager(TOPSIDE, [LinkConfig(0, nui(), rate=5, dst=VEHICLE)])
    assert top.capacity(0) == pytest.approx(2 * 6 * 2048 / 120)


def _acked(mgr: ChannelManager, frames_ok: int, frames_lost: int, t: float) -> float:
    """Send packets (filling every frame) and acknowledge the first ``frames_ok`` of them;
    returns the time after."""
    n = frames_ok + frames_lost
    sent: list[tuple[int, int]] = []
    while len(sent) < n:
        t += 1.0
        for tx in mgr.poll(t):
            sent += [((tx.seq + i) % 256, i) for i in range(len(tx.frames))]
    ok = sent[:frames_ok]
    t += 1.0
    for seq, _ in ok:
        mgr.on_ack(FrameAck(VEHICLE, 0, (FrameAckEntry(seq, 1),)), t)
    t += 200.0
    mgr.poll(t)  # the rest time out: lost
    return t


def test_the_measured_loss_makes_a_rate_1_link_low_and_rate_5_stays_normal() -> None:
    """Throughput is capacity less the measured frame loss; below 48 B/s the link is low and
    every sender hears it before the next packet; a rate-5 link at 60 % loss is not low."""
    mgr, s = vehicle(1)
    t = mgr.next_event(0.0) or 0.0
    mgr.poll(t)
    assert s.told and s.told[-1][0] == pytest.approx(32.0)  # no loss measured yet: the capacity
    assert s.told[-1][1] is True  # 32 B/s is below 48 already
    fast, f = vehicle(5)
    t5 = _acked(fast, 16, 24, fast.next_event(0.0) or 0.0)
    assert fast.frame_loss(0) == pytest.approx(0.6)
    assert fast.throughput() == pytest.approx(409.6 * 0.4)
    fast.poll(fast.next_event(t5) or t5)
    assert f.told[-1][1] is False and not fast.link_low()
    assert fast.link_state(0)["throughput"] == pytest.approx(163.8, abs=0.1)


def test_low_has_hysteresis() -> None:
    """Low below ``low_throughput``, normal again only above ``normal_throughput``: between
    the two the link stays as it was."""
    mgr, s = vehicle(5)
    t = _acked(mgr, 10, 30, mgr.next_event(0.0) or 0.0)
    bps = mgr.throughput()
    assert bps == pytest.approx(mgr.capacity(0) * (1 - (mgr.frame_loss(0) or 0.0)))

    def packet(low: float, normal: float) -> bool:
        nonlocal t
        mgr.low_throughput, mgr.normal_throughput = low, normal
        t = mgr.next_event(t + 1.0) or t
        mgr.poll(t)
        assert s.told[-1][1] == mgr.link_low()
        return mgr.link_low()

    assert not packet(bps - 10, bps + 10)
    assert packet(bps + 10, bps + 20)
    assert packet(bps - 10, bps + 10), "between the thresholds it stays low"
    assert not packet(bps - 20, bps - 10)
    assert not packet(bps - 10, bps + 10), "and normal"
    with pytest.raises(ConfigError):
        ChannelManager(VEHICLE, [LinkConfig(0, nui())], low_throughput=80.0, normal_throughput=40.0)


class Watcher(ModalitySender):
    def ingest(self, data: Any, now: float) -> None:
        pass

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        return []

    def handle(self, message: Message, now: float) -> list[Message]:
        return []


class Watching(Modality):
    name = "watching"

    def sender(self, config: Any = None) -> ModalitySender:
        return Watcher()

    def receiver(self, config: Any = None) -> ModalityReceiver:
        return Rx()  # the tests use the sender side only


class Rx(ModalityReceiver):
    def receive(self, message: Message, now: float) -> list[Product]:
        return []

    def poll(self, now: float) -> list[Message]:
        return []

    def products(self) -> list[Product]:
        return []


def test_a_sender_finds_the_other_senders_of_its_node_also_after_a_restore() -> None:
    """``peer(name)`` is the sender of another modality on the same node (inside any remap
    wrapper), bound again when the node's state is restored into a new node."""
    from coex_core.state import persistent

    persistent("test.Listener")(Listener)
    persistent("test.Watcher")(Watcher)

    def build() -> tuple[Node, Watcher, Listener]:
        node = Node(ChannelManager(VEHICLE, [LinkConfig(0, nui(), dst=TOPSIDE)]))
        w, t = Watcher(), Listener()
        node.add_sender(Watching, w, StreamConfig(3, "watching"))
        node.add_sender(Thing, t, StreamConfig(4, "thing"), ids={200: 210})
        return node, w, t

    node, w, t = build()
    assert w.peer("thing") is t and t.peer("watching") is w and w.peer("nobody") is None
    assert Watcher().peer("thing") is None  # not on a node
    saved = node.export_state()
    again, _, _ = build()
    again.restore_state(saved)
    w2 = again.sender("watching")
    assert isinstance(w2, Watcher) and w2 is not w
    t2 = w2.peer("thing")
    assert isinstance(t2, Listener) and t2 is not t


class Tagged(Listener):
    """Always has a 40-byte piece of its own id."""

    def __init__(self, tid: int) -> None:
        super().__init__()
        self.tid = tid

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        return [Opaque(self.tid, bytes(37))] if max_bytes >= 40 else []


def _shares(rate: int) -> dict[int, int]:
    """Messages of two always-backlogged streams over 20 cycles: priority 10 (90 on a low link)
    against priority 30."""
    from coex_core.wire import unpack

    mgr = ChannelManager(VEHICLE, [LinkConfig(0, nui(), rate=rate, dst=TOPSIDE)])
    mgr.add_stream(StreamConfig(3, "a", priority=10, low_priority=90), Tagged(200))
    mgr.add_stream(StreamConfig(4, "b", priority=30), Tagged(201))
    got = {200: 0, 201: 0}
    t = 0.0
    while t < 20 * 120.0:
        t = mgr.next_event(t) or t + 1.0
        for tx in mgr.poll(t):
            for fr in tx.frames:
                for msg in unpack(fr):
                    if isinstance(msg, Opaque):
                        got[msg.type_id] += 1
            # every frame arrives: no loss measured, the link is as fast as its slots
            mgr.on_ack(FrameAck(VEHICLE, 0, (FrameAckEntry(tx.seq, (1 << len(tx.frames)) - 1),)), t + 0.5)
    return got


def test_a_streams_low_priority_takes_over_while_the_link_is_low() -> None:
    """Two backlogged streams share the packets by priority: 10 against 30 on a normal link
    (rate 5), by ``low_priority`` (90 against 30) on a low one (rate 1)."""
    normal, low = _shares(5), _shares(1)
    assert normal[201] > 2 * normal[200], normal
    assert low[200] > 2 * low[201], low
    with pytest.raises(ConfigError):
        StreamConfig(3, "a", low_priority=128)
    assert StreamConfig(3, priority=10, low_priority=90).priority_now(True) == 90
    assert StreamConfig(3, priority=10, low_priority=90).priority_now(False) == 10
    assert StreamConfig(3, priority=10).priority_now(True) == 10


def test_topside_tells_the_vehicles_throughput_from_the_frames_it_hears() -> None:
    """``peer_throughput``: the peer's slots' capacity less the loss of its frames seen here
    (gaps in their sequence numbers)."""
    from coex_core.messages import FrameHeader

    top = ChannelManager(TOPSIDE, [LinkConfig(0, nui(), rate=1, dst=VEHICLE)])
    assert top.peer_throughput(VEHICLE) == pytest.approx(32.0)  # nothing heard: the capacity
    for seq in range(0, 40, 2):  # every other frame of the vehicle's is missing
        top.on_frame(0, FrameHeader(src=VEHICLE, dst=TOPSIDE, seq=seq), float(seq), True)
    assert top.peer_throughput(VEHICLE) == pytest.approx(32.0 * 20 / 39, rel=0.01)


class _Failing(Listener):
    def throughput(self, bytes_per_second: float, low: bool, now: float) -> None:
        raise RuntimeError("boom")


class _Quiet(Listener):
    """Keeps the base class's throughput() (declared, documented default: nothing)."""

    throughput = ModalitySender.throughput


def test_every_sender_is_told_through_the_declared_hook_and_a_failing_one_is_reported() -> None:
    """``throughput`` is declared on ModalitySender (default: nothing); the channel calls it on
    every sender and a hook that raises is a SenderFailed event, never a failed packet."""
    from coex_core.channel.events import SenderFailed

    mgr = ChannelManager(VEHICLE, [LinkConfig(0, nui(), rate=1, dst=TOPSIDE)])
    told, failing, quiet = Listener(), _Failing(), _Quiet()
    for sid, s in ((3, told), (4, failing), (5, quiet)):
        mgr.add_stream(StreamConfig(sid, f"s{sid}"), s)
    t = mgr.next_event(0.0) or 0.0
    assert mgr.poll(t)  # a packet, in spite of the failing hook
    assert told.told and told.told[-1][2] == t and quiet.told == []
    failed = [e for e in mgr.events() if isinstance(e, SenderFailed)]
    assert failed and failed[0].stream == 4 and "throughput() failed: RuntimeError: boom" in failed[0].error
    assert mgr.stats["sender_failures"] >= 1


def test_a_wrapper_declares_what_it_wraps_through_inner() -> None:
    """``inner`` is declared on ModalitySender and ModalityReceiver (None: wraps none); the node
    reaches the innermost sender through it (bind_peers, state), through nested wrappers, and
    never through an ``inner`` that is not a sender."""
    from coex_core.node import _innermost
    from coex_core.remap import RemappedSender

    assert ModalitySender.inner is None and ModalityReceiver.inner is None
    plain = Listener()
    assert _innermost(plain) is plain

    class Recording(Listener):
        def __init__(self, inner: ModalitySender) -> None:
            super().__init__()
            self.inner = inner

    class NotAWrapper(Listener):
        def __init__(self) -> None:
            super().__init__()
            self.inner = "a name of its own"  # type: ignore[assignment]

    core = Listener()
    outer = RemappedSender(Recording(core), {200: 201})
    assert _innermost(outer) is core
    odd = NotAWrapper()
    assert _innermost(odd) is odd
    node = Node(ChannelManager(VEHICLE, [LinkConfig(0, nui(), rate=1, dst=TOPSIDE)]))
    node.add_sender(Thing, Recording(core), StreamConfig(3, "thing"))
    assert core.peer("thing") is core  # bound on the innermost sender, which the peer lookup gives
