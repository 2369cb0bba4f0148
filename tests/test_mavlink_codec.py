"""The sans-I/O side of the MAVLink binding: fragmentation, reassembly, TunnelCodec."""

from __future__ import annotations

import os
import random
import subprocess
import sys

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink2

from coex_core.errors import ConfigError, DecodeError, EncodeError
from coex_transports.mavlink import (
    CHUNK_BYTES,
    MAX_FRAME_BYTES,
    PAYLOAD_TYPE,
    Fragment,
    Reassembler,
    TunnelCodec,
    fragments_needed,
    parse_fragment,
    split_frame,
)


def _frame(n: int, seed: int = 0) -> bytes:
    return random.Random(seed * 100003 + n).randbytes(n)


def _tunnel(payload: bytes, *, payload_length: int | None = None, sysid: int = 7, compid: int = 1,
            payload_type: int = PAYLOAD_TYPE, target: tuple[int, int] = (0, 0)) -> bytes:
    """A TUNNEL packet built by stock pymavlink (valid CRC), payload zero-filled to 128."""
    mav = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    length = len(payload) if payload_length is None else payload_length
    body = list(payload) + [0] * (128 - len(payload))
    return bytes(mav.tunnel_encode(target[0], target[1], payload_type, length, body).pack(mav))


# --------------------------------------------------------------------------- fragmentation
@pytest.mark.parametrize("size", [0, 1, 123, 124, 125, 248, 249, 2048, MAX_FRAME_BYTES])
def test_split_then_parse_roundtrip(size: int) -> None:
    frame = _frame(size)
    payloads = split_frame(frame, 42)
    assert len(payloads) == fragments_needed(size) == max(1, -(-size // 124))
    assert all(len(p) <= 128 for p in payloads)
    frags = [parse_fragment(p) for p in payloads]
    assert [f.index for f in frags] == list(range(len(frags)))
    assert {f.count for f in frags} == {len(frags)} and {f.frame_id for f in frags} == {42}
    assert b"".join(f.chunk for f in frags) == frame
    # every fragment but the last carries exactly CHUNK_BYTES
    assert all(len(f.chunk) == CHUNK_BYTES for f in frags[:-1])


def test_fragment_header_layout_is_as_specified() -> None:
    payloads = split_frame(bytes(range(130)), 0x2A)
    assert payloads[0][:4] == bytes([0x10, 0x2A, 0, 2])
    assert payloads[1] == bytes([0x10, 0x2A, 1, 2]) + bytes(range(124, 130))


def test_split_refuses_oversize_and_bad_id() -> None:
    with pytest.raises(EncodeError):
        split_frame(bytes(MAX_FRAME_BYTES + 1), 0)
    with pytest.raises(EncodeError):
        split_frame(b"x", 256)


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (b"", "truncated"),
        (b"\x10\x00\x00", "truncated"),
        (bytes([0x10, 0, 0, 1]) + bytes(125), "exceeds"),  # 129 bytes
        (bytes([0x20, 0, 0, 1]) + b"abc", "version"),
        (bytes([0x11, 0, 0, 1]) + b"abc", "reserved"),
        (bytes([0x10, 0, 0, 0]) + b"abc", "count is 0"),
        (bytes([0x10, 0, 3, 3]) + b"abc", "not below"),
        (bytes([0x10, 0, 0, 2]) + b"abc", "exactly 124"),
        (bytes([0x10, 0, 1, 2]), "empty"),
    ],
)
def test_parse_fragment_rejects_malformed(payload: bytes, reason: str) -> None:
    with pytest.raises(DecodeError, match=reason):
        parse_fragment(payload)


def test_parse_fragment_rejects_non_bytes() -> None:
    with pytest.raises(DecodeError):
        parse_fragment("abcd")  # type: ignore[arg-type]


# ------------------------------------------------------------------------------ reassembly
def _frags(frame: bytes, frame_id: int = 1) -> list[Fragment]:
    return [parse_fragment(p) for p in split_frame(frame, frame_id)]


