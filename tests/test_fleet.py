"""Three nodes on one acoustic network (issue 43, the core): topside and two vehicles on simulated
links. Per-peer acks and loss, frames addressed to one node never consumed by another,
broadcasts reaching both, a schedule change agreed by all three (and not taken without every
ACCEPTED), one vehicle silenced while the other two keep delivering (its watchdog falls back
alone)."""

from __future__ import annotations

import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

import pytest

from coex import SimNetwork
from coex_core.acoustic import AcousticChannel
from coex_core.channel import (
    ChannelManager,
    CommandApplied,
    CommandResult,
    LinkConfig,
    Schedule,
    ScheduleSwitched,
    StreamConfig,
)
from coex_core.messages import AckStatus, Message, Opaque, VehicleMode, VehicleStatus
from coex_core.modality import Modality, ModalityReceiver, ModalitySender, Product
from coex_core.node import Node
from coex_core.state import dumps, loads

TOPSIDE, A, B = 1, 2, 3
DATA, REQUEST = 100, 120


class Sender(ModalitySender):
    """Endless data: body = (own node id, tag, counter); a request (body = tag) makes the next
    three messages carry its tag."""

    def __init__(self, node: int) -> None:
        self.node = node
        self.counter = 0
        self.urgent: list[int] = []
        self.requests: list[int] = []

    def ingest(self, data: Any, now: float) -> None:
        pass

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        out: list[Message] = []
        room = max_bytes
        while room >= 40:
            tag = self.urgent.pop(0) if self.urgent else 0
            self.counter += 1
            body = bytes([self.node, tag]) + self.counter.to_bytes(4, "big") + bytes(30)
            out.append(Opaque(DATA, body))
            room -= len(body) + 3
        return out

    def handle(self, message: Message, now: float) -> list[Message]:
        assert isinstance(message, Opaque)
        self.requests.append(message.body[0])
        self.urgent.extend([message.body[0]] * 3)
        return []


class Receiver(ModalityReceiver):
    def __init__(self) -> None:
        self.got: list[Opaque] = []

    def receive(self, message: Message, now: float) -> list[Product]:
        assert isinstance(message, Opaque)
        self.got.append(message)
        return []

    def poll(self, now: float) -> list[Message]:
        return []

    def products(self) -> list[Product]:
        return []


class Fake(Modality):
    name = "fake"
    message_ids: ClassVar[tuple[int, ...]] = (DATA,)
    request_ids: ClassVar[tuple[int, ...]] = (REQUEST,)

    def sender(self, config: Mapping[str, Any] | None = None) -> ModalitySender:
        return Sender(0)

    def receiver(self, config: Mapping[str, Any] | None = None) -> ModalityReceiver:
        return Receiver()


def safe() -> Schedule:
    return Schedule.simple([TOPSIDE, A, B], 20.0, 2.0)


class Fleet:
    """Topside (broadcast by default) and vehicles A and B (sending to topside), one link."""

    def __init__(self, loss: float = 0.0, seed: int = 1) -> None:
        self.mgr = {TOPSIDE: ChannelManager(TOPSIDE, [LinkConfig(0, safe(), watchdog_cycles=3)])}
        self.node = {TOPSIDE: Node(self.mgr[TOPSIDE])}
        self.senders: dict[int, Sender] = {}
        self.rx: dict[int, Receiver] = {}
        for v in (A, B):
            self.mgr[v] = ChannelManager(v, [LinkConfig(0, safe(), watchdog_cycles=3, dst=TOPSIDE)])
            self.node[v] = Node(self.mgr[v])
            self.senders[v] = Sender(v)
            self.node[v].add_sender(Fake, self.senders[v], StreamConfig(5, "fake", priority=30,
                                                                         ack_required=True))
            self.rx[v] = Receiver()
            self.node[TOPSIDE].add_receiver(Fake, self.rx[v], peer=v)
        self.channel = AcousticChannel(loss=loss, seed=seed)
        self.net = SimNetwork({0: self.channel})
        for nid, pos in ((TOPSIDE, (0.0, 0.0, 0.0)), (A, (300.0, 400.0, 900.0)), (B, (-400.0, 300.0, 900.0))):
            self.net.add_node(self.node[nid], pos)
        self.events: dict[int, list[Any]] = {n: [] for n in self.node}
        for v in (A, B):
            self.net.every(10.0, lambda now, v=v: self.node[v].push_status(
                VehicleStatus(int(now), 1.0, 2.0, 1000.0, 10.0, 0.0, 1.0, 90, VehicleMode.SURVEY, 0), now)
                if v in self.net.nodes else None)

    def run(self, until: float) -> None:
        self.net.run(until)
        for n, node in self.node.items():
            self.events[n] += node.events()

    def switches(self, n: int) -> list[tuple[int, int, float, str]]:
        return [(e.version, e.cycle, e.time, e.reason) for e in self.events[n] if isinstance(e, ScheduleSwitched)]


