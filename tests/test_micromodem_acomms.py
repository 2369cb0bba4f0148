"""Interoperability with WHOI's own host library, ``acomms`` 3.1.1 (pyacomms), as an independent peer.

pyacomms ``Micromodem`` objects are pointed at the simulator's pseudo-terminals; they send and
receive legacy data packets, FDP packets, pings, and parse our CAXST/CACST. Our driver and
pyacomms exchange data through two simulated modems in both directions, and the sentences our
driver writes are compared byte for byte with what pyacomms writes for the same operation and
with the reference lines of ``micromodem.md``.

Only the parts of pyacomms the reference note (§4) found working are used: good-path legacy
packets, CCTDP transmit, ping, statistics and configuration. Its threads are confined to this
module: the fixture stops them (their read loop has no exit, so ``readline`` is replaced by one
that ends the thread) and removes the log handlers it adds to the root logger.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from coex_core.acoustic import AcousticChannel
from coex_transports.micromodem import MicromodemTransport, nmea
from coex_transports.micromodem.driver import DriverConfig, MicromodemDriver
from coex_transports.micromodem.simulator import ModemNetwork, PtySimulator

pytestmark = [
    pytest.mark.filterwarnings("ignore::DeprecationWarning"),
    pytest.mark.filterwarnings("ignore::PendingDeprecationWarning"),
]

SPEED = 5.0  # simulated seconds per real second: a rate-1 packet (3.1 s on air) takes 0.6 s


def _stop_acomms(modem: Any) -> None:
    conn = modem.connection
    if conn is None:
        return

    def _exit() -> None:
        raise SystemExit  # ends pyacomms' reader thread quietly (its loop never exits otherwise)

    hook = threading.excepthook

    def quiet(args: Any) -> None:
        if args.exc_type is not SystemExit:
            hook(args)

    threading.excepthook = quiet
    try:
        conn.readline = _exit
        conn._thread.join(timeout=3)
    finally:
        threading.excepthook = hook
    assert not conn._thread.is_alive()
    try:
        conn._serialport.close()
    except Exception:
        pass
    modem.close_loggers()


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from acomms.micromodem import Micromodem
    root = logging.getLogger()
    handlers_before = list(root.handlers)
    positions = {1: (0.0, 0.0, 0.0), 2: (1000.0, 0.0, 0.0), 3: (0.0, 1000.0, 0.0)}
    network = ModemNetwork(positions, channel=AcousticChannel(seed=3))
    for m in network.modems.values():
        m.nvram["DTO"] = "30"  # pyacomms answers a CADRQ per 0.1 s read loop: no flaky DATA_TIMEOUT on a busy CI
    sim = PtySimulator(network, speed=SPEED)
    sim.start()
    logs = tmp_path_factory.mktemp("acomms_logs")
    a = Micromodem("A", log_path=str(logs))
    b = Micromodem("B", log_path=str(logs))
    ours = None
    try:
        a.connect_serial(sim.paths[1], 19200)
        b.connect_serial(sim.paths[2], 19200)
        a.set_config("XST", 1)
        b.set_config("CST", 1)
        ours = MicromodemTransport.from_uri(f"micromodem://{sim.paths[3]}?src=3&dest=2&rate=1")
        assert ours.wait_ready(20), ours.stats()
        yield {"a": a, "b": b, "sim": sim, "network": network, "ours": ours}
    finally:
        if ours is not None:
            ours.close()
        for m in (a, b):
            _stop_acomms(m)
        sim.stop()
        for h in list(root.handlers):
            if h not in handlers_before:
                root.removeHandler(h)
                h.close()


def _host_lines(setup: dict[str, Any], node: int) -> list[bytes]:
    return list(setup["sim"].call(lambda net: list(net.modems[node].host_lines)))


def _drain(q: queue.Queue[Any]) -> None:
    while not q.empty():
        q.get_nowait()


def _wait_idle(modem: Any, timeout: float = 30.0) -> None:
    end = time.monotonic() + timeout
    while str(modem.state) != "Idle" and time.monotonic() < end:
        time.sleep(0.05)
    assert str(modem.state) == "Idle"


def test_acomms_learns_its_id_and_sets_config(setup: dict[str, Any]) -> None:
    a, b = setup["a"], setup["b"]
    assert (a.id, b.id) == (1, 2)
    assert setup["network"].modems[1].nvram["XST"] == "1"
    assert b.get_config("CST") == {"CST": "1"}


def test_acomms_legacy_packet_and_statistics(setup: dict[str, Any]) -> None:
    a, b = setup["a"], setup["b"]
    rx: queue.Queue[Any] = queue.Queue()
    xst: queue.Queue[Any] = queue.Queue()
    cst: queue.Queue[Any] = queue.Queue()
    b.attach_packetrx_queue(rx)
    a.attach_incoming_xst_queue(xst)
    b.attach_incoming_cst_queue(cst)
    try:
        payload = bytes(range(150))
        a.send_packet_data(2, payload, rate_num=1)
        packet = rx.get(timeout=15)
        assert b"".join(bytes(f.data) for f in packet.frames) == payload
        assert [f.frame_num for f in packet.frames] == [1, 2, 3]
        tx = xst.get(timeout=10)
        assert (tx["version_number"], tx["rate_num"], tx["src"], tx["dest"]) == (6, 1, 1, 2)
        assert (tx["num_frames_expected"], tx["num_frames_sent"], tx["nbytes"]) == (3, 3, 150)
        assert tx["packet_type"] == 3
        rs = cst.get(timeout=10)
        assert (rs["version_number"], rs["mode"], rs["rate_num"], rs["src"], rs["dest"]) == (6, 0, 1, 1, 2)
        assert (rs["num_frames"], rs["bad_frames_num"], rs["psk_error"]) == (3, 0, 0)
        _wait_idle(a)
        _wait_idle(b)
        # the cycle as the host wrote it, and the CADRQ loop it answered (64 + 64 + 22 bytes)
        lines = [line for line in _host_lines(setup, 1) if line.startswith((b"$CCCYC", b"$CCTXD"))]
        assert lines[-4].startswith(b"$CCCYC,0,1,2,1,0,3*")
        assert [len(nmea.parse(x).fields[3]) // 2 for x in lines[-3:]] == [64, 64, 22]
    finally:
        b.packetrx_queues.remove(rx)
        a.incoming_xst_queues.remove(xst)
        b.incoming_cst_queues.remove(cst)


def test_acomms_fdp_transmit(setup: dict[str, Any]) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from acomms.flexibledataprotocol import FDPacket
    a, b = setup["a"], setup["b"]
    raw: queue.Queue[Any] = queue.Queue()
    b.attach_incoming_msg_queue(raw)
    try:
        data = bytes.fromhex("00112233445566778899001122334455667788990011")
        a.send_fdpacket(FDPacket(1, 2, None, 1, 0, databytes=bytearray(data)), use_tdp=True)
        end = time.monotonic() + 15
        got = None
        while got is None and time.monotonic() < end:
            msg = raw.get(timeout=15)
            if msg["type"] == "CARDP":
                got = nmea.parse_cardp(nmea.parse(msg["raw"]))
        assert got is not None
        assert (got.src, got.dest, got.rate) == (1, 2, 1)
        assert [(f.crc_ok, f.data) for f in got.data] == [(True, data)]
        assert f"$CCTDP,2,1,0,0,{data.hex()}*".encode() in b"\n".join(_host_lines(setup, 1))
        _wait_idle(a)
    finally:
        b.incoming_msg_queues.remove(raw)


def test_acomms_ping_reports_travel_time(setup: dict[str, Any]) -> None:
    a = setup["a"]
    _wait_idle(a)
    a.send_ping(2)
    owtt = a.wait_for_ping_reply(2, timeout=15)
    assert owtt == pytest.approx(1000.0 / 1500.0, abs=1e-3)


def test_our_driver_sends_to_acomms(setup: dict[str, Any]) -> None:
    b, ours = setup["b"], setup["ours"]
    _wait_idle(b)
    rx: queue.Queue[Any] = queue.Queue()
    b.attach_packetrx_queue(rx)
    try:
        frames = [bytes([0x40 + i for i in range(64)]), b"coex frame two"]
        ours.send_packet(frames, rate=1)
        ours.flush(timeout=20)
        packet = rx.get(timeout=15)
        assert [bytes(f.data) for f in packet.frames] == frames
        assert (packet.cycleinfo.src, packet.cycleinfo.dest, packet.cycleinfo.rate_num) == (3, 2, 1)
        _wait_idle(b)
    finally:
        b.packetrx_queues.remove(rx)


def test_acomms_sends_to_our_driver(setup: dict[str, Any]) -> None:
    b, ours = setup["b"], setup["ours"]
    _wait_idle(b)
    payload = bytes((i * 7) % 256 for i in range(100))
    b.send_packet_data(3, payload, rate_num=1)
    got = [ours.recv(timeout=15), ours.recv(timeout=15)]
    assert got == [payload[:64], payload[64:]]
    status = ours.link_status()
    assert status is not None and (status.frames, status.bad_frames) == (2, 0)
    assert status.snr is not None
    _wait_idle(b)


def _acomms_lines(tmp: Path, actions: Any) -> list[str]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from acomms.micromodem import Micromodem
    root = logging.getLogger()
    before = list(root.handlers)
    m = Micromodem("golden", log_path=str(tmp))
    try:
        m.id = 1
        actions(m)
        out = []
        while not m.serial_tx_queue.empty():
            out.append(m.serial_tx_queue.get_nowait())
        return out
    finally:
        m.close_loggers()
        for h in list(root.handlers):
            if h not in before:
                root.removeHandler(h)
                h.close()


def _script(driver: MicromodemDriver, now: float = 1000.0) -> None:
    """Answer the driver's startup as a modem would, so it is ready to transmit."""
    driver.start(now)
    for _ in range(20):
        out = driver.data_to_send()
        if not out:
            driver.poll(now + 0.05)  # the clock set waits for 50 ms past the top of a second
            out = driver.data_to_send()
        if not out:
            break
        for line in out.splitlines():
            s = nmea.parse(line)
            if s.ident == "CCCFQ":
                driver.feed(nmea.format_sentence("CACFG", [s.fields[0], "2.0.35490"]), now)
            else:
                driver.feed(nmea.format_sentence({"CCCFG": "CACFG", "CCTMS": "CATMS"}[s.ident], s.fields), now)
    assert driver.ready


