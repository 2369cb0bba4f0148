"""ResilientTransport: a link that goes away is reopened with backoff, logged once per change of
state, counted (outages, time down), and never makes the loop spin or the node stop; the URI
checks (``Transport.check_uri``) that ``coex config check`` and the daemons share."""

from __future__ import annotations

import logging
import socket
import threading
import time
from typing import Any

import pytest

from coex_core.errors import ConfigError, FrameTooLarge, LinkDown, TransportError
from coex_core.registry import check_transport_uri
from coex_core.transport import Transport
from coex_transports.recovery import ResilientTransport, describe_seconds
from coex_transports.testing import free_port


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t

    def sleep(self, dt: float) -> None:
        self.t += dt


class Fake(Transport):
    """A transport whose device can be unplugged: ``Device.present`` and ``Device.broken``."""

    def __init__(self, device: Device) -> None:
        super().__init__(64)
        self.device = device
        self.sent: list[bytes] = []

    def _send_internal(self, frame: bytes) -> None:
        if self.device.broken:
            raise TransportError("write failed: device disconnected")
        self.sent.append(frame)
        self.device.sent.append(frame)

    def _recv_internal(self, timeout: float | None) -> bytes | None:
        if self.device.broken:
            raise TransportError("read failed: device disconnected")
        if self.device.inbox:
            return self.device.inbox.pop(0)
        self.device.clock.sleep(timeout or 0.0)
        return None

    def link_up(self) -> bool:
        return self.device.away is False


class Device:
    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        self.present = True
        self.broken = False
        self.away = False
        self.opens = 0
        self.inbox: list[bytes] = []
        self.sent: list[bytes] = []

    def open(self, uri: str) -> Fake:
        self.opens += 1
        if not self.present:
            raise TransportError(f"cannot open {uri}: No such file or directory")
        self.broken = False
        return Fake(self)

    def unplug(self) -> None:
        self.present, self.broken = False, True


def _link(device: Device, clock: Clock, **kw: Any) -> ResilientTransport:
    return ResilientTransport("loopback://x?mtu=64", name="link 0", clock=clock, sleep=clock.sleep,
                              opener=device.open, **kw)


def test_a_lost_device_is_reopened_with_backoff_and_counted(caplog: pytest.LogCaptureFixture) -> None:
    clock = Clock()
    dev = Device(clock)
    link = _link(dev, clock)
    assert link.up and link.mtu == 64
    link.send(b"a")
    dev.inbox.append(b"hello")
    assert link.recv(1.0) == b"hello"
    caplog.set_level(logging.INFO, "coex.link")
    dev.unplug()
    t0 = clock.t
    assert link.recv(0.1) is None  # the failure marks it down; recv waits, never raises
    assert not link.up
    with pytest.raises(LinkDown):
        link.send(b"b")
    # 10 minutes of a runner polling every 0.2 s while the device is gone
    opens_before = dev.opens
    for _ in range(3000):
        link.recv(0.2)
    attempts = dev.opens - opens_before
    # 0.5, 1, 2, 4, 8, 16, then every 30 s: about 6 + 590 / 30 attempts, not one per read
    assert 20 <= attempts <= 30
    h = link.health()
    assert not h.up and h.outages == 1 and h.down_total == pytest.approx(clock.t - t0, abs=0.5)
    dev.present = True
    dev.inbox.append(b"again")
    got = [link.recv(0.2) for _ in range(200)]
    assert b"again" in got and link.up
    link.send(b"c")
    assert dev.sent[-1] == b"c"
    h = link.health()
    assert h.up and h.outages == 1 and h.last_down == pytest.approx(h.down_total) and h.down_total > 600
    text = [r.getMessage() for r in caplog.records]
    assert sum("lost:" in t for t in text) == 1
    assert sum("still down" in t for t in text) == 1  # once, when the backoff reached 30 s
    assert sum("back after" in t for t in text) == 1
    assert any("back after 10 min" in t and "1 frames not sent" in t for t in text)
    assert len(text) <= 4


def test_a_device_absent_at_start_is_waited_for_unless_required() -> None:
    clock = Clock()
    dev = Device(clock)
    dev.present = False
    link = _link(dev, clock)
    assert not link.up and link.mtu == 64  # the MTU from the URI: the node is built meanwhile
    assert link.recv(5.0) is None
    dev.present = True
    for _ in range(100):
        link.recv(0.5)
    assert link.up and link.health().outages == 1
    with pytest.raises(TransportError, match="cannot open"):
        dev.present = False
        _link(dev, clock, required=True)