def test_each_vehicle_delivers_to_topside_with_its_own_acks_and_loss() -> None:
    f = Fleet(loss=0.2, seed=3)
    f.run(1800.0)
    for v in (A, B):
        got = f.rx[v].got
        assert len(got) > 50
        assert {m.body[0] for m in got} == {v}  # each per-peer receiver: its vehicle's data only
        # acked per peer: what the vehicle sent left its queue on topside's frame acks
        assert f.mgr[v].stats["acked"] > 50
    top = f.mgr[TOPSIDE]
    for v in (A, B):
        loss = top.frame_loss(0, v)  # of v's frames heard by topside (gaps in v's seqs)
        assert loss is not None and 0.05 < loss < 0.4
        assert top.last_heard(0, v) is not None and top.last_heard(0, v) > 1700.0
        vloss = f.mgr[v].frame_loss(0, TOPSIDE)  # of the vehicle's frames, from topside's acks
        assert vloss is not None and 0.05 < vloss < 0.5
    assert set(top.link_state(0)["peers"]) >= {A, B}
    # the vehicles overheard each other's frames (and topside's frames for the other vehicle)
    # and consumed none of them
    assert f.node[A].stats["foreign"] > 0 and f.node[B].stats["foreign"] > 0
    assert f.mgr[A].stats.get("foreign_answers", 0) == 0


def test_a_frame_for_one_vehicle_is_never_consumed_by_the_other_and_broadcast_reaches_both() -> None:
    f = Fleet()
    f.run(200.0)
    top = f.node[TOPSIDE]
    top.request(Opaque(REQUEST, bytes([7])), 200.0, dst=B)
    cid = top.queue_config(5, 200.0, priority=40, dst=A)
    f.run(500.0)
    assert f.senders[B].requests == [7] and f.senders[A].requests == []
    assert {m.body[0] for m in f.rx[B].got if m.body[1] == 7} == {B}
    applied = {n: [e for e in f.events[n] if isinstance(e, CommandApplied)] for n in (A, B)}
    assert [e.command.command_id for e in applied[A]] == [cid] and applied[B] == []
    assert f.mgr[A].stream(5).config.priority == 40 and f.mgr[B].stream(5).config.priority == 30
    results = [e for e in f.events[TOPSIDE] if isinstance(e, CommandResult)]
    assert [(e.command_id, e.status) for e in results] == [(cid, AckStatus.ACCEPTED)]
    # the frames carrying B's request were addressed to B: A overheard them and took nothing
    assert f.node[A].stats["foreign"] > 0
    top.request(Opaque(REQUEST, bytes([9])), 500.0, dst=0)  # broadcast
    f.run(800.0)
    assert f.senders[A].requests == [9] and f.senders[B].requests == [7, 9]
    for v in (A, B):
        assert any(m.body[1] == 9 for m in f.rx[v].got)