def test_reassembly_any_order() -> None:
    frame = _frame(1000)
    frags = _frags(frame)
    random.Random(3).shuffle(frags)
    r = Reassembler(max_frame=2048)
    out = [r.add("a", f, 0.0) for f in frags]
    assert out[:-1] == [None] * (len(frags) - 1) and out[-1] == frame
    assert len(r) == 0 and r.buffered_bytes == 0


def test_partial_frame_is_never_delivered_and_expires() -> None:
    frame = _frame(600)
    frags = _frags(frame)
    r = Reassembler(timeout=2.0, max_frame=2048)
    for f in frags[:-2] + frags[-1:]:  # fragment n-2 lost
        assert r.add("a", f, 0.5) is None
    assert len(r) == 1 and r.buffered_bytes > 0
    assert r.expire(2.4) == 0
    assert r.expire(2.6) == 1 and len(r) == 0 and r.expired == 1
    # the lost fragment arriving late starts a new partial that can never complete
    assert r.add("a", frags[-2], 3.0) is None
    assert r.add("a", frags[0], 3.0) is None
    r.expire(100.0)
    assert r.completed == 0 and len(r) == 0


def test_memory_is_bounded_by_max_partial() -> None:
    r = Reassembler(max_partial=3, max_frame=2048)
    for fid in range(50):
        r.add("a", _frags(_frame(2048, fid), fid % 256)[0], float(fid) * 0.01)
        assert len(r) <= 3
    assert r.evicted == 47
    assert r.buffered_bytes <= 3 * 124


def test_sources_are_kept_apart() -> None:
    f1, f2 = _frame(300, 1), _frame(300, 2)
    a, b = _frags(f1, 5), _frags(f2, 5)  # same frame id from two senders
    r = Reassembler()
    got = [r.add(src, frag, 0.0) for pair in zip(a, b) for src, frag in zip(("x", "y"), pair)]
    assert [g for g in got if g is not None] == [f1, f2]


def test_frame_id_reuse_drops_stale_partial() -> None:
    old, new = _frame(500, 1), _frame(300, 2)
    r = Reassembler()
    for f in _frags(old, 9)[:2]:
        r.add("a", f, 0.0)
    got = [r.add("a", f, 0.1) for f in _frags(new, 9)]  # different count -> conflict
    assert got[-1] == new and r.conflicts == 1
    # same count, different bytes at a held index: conflict too, and no mixed frame comes out
    a, b = _frame(300, 3), _frame(300, 4)
    fa, fb = _frags(a, 1), _frags(b, 1)
    r.add("a", fa[0], 0.2)
    assert r.add("a", fb[0], 0.2) is None
    assert r.add("a", fb[1], 0.2) is None
    assert r.add("a", fb[2], 0.2) == b
    assert r.conflicts == 2


def test_identical_duplicate_is_ignored() -> None:
    frame = _frame(300)
    fr = _frags(frame)
    r = Reassembler()
    assert r.add("a", fr[0], 0) is None
    assert r.add("a", fr[0], 0) is None
    assert r.add("a", fr[1], 0) is None
    assert r.add("a", fr[2], 0) == frame
    assert r.duplicates == 1


def test_oversize_frame_rejected() -> None:
    r = Reassembler(max_frame=200)
    big = _frags(_frame(400))  # 4 fragments > 2 allowed
    with pytest.raises(DecodeError, match="MTU"):
        r.add("a", big[0], 0)
    two = _frags(_frame(240))  # 2 fragments, 240 B > 200
    assert r.add("a", two[0], 0) is None
    with pytest.raises(DecodeError, match="MTU"):
        r.add("a", two[1], 0)
    assert r.oversize == 2 and r.completed == 0


@pytest.mark.parametrize("kwargs", [{"timeout": 0}, {"max_partial": 0}, {"max_frame": MAX_FRAME_BYTES + 1}])
def test_reassembler_config_checked(kwargs: dict[str, float]) -> None:
    with pytest.raises(ConfigError):
        Reassembler(**kwargs)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------- TunnelCodec
def _pair(**kw: int) -> tuple[TunnelCodec, TunnelCodec]:
    return TunnelCodec(system_id=1, component_id=191, **kw), TunnelCodec(system_id=2, component_id=191)


