"""LcmTransport: URIs, channels per direction, shared memq instances, udpm on loopback, logs,
bad input, and `coex send` / `coex listen` with --transport lcm:..."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import lcm
import pytest

from coex_core import registry, wire
from coex_core.cli import main as coex_main
from coex_core.errors import ConfigError, FrameTooLarge, TransportError
from coex_core.messages import FrameHeader, VehicleMode, VehicleStatus
from coex_transports.lcm import (
    DEFAULT_URL,
    LcmConfig,
    LcmTransport,
    decode_frame,
    encode_frame,
    parse_lcm_uri,
)
from coex_transports.lcm.testing import TEST_UDPM_URL, ensure_multicast_route, unique_channel


@pytest.fixture(scope="module")
def multicast() -> Iterator[None]:
    """udpm:// on loopback needs a multicast route; added (as root) only when missing."""
    undo = ensure_multicast_route()
    yield
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        undo()


# ------------------------------------------------------------------------ URIs and config
def test_uri_of_the_issue() -> None:
    cfg = parse_lcm_uri("lcm:udpm://239.255.76.67:7667?ttl=0&channel=COEX")
    assert cfg == LcmConfig(url="udpm://239.255.76.67:7667?ttl=0", tx="COEX", rx="COEX")


def test_uri_channels_per_direction_and_provider_options() -> None:
    cfg = parse_lcm_uri("lcm:udpm://239.255.76.67:7668?ttl=1&tx=COEX_UP&rx=COEX_DOWN&recv_buf_size=65536&mtu=300")
    assert cfg.url == "udpm://239.255.76.67:7668?ttl=1&recv_buf_size=65536"
    assert (cfg.tx, cfg.rx, cfg.mtu) == ("COEX_UP", "COEX_DOWN", 300)
    assert cfg.swapped().tx == "COEX_DOWN" and cfg.swapped().rx == "COEX_UP"
    # channel= sets both, tx/rx override one direction
    cfg = parse_lcm_uri("lcm:memq://?channel=A&rx=B")
    assert (cfg.url, cfg.tx, cfg.rx) == ("memq://", "A", "B")
    cfg = parse_lcm_uri("lcm:file:///tmp/dive.lcmlog?speed=0&channel=C&share=s")
    assert (cfg.url, cfg.provider, cfg.share) == ("file:///tmp/dive.lcmlog?speed=0", "file", "s")


