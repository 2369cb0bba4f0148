"""The Micromodem simulator: in process on a simulated clock through the real driver, and on
pseudo-terminals / TCP for external hosts (``coex modem-sim``, ``coex send``/``coex listen``)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from typing import Any

import pytest

from coex_core.acoustic import AcousticChannel
from coex_core.messages import LinkStatus
from coex_core.registry import open_transport
from coex_transports.micromodem import MicromodemTransport, nmea
from coex_transports.micromodem.driver import Acked, DriverConfig, PingResult, Rebooted, TxDone
from coex_transports.micromodem.simulator import ModemNetwork, PtySimulator

COEX = [os.path.join(os.path.dirname(sys.executable), "coex")]


def pair(**channel: Any) -> tuple[ModemNetwork, MicromodemTransport, MicromodemTransport]:
    net = ModemNetwork({1: (0.0, 0.0, 0.0), 2: (1500.0, 0.0, 0.0)}, channel=AcousticChannel(**channel))
    return net, net.transport(1, dest=2), net.transport(2, dest=1)


def modem_lines(net: ModemNetwork, node: int) -> list[str]:
    return [x.decode() for x in net.modems[node].host_lines]


def test_frames_arrive_one_airtime_plus_travel_time_later() -> None:
    net, a, b = pair(seed=1)
    assert a.wait_ready(5) and b.wait_ready(5)
    t0 = net.now
    frames = [bytes([i]) * 200 for i in range(3)]
    for f in frames:
        a.send(f)
    got = [b.recv(timeout=10) for _ in frames]
    assert got == frames
    from coex_core.acoustic import RATES

    expected = RATES[5].packet_airtime(3) + 1.0  # one packet of 3 frames, 1500 m at 1500 m/s
    assert net.now - t0 == pytest.approx(expected, abs=1e-3)
    events = a.events()
    assert [type(e) for e in events if isinstance(e, TxDone)] == [TxDone]
    status = b.link_status()
    assert isinstance(status, LinkStatus) and (status.frames, status.bad_frames) == (3, 0)


def test_lossy_channel_good_frames_of_damaged_packets_still_arrive() -> None:
    net, a, b = pair(seed=5, loss=0.3, bit_error_rate=2e-4)
    sent = [bytes([i % 256, i // 256]) * 100 for i in range(240)]
    for f in sent:
        a.send(f)
    got = []
    while True:
        f = b.recv(timeout=60)
        if f is None:
            break
        got.append(f)
    st = b.stats()
    assert st["bad_frames"] > 30  # losses and CRC failures were reported as bad frames ...
    assert len(got) + st["bad_frames"] == len(sent)  # ... and every other frame was delivered
    assert got == [f for f in sent if f in set(got)]  # unaltered, in order
    lines = modem_lines(net, 2)
    assert lines  # the host side of modem 2 is our driver
    assert b.link_status() is not None


def test_bad_crc_reported_as_a_real_modem_does() -> None:
    net, a, b = pair(seed=2, loss=0.5)
    outs: list[bytes] = []
    net.modems[2].keep_host_lines = 0
    orig = net.modems[2].data_to_send

    def spy() -> bytes:
        out = orig()
        outs.append(out)
        return out

    net.modems[2].data_to_send = spy  # type: ignore[method-assign]
    for i in range(8):
        a.send(bytes([i]) * 100)
    while b.recv(timeout=30) is not None:
        pass
    text = b"".join(outs).decode()
    seq = [line.split(",")[0].split("*")[0] for line in text.split("\r\n") if line.startswith(("$CARX", "$CACYC", "$CAMSG", "$CACST"))]
    assert "$CAMSG" in seq
    cyc = seq.index("$CACYC")
    assert seq[cyc - 1] == "$CARXP" and seq[cyc + 9] == "$CACST"
    cst = [nmea.parse_cacst(nmea.parse(x)) for x in text.split("\r\n") if x.startswith("$CACST")]
    data_cst = [c for c in cst if c.frames == 8]
    assert data_cst and data_cst[0].mode == 1 and data_cst[0].psk_error == 3 and data_cst[0].bad_frames > 0
    assert data_cst[0].version == 6


def test_fdp_mode_round_trip() -> None:
    net = ModemNetwork({1: (0.0, 0.0, 0.0), 2: (300.0, 0.0, 0.0)})
    a = net.transport(1, dest=2, rate=1, mode="fdp")
    b = net.transport(2, dest=1, rate=1, mode="fdp")
    a.send(b"first")
    a.send(bytes(64))
    a.send(b"third")
    got = [b.recv(timeout=20) for _ in range(3)]
    assert got[0] == b"first".ljust(64, b"\x00")  # padded to the frame grid (CoEx frames are self-delimiting)
    assert got[1] == bytes(64) and got[2] == b"third"
    assert any(x.startswith("$CCTDP,2,1,0,0,") for x in modem_lines(net, 1))


def test_rate0_two_cycle_stats_and_acks() -> None:
    net = ModemNetwork({1: (0.0, 0.0, 0.0), 2: (750.0, 0.0, 0.0)})
    a = net.transport(1, dest=2, rate=0, ack=True)
    b = net.transport(2, dest=1, rate=0)
    a.send(bytes(range(32)))
    assert b.recv(timeout=30) == bytes(range(32))
    net.run_for(20)
    acked = [e for e in a.events() if isinstance(e, Acked)]
    assert acked == [Acked(2, 1, acked[0].time)]
    csts = [e for e in b.events() if isinstance(e, LinkStatus)]
    assert len(csts) == 2  # the FSK cycle-init mini-packet and the data packet


def test_ping_reports_one_way_travel_time() -> None:
    net, a, _ = pair()
    a.wait_ready(5)
    a.ping(2)
    net.run_for(20)
    pings = [e for e in a.events() if isinstance(e, PingResult)]
    assert len(pings) == 1 and pings[0].owtt == pytest.approx(1.0, abs=1e-4)
    assert a.stats()["last_owtt"] == pytest.approx(1.0, abs=1e-4)


def test_modem_reboot_mid_transfer_loses_nothing() -> None:
    net, a, b = pair()
    a.wait_ready(5)
    for i in range(6):
        a.send(bytes([i]) * 50)
    net.run_for(0.05)
    net.modems[1].reboot(net.now)
    got = [b.recv(timeout=60) for _ in range(6)]
    assert got == [bytes([i]) * 50 for i in range(6)]
    assert any(isinstance(e, Rebooted) for e in a.events())
    assert a.stats()["reboots"] == 1 and a.stats()["tx_retries"] >= 1


def test_host_that_misses_the_data_request_gets_data_timeout() -> None:
    net = ModemNetwork()
    m = net.modems[1]
    m.feed(nmea.format_sentence("CCCFG", ["XST", 1]) + nmea.format_sentence("CCCYC", [0, 1, 2, 1, 0, 2]), net.now)
    out = m.data_to_send().decode()
    assert "$CACYC,0,1,2,1,0,2*" in out and "$CADRQ," in out
    net.run_for(10)
    out = m.data_to_send().decode().split("\r\n")
    assert out[0].startswith("$CAERR,") and ",DATA_TIMEOUT,1," in out[0]
    xst = nmea.parse_caxst(nmea.parse(next(x for x in out if x.startswith("$CAXST"))))
    assert xst.mode == 4 and xst.frames_sent == 0
    assert any(x.startswith("$CATXF") for x in out)


def test_simulated_modem_answers_config_queries_and_rejects_nonsense() -> None:
    net = ModemNetwork()
    m = net.modems[2]
    m.feed(b"$CCCFQ,SRC\r\n$CCCFQ,TOP\r\n$CCXYZ,1\r\n$CCCFG,SRC,1*30\r\ngarbage\r\n$CCTMQ,0\r\n", net.now)
    out = m.data_to_send().decode().split("\r\n")
    assert out[0].startswith("$CACFG,SRC,2*")
    assert sum(1 for x in out if x.startswith("$CACFG")) > 10
    # unknown command and bad checksum (a line without '$' is line noise, ignored)
    assert sum(1 for x in out if x.startswith("$CAERR")) == 2
    assert m.nvram["SRC"] == "2"  # the corrupted set was not applied
    assert out[-2].startswith("$CATMQ,2025-01-01T00:00:00")


def test_two_hour_dive_runs_fast_through_the_real_driver() -> None:
    net, a, b = pair(seed=9, loss=0.1)
    start = time.process_time()
    t_end = net.now + 7200.0
    sent = received = 0
    while net.now < t_end:
        for _ in range(8):
            a.send(bytes([sent % 256]) * 240)
            sent += 1
        b.send(b"ack")
        while b.recv(timeout=20.0) is not None:
            received += 1
        a.recv(timeout=0)
    elapsed = time.process_time() - start
    assert net.now >= t_end
    assert received > 0.8 * sent > 1000
    assert elapsed < 20.0, elapsed


# ----------------------------------------------------------------------- pseudo-terminals


@pytest.fixture
def pty_sim() -> Iterator[PtySimulator]:
    net = ModemNetwork({1: (0.0, 0.0, 0.0), 2: (1000.0, 0.0, 0.0)})
    sim = PtySimulator(net, tcp_ports={2: 0}, speed=4.0)
    sim.start()
    yield sim
    sim.stop()


def test_driver_over_pty_and_tcp(pty_sim: PtySimulator) -> None:
    host, port = pty_sim.tcp_addresses[2]
    a = open_transport(f"micromodem://{pty_sim.paths[1]}?src=1&dest=2&rate=5")
    b = open_transport(f"micromodem:socket://{host}:{port}?src=2&dest=1&rate=5")
    try:
        assert a.wait_ready(10) and b.wait_ready(10)
        a.send(b"over a pty")
        a.send(bytes(256))
        assert b.recv(timeout=10) == b"over a pty"
        assert b.recv(timeout=10) == bytes(256)
        b.send(b"and back over tcp")
        assert a.recv(timeout=10) == b"and back over tcp"
        assert a.stats()["firmware_version"] is None or a.stats()["firmware_version"]
    finally:
        a.close()
        b.close()


def test_coex_send_and_listen_over_simulated_modems(pty_sim: PtySimulator) -> None:
    listen = subprocess.Popen(
        [*COEX, "listen", "--transport", f"micromodem://{pty_sim.paths[2]}?src=2&dest=1", "--count", "2",
         "--timeout", "40"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert listen.stderr is not None
        ready = listen.stderr.readline()  # sent before the listener's modem is open, a frame is gone
        assert ready.startswith("coex listen: listening on"), ready
        sent = subprocess.run(
            [*COEX, "send", "--transport", f"micromodem://{pty_sim.paths[1]}?src=1&dest=2", "--hex", "c0ffee",
             "--hex", "00" * 3 + "ff"], capture_output=True, text=True, timeout=60)
        assert sent.returncode == 0, sent.stderr
        out, err = listen.communicate(timeout=60)
    finally:
        listen.kill()
    assert listen.returncode == 0, err
    assert out.split() == ["c0ffee", "000000ff"]


def test_modem_sim_command_prints_device_paths() -> None:
    proc = subprocess.run([*COEX, "modem-sim", "--nodes", "1,2,3", "--duration", "0.5"], capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert [x.split(":")[0] for x in lines] == ["modem 1", "modem 2", "modem 3"]
    assert all(x.split(": ")[1].startswith("/dev/") for x in lines)
    from coex_transports.testing import free_port

    base = free_port(2)
    proc = subprocess.run([*COEX, "modem-sim", "--tcp-base", str(base), "--duration", "0.3"], capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert [x.split(" tcp ")[1] for x in proc.stdout.splitlines()] == [f"127.0.0.1:{base}", f"127.0.0.1:{base + 1}"]
    bad = subprocess.run([*COEX, "modem-sim", "--nodes", "1"], capture_output=True, text=True, timeout=60)
    assert bad.returncode != 0 and "two distinct" in bad.stderr


def test_serial_thread_survives_garbage_on_a_pyserial_loop_url() -> None:
    """The threaded driver on pyserial's ``loop://``: our own sentences come back (ignored), random
    bytes and truncated lines are dropped, and a good frame in between is still delivered."""
    import random

    import serial

    port = serial.serial_for_url("loop://", timeout=0.05)
    t = MicromodemTransport.on_port(port, DriverConfig(src=1, set_clock=False, reply_timeout=0.2, retries=0))
    try:
        rng = random.Random(3)
        for _ in range(50):
            port.write(bytes(rng.randrange(256) for _ in range(rng.randrange(1, 60))))
            port.write(b"$CARXD,2,1,0,1,01"[: rng.randrange(1, 17)] + b"\r\n")
        port.write(b"\r\n" + nmea.format_sentence("CARXD", [2, 1, 0, 1, "c0ffee"]))
        assert t.recv(timeout=10) == b"\xc0\xff\xee"
        st = t.stats()
        assert st["garbage_bytes"] > 0 and st["malformed"] + st["bad_checksum"] > 0
        assert st["handler_errors"] == 0
    finally:
        t.close()


def test_unplugged_modem_gives_a_transport_error() -> None:
    from coex_core.errors import TransportError

    net = ModemNetwork()
    sim = PtySimulator(net, speed=4.0)
    sim.start()
    t = open_transport(f"micromodem://{sim.paths[1]}?src=1&dest=2")
    try:
        assert t.wait_ready(10)
        sim.stop()  # closes the pseudo-terminals under the driver
        with pytest.raises(TransportError):
            for _ in range(50):
                t.recv(timeout=0.2)
    finally:
        t.close()
    assert t.closed


def test_coex_frames_survive_modem_zero_padding_and_fdp_grid() -> None:
    """Firmware that pads frames with zeros (goby3 #286) and the FDP frame grid both hand the
    receiver a longer frame; CoEx frames carry their own lengths, so the messages are the same."""
    from coex_core import wire
    from coex_core.messages import FrameHeader, LinkStatus

    msgs = [LinkStatus(100, 1, 8, 1, 12.5, -0.3)]
    frame = wire.pack(msgs, 64, FrameHeader(src=1, dst=2, seq=3, crc=True))
    assert len(frame) < 64
    net = ModemNetwork({1: (0.0, 0.0, 0.0), 2: (300.0, 0.0, 0.0)})
    a = net.transport(1, dest=2, rate=1, mode="fdp")
    b = net.transport(2, dest=1, rate=1, mode="fdp")
    a.send(frame)
    a.send(frame)
    got = [b.recv(timeout=20), b.recv(timeout=20)]
    assert got[0] == frame.ljust(64, b"\x00") and got[1] == frame
    assert [wire.unpack(g) for g in got] == [msgs, msgs]
    # a padded legacy CARXD, as early Micromodem-2 firmware reports it
    from coex_transports.micromodem.driver import MicromodemDriver

    d = MicromodemDriver(DriverConfig(src=2))
    d.feed(nmea.format_sentence("CARXD", [1, 2, 0, 1, frame.ljust(64, b"\x00").hex()]), 0.0)
    received = d.receive()
    assert received is not None and wire.unpack(received.data) == msgs


# ------------------------------------------------- goby3 driver_tester vectors (micromodem.md §5)


def test_goby3_vector_rate0_with_ack() -> None:
    """test4: rate 0, 1 -> 2, ACK on, one 32-byte frame 0x00..0x1F; frame at 2, frame 1 acked at 1."""
    net = ModemNetwork()
    a, b = net.transport(1, dest=2, rate=0), net.transport(2, dest=1, rate=0)
    a.send_packet([bytes(range(0x20))], rate=0, ack=True)
    assert b.recv(timeout=30) == bytes(range(0x20))
    net.run_for(15)
    assert [(e.src, e.frame) for e in a.events() if isinstance(e, Acked)] == [(2, 1)]


def test_goby3_vector_rate2_three_frames_acked() -> None:
    """test5: rate 2, 1 -> 2, ACK on, frames 0x40..0x7F, 0x80..0xBF, 0xC0..0xFF."""
    net = ModemNetwork()
    a, b = net.transport(1, dest=2, rate=2), net.transport(2, dest=1, rate=2)
    frames = [bytes(range(0x40, 0x80)), bytes(range(0x80, 0xC0)), bytes(range(0xC0, 0x100))]
    a.send_packet(frames, rate=2, ack=True)
    assert [b.recv(timeout=30) for _ in frames] == frames
    net.run_for(15)
    assert [e.frame for e in a.events() if isinstance(e, Acked)] == [1, 2, 3]
    assert "$CCCYC,0,1,2,2,1,3" in [x.split("*")[0] for x in modem_lines(net, 1)]


def test_goby3_vector_fdp_rate1() -> None:
    """test6: FDP 2 -> 1 at rate 1 after psk.packet.mod_hdr_version,1; 22-byte payload."""
    net = ModemNetwork()
    payload = bytes.fromhex("00112233445566778899001122334455667788990011")
    a = net.transport(1, dest=2, rate=1, mode="fdp")
    b = net.transport(2, dest=1, rate=1, mode="fdp", nvram=(("psk.packet.mod_hdr_version", "1"),))
    b.send(payload)
    assert a.recv(timeout=30) == payload
    rdp = [x for x in modem_lines(net, 2) if x.startswith("$CCTDP")]
    assert rdp and rdp[0].split("*")[0] == f"$CCTDP,1,1,0,0,{payload.hex()}"
    assert a.driver.events and any(getattr(e, "fdp", False) and e.src == 2 and e.rate == 1 for e in a.events())


def test_goby3_startup_is_accepted_by_the_simulator() -> None:
    net = ModemNetwork()
    m = net.modems[1]
    cmds = [("CCCFG", ["ALL", 0]), ("CCCFG", ["CST", 1]), ("CCCFG", ["AGC", 0]), ("CCCFG", ["SRC", 1]),
            ("CCCFG", ["REV", 1]), ("CCCFG", ["RXP", 1]), ("CCCFG", ["recv.base64data", 1]), ("CCMSC", [1, 1, 0]),
            ("CCTMS", ["2025-01-01T00:00:01Z", 0]), ("CCCLK", [2025, 1, 1, 0, 0, 1]), ("CCCFQ", ["TOP"]),
            ("CCTMQ", [0]), ("CCCFQ", ["SRC"])]
    replies = []
    for ident, fields in cmds:
        m.feed(nmea.format_sentence(ident, fields), net.now)
        replies.append([nmea.parse(x) for x in m.data_to_send().split(b"\r\n") if x])
    assert [r[0].ident for r in replies] == ["CACFG"] * 7 + ["CAMSC", "CATMS", "CACLK", "CACFG", "CATMQ", "CACFG"]
    assert [r[0].fields[:2] for r in replies[:7]] == [(str(f[0]), str(f[1])) for _, f in cmds[:7]]
    assert len(replies[10]) == len(m.nvram) > 10  # the whole configuration
    assert replies[-1][0].fields == ("SRC", "1")


def test_base64_fdp_receive() -> None:
    net = ModemNetwork()
    a = net.transport(1, dest=2, rate=5, mode="fdp")
    b = net.transport(2, dest=1, rate=5, mode="fdp", base64=True)
    a.send(bytes(range(200)))
    assert b.recv(timeout=30) == bytes(range(200))
    rdp = [x for x in net.modems[2].host_lines if x.startswith(b"$CCCFG,recv.base64data")]
    assert rdp


def test_flush_reports_a_silent_modem() -> None:
    """A port with no modem behind it (pyserial ``loop://`` only echoes our own sentences): the
    startup commands time out, the packet fails, and ``flush`` says so instead of succeeding."""
    import serial

    from coex_core.errors import TransportError

    port = serial.serial_for_url("loop://", timeout=0.05)
    t = MicromodemTransport.on_port(port, DriverConfig(src=1, reply_timeout=0.1, retries=0, max_attempts=1))
    try:
        t.send(b"lost")
        with pytest.raises(TransportError, match="could not be sent"):
            t.flush(timeout=20)
        st = t.stats()
        assert st["command_failures"] >= 6 and st["tx_failed"] == 1
    finally:
        t.close()


def test_closing_a_simulated_transport_frees_its_modem() -> None:
    net, a, b = pair()
    a.send(b"x")
    assert b.recv(timeout=10) == b"x"
    b.close()
    a.send(b"to nobody")
    net.run_for(30)
    assert net.modems[2].data_to_send() == b""  # discarded, not piling up
    b2 = net.transport(2, dest=1)
    a.send(b"y")
    assert b2.recv(timeout=10) == b"y"
    from coex_core.errors import ConfigError

    with pytest.raises(ConfigError):
        net.transport(2)


def test_carxp_at_the_first_bit_data_after_the_last() -> None:
    from coex_core.acoustic import RATES

    net = ModemNetwork({1: (0.0, 0.0, 0.0), 2: (1500.0, 0.0, 0.0)})
    m1, m2 = net.modems[1], net.modems[2]
    for m in (m1, m2):
        m.feed(nmea.format_sentence("CCCFG", ["RXP", 1]), net.now)
        m.data_to_send()
    t0 = net.now
    m1.feed(nmea.format_sentence("CCCYC", [0, 1, 2, 5, 0, 1]), t0)
    m1.feed(nmea.format_sentence("CCTXD", [1, 2, 0, "abcd"]), t0)
    net.run_until(t0 + 0.999)
    assert m2.data_to_send() == b""  # 1500 m at 1500 m/s: nothing yet
    net.run_until(t0 + 1.001)
    assert m2.data_to_send() == b"$CARXP*58\r\n"
    net.run_until(t0 + 1.0 + RATES[5].packet_airtime(1) - 0.01)
    assert m2.data_to_send() == b""
    net.run_until(t0 + 1.0 + RATES[5].packet_airtime(1) + 0.01)
    out = [x.split(",")[0].split("*")[0] for x in m2.data_to_send().decode().split("\r\n") if x]
    assert out == ["$CACYC", "$CARXD"]  # CST is off on this modem; no second CARXP


def test_an_unplugged_simulated_modem_fails_like_a_serial_port_and_is_reopened() -> None:
    """ModemNetwork.unplug pulls a modem's cable: the host's transport fails at its next use and
    stays dead, opening one fails until ModemNetwork.plug; a ResilientTransport over the network's
    opener reopens it on the simulated clock and counts the outage."""
    from coex_core.errors import LinkDown, TransportError
    from coex_transports.recovery import ResilientTransport

    net = ModemNetwork({1: (0.0, 0.0, 0.0), 2: (1500.0, 0.0, 0.0)})
    a = ResilientTransport("micromodem:///dev/sim/modem1?src=1&dest=2", name="link 0", clock=lambda: net.now,
                           sleep=net.run_for, opener=net.open_uri)
    b = net.transport(2, dest=1)
    a.send(b"one")
    assert b.recv(timeout=30) == b"one"
    plain = a.inner
    net.unplug(1)
    with pytest.raises(LinkDown):
        a.send(b"lost")
    assert not a.up and plain is not None and plain.closed
    with pytest.raises(TransportError, match="unplugged"):
        net.transport(1)
    net.run_for(120.0)
    assert a.recv(timeout=0) is None and not a.up  # tried again meanwhile, in vain
    assert a.health().attempts >= 1
    net.plug(1)
    net.run_for(31.0)
    assert a.recv(timeout=0) is None and a.up
    h = a.health()
    assert h.outages == 1 and 120.0 <= h.last_down <= 200.0
    a.send(b"two")
    assert b.recv(timeout=30) == b"two"
    # a plain transport whose cable is pulled fails at its next use, as a serial port does
    net.unplug(2)
    with pytest.raises(TransportError, match="serial port failed"):
        b.recv(timeout=0)
    b.close()
    a.close()