def test_codec_roundtrip_stream_and_datagrams() -> None:
    a, b = _pair()
    frames = [_frame(n, 7) for n in (3, 124, 125, 700, 2048)]
    packets = [p for f in frames for p in a.encode(f)]
    assert len(packets) == sum(fragments_needed(len(f)) for f in frames)
    # one datagram per packet
    assert [f for p in packets for f in b.receive(p, 0.0, datagram=True)] == frames
    # the same bytes as a stream, cut at random places
    c = TunnelCodec(system_id=3)
    stream = b"".join(p for f in frames for p in a.encode(f))
    rng = random.Random(1)
    got: list[bytes] = []
    i = 0
    while i < len(stream):
        j = i + rng.randint(1, 300)
        got += c.receive(stream[i:j], 0.0)
        i = j
    assert got == frames
    assert b.counters["rejected"] == 0 and c.counters["rejected"] == 0


def test_codec_packets_are_tunnel_messages_with_configured_ids() -> None:
    a = TunnelCodec(system_id=9, component_id=77, target_system=4, target_component=5)
    reader = mavlink2.MAVLink(None)
    msgs = reader.parse_buffer(b"".join(a.encode(_frame(300))))
    assert msgs is not None and len(msgs) == 3
    for i, m in enumerate(msgs):
        assert m.get_type() == "TUNNEL"
        assert (m.get_srcSystem(), m.get_srcComponent()) == (9, 77)
        assert (m.target_system, m.target_component, m.payload_type) == (4, 5, PAYLOAD_TYPE)
        assert m.get_seq() == i  # the MAVLink sequence number advances per packet
    assert [m.payload_length for m in msgs] == [128, 128, 4 + 300 - 248]


def test_codec_refuses_oversize_frame() -> None:
    a = TunnelCodec(mtu=500)
    with pytest.raises(EncodeError):
        a.encode(bytes(501))
    assert len(a.encode(bytes(500))) == 5


def test_heartbeat_schedule_and_content() -> None:
    a = TunnelCodec(system_id=3, component_id=191, heartbeat_interval=1.0)
    assert len(a.poll(10.0)) == 1  # first poll: at once
    assert a.poll(10.5) == []
    assert a.next_deadline() == 11.0
    beats = a.poll(11.0)
    assert len(beats) == 1
    hb = mavlink2.MAVLink(None).parse_buffer(beats[0])
    assert hb is not None and hb[0].get_type() == "HEARTBEAT"
    assert (hb[0].get_srcSystem(), hb[0].get_srcComponent()) == (3, 191)
    assert hb[0].type == mavlink2.MAV_TYPE_ONBOARD_CONTROLLER
    assert hb[0].autopilot == mavlink2.MAV_AUTOPILOT_INVALID
    assert a.poll(11.2, can_send=False) == []
    assert TunnelCodec(heartbeat_interval=0).poll(0.0) == []
    # the receiver records who it heard
    b = TunnelCodec(system_id=4)
    assert b.receive(beats[0], 5.0) == []
    assert b.peers == {(3, 191): 5.0}


def test_target_filter_own_echo_and_foreign_payload_type() -> None:
    me = TunnelCodec(system_id=1, component_id=191)
    one = _tunnel(split_frame(b"hello", 0)[0])
    assert me.receive(one, 0.0) == [b"hello"]
    assert me.receive(_tunnel(split_frame(b"x", 1)[0], target=(2, 0)), 0) == []
    assert me.receive(_tunnel(split_frame(b"x", 1)[0], target=(1, 5)), 0) == []
    assert me.counters["not_for_us"] == 2
    assert me.receive(_tunnel(split_frame(b"to me", 1)[0], target=(1, 191)), 0) == [b"to me"]
    assert me.receive(_tunnel(split_frame(b"x", 2)[0], sysid=1, compid=191), 0) == []
    assert me.counters["own"] == 1
    assert me.receive(_tunnel(split_frame(b"x", 3)[0], payload_type=32768), 0) == []
    assert me.counters["other_payload_type"] == 1
    assert me.counters["rejected"] == 0