def test_a_command_answer_from_the_wrong_vehicle_answers_nothing() -> None:
    f = Fleet()
    f.run(100.0)
    top = f.mgr[TOPSIDE]
    cid = f.node[TOPSIDE].queue_config(5, 100.0, priority=50, dst=A)
    assert not top.answers(cid, B) and top.answers(cid, A)
    from coex_core.messages import CommandAck
    assert top.on_command_ack(CommandAck(cid, AckStatus.ACCEPTED), 101.0, src=B) is None
    res = top.on_command_ack(CommandAck(cid, AckStatus.ACCEPTED), 102.0, src=A)
    assert res is not None and res.command_id == cid


def test_a_schedule_change_is_agreed_by_all_three_before_it_takes_effect() -> None:
    f = Fleet()
    f.run(130.0)
    new = Schedule.simple([TOPSIDE, A, B, A, B], 20.0, 2.0, version=4)
    f.node[TOPSIDE].schedule_update(0, new, 130.0, activate_cycle=6)  # starts at 6 * 60 = 360 s
    f.run(700.0)
    for n in (TOPSIDE, A, B):
        assert f.switches(n) == [(4, 6, 360.0, "activation")]
        assert f.mgr[n].schedule(0).slots == new.slots
    assert not f.mgr[TOPSIDE].link_state(0)["pending"]
    after = [tx for _, tx in f.net.transmissions if tx.start >= 360.0]
    before = [tx for _, tx in f.net.transmissions if tx.start < 360.0]
    assert after and all(tx.schedule == 4 for tx in after)
    assert all(tx.schedule == 0 for tx in before)
    got = {v: len(f.rx[v].got) for v in (A, B)}
    f.run(1000.0)
    assert all(len(f.rx[v].got) > got[v] for v in (A, B))  # both keep delivering on it


def test_a_schedule_one_vehicle_refuses_is_taken_by_nobody() -> None:
    f = Fleet()
    f.run(130.0)
    new = Schedule.simple([TOPSIDE, A, A], 20.0, 2.0, version=5)  # B has no slot: it refuses
    f.node[TOPSIDE].schedule_update(0, new, 130.0, activate_cycle=6, peers=(A, B))
    f.run(700.0)
    for n in (TOPSIDE, A, B):
        assert f.switches(n) == [] and f.mgr[n].schedule(0).version == 0
        assert f.mgr[n].pending_schedule(0) is None
    applied = [e for e in f.events[B] if isinstance(e, CommandApplied)]
    assert applied and applied[0].status == AckStatus.REJECTED
    assert f.mgr[TOPSIDE].stats["schedules_not_agreed"] == 1
    assert f.mgr[A].stats["schedules_not_agreed"] == 1  # A accepted, was never committed


def test_a_silent_vehicle_does_not_block_the_others_and_falls_back_alone() -> None:
    f = Fleet()
    new = Schedule.simple([TOPSIDE, A, B, A, B], 20.0, 2.0, version=2)
    f.run(100.0)
    f.node[TOPSIDE].schedule_update(0, new, 100.0, activate_cycle=5)
    f.run(400.0)
    assert all(f.mgr[n].schedule(0).version == 2 for n in (TOPSIDE, A, B))
    # B goes silent and deaf (out of the water): A and topside keep delivering on the new schedule
    del f.net.nodes[B]
    b = f.node[B]
    falls: list[ScheduleSwitched] = []
    n_a = len(f.rx[A].got)
    for t in range(400, 1400, 5):
        f.net.run(float(t))
        b.poll(float(t))  # B runs alone: nothing heard, its packets reach nobody
        falls += [e for e in b.events() if isinstance(e, ScheduleSwitched)]
    f.run(1400.0)
    assert [(e.version, e.reason) for e in falls] == [(0, "watchdog")]
    assert f.mgr[TOPSIDE].schedule(0).version == 2 and f.mgr[A].schedule(0).version == 2
    assert len(f.rx[A].got) > n_a + 50
    assert not any(isinstance(e, ScheduleSwitched) for n in (TOPSIDE, A) for e in f.events[n]
                   if e.time > 400.0)
    # a further change is agreed by topside and A alone: silent B is not waited for
    newer = Schedule.simple([TOPSIDE, A, A], 20.0, 2.0, version=3)
    f.node[TOPSIDE].schedule_update(0, newer, 1400.0)
    f.run(2000.0)
    assert f.mgr[TOPSIDE].schedule(0).version == 3 and f.mgr[A].schedule(0).version == 3
    n_a = len(f.rx[A].got)
    f.run(2400.0)
    assert len(f.rx[A].got) > n_a


