"""The native MOOS client: its wire codec, and the client against a real MOOSDB (tests/_moos.py)."""

from __future__ import annotations

import socket
import struct
import time

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from coex_transports.moos.client import (
    PROTOCOL,
    MoosClient,
    MoosProtocolError,
    RawMessage,
    _Packet,
    decode_packet,
    encode_packet,
)

from ._moos import MoosDB, free_port, unique

# ---------------------------------------------------------------------------------- wire codec


def test_message_layout_is_core_moos() -> None:
    """CMOOSMsg::Serialize: length, id, type, data type, source, source_aux, community, key,
    time, dval, dval2, value; little-endian, strings as int32 size + bytes."""
    raw = RawMessage("N", "B", b"KEY", 1.5, -1.0, -1.0, b"\x00\xff", b"src", b"", b"com", 7)
    s = lambda b: struct.pack("<i", len(b)) + b  # noqa: E731
    body = (struct.pack("<i", 7) + b"NB" + s(b"src") + s(b"") + s(b"com") + s(b"KEY")
            + struct.pack("<ddd", 1.5, -1.0, -1.0) + s(b"\x00\xff"))
    assert raw.encode() == struct.pack("<i", 4 + len(body)) + body
    packet = encode_packet([raw, raw])
    assert packet[:9] == struct.pack("<iiB", len(packet), 2, 0)
    assert decode_packet(packet) == [raw, raw]
    assert PROTOCOL == b"ELKS CAN'T DANCE 2/8/10"


@given(
    key=st.binary(max_size=40),
    sval=st.binary(max_size=3000),
    t=st.floats(allow_nan=False),
    dval=st.floats(allow_nan=False),
    ident=st.integers(-(2**31), 2**31 - 1),
    dtype=st.sampled_from("DSB"),
)
def test_codec_round_trips_every_byte(key: bytes, sval: bytes, t: float, dval: float, ident: int, dtype: str) -> None:
    raw = RawMessage("N", dtype, key, t, dval, -1.0, sval, b"a\x00b", b"aux", b"", ident)
    assert decode_packet(encode_packet([raw])) == [raw]


def test_codec_rejects_malformed_packets() -> None:
    good = encode_packet([RawMessage("N", "S", b"K", 1.0, sval=b"value")])
    for bad in (
        good[:-1],                                     # truncated
        good + b"\x00",                                # trailing byte
        struct.pack("<i", len(good) - 3) + good[4:],   # wrong length field
        good[:8] + b"\x01" + good[9:],                 # compressed
        good[:4] + struct.pack("<i", 2) + good[8:],    # more messages than present
        good[:-9] + struct.pack("<i", 500) + good[-5:],  # string overruns its message
    ):
        with pytest.raises(MoosProtocolError):
            decode_packet(bad)


# ------------------------------------------------------------------ receive rules (no MOOSDB)


def _mail(client: MoosClient, token: float, messages: list[RawMessage], registers: set[bytes] = frozenset()) -> None:  # type: ignore[assignment]
    """Feed the client one packet from MOOSDB: the answer to its packet ``token``."""
    client._inflight[token] = _Packet([], set(registers))
    client._on_packet([RawMessage("T", "D", b"_async_timing", token), *messages])


def test_replay_on_first_registration_dropped_exact_duplicates_dropped() -> None:
    c = MoosClient("localhost", 1, "me")
    stored = RawMessage("N", "B", b"V", 10.0, sval=b"old", source=b"w", id=-1)
    _mail(c, 1.0, [stored], {b"V"})                       # the replay in the answer to our REGISTER
    assert c.fetch() == [] and c.stats()["replays_ignored"] == 1
    new = RawMessage("N", "B", b"V", 20.0, sval=b"new", source=b"w", id=3)
    _mail(c, 2.0, [new, new])                             # MOOSDB (or a resend) delivers it twice
    assert [m.value for m in c.fetch()] == [b"new"] and c.stats()["duplicates"] == 1
    # after a reconnect: registered again; the replay of a value already delivered is dropped ...
    _mail(c, 3.0, [RawMessage("N", "B", b"V", 20.0, sval=b"new", source=b"w", id=-1)], {b"V"})
    assert c.fetch() == []
    # ... one written while we were away (never seen) is delivered
    _mail(c, 4.0, [RawMessage("N", "B", b"V", 30.0, sval=b"missed", source=b"w", id=-1)], {b"V"})
    assert [m.value for m in c.fetch()] == [b"missed"]
    # the same bytes written again later (new time) are a new frame
    _mail(c, 5.0, [RawMessage("N", "B", b"V", 40.0, sval=b"new", source=b"w", id=9)])
    assert [(m.value, m.time) for m in c.fetch()] == [(b"new", 40.0)]
    c.close()