def test_bad_uri_and_oversized_frames_are_not_outages() -> None:
    clock = Clock()
    dev = Device(clock)
    with pytest.raises(ConfigError, match="unknown option 'mut'"):
        ResilientTransport("loopback://x?mut=64", opener=dev.open)
    link = _link(dev, clock)
    with pytest.raises(FrameTooLarge):
        link.send(bytes(65))
    assert link.up and link.health().outages == 0


def test_a_transport_that_reconnects_by_itself_is_counted_not_reopened() -> None:
    clock = Clock()
    dev = Device(clock)
    link = _link(dev, clock)
    dev.away = True  # e.g. the MOOS client while MOOSDB restarts
    link.recv(0.1)
    assert not link.up and dev.opens == 1
    clock.sleep(42.0)
    dev.away = False
    link.recv(0.1)
    h = link.health()
    assert h.up and h.outages == 1 and h.last_down == pytest.approx(42.1, abs=0.2) and dev.opens == 1


def test_a_server_waiting_for_its_client_is_not_reopened() -> None:
    clock = Clock()

    class Waiting(Fake):
        def _send_internal(self, frame: bytes) -> None:
            raise LinkDown("tcpin: no client connected")

    dev = Device(clock)
    link = ResilientTransport("loopback://x?mtu=64", clock=clock, sleep=clock.sleep,
                              opener=lambda uri: Waiting(dev))
    with pytest.raises(LinkDown):
        link.send(b"x")
    assert link.up and link.health().outages == 0 and link.health().not_sent == 1


def test_mavlink_tcp_peer_gone_and_back() -> None:
    """A real MAVLink TCP client link: the server (a MAVProxy, a SITL) closes and comes back on
    the same port; frames flow again without a restart."""
    pytest.importorskip("pymavlink")
    from coex_transports.mavlink.codec import TunnelCodec

    # a port nobody else is given (coex_transports.testing): nobody takes it while the server is
    # down, and the link's reconnections never get it as their own end
    port = free_port()
    srv = socket.socket()
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(("127.0.0.1", port))
    srv.listen(1)
    uri = f"mavlink:tcp:127.0.0.1:{port}?heartbeat=0"
    link = ResilientTransport(uri, name="link 0", first_retry=0.05, max_retry=0.2)
    conn, _ = srv.accept()
    codec = TunnelCodec(system_id=9, component_id=191, heartbeat_interval=0)  # the peer's TUNNEL bytes
    conn.sendall(b"".join(codec.encode(b"frame-1")))
    assert link.recv(5.0) == b"frame-1"
    conn.close()
    srv.close()  # the server goes away: the link sees the connection closed
    assert link.recv(1.0) is None and not link.up
    srv = socket.socket()
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(("127.0.0.1", port))
    srv.listen(1)
    got: list[bytes | None] = []
    t = threading.Thread(target=lambda: got.append(link.recv(10.0)))
    t.start()
    conn, _ = srv.accept()
    conn.sendall(b"".join(codec.encode(b"frame-2")))
    t.join(15)
    assert got == [b"frame-2"] and link.up and link.health().outages == 1
    link.close()
    conn.close()
    srv.close()


@pytest.mark.parametrize(("uri", "words"), [
    ("micromodem:///dev/ttyUSB0?dst=1", "unknown option 'dst'"),
    ("micromodem:///dev/ttyUSB0?rate=9", "rate 9 is not valid"),
    ("micromodem:socket://127.0.0.1?src=2", "expected HOST:PORT"),
    ("mavlink:udpot:127.0.0.1:14550", "connection kind must be one of"),
    ("mavlink:udpout:127.0.0.1:14550?mtu=99999", "mtu must be"),
    ("lcm:udpm://239.255.76.67:7667?ttl=0&chanel=COEX", "unknown option 'chanel'"),
    ("moos://localhost:9000?nme=pCoex", "unknown option 'nme'"),
    ("loopback://x?mtu=0", "option mtu: 0 is below 1"),
])
def test_every_transport_checks_its_uri_without_opening_anything(uri: str, words: str) -> None:
    with pytest.raises(ConfigError, match=words):
        check_transport_uri(uri)


def test_check_uri_says_mtu_devices_and_rate() -> None:
    info = check_transport_uri("micromodem:///dev/ttyUSB7?rate=1")
    assert (info.mtu, info.paths, info.rate) == (64, ("/dev/ttyUSB7",), 1)
    assert check_transport_uri("mavlink:serial:/dev/ttyACM3:57600").paths == ("/dev/ttyACM3",)
    assert check_transport_uri("moos://localhost:9000?mtu=512").mtu == 512
    assert check_transport_uri("micromodem:socket://127.0.0.1:4001").paths == ()