def test_per_peer_state_survives_a_save_and_an_old_manager_state_upgrades() -> None:
    f = Fleet(loss=0.2, seed=2)
    f.run(900.0)
    top = f.mgr[TOPSIDE]
    back = loads(dumps(top))
    assert back.frame_loss(0, A) == top.frame_loss(0, A) and back.last_heard(0, B) == top.last_heard(0, B)
    # a version-3 manager (saved before per-peer bookkeeping) loads with it empty
    from coex_core.channel.manager import _upgrade_manager
    old = {k: v for k, v in vars(top).items() if k not in
           ("_frame_dst", "_peer_tx", "_peer_rx", "_peer_heard", "_command_dst")}
    up = _upgrade_manager(dict(old), 3)
    assert up["_peer_heard"] == {} and up["_command_dst"] == {} and up["_frame_dst"] == {}


def test_three_nodes_over_simulated_micromodems_on_pseudo_terminals() -> None:
    """The same three nodes through the Micromodem driver, each host's NMEA on a real
    pseudo-terminal: the topside's modem sends to every modem (dest 0), the CoEx header
    addresses each packet; each vehicle's data reaches its receiver, a request for B is
    handled by B alone, and a schedule change is agreed by all three."""
    from coex import Runner
    from coex_transports.micromodem import ModemNetwork

    sched = Schedule.simple([TOPSIDE, A, B], 10.0, 1.0)
    top = Node(ChannelManager(TOPSIDE, [LinkConfig(0, sched, rate=1, frames=3)]))
    nodes, senders, rxs = {TOPSIDE: top}, {}, {}
    for v in (A, B):
        nodes[v] = Node(ChannelManager(v, [LinkConfig(0, sched, rate=1, frames=3, dst=TOPSIDE)]))
        senders[v] = Sender(v)
        nodes[v].add_sender(Fake, senders[v], StreamConfig(5, "fake", ack_required=True))
        rxs[v] = Receiver()
        top.add_receiver(Fake, rxs[v], peer=v)
    net = ModemNetwork({TOPSIDE: (0.0, 0.0, 0.0), A: (1500.0, 0.0, 0.0), B: (0.0, 1200.0, 0.0)},
                       channel=AcousticChannel(loss=0.05, seed=4), ptys=True)
    try:
        clock = net.as_clock()
        transports = {TOPSIDE: net.transport(TOPSIDE, dest=0, rate=1),
                      A: net.transport(A, dest=TOPSIDE, rate=1), B: net.transport(B, dest=TOPSIDE, rate=1)}
        runners = {n: Runner(nodes[n], {0: transports[n]}, clock) for n in nodes}
        events: dict[int, list[Any]] = {n: [] for n in nodes}

        def run(until: float) -> None:
            while clock.time() < until:
                nxt = min(min(r.step() for r in runners.values()), clock.time() + 0.25)
                clock.wait_until(max(nxt, clock.time() + 1e-3))
            for n, node in nodes.items():
                events[n] += node.events()

        t0 = clock.time()
        run(t0 + 300.0)
        top.request(Opaque(REQUEST, bytes([5])), clock.time(), dst=B)
        new = Schedule.simple([TOPSIDE, A, B, A, B], 10.0, 1.0, version=6)
        top.schedule_update(0, new, clock.time())
        run(t0 + 900.0)
        assert all(r.error_count == 0 for r in runners.values()), {n: r.errors for n, r in runners.items()}
        for v in (A, B):
            assert len(rxs[v].got) > 20 and {m.body[0] for m in rxs[v].got} == {v}
            assert nodes[v].manager.stats["acked"] > 20
        assert senders[B].requests == [5] and senders[A].requests == []
        switched = {n: [(e.version, e.reason) for e in events[n] if isinstance(e, ScheduleSwitched)]
                    for n in nodes}
        assert switched == {n: [(6, "activation")] for n in nodes}
        assert len({nodes[n].manager.schedule(0) for n in nodes}) == 1
    finally:
        net.close()