def test_values_by_type() -> None:
    c = MoosClient("localhost", 1, "me")
    _mail(c, 1.0, [
        RawMessage("N", "D", b"NAV_X", 1.0, dval=12.5, source=b"nav", community=b"c"),
        RawMessage("N", "S", b"WPT", 1.0, sval="süd".encode(), source=b"helm"),
        RawMessage("N", "B", b"F", 1.0, sval=b"\x00" * 3, source=b"m"),
        RawMessage("N", "B", b"PROC_SUMMARY", 1.0, sval=b"x:SUBSCRIBED=,F", id=-2),  # server answer
    ])
    got = c.fetch()
    assert [(m.key, m.kind, m.value) for m in got] == [("NAV_X", "D", 12.5), ("WPT", "S", "süd"), ("F", "B", b"\0\0\0")]
    assert got[0].community == "c" and got[0].source == "nav" and got[0].is_double and got[2].is_binary
    c.close()


def test_calls_never_block_without_moosdb() -> None:
    c = MoosClient("127.0.0.1", free_port(), "lonely")
    t0 = time.monotonic()
    c.notify("X", b"frame")
    c.register("Y")
    assert c.fetch() == []
    assert c.connect(timeout=0.3) is False
    assert not c.flush(timeout=0.2) and c.pending() == 1
    assert not c.wait_for_mail(0.1)
    assert time.monotonic() - t0 < 2.0
    assert "cannot connect" in c.stats()["last_error"]
    c.close()
    c.close()
    assert c.closed


# ----------------------------------------------------------------------- against a real MOOSDB


def _client(db: MoosDB, name: str, **kw: object) -> MoosClient:
    c = MoosClient("127.0.0.1", db.port, name, **kw)  # type: ignore[arg-type]
    return c


def _collect(c: MoosClient, n: int, timeout: float = 10.0) -> list:
    out: list = []
    deadline = time.monotonic() + timeout
    while len(out) < n and time.monotonic() < deadline:
        c.wait_for_mail(0.2)
        out += c.fetch()
    return out


def test_binary_double_string_through_moosdb(moosdb: MoosDB) -> None:
    b_var, s_var, d_var = unique("BIN"), unique("STR"), unique("DBL")
    rx = _client(moosdb, unique("rx"))
    for v in (b_var, s_var, d_var):
        rx.register(v)
    assert rx.connect(5)
    tx = _client(moosdb, unique("tx"))
    assert tx.connect(5) and tx.community == moosdb.community
    values = [bytes(range(256)) * 4, b"\x00", b"", b"\x00" * 100 + b"\xff", bytes(range(255, -1, -1))]
    for v in values:
        tx.notify(b_var, v)
    tx.notify(s_var, "a string, ünïcode")
    tx.notify(d_var, 3.25)
    tx.notify(d_var, np.int64(7))
    assert tx.flush(5)
    got = _collect(rx, len(values) + 3)
    assert [m.value for m in got if m.key == b_var] == values
    assert all(m.kind == "B" for m in got if m.key == b_var)
    assert [m.value for m in got if m.key == s_var] == ["a string, ünïcode"]
    assert [m.value for m in got if m.key == d_var] == [3.25, 7.0]
    assert {m.source for m in got} == {tx.name} and {m.community for m in got} == {moosdb.community}
    times = [m.time for m in got if m.key == b_var]
    assert times == sorted(times) and len(set(times)) == len(times)
    # the first write fixed each variable's type: MOOSDB ignores a write of another type
    tx.notify(b_var, "not binary")
    tx.notify(b_var, b"binary again")
    assert tx.flush(5)
    assert [m.value for m in _collect(rx, 1)] == [b"binary again"]
    tx.close()
    rx.close()


def test_time_warp_stamps_moos_time_and_undoes_it(moosdb: MoosDB) -> None:
    """MOOS time is the Unix time times MOOSTimeWarp (MOOSLocalTime): a warped client stamps
    its values that way, and real_time() takes a received time back to Unix seconds."""
    var = unique("WARPED")
    rx = _client(moosdb, unique("rx"))
    rx.register(var)
    assert rx.connect(5)
    tx = MoosClient("127.0.0.1", moosdb.port, unique("tx"), time_warp=20.0)
    assert tx.connect(5)
    before = time.time()
    assert before * 20 <= tx.moos_time() <= time.time() * 20
    tx.notify(var, 1.0)
    tx.notify(var, 2.0, time=12345.0)  # an explicit MOOS time is kept
    assert tx.flush(5)
    got = _collect(rx, 2)
    assert before * 20 <= got[0].time <= time.time() * 20
    assert got[1].time == 12345.0
    assert before - 1 <= tx.real_time(got[0].time) <= time.time()
    for bad in (0, -1.0, 401.0, float("nan"), True):
        with pytest.raises(ValueError, match="time_warp"):
            MoosClient("127.0.0.1", moosdb.port, "x", time_warp=bad)
    tx.close()
    rx.close()