def test_malformed_tunnels_rejected_and_next_good_one_kept() -> None:
    me = TunnelCodec()
    good = _tunnel(split_frame(b"good frame", 0)[0])
    bad = [
        _tunnel(bytes([0x10, 0, 0, 1]) + bytes(124), payload_length=200),  # payload_length > 128
        _tunnel(bytes([0x10, 0, 0, 1]) + b"ab" + b"\x01", payload_length=6),  # non-zero tail
        _tunnel(b"\x10\x00"),  # shorter than the fragment header
        _tunnel(bytes([0x30, 0, 0, 1]) + b"x"),  # bad version
        good[:-1] + bytes([good[-1] ^ 0xFF]),  # CRC
    ]
    got = me.receive(b"".join(bad) + good, 0.0)
    assert got == [b"good frame"]
    assert me.counters["rejected"] == len(bad)
    reasons = " | ".join(str(e) for e in me.errors)
    for word in ("payload_length 200 exceeds 128", "non-zero bytes after", "truncated", "version", "CRC"):
        assert word in reasons
    assert all(isinstance(e, DecodeError) for e in me.errors)


@pytest.mark.parametrize(
    "junk",
    [
        # MAVLink 2 TUNNEL header with a huge length: fails its CRC once complete
        bytes([0xFD, 0xFF, 0x00, 0x00, 0x00, 0x01, 0x01, 0x81, 0x01, 0x00]),
        # MAVLink 2 header of an implausible id (0x563412): pymavlink cannot check its CRC
        bytes([0xFD, 0xFF, 0x00, 0x00, 0x00, 0x01, 0x01, 0x12, 0x34, 0x56]),
        # MAVLink 1 header of an id common.xml lacks (154): no CRC check possible either
        bytes([0xFE, 0xFF, 0x00, 0x01, 0x01, 0x9A]),
        # line noise
        bytes([0x00, 0xFD, 0x13, 0xFE]),
    ],
)
def test_resync_finds_good_packet_behind_false_start(junk: bytes) -> None:
    good = _tunnel(split_frame(b"behind the junk", 0)[0])
    for datagram in (True, False):
        me = TunnelCodec()
        got = me.receive(junk + good, 0.0, datagram=datagram)
        if not datagram:  # a stream waits for the false start's length, then re-scans
            got += me.receive(bytes(300), 0.0)
        assert got == [b"behind the junk"], datagram
        assert me.counters["rejected"] + me.counters["other_messages"] >= 1


def test_truncated_packet_at_end_of_datagram_is_rejected_not_kept() -> None:
    me = TunnelCodec()
    good = _tunnel(split_frame(b"abc", 0)[0])
    assert me.receive(good[:-5], 0.0, datagram=True) == []
    assert me.counters["rejected"] == 1
    assert "truncated MAVLink packet" in str(me.errors[0])
    # the next datagram starts clean
    assert me.receive(good, 0.0, datagram=True) == [b"abc"]


def test_other_messages_and_mavlink1_are_ignored() -> None:
    mav = mavlink2.MAVLink(None, 5, 1)
    other = mav.param_request_list_encode(0, 0).pack(mav)
    v1 = mav.heartbeat_encode(2, 3, 0, 0, 4).pack(mav, force_mavlink1=True)
    me = TunnelCodec()
    assert me.receive(other + v1, 0.0) == []
    assert me.counters["other_messages"] == 1 and me.counters["rejected"] == 0
    assert (5, 1) in me.peers


def test_lost_fragment_over_codec_drops_frame_and_next_frame_arrives() -> None:
    a, b = _pair()
    lost = a.encode(_frame(400))
    nxt = a.encode(_frame(200, 1))
    out = [f for p in lost[:1] + lost[2:] + nxt for f in b.receive(p, 0.0, datagram=True)]
    assert out == [_frame(200, 1)]
    b.poll(100.0)
    assert b.reassembler.expired == 1 and len(b.reassembler) == 0