def _counts(lines: Any) -> dict[int, int]:
    last = [x for x in lines.lines if x.startswith("rx ")]
    return {int(k): int(v) for k, v in (p.split("=") for p in last[-1].split()[1:])} if last else {}


def _acked(lines: Any) -> int:
    got = [int(x.split("=")[1]) for x in lines.lines if x.startswith("acked=")]
    return got[-1] if got else 0


@pytest.mark.slow
def test_kill_9_of_one_vehicle_process_while_the_other_keeps_delivering(tmp_path: Path) -> None:
    """Three processes on ``coex modem-sim`` (real time): topside and vehicles 2 and 3 deliver;
    vehicle 3 is killed with SIGKILL; topside and vehicle 2 keep delivering."""
    pytest.importorskip("serial")
    import os
    import signal
    import subprocess
    import sys

    from ._modemsim import ROOT, modem_sim
    from ._procs import Lines, wait_for

    env = dict(os.environ, PYTHONUNBUFFERED="1")
    procs: dict[str, subprocess.Popen[str]] = {}
    logs: dict[int, Lines] = {}
    with modem_sim((TOPSIDE, A, B)) as uris:
        try:
            for nid in (TOPSIDE, A, B):
                dest = 0 if nid == TOPSIDE else TOPSIDE
                uri = f"{uris[nid]}?src={nid}&dest={dest}&rate=5"
                p = subprocess.Popen([sys.executable, "-m", "tests._fleet_node", str(nid), uri], env=env,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT)
                procs[f"node {nid}"] = p
                logs[nid] = Lines(p, tmp_path / f"node{nid}.log")
            top = logs[TOPSIDE]
            # three packets from each (one per 21 s cycle), and topside's acks reached both
            wait_for("data from both vehicles", lambda: all(_counts(top).get(v, 0) >= 144 for v in (A, B)),
                     240, procs)
            wait_for("acks at both vehicles", lambda: all(_acked(logs[v]) >= 96 for v in (A, B)), 120, procs)
            victim = procs.pop(f"node {B}")
            victim.send_signal(signal.SIGKILL)
            assert victim.wait(timeout=10) == -signal.SIGKILL
            time.sleep(2.0)
            after_kill = _counts(top)
            acked_before = _acked(logs[A])
            wait_for("vehicle 2 delivering after vehicle 3 was killed",
                     lambda: _counts(top).get(A, 0) >= after_kill[A] + 96, 150, procs)
            wait_for("topside's acks still reaching vehicle 2",
                     lambda: _acked(logs[A]) >= acked_before + 96, 120, procs)
            assert _counts(top)[B] <= after_kill[B] + 48  # at most a packet that was in the water
        finally:
            for p in procs.values():
                if p.poll() is None:
                    p.send_signal(signal.SIGKILL)
                    p.wait(timeout=10)