def test_describe_seconds() -> None:
    assert [describe_seconds(s) for s in (4.4, 60, 192, 7500)] == ["4 s", "1 min", "3 min 12 s", "2 h 5 min"]


def test_moosdb_restarted_under_a_resilient_link_is_counted_and_nothing_lost(moosdb_path: str) -> None:
    """The MOOS client reconnects by itself: the link counts the outage (the vehicle tells topside)
    and never reopens it; frames sent meanwhile arrive after MOOSDB is back."""
    from ._moos import MoosDB, unique

    db = MoosDB(moosdb_path)
    db.start()
    try:
        a_name, b_name = unique("a"), unique("b")
        base = f"moos://127.0.0.1:{db.port}"
        a = ResilientTransport(f"{base}?name={a_name}&tx=X_UP&rx=X_DOWN&hold=3", name="link 0")
        b = ResilientTransport(f"{base}?name={b_name}&tx=X_DOWN&rx=X_UP&hold=3", name="peer")
        a.send(b"one")
        assert b.recv(timeout=10) == b"one"
        db.stop()
        end = time.monotonic() + 20
        while a.up and time.monotonic() < end:
            a.recv(0.2)
        assert not a.up and a.health().outages == 1
        a.send(b"two")  # queued by the MOOS client while MOOSDB is away
        db.start()
        assert b.recv(timeout=20) == b"two"
        end = time.monotonic() + 20
        while not a.up and time.monotonic() < end:
            a.recv(0.2)
        h = a.health()
        assert h.up and h.outages == 1 and h.last_down > 0
        a.close()
        b.close()
    finally:
        db.close()


def test_lcm_link_that_fails_is_reopened_and_frames_flow_again() -> None:
    """A real LCM multicast end whose LCM instance fails (a network interface gone down and up
    breaks a multicast membership; LCM then fails to publish or handle): the resilient link makes
    a new LCM instance, which joins again, and frames flow."""
    pytest.importorskip("lcm")
    from ._modemsim import free_tcp_base

    port = free_tcp_base(1, socket.SOCK_DGRAM)
    url = f"udpm://239.255.76.67:{port}?ttl=0"
    link = ResilientTransport(f"lcm:{url}&tx=R_UP&rx=R_DOWN", name="link 0", first_retry=0.05, max_retry=0.2)
    peer = ResilientTransport(f"lcm:{url}&tx=R_DOWN&rx=R_UP", name="peer")
    try:
        link.send(b"before")
        assert peer.recv(5.0) == b"before"

        class Broken:
            def publish(self, *a: Any) -> None:
                raise OSError("Network is unreachable")

            def handle_timeout(self, *a: Any) -> None:
                raise OSError("Network is down")

            def unsubscribe(self, *a: Any) -> None:
                raise OSError("gone")

        inner = link.inner
        assert inner is not None
        inner._inst.lcm = Broken()  # type: ignore[attr-defined]
        with pytest.raises(LinkDown):
            link.send(b"lost")
        assert not link.up
        end = time.monotonic() + 10
        while not link.up and time.monotonic() < end:
            link.recv(0.1)
        assert link.up and link.inner is not inner and link.health().outages == 1
        link.send(b"after")
        assert peer.recv(5.0) == b"after"
        peer.send(b"back")
        assert link.recv(5.0) == b"back"
    finally:
        link.close()
        peer.close()


def test_a_packet_that_never_left_is_sent_again_at_once_and_is_not_an_acoustic_loss() -> None:
    from coex_core import wire
    from coex_core.channel import ChannelManager, LinkConfig, Schedule
    from coex_core.messages import QueueConfig
    from coex_core.node import Node

    def commands(txs: list[Any]) -> list[Any]:
        return [m for t in txs for f in t.frames for m in wire.unpack_frame(f).messages
                if isinstance(m, QueueConfig)]

    def node() -> Node:
        return Node(ChannelManager(1, [LinkConfig(0, Schedule.simple([1, 2], 10.0, 1.0), rate=5, dst=2)]))

    for down in (False, True):
        top = node()
        top.queue_config(3, 0.0, enabled=False)
        [tx] = top.poll(0.0)  # slot 0 is topside's
        assert len(commands([tx])) == 1
        if down:
            top.not_sent(tx, 0.5)  # the modem was down: it never left
        again = commands([t for now in (4.0, 5.0, 6.0) for t in top.poll(now)])
        if down:  # sent again in the same slot, not one ack timeout (a whole cycle) later
            assert len(again) == 1
            assert top.manager.stats["not_sent_frames"] == len(tx.frames)
            assert not top.manager.frame_loss(0)  # not frames the water lost
        else:
            assert again == []  # it waits for its ack