@pytest.mark.parametrize(
    "kwargs",
    [{"system_id": 0}, {"component_id": 256}, {"payload_type": 100}, {"mtu": 0},
     {"mtu": MAX_FRAME_BYTES + 1}, {"heartbeat_interval": -1}, {"target_system": -1}],
)
def test_codec_config_checked(kwargs: dict[str, int]) -> None:
    with pytest.raises(ConfigError):
        TunnelCodec(**kwargs)  # type: ignore[arg-type]


def test_library_never_imports_mavutil() -> None:
    code = (
        "import os, sys\n"
        "import coex_transports.mavlink as m\n"
        "from coex_core.registry import load_transport\n"
        "assert load_transport('mavlink') is m.MavlinkTransport\n"
        "assert 'pymavlink.mavutil' not in sys.modules, 'mavutil imported'\n"
        "assert 'MAVLINK_DIALECT' not in os.environ and 'MAVLINK20' not in os.environ\n"
    )
    # a clean environment: another test of this worker may have used mavutil, which sets them
    env = {k: v for k, v in os.environ.items() if k not in ("MAVLINK_DIALECT", "MAVLINK20")}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=env)
    assert proc.returncode == 0, proc.stderr


# ------------------------------------------------------------------------------- fuzzing
_SEED_PACKETS = None


def _seeds() -> list[bytes]:
    global _SEED_PACKETS
    if _SEED_PACKETS is None:
        a = TunnelCodec(system_id=5, component_id=10)
        _SEED_PACKETS = [*a.encode(_frame(300)), *a.encode(_frame(20)), a.heartbeat()]
    return _SEED_PACKETS


@st.composite
def _mutated_streams(draw: st.DrawFn) -> bytes:
    seeds = _seeds()
    parts = draw(st.lists(st.sampled_from(seeds), min_size=1, max_size=5))
    data = bytearray(b"".join(parts))
    for _ in range(draw(st.integers(0, 6))):
        op = draw(st.sampled_from(["flip", "insert", "delete", "set"]))
        pos = draw(st.integers(0, max(0, len(data) - 1)))
        if op == "flip" and data:
            data[pos] ^= 1 << draw(st.integers(0, 7))
        elif op == "insert":
            data[pos:pos] = draw(st.binary(min_size=1, max_size=8))
        elif op == "delete" and data:
            del data[pos:pos + draw(st.integers(1, 8))]
        elif data:
            data[pos] = draw(st.sampled_from([0x00, 0xFD, 0xFE, 0xFF, 0x80, 129, 1]))
    return bytes(data)


@settings(max_examples=300, deadline=None)
@given(chunks=st.lists(st.one_of(_mutated_streams(), st.binary(max_size=300)), max_size=6),
       datagram=st.booleans())
def test_fuzz_receive_never_raises_and_stays_bounded(chunks: list[bytes], datagram: bool) -> None:
    me = TunnelCodec(mtu=2048, max_partial=4)
    now = 0.0
    for chunk in chunks:
        frames = me.receive(chunk, now, datagram=datagram)
        assert all(isinstance(f, bytes) and len(f) <= 2048 for f in frames)
        assert len(me.reassembler) <= 4
        now += 0.7
    assert me.counters["frames_received"] <= me.counters["fragments_received"]


@settings(max_examples=100, deadline=None)
@given(frames=st.lists(st.binary(max_size=700), min_size=1, max_size=4),
       junk=st.lists(st.binary(max_size=40), min_size=1, max_size=4))
def test_fuzz_good_packets_survive_interleaved_junk(frames: list[bytes], junk: list[bytes]) -> None:
    """Garbage before every packet never costs a good frame, as datagrams or in a stream."""
    a, b, c = TunnelCodec(system_id=1), TunnelCodec(system_id=2), TunnelCodec(system_id=3)
    out_d: list[bytes] = []
    out_s: list[bytes] = []
    for i, f in enumerate(frames):
        for p in a.encode(f):
            j = junk[i % len(junk)]
            out_d += b.receive(j, 0.0, datagram=True)
            out_d += b.receive(p, 0.0, datagram=True)
            out_s += c.receive(j + p, 0.0)
    out_s += c.receive(bytes(300), 0.0)  # completes any false start still waiting for bytes
    assert out_d == frames
    assert out_s == frames