def test_per_peer_command_keys_and_counters() -> None:
    """Each vehicle shares its own key with topside (and all share the network key, for
    broadcasts): a command for A is signed with A's key under A's counter; B cannot be made to
    take a frame signed with A's key; broadcasts use the network key; the counters survive a
    save."""
    from coex_core import wire
    from coex_core.auth import CommandVerifier

    net_key, key_a, key_b = b"n" * 16, b"a" * 16, b"b" * 16
    link = LinkConfig(0, safe())
    top = ChannelManager(TOPSIDE, [link], command_key=net_key, peer_keys={A: key_a, B: key_b})
    top_node = Node(top)
    va = Node(ChannelManager(A, [LinkConfig(0, safe(), dst=TOPSIDE)], command_key=net_key, peer_keys={TOPSIDE: key_a}))
    vb = Node(ChannelManager(B, [LinkConfig(0, safe(), dst=TOPSIDE)], command_key=net_key, peer_keys={TOPSIDE: key_b}))
    top_node.queue_config(2, 0.0, priority=100, dst=A)
    (tx,) = top.poll(0.0)
    frame = tx.frames[0]
    assert wire.unpack_frame(frame).header.dst == A
    assert CommandVerifier(key_a).unpack(frame)  # signed with A's own key
    assert top.peer_signers[A].counter == 1 and top.peer_signers[B].counter == 0 and top.signer.counter == 0
    va.receive(0, frame, 1.0)
    assert [e.status for e in va.events() if isinstance(e, CommandApplied)] == [AckStatus.ACCEPTED]
    assert va.manager.peer_verifiers[TOPSIDE].counter == 1
    for vtx in va.poll(21.0):  # A's ack and answer reach topside
        for f in vtx.frames:
            top_node.receive(0, f, 22.0)
    assert not top.stream(2).entries
    # the same frame re-addressed to B (header byte 1: src << 4 | dst) fails B's key
    forged = frame[:1] + bytes([TOPSIDE << 4 | B]) + frame[2:]
    vb.receive(0, forged, 1.0)
    assert vb.stats["unauthenticated"] == 1 and not [e for e in vb.events() if isinstance(e, CommandApplied)]
    # a broadcast command: the network key, which both check
    top_node.spare_config(50, 60.0, dst=0)
    txs = top.poll(60.0)
    assert txs and top.signer.counter == 1
    for v in (va, vb):
        for f in txs[0].frames:
            v.receive(0, f, 61.0)
        assert [e.status for e in v.events() if isinstance(e, CommandApplied)] == [AckStatus.ACCEPTED]
    # the counters are saved with the node and with the settings
    saved = top_node.export_state()
    fresh = Node(ChannelManager(TOPSIDE, [link], command_key=net_key, peer_keys={A: key_a, B: key_b}))
    fresh.restore_state(saved)
    assert fresh.manager.peer_signers[A].counter == 1 and fresh.manager.signer.counter == 1
    settings = top.export_settings()
    again = ChannelManager(TOPSIDE, [link], command_key=net_key, peer_keys={A: key_a, B: key_b})
    again.import_settings(settings)
    assert again.peer_signers[A].counter == 1 + ChannelManager.COUNTER_MARGIN


def test_an_uncommitted_fleet_update_stays_uncommitted_across_a_settings_restart() -> None:
    f = Fleet()
    f.run(130.0)
    f.mgr[TOPSIDE]._peer_heard[(0, 9)] = 10_000.0  # node 9 counts as heard but never answers:
    f.node[TOPSIDE].schedule_update(0, Schedule.simple([TOPSIDE, A, B, A, B], 20.0, 2.0, version=4),
                                    130.0, activate_cycle=8, peers=(A, B, 9))  # no commit comes
    f.run(300.0)
    pending = f.mgr[A].export_settings()["links"]["0"]["pending"]
    assert pending["fleet"] is True and pending["committed"] is False
    again = ChannelManager(A, [LinkConfig(0, safe(), dst=TOPSIDE)])
    again.import_settings(f.mgr[A].export_settings(), 300.0)
    assert again.pending_schedule(0) is not None
    again.poll(8 * 60.0 + 1.0)  # its activation passes without a commit: it does not switch
    assert again.schedule(0).version == 0
