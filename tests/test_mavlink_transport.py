"""MavlinkTransport over real sockets (loopback only), a pty serial line, and stock pymavlink.

The stock-pymavlink peers run in a subprocess: ``pymavlink.mavutil`` changes process-wide state
when imported, and a separate process is what a ground station or router is anyway. They use the
common dialect only and know nothing of CoEx except the binding in ``spec/bindings/mavlink.md``.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from coex_core.errors import ConfigError, FrameTooLarge, TransportError
from coex_core.messages import FrameHeader, Opaque
from coex_core.registry import open_transport
from coex_core.wire import pack, unpack_frame
from coex_transports.mavlink import PAYLOAD_TYPE, MavlinkTransport, parse_mavlink_uri, split_frame
from coex_transports.testing import free_port as free_tcp_port
from coex_transports.testing import free_port as free_udp_port


def coex_frames() -> list[bytes]:
    """Real CoEx frames: small ones and multi-fragment ones (with and without a CoEx CRC)."""
    small = pack([Opaque(96, b"\x01\x02"), Opaque(200, bytes(16))], 256, FrameHeader(src=2, dst=1, seq=7))
    exact = pack([Opaque(300, bytes(range(118)))], 256, FrameHeader(src=3))
    big = pack([Opaque(200, bytes(range(200)))] * 5, 2048, FrameHeader(src=2, dst=1, seq=9, crc=True))
    huge = pack([Opaque(4000 + i, bytes([i]) * 240) for i in range(8)], 2048, FrameHeader(src=1, seq=200))
    assert len(exact) == 124 and 124 < len(big) < len(huge) <= 2048
    return [small, exact, big, huge]


@pytest.fixture
def udp_pair() -> Iterator[tuple[MavlinkTransport, MavlinkTransport]]:
    a = MavlinkTransport.from_uri("mavlink:udpin:127.0.0.1:0?sysid=1&compid=191")
    port = a.link.local[1]  # type: ignore[attr-defined]
    b = MavlinkTransport.from_uri(f"mavlink:udpout:127.0.0.1:{port}?sysid=2&compid=191")
    assert a.recv(timeout=0.3) is None  # a hears b's heartbeat and learns where b is
    yield a, b
    a.close()
    b.close()


# ------------------------------------------------------------------------------------ URIs
@pytest.mark.parametrize(
    ("uri", "kind", "address", "port"),
    [
        ("mavlink:udpout:127.0.0.1:14550?sysid=1&compid=191", "udpout", "127.0.0.1", 14550),
        ("mavlink:udpin:0.0.0.0:14550", "udpin", "0.0.0.0", 14550),
        ("mavlink:tcp:localhost:5760", "tcp", "localhost", 5760),
        ("mavlink:tcpin:0.0.0.0:5760", "tcpin", "0.0.0.0", 5760),
        ("mavlink:serial:/dev/ttyUSB0:57600", "serial", "/dev/ttyUSB0", 57600),
        ("mavlink:serial:/dev/ttyACM0", "serial", "/dev/ttyACM0", 57600),
        ("mavlink:serial:loop://", "serial", "loop://", 57600),
    ],
)
def test_uri_forms(uri: str, kind: str, address: str, port: int) -> None:
    ep = parse_mavlink_uri(uri)
    assert (ep.kind, ep.address, ep.port) == (kind, address, port)


def test_uri_options_reach_the_codec() -> None:
    t = MavlinkTransport.from_uri(
        "mavlink:udpout:127.0.0.1:9?sysid=12&compid=34&target_system=5&target_component=6"
        "&payload_type=40000&mtu=600&heartbeat=0&reassembly_timeout=2.5&max_partial=3"
    )
    try:
        c = t.codec
        assert (c.system_id, c.component_id, c.target_system, c.target_component) == (12, 34, 5, 6)
        assert (c.payload_type, t.mtu, c.heartbeat_interval) == (40000, 600, 0.0)
        assert (c.reassembler.timeout, c.reassembler.max_partial) == (2.5, 3)
    finally:
        t.close()


@pytest.mark.parametrize(
    "uri",
    [
        "mavlink:udpfoo:127.0.0.1:1",
        "mavlink:udpout:127.0.0.1",
        "mavlink:udpout:127.0.0.1:notaport",
        "mavlink:udpout:127.0.0.1:70000",
        "mavlink:udpout:127.0.0.1:1?sysid=0",
        "mavlink:udpout:127.0.0.1:1?compid=300",
        "mavlink:udpout:127.0.0.1:1?payload_type=5",
        "mavlink:udpout:127.0.0.1:1?mtu=40000",
        "mavlink:udpout:127.0.0.1:1?colour=red",
        "mavlink:udpout:127.0.0.1:1?sysid=x",
        "mavlink:serial:",
        "micromodem:udpout:127.0.0.1:1",
    ],
)
def test_bad_uris_raise_config_error(uri: str) -> None:
    with pytest.raises(ConfigError):
        MavlinkTransport.from_uri(uri)


def test_open_transport_finds_the_plugin() -> None:
    with open_transport("mavlink:udpout:127.0.0.1:9?heartbeat=0") as t:
        assert isinstance(t, MavlinkTransport) and t.mtu == 2048


# --------------------------------------------------------------------- two CoEx nodes, UDP
def test_two_coex_nodes_exchange_frames_over_udp(udp_pair: tuple[MavlinkTransport, MavlinkTransport]) -> None:
    a, b = udp_pair
    frames = coex_frames()
    for f in frames:
        a.send(f)
    got = [b.recv(timeout=3.0) for _ in frames]
    assert got == frames
    assert [unpack_frame(g) for g in got if g is not None] == [unpack_frame(f) for f in frames]
    for f in reversed(frames):
        b.send(f)
    assert [a.recv(timeout=3.0) for _ in frames] == frames[::-1]
    assert a.stats()["rejected"] == 0 and b.stats()["rejected"] == 0
    assert (2, 191) in a.stats()["peers"] and (1, 191) in b.stats()["peers"]


def test_udpin_without_peer_refuses_to_send() -> None:
    with MavlinkTransport.from_uri("mavlink:udpin:127.0.0.1:0?heartbeat=0") as t, \
            pytest.raises(TransportError, match="no peer"):
        t.send(b"abc")


def test_over_mtu_refused_and_nothing_sent(udp_pair: tuple[MavlinkTransport, MavlinkTransport]) -> None:
    a, b = udp_pair
    sent = a.stats()["packets_sent"]
    with pytest.raises(FrameTooLarge):
        a.send(bytes(2049))
    assert a.stats()["packets_sent"] == sent
    a.send(b"ok")
    assert b.recv(timeout=2.0) == b"ok"


def test_target_system_is_honoured() -> None:
    """Three nodes on one udpin: a frame addressed to system 3 reaches 3 and not 2."""
    hub = MavlinkTransport.from_uri("mavlink:udpin:127.0.0.1:0?sysid=1&heartbeat=0")
    port = hub.link.local[1]  # type: ignore[attr-defined]
    two = MavlinkTransport.from_uri(f"mavlink:udpout:127.0.0.1:{port}?sysid=2")
    three = MavlinkTransport.from_uri(f"mavlink:udpout:127.0.0.1:{port}?sysid=3")
    try:
        hub.recv(timeout=0.3)
        hub.recv(timeout=0.1)
        assert len(hub.link.peers) == 2  # type: ignore[attr-defined]
        hub.codec.target_system = 3
        hub.send(b"for three only")
        hub.codec.target_system = 0
        hub.send(b"for everyone")
        assert three.recv(timeout=2.0) == b"for three only"
        assert three.recv(timeout=2.0) == b"for everyone"
        assert two.recv(timeout=2.0) == b"for everyone"
        assert two.recv(timeout=0.2) is None
        assert two.stats()["not_for_us"] == 1
    finally:
        for t in (hub, two, three):
            t.close()


def test_malformed_and_oversize_datagrams_rejected_good_frame_kept() -> None:
    """Raw datagrams from a hostile peer: each bad one is counted and the good one delivered."""
    with MavlinkTransport.from_uri("mavlink:udpin:127.0.0.1:0?heartbeat=0") as t:
        port = t.link.local[1]  # type: ignore[attr-defined]
        mav = mavlink2.MAVLink(None, 9, 1)

        def tunnel(payload: bytes, length: int | None = None) -> bytes:
            body = list(payload) + [0] * (128 - len(payload))
            n = len(payload) if length is None else length
            return bytes(mav.tunnel_encode(0, 0, PAYLOAD_TYPE, n, body).pack(mav))

        good = tunnel(split_frame(b"the good frame", 3)[0])
        bad = [
            tunnel(bytes([0x10, 0, 0, 1]) + bytes(124), length=129),  # payload_length > 128
            tunnel(bytes([0x10, 0, 0, 1]) + bytes(124), length=255),
            tunnel(bytes([0x10, 1, 0, 2]) + b"short"),  # non-last fragment not 124 B
            tunnel(bytes([0x10, 2, 5, 2]) + b"x"),  # index >= count
            tunnel(bytes([0x10, 4, 0, 200]) + bytes(124)),  # frame above the 2048 B MTU
            good[:20],  # truncated
            b"\x00" * 40,  # noise
            good[:-2] + b"\x00\x00",  # bad CRC
        ]
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for d in bad:
                s.sendto(d, ("127.0.0.1", port))
            s.sendto(good, ("127.0.0.1", port))
            assert t.recv(timeout=2.0) == b"the good frame"
        st = t.stats()
        assert st["rejected"] == len(bad), st
        assert st["frames_received"] == 1
        assert "exceeds 128" in " ".join(str(e) for e in t.codec.errors)


def test_lost_fragment_never_delivers_a_partial_frame() -> None:
    with MavlinkTransport.from_uri("mavlink:udpin:127.0.0.1:0?heartbeat=0&reassembly_timeout=0.2") as t:
        port = t.link.local[1]  # type: ignore[attr-defined]
        sender = MavlinkTransport.from_uri(f"mavlink:udpout:127.0.0.1:{port}?sysid=4&heartbeat=0")
        packets = sender.codec.encode(bytes(range(256)) * 2)  # 5 fragments
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for p in packets[:2] + packets[3:]:
                s.sendto(p, ("127.0.0.1", port))
            assert t.recv(timeout=0.5) is None
            s.sendto(sender.codec.encode(b"next")[0], ("127.0.0.1", port))
            assert t.recv(timeout=2.0) == b"next"
        assert t.stats()["reassembly_expired"] == 1
        assert t.stats()["reassembly_partial"] == 0
        sender.close()


def test_heartbeats_are_periodic_while_waiting() -> None:
    with MavlinkTransport.from_uri("mavlink:udpin:127.0.0.1:0?heartbeat=0") as ear:
        port = ear.link.local[1]  # type: ignore[attr-defined]
        with MavlinkTransport.from_uri(f"mavlink:udpout:127.0.0.1:{port}?sysid=8&heartbeat=0.1") as node:
            node.recv(timeout=0.55)  # nothing to receive; it still beats while it waits
        ear.recv(timeout=0.2)
        assert ear.codec.peers.get((8, 191)) is not None
        assert 3 <= ear.stats()["packets_received"] <= 8  # 6 expected; slack for a loaded CI


# -------------------------------------------------------------------------- TCP and serial
def test_tcp_client_and_server() -> None:
    port = free_tcp_port()
    server = MavlinkTransport.from_uri(f"mavlink:tcpin:127.0.0.1:{port}?sysid=1")
    client = MavlinkTransport.from_uri(f"mavlink:tcp:127.0.0.1:{port}?sysid=2")
    try:
        frames = coex_frames()
        for f in frames:
            client.send(f)
        assert [server.recv(timeout=3.0) for _ in frames] == frames
        for f in frames:
            server.send(f)
        assert [client.recv(timeout=3.0) for _ in frames] == frames
    finally:
        client.close()
        server.close()


def test_tcp_peer_gone_and_no_client_are_transport_errors() -> None:
    port = free_tcp_port()
    server = MavlinkTransport.from_uri(f"mavlink:tcpin:127.0.0.1:{port}?heartbeat=0")
    try:
        with pytest.raises(TransportError, match="no client"):
            server.send(b"nobody listens")
        client = MavlinkTransport.from_uri(f"mavlink:tcp:127.0.0.1:{port}?sysid=2&heartbeat=0")
        client.send(b"hi")
        assert server.recv(timeout=2.0) == b"hi"
        server.close()
        with pytest.raises(TransportError, match="closed by peer"):
            client.recv(timeout=2.0)
        client.close()
    finally:
        server.close()


def test_tcp_connect_refused_is_transport_error() -> None:
    with pytest.raises(TransportError):
        MavlinkTransport.from_uri(f"mavlink:tcp:127.0.0.1:{free_tcp_port()}")


@pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs a POSIX pty")
def test_serial_over_a_pty_with_line_noise() -> None:
    master, slave = os.openpty()
    name = os.ttyname(slave)
    t = MavlinkTransport.from_uri(f"mavlink:serial:{name}:115200?sysid=1&heartbeat=0")
    peer = MavlinkTransport.from_uri("mavlink:udpout:127.0.0.1:9?sysid=2&heartbeat=0")  # codec only
    try:
        frames = coex_frames()
        # the peer's packets, with line noise between them, cut into odd pieces
        stream = b"".join(b"\x00\xfd\x07noise" + p for f in frames for p in peer.codec.encode(f))
        for i in range(0, len(stream), 97):
            os.write(master, stream[i:i + 97])
        assert [t.recv(timeout=3.0) for _ in frames] == frames
        # and the other way: what we write comes out of the pty as TUNNEL packets
        t.send(frames[2])
        t.flush()
        got: list[bytes] = []
        deadline = time.monotonic() + 3.0
        while not got and time.monotonic() < deadline:
            got = peer.codec.receive(os.read(master, 4096), 0.0)
        assert got == [frames[2]]
    finally:
        t.close()
        peer.close()
        os.close(master)
        os.close(slave)


def test_serial_open_failure_is_transport_error() -> None:
    with pytest.raises(TransportError):
        MavlinkTransport.from_uri("mavlink:serial:/dev/does-not-exist-coex:57600")


# ------------------------------------------------------------------- stock pymavlink peer
STOCK_PEER = textwrap.dedent(
    """
    import json, os, sys, time
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil
    port, want, payload_type = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
    conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", dialect="common",
                                      source_system=42, source_component=1)
    print("ready", flush=True)
    deadline = time.monotonic() + 20
    tunnels, heartbeats = [], []
    while len(tunnels) < want and time.monotonic() < deadline:
        m = conn.recv_match(blocking=True, timeout=0.5)
        if m is None:
            continue
        t = m.get_type()
        if t == "HEARTBEAT":
            heartbeats.append([m.get_srcSystem(), m.get_srcComponent(), m.type, m.autopilot])
        elif t == "TUNNEL":
            tunnels.append(dict(src=[m.get_srcSystem(), m.get_srcComponent()],
                                payload_type=m.payload_type, payload_length=m.payload_length,
                                target=[m.target_system, m.target_component],
                                payload=bytes(m.payload).hex()))
            # echo each TUNNEL back with stock pymavlink (it answers the last sender)
            conn.mav.tunnel_send(m.get_srcSystem(), m.get_srcComponent(), m.payload_type,
                                 m.payload_length, m.payload)
    print(json.dumps(dict(tunnels=tunnels, heartbeats=heartbeats)), flush=True)
    """
)


def _reassemble_per_spec(tunnels: list[dict[str, object]]) -> list[bytes]:
    """An independent reading of spec/bindings/mavlink.md: 4-byte header, 124-byte chunks."""
    frames: list[bytes] = []
    parts: dict[int, bytes] = {}
    for t in tunnels:
        payload = bytes.fromhex(str(t["payload"]))[: int(str(t["payload_length"]))]
        version, frame_id, index, count = payload[0] >> 4, payload[1], payload[2], payload[3]
        assert version == 1 and payload[0] & 0xF == 0
        parts[index] = payload[4:]
        if len(parts) == count:
            frames.append(b"".join(parts[i] for i in range(count)))
            parts = {}
        del frame_id
    return frames


def test_stock_pymavlink_reads_our_tunnels_and_answers() -> None:
    frames = coex_frames()
    packets = sum(max(1, -(-len(f) // 124)) for f in frames)
    port = free_udp_port()
    env = {k: v for k, v in os.environ.items() if k not in ("MAVLINK_DIALECT", "MAVLINK20")}
    proc = subprocess.Popen(
        [sys.executable, "-c", STOCK_PEER, str(port), str(packets), str(PAYLOAD_TYPE)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "ready"
        with MavlinkTransport.from_uri(f"mavlink:udpout:127.0.0.1:{port}?sysid=5&compid=191") as t:
            for f in frames:
                t.send(f)
            echoed = [t.recv(timeout=10.0) for _ in frames]
            out, err = proc.communicate(timeout=30)
            assert proc.returncode == 0, err
            report = json.loads(out.strip().splitlines()[-1])
            stats = t.stats()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    tunnels = report["tunnels"]
    assert len(tunnels) == packets
    for tun in tunnels:
        assert tun["src"] == [5, 191] and tun["payload_type"] == PAYLOAD_TYPE == 0xC0E5
        assert tun["target"] == [0, 0] and 4 < tun["payload_length"] <= 128
    # the stock reader's payloads decode as CoEx frames
    received = _reassemble_per_spec(tunnels)
    assert received == frames
    assert [unpack_frame(r) for r in received] == [unpack_frame(f) for f in frames]
    # it saw our heartbeat: an onboard controller with our ids
    assert [5, 191, mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_AUTOPILOT_INVALID] in report["heartbeats"]
    # and the TUNNELs stock pymavlink sent back were reassembled into the same frames
    assert echoed == frames
    assert stats["rejected"] == 0


def test_serial_url_handler_echo_is_ignored() -> None:
    """pyserial's ``loop://`` echoes what we write: our own packets come back and are ignored."""
    with MavlinkTransport.from_uri("mavlink:serial:loop://?heartbeat=0") as t:
        assert t.link._fd is None  # type: ignore[attr-defined]  # the pyserial-timeout path
        t.send(b"echo")
        assert t.recv(timeout=0.3) is None
        assert t.stats()["own"] == 1 and t.stats()["frames_received"] == 0