def test_stored_value_is_not_replayed_as_new(moosdb: MoosDB) -> None:
    var = unique("STORED")
    tx = _client(moosdb, unique("tx"))
    assert tx.connect(5)
    tx.notify(var, b"written before anyone registered")
    assert tx.flush(5)
    rx = _client(moosdb, unique("rx"))
    rx.register(var)
    assert rx.connect(5)
    assert not rx.wait_for_mail(0.5) and rx.stats()["replays_ignored"] == 1
    tx.notify(var, b"new")
    assert tx.flush(5)
    assert [m.value for m in _collect(rx, 1)] == [b"new"]
    # registering while connected: MOOSDB replays again; already delivered, so dropped
    rx.register(var)
    assert not rx.wait_for_mail(0.5)
    tx.close()
    rx.close()


def test_name_clash_is_reported_and_retried(moosdb: MoosDB) -> None:
    name = unique("same")
    first = _client(moosdb, name)
    assert first.connect(5)
    second = _client(moosdb, name, retry=0.2)
    assert not second.connect(1.0)
    assert "refused" in second.stats()["last_error"]
    first.close()
    assert second.connect(10)  # MOOSDB forgets the first once it has gone
    second.close()


def test_notifications_wait_for_a_subscriber(moosdb: MoosDB) -> None:
    """Values queued before anyone registered are held (up to await_timeout), then all delivered,
    not only the last one MOOSDB would store."""
    var = unique("HELD")
    tx = _client(moosdb, unique("tx"), await_subscribers=[var], await_timeout=20)
    assert tx.connect(5)
    frames = [i.to_bytes(2, "little") * 500 for i in range(1500)]  # 1.5 MB: more than one packet
    for f in frames:
        tx.notify(var, f)
    assert not tx.flush(0.5) and tx.pending() == len(frames)
    rx = _client(moosdb, unique("rx"))
    rx.register(var)
    assert rx.connect(5)
    assert tx.flush(10)
    assert [m.value for m in _collect(rx, len(frames))] == frames
    tx.close()
    rx.close()


def test_reconnects_after_restart_registers_again_and_resends(moosdb_path: str) -> None:
    db = MoosDB(moosdb_path)
    db.start()
    connects: list[float] = []
    try:
        var = unique("R")
        rx = _client(db, unique("rx"), on_connect=lambda: connects.append(time.monotonic()))
        rx.register(var)
        tx = _client(db, unique("tx"), await_subscribers=[var], await_timeout=10)
        assert rx.connect(5) and tx.connect(5)
        tx.notify(var, b"before")
        assert [m.value for m in _collect(rx, 1)] == [b"before"]
        db.stop()
        deadline = time.monotonic() + 5
        while (tx.connected or rx.connected) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not tx.connected and not rx.connected
        for i in range(3):
            tx.notify(var, b"while down %d" % i)
        db.start()
        assert tx.flush(15), tx.stats()
        got = _collect(rx, 3, timeout=15)
        assert [m.value for m in got] == [b"while down %d" % i for i in range(3)]
        assert not rx.wait_for_mail(1.0)  # nothing twice
        assert len(connects) == 2 and tx.stats()["connects"] == 2
        tx.close()
        rx.close()
    finally:
        db.close()


def test_server_garbage_drops_the_connection() -> None:
    """A server that does not speak MOOS: the client gives up on that connection, reports why,
    and keeps trying (it never raises into the caller)."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen()
    port = srv.getsockname()[1]
    c = MoosClient("127.0.0.1", port, "victim", retry=0.1)
    assert not c.connect(0.01)
    conn, _ = srv.accept()
    conn.settimeout(5)
    assert conn.recv(32).startswith(PROTOCOL)
    conn.sendall(struct.pack("<i", 3) + b"junk")
    deadline = time.monotonic() + 5
    while "bad packet length" not in c.stats()["last_error"] and time.monotonic() < deadline:
        time.sleep(0.05)
    assert "bad packet length" in c.stats()["last_error"]
    conn.close()
    c.close()
    srv.close()