def test_driver_sentences_match_acomms_and_reference(tmp_path: Path) -> None:
    from acomms.messageparams import CycleInfo, DataFrame

    frames = [bytes(range(64)), bytes(range(64, 128)), bytes(range(128, 150))]

    def legacy(m: Any) -> None:
        m.send_cycleinit(CycleInfo(1, 2, 1, False, 3))
        for i, f in enumerate(frames):
            m.send_frame(DataFrame(1, 2, False, i, bytearray(f)))
        m.send_ping(2)

    golden = [line.encode() for line in _acomms_lines(tmp_path, legacy)]
    d = MicromodemDriver(DriverConfig(src=1, dest=2, rate=1))
    _script(d)
    d.send_packet(frames, rate=1)
    d.poll(1000.0)
    ours = [d.data_to_send()]
    d.feed(nmea.format_sentence("CACYC", [0, 1, 2, 1, 0, 3]), 1000.0)
    for f in (1, 2, 3):
        d.feed(nmea.format_sentence("CADRQ", ["000000", 1, 2, 0, 64, f]), 1000.0)
        ours.append(d.data_to_send())
    d.feed(nmea.format_sentence("CATXP") + nmea.format_sentence("CATXF"), 1001.0)  # cycle over
    d.ping(2, 1001.0)
    ours.append(d.data_to_send())
    assert ours == golden
    # the reference lines of micromodem.md (§1, §4, §5)
    assert golden[0] == b"$CCCYC,0,1,2,1,0,3*58\r\n"

    fdp_data = bytes.fromhex("00112233445566778899001122334455667788990011")

    def fdp(m: Any) -> None:
        from acomms.flexibledataprotocol import FDPacket

        m.send_fdpacket(FDPacket(1, 2, None, 5, 0, databytes=bytearray(fdp_data)), use_tdp=True)

    golden_fdp = _acomms_lines(tmp_path, fdp)[0].encode()
    d2 = MicromodemDriver(DriverConfig(src=1, dest=2, rate=5, mode="fdp"))
    _script(d2)
    d2.send_packet([fdp_data])
    d2.poll(1000.0)
    assert d2.data_to_send() == golden_fdp == nmea.format_sentence("CCTDP", [2, 5, 0, 0, fdp_data.hex()])
    assert nmea.format_sentence("CCCFG", ["SRC", 0]) == b"$CCCFG,SRC,0*30\r\n"
    assert nmea.format_sentence("CCTMQ", [0]) == b"$CCTMQ,0*54\r\n"