def test_empty_provider_is_explicit_udpm_not_lcm_default_url(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("LCM_DEFAULT_URL", "memq://")
    assert parse_lcm_uri("lcm:").url == DEFAULT_URL == "udpm://239.255.76.67:7667?ttl=0"
    assert parse_lcm_uri("lcm:?channel=X").tx == "X"
    assert parse_lcm_uri("lcm://?channel=Y").rx == "Y"


@pytest.mark.parametrize(
    "uri",
    [
        "udpm://239.255.76.67:7667",  # not lcm:
        "lcm:udpm",  # no provider URL
        "lcm:memq://?mtu=big",
        "lcm:memq://?mtu=0",
        "lcm:memq://?queue=0",
        "lcm:memq://?channel=",
        "lcm:memq://?tx=" + "X" * 64,
    ],
)
def test_bad_uris_raise_config_error(uri: str) -> None:
    with pytest.raises(ConfigError):
        parse_lcm_uri(uri)


def test_unknown_provider_or_option_is_a_config_error_before_anything_opens() -> None:
    with pytest.raises(ConfigError, match="unknown LCM provider 'nosuchprovider'"):
        LcmTransport.from_uri("lcm:nosuchprovider://x")
    with pytest.raises(ConfigError, match="unknown option 'chanel'"):  # LCM itself would only warn
        LcmTransport.check_uri("lcm:udpm://239.255.76.67:7667?ttl=0&chanel=COEX")
    with pytest.raises(ConfigError, match="unknown option 'speed'"):  # a file option on udpm
        LcmTransport.check_uri("lcm:udpm://239.255.76.67:7667?speed=2")
    assert LcmTransport.check_uri("lcm:file:///tmp/x.log?speed=2&channel=C").paths == ("/tmp/x.log",)
    assert LcmTransport.check_uri("lcm:file:///tmp/x.log?mode=w").paths == ()


def test_registered_and_opened_by_uri() -> None:
    assert registry.load_transport("lcm") is LcmTransport
    with registry.open_transport("lcm:memq://?tx=UP1&rx=DN1") as end:
        assert isinstance(end, LcmTransport)
        assert end.stats()["tx"] == "UP1" and end.mtu == 65536


# ------------------------------------------------------------------------ memq
def test_memq_ends_opened_by_uri_share_one_instance() -> None:
    a = registry.open_transport("lcm:memq://?tx=M_UP&rx=M_DOWN")
    b = registry.open_transport("lcm:memq://?tx=M_DOWN&rx=M_UP")
    try:
        a.send(b"up")
        b.send(b"down")
        assert b.recv(timeout=1.0) == b"up"
        assert a.recv(timeout=1.0) == b"down"
        assert a.recv(timeout=0.05) is None and b.recv(timeout=0.05) is None
    finally:
        a.close()
        b.close()
    # the shared instance is released with its last user
    assert not any(key[0] == "memq://" for key in LcmTransport._shared)


def test_one_channel_both_ways_ignores_own_frames() -> None:
    channel = unique_channel()
    a, b = LcmTransport.pair(LcmConfig(url="memq://", tx=channel, rx=channel))
    try:
        a.send(b"from a")
        assert a.recv(timeout=0.1) is None  # its own frame is not echoed back
        assert b.recv(timeout=1.0) == b"from a"
        assert a.stats()["own"] == 1 and a.stats()["received"] == 0
        assert b.stats()["received"] == 1 and a.stats()["sent"] == 1
    finally:
        a.close()
        b.close()


def test_bad_messages_are_counted_and_logged_never_returned(caplog: pytest.LogCaptureFixture) -> None:
    a, b = LcmTransport.pair()
    try:
        raw = b._inst.lcm  # an LCM user on the same instance publishing junk on b's channel
        a.send(b"good 1")
        raw.publish(b.config.rx, b"not a frame_t")
        raw.publish(b.config.rx, encode_frame(b"x")[:-1])
        a.send(b"good 2")
        with caplog.at_level(logging.WARNING):
            assert b.recv(timeout=1.0) == b"good 1"
            assert b.recv(timeout=1.0) == b"good 2"
        assert b.stats()["bad"] == 2
        assert "bad message on LCM channel" in caplog.text
    finally:
        a.close()
        b.close()


def test_receive_queue_overflow_drops_oldest_and_counts() -> None:
    cfg = LcmConfig(url="memq://", tx=unique_channel(), rx=unique_channel(), queue=3)
    a, b = LcmTransport.pair(cfg)
    try:
        for i in range(5):
            a.send(bytes([i]))
        # a's recv dispatches the shared instance, filling b's queue while b does not read
        assert a.recv(timeout=0.3) is None
        assert b.pending() == 3
        assert [b.recv(timeout=1.0) for _ in range(3)] == [b"\x02", b"\x03", b"\x04"]
        assert b.stats()["dropped"] == 2
    finally:
        a.close()
        b.close()


def test_mtu_and_closed_transport() -> None:
    a, b = LcmTransport.pair(LcmConfig(url="memq://", tx=unique_channel(), rx=unique_channel(), mtu=10))
    with pytest.raises(FrameTooLarge):
        a.send(bytes(11))
    a.send(bytes(10))
    assert b.recv(timeout=1.0) == bytes(10)
    assert isinstance(b.fileno(), int)
    a.close()
    a.close()
    with pytest.raises(TransportError):
        a.send(b"x")
    with pytest.raises(TransportError):
        a.recv(timeout=0)
    with pytest.raises(TransportError):
        a.fileno()
    b.close()


def test_existing_lcm_instance_can_be_used() -> None:
    instance = lcm.LCM("memq://")
    channel = unique_channel()
    got: list[bytes] = []
    instance.subscribe(channel, lambda _c, data: got.append(data))
    with LcmTransport(LcmConfig(url="memq://", tx=channel, rx=unique_channel()), instance=instance) as end:
        end.send(b"\x10\x20")
        instance.handle_timeout(100)
    assert decode_frame(got[0]).data == b"\x10\x20"
    instance.publish(channel, b"still usable after the transport closed")


# ------------------------------------------------------------------------ udpm on loopback
def test_udpm_two_instances_per_direction_channels(multicast: None) -> None:
    up, down = unique_channel("UP"), unique_channel("DOWN")
    vehicle = LcmTransport.from_uri(f"lcm:{TEST_UDPM_URL}&tx={up}&rx={down}")
    ship = LcmTransport.from_uri(f"lcm:{TEST_UDPM_URL}&tx={down}&rx={up}")
    try:
        status = VehicleStatus(stamp=1, x=1.0, y=2.0, depth=30.0, altitude=None, heading=0.0,
                               speed=0.5, battery=90, mode=VehicleMode.SURVEY, faults=0)
        packet = wire.pack([status], 64, FrameHeader(src=2, dst=1, seq=1))
        vehicle.send(packet)
        got = ship.recv(timeout=5.0)
        assert got == packet and wire.unpack(got) == [status]
        ship.send(b"\x01\x02")
        assert vehicle.recv(timeout=5.0) == b"\x01\x02"
        assert vehicle.recv(timeout=0.1) is None  # its own uplink frame is on another channel
    finally:
        vehicle.close()
        ship.close()


def test_udpm_large_frame_is_fragmented_and_reassembled(multicast: None) -> None:
    channel = unique_channel()
    a = LcmTransport(LcmConfig(url=TEST_UDPM_URL, tx=channel, rx=channel))
    b = LcmTransport(LcmConfig(url=TEST_UDPM_URL, tx=channel, rx=channel))
    try:
        frame = bytes(range(256)) * 250  # 64000 B: several UDP fragments
        a.send(frame)
        assert b.recv(timeout=5.0) == frame
    finally:
        a.close()
        b.close()


def test_udpm_shared_instance(multicast: None) -> None:
    channel = unique_channel()
    cfg = LcmConfig(url=TEST_UDPM_URL, tx=channel, rx=channel, share="test")
    a, b = LcmTransport(cfg), LcmTransport(cfg)
    try:
        assert a._inst is b._inst
        a.send(b"same instance")
        assert b.recv(timeout=5.0) == b"same instance"
        assert a.recv(timeout=0.1) is None
    finally:
        a.close()
        b.close()


# ------------------------------------------------------------------------ file:// provider
def _write_log(path: Path, channel: str, frames: list[bytes]) -> None:
    log = lcm.EventLog(str(path), "w", overwrite=True)
    for i, frame in enumerate(frames):
        log.write_event(1_000_000 * (i + 1), channel, encode_frame(frame, utime=i, origin=7))
        log.write_event(1_000_000 * (i + 1) + 1, channel, b"junk")
        log.write_event(1_000_000 * (i + 1) + 2, "OTHER", encode_frame(b"other channel"))
    log.close()


def test_file_provider_reads_a_log_then_reports_nothing(tmp_path: Path) -> None:
    path = tmp_path / "session.lcmlog"
    frames = [b"\x00\x01", b"\x02" * 300, b"\x03"]
    _write_log(path, "COEX", frames)
    with LcmTransport.from_uri(f"lcm:file://{path}?speed=0&channel=COEX") as end:
        got = [end.recv(timeout=1.0) for _ in range(3)]
        assert got == frames
        assert end.recv(timeout=0.2) is None  # end of the log
        assert end.recv(timeout=None) is None
        assert end.stats()["bad"] == 3


def test_file_provider_writes_a_log(tmp_path: Path) -> None:
    path = tmp_path / "out.lcmlog"
    with LcmTransport.from_uri(f"lcm:file://{path}?mode=w&tx=REC") as end:
        end.send(b"\xaa\xbb")
        end.send(b"\xcc")
    events = list(lcm.EventLog(str(path), "r"))
    assert [e.channel for e in events] == ["REC", "REC"]
    assert [decode_frame(e.data).data for e in events] == [b"\xaa\xbb", b"\xcc"]


def test_coex_listen_reads_frames_from_a_log(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "session.lcmlog"
    _write_log(path, "COEX", [b"\x10\x11", b"\x12"])
    rc = coex_main(["listen", "--transport", f"lcm:file://{path}?speed=0", "--count", "2", "--timeout", "5"])
    assert rc == 0
    assert capsys.readouterr().out.split() == ["1011", "12"]


# ------------------------------------------------------------------------ coex send / listen
def _coex(*args: str) -> list[str]:
    return [sys.executable, "-m", "coex_core.cli", *args]


def test_coex_send_and_listen_over_udpm(multicast: None) -> None:
    """`coex listen` and `coex send` as separate processes on one udpm channel."""
    uri = f"lcm:{TEST_UDPM_URL}&channel={unique_channel()}"
    frames = ["0102", "a0b0c0"]
    listener = subprocess.Popen(_coex("listen", "--transport", uri, "--count", "2", "--timeout", "30"),
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        # the listener subscribes after start-up; send until it has both frames and exits
        while listener.poll() is None and time.monotonic() < deadline:
            sent = subprocess.run(_coex("send", "--transport", uri, "--hex", frames[0], "--hex", frames[1]),
                                  capture_output=True, text=True, timeout=30)
            assert sent.returncode == 0, sent.stderr
            try:
                listener.wait(timeout=1.0)
            except subprocess.TimeoutExpired:
                pass
        out, err = listener.communicate(timeout=10)
    finally:
        if listener.poll() is None:
            listener.kill()
            listener.wait(timeout=10)
    assert listener.returncode == 0, err
    lines = out.split()
    assert len(lines) == 2 and lines[0] == frames[0]
    assert lines[1] in frames  # the second may be the repeat of the first from a later send


def test_recv_with_zero_timeout_returns_what_already_arrived() -> None:
    a, b = LcmTransport.pair()
    try:
        assert b.recv(timeout=0) is None
        a.send(b"x")
        a.send(b"y")
        assert [b.recv(timeout=0), b.recv(timeout=0), b.recv(timeout=0)] == [b"x", b"y", None]
        a.send(b"z")
        assert b.recv(timeout=None) == b"z"  # blocks until a frame is there
    finally:
        a.close()
        b.close()


@pytest.mark.parametrize("provider", ["memq", "udpm"])
def test_a_blocked_reader_thread_gets_frames_sent_from_another_thread(provider: str, request: pytest.FixtureRequest) -> None:
    import threading

    if provider == "udpm":
        request.getfixturevalue("multicast")
        cfg = LcmConfig(url=TEST_UDPM_URL, tx=unique_channel(), rx=unique_channel())
    else:
        cfg = LcmConfig(url="memq://", tx=unique_channel(), rx=unique_channel())
    a, b = LcmTransport.pair(cfg)
    got: list[bytes | None] = []
    reader = threading.Thread(target=lambda: got.extend(b.recv(timeout=5.0) for _ in range(3)))
    try:
        reader.start()
        for i in range(3):
            time.sleep(0.05)
            a.send(bytes([i]) * 10)
        reader.join(timeout=10)
        assert not reader.is_alive()
        assert got == [bytes([i]) * 10 for i in range(3)]
    finally:
        reader.join(timeout=10)
        a.close()
        b.close()


def test_rx_is_an_exact_channel_name_not_a_regex() -> None:
    base = unique_channel()
    a, b = LcmTransport.pair(LcmConfig(url="memq://", tx=f"{base}.UP", rx=f"{base}.DOWN"))
    c = LcmTransport(LcmConfig(url="memq://", tx=f"{base}XUP", rx=unique_channel(), share=a.config.share))
    try:
        c.send(b"other channel")  # 'X' would match '.' if rx were used as a regex
        a.send(b"right channel")
        assert b.recv(timeout=1.0) == b"right channel"
        assert b.recv(timeout=0.1) is None
    finally:
        a.close()
        b.close()
        c.close()


def test_decoded_option_publishes_vehicle_status_and_map_levels() -> None:
    import dataclasses

    from coex_conformance import load_vectors
    from coex_core import jsonfmt
    from coex_transports.lcm import map_level_t, vehicle_status_t
    from coex_transports.lcm.products import vehicle_status_from_lcm

    assert parse_lcm_uri("lcm:memq://?decoded=1").decoded
    with pytest.raises(ConfigError):
        parse_lcm_uri("lcm:memq://?decoded=maybe")
    fields = next(v for v in load_vectors("messages") if v["type"] == "Subgrid")["fields"]
    sub = jsonfmt.from_json({"type": "Subgrid", **fields})
    status = VehicleStatus(stamp=9, x=1.0, y=2.0, depth=30.0, altitude=None, heading=10.0,
                           speed=0.5, battery=90, mode=VehicleMode.SURVEY, faults=0)
    cfg = LcmConfig(url="memq://", tx=unique_channel(), rx=unique_channel(), decoded=True)
    a, b = LcmTransport.pair(cfg)
    seen: dict[str, list[bytes]] = {"COEX_VEHICLE_STATUS": [], "COEX_MAP_LEVEL": []}
    raw = b._inst.lcm
    for channel, box in seen.items():
        raw.subscribe(channel, lambda _c, data, box=box: box.append(data))
    try:
        frame = wire.pack([status, dataclasses.replace(sub, level=2, ix=3, iy=4)], 256, FrameHeader(src=2))
        a.send(frame)
        a.send(encode_frame(b"not a coex frame"))  # a valid frame_t whose CoEx frame is bad
        assert b.recv(timeout=1.0) == frame
        assert b.recv(timeout=1.0) == encode_frame(b"not a coex frame")  # still delivered
        for _ in range(4):
            raw.handle_timeout(50)
        assert [vehicle_status_from_lcm(vehicle_status_t.decode(d)) for d in seen["COEX_VEHICLE_STATUS"]] == [status]
        (level,) = [map_level_t.decode(d) for d in seen["COEX_MAP_LEVEL"]]
        assert (level.level, level.subgrids) == (2, 1)
        assert b.stats()["decoded"] == 2 and b.stats()["undecodable"] == 1
        assert "decoded" not in a.stats() or a.stats()["decoded"] == 0
    finally:
        a.close()
        b.close()
