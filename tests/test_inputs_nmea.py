"""The ``nmea`` input: sentences over UDP (a socket sender) and a serial port (a pty), checksums,
every sentence it knows, and the ``channels`` mapping."""

from __future__ import annotations

import logging
import os
import socket
import time

import numpy as np
import pytest

from coex import InputContext, Item, Nav, Samples, check_options
from coex_core.errors import ConfigError
from coex_plugins.inputs.nmea import NmeaError, NmeaInput, checksum, parse_sentence
from coex_transports.testing import free_port as free_udp_port

KNOT = 1852.0 / 3600.0


def nmea(body: str) -> str:
    return f"${body}*{checksum(body):02X}\r\n"


def collect(adapter: NmeaInput, now: float, want: int, timeout: float = 3.0) -> list[Item]:
    got: list[Item] = []
    deadline = time.monotonic() + timeout
    while len(got) < want and time.monotonic() < deadline:
        got += adapter.poll(now)
        if len(got) < want:
            time.sleep(0.01)
    time.sleep(0.05)
    return got + adapter.poll(now)


def test_parse_sentence_and_checksum() -> None:
    line = "$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47"
    assert parse_sentence(line)[:6] == ["GPGGA", "123519", "4807.038", "N", "01131.000", "E"]
    assert parse_sentence(line.replace("*47", "*47").lower().upper())  # hex case does not matter
    with pytest.raises(NmeaError, match="checksum 48 is not 47"):
        parse_sentence(line.replace("*47", "*48"))
    with pytest.raises(NmeaError, match="no checksum"):
        parse_sentence(line[:-3])
    assert parse_sentence(line[:-3], require_checksum=False)[0] == "GPGGA"
    assert parse_sentence("\\s:sounder*22\\" + line)[0] == "GPGGA"  # NMEA 4 tag block
    for bad in ("GPGGA,1,2", "$", "$gp gga,1*00", "$GPGGA*4"):
        with pytest.raises(NmeaError):
            parse_sentence(bad, require_checksum=False)


def test_options() -> None:
    assert check_options(NmeaInput, {}) == ["input 'nmea' needs the option 'serial' or 'udp' (or both)"]
    assert check_options(NmeaInput, {"udp": "10110", "channels": {"VHW": "speed", "VHW.5": ""}}) == [
        "input 'nmea': option 'udp' must be 'host:port' (e.g. '0.0.0.0:10110'), not '10110'",
        "input 'nmea': option 'channels.VHW': the key must be a sentence and a field index from 1, "
        "like \"VHW.5\" or \"IIVHW.5\"",
        "input 'nmea': option 'channels.VHW.5' must be a channel name",
    ]
    with pytest.raises(ConfigError, match="input 'nmea': baud: not an integer, got 'fast'"):
        NmeaInput({"serial": "loop://", "baud": "fast"}, InputContext())


def test_udp_every_sentence(caplog: pytest.LogCaptureFixture) -> None:
    port = free_udp_port()
    adapter = NmeaInput({"udp": f"127.0.0.1:{port}", "variation": -14.0,
                         "channels": {"VHW.5": "speed_through_water", "IIMTA.1": "air_temperature"}},
                        InputContext())
    adapter.open()
    lines = [
        nmea("GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"),
        nmea("GPGGA,123520,,,,,0,00,,,M,,M,,"),  # no fix
        nmea("GPRMC,123519,A,4807.038,S,01131.000,W,10.0,084.4,230394,003.1,W"),
        nmea("GPRMC,123519,V,,,,,,,230394,,"),  # void
        nmea("HEHDT,274.07,T"),
        nmea("HCHDM,100.0,M"),  # + variation option (-14)
        nmea("HCHDG,100.0,2.0,E,10.0,W"),  # 100 + 2 - 10
        nmea("SDDBT,32.8,f,10.0,M,5.5,F"),
        nmea("SDDBT,16.4,f,,M,,F"),  # feet only
        nmea("SDDPT,7.25,0.5,100"),
        nmea("YXMTW,9.5,C"),
        nmea("YXXDR,C,4.25,C,WATER,P,1.013,B,BARO"),
        nmea("VWVHW,,T,,M,3.5,N,6.5,K"),
        nmea("IIMTA,21.5,C"),
        nmea("GPZDA,123519,23,03,1994,00,00"),  # unknown: counted
        nmea("GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,").replace("*", "*0"),
        "$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*00\r\n",  # bad checksum
        nmea("GPGGA,123519,48x7.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"),  # bad number
        "garbage\r\n",
    ]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        tx.sendto("".join(lines[:8]).encode(), ("127.0.0.1", port))  # several lines per datagram
        for line in lines[8:]:
            tx.sendto(line.rstrip().encode(), ("127.0.0.1", port))  # and one without its newline
        with caplog.at_level(logging.WARNING):
            items = collect(adapter, 500.0, 12)
    navs = [i for i in items if isinstance(i, Nav)]
    assert all(i.time == 500.0 for i in navs)
    gga, rmc, hdt, hdm, hdg, dbt, dbt_feet, dpt = navs
    assert (gga.lat, gga.lon) == pytest.approx((48 + 7.038 / 60, 11 + 31 / 60))
    assert (rmc.lat, rmc.lon) == pytest.approx((-(48 + 7.038 / 60), -(11 + 31 / 60)))
    assert rmc.speed == pytest.approx(10 * KNOT) and rmc.extra == {"course": 84.4} and rmc.heading is None
    assert hdt.heading == pytest.approx(274.07)
    assert hdm.heading == pytest.approx(86.0) and hdg.heading == pytest.approx(92.0)
    assert dbt.altitude == 10.0 and dbt_feet.altitude == pytest.approx(16.4 * 0.3048) and dpt.altitude == 7.25
    samples = {s.channel: s for s in items if isinstance(s, Samples)}
    assert {k: s.values.tolist() for k, s in samples.items()} == {
        "water_temperature": [9.5], "WATER": [4.25], "BARO": [1.013],
        "speed_through_water": [3.5], "air_temperature": [21.5]}
    assert samples["WATER"].times.tolist() == [500.0]
    assert adapter.counts == {"lines": 19, "used": 14, "bad_checksum": 2, "bad": 2, "unknown": 1,
                              "skipped": 4}  # the bad ones: every input counts what it skips
    assert sum("checksum" in r.getMessage() for r in caplog.records) == 1  # logged once, counted always
    adapter.close()


def test_dbt_as_time_series_when_the_transducer_is_not_below_the_vehicle() -> None:
    port = free_udp_port()
    adapter = NmeaInput({"udp": f"127.0.0.1:{port}", "dbt_is_altitude": False}, InputContext())
    adapter.open()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        tx.sendto((nmea("SDDBT,,f,42.0,M,,F") + nmea("SDDPT,43.5,0.0")).encode(), ("127.0.0.1", port))
        (item,) = collect(adapter, 1.0, 1)
    assert isinstance(item, Samples) and item.channel == "depth_below_transducer"
    assert item.values.tolist() == [42.0, 43.5]
    adapter.close()


def test_serial_over_a_pty_with_lines_split_across_reads() -> None:
    pytest.importorskip("serial")
    master, slave = os.openpty()
    try:
        adapter = NmeaInput({"serial": os.ttyname(slave), "baud": 38400}, InputContext())
        adapter.open()
        sentence = nmea("GPGGA,000001,0100.000,N,00200.000,W,2,08,0.9,0.0,M,0.0,M,,").encode()
        os.write(master, sentence[:20])
        assert collect(adapter, 3.0, 0, timeout=0.1) == []  # half a line: nothing yet
        os.write(master, sentence[20:] + nmea("YXMTW,3.25,C").encode())
        items = collect(adapter, 4.0, 2)
        nav, temp = items
        assert isinstance(nav, Nav) and (nav.lat, nav.lon) == pytest.approx((1.0, -2.0)) and nav.time == 4.0
        assert isinstance(temp, Samples) and temp.values.tolist() == [3.25]
        adapter.close()
    finally:
        os.close(master)
        os.close(slave)


def test_a_missing_serial_port_is_retried(caplog: pytest.LogCaptureFixture) -> None:
    adapter = NmeaInput({"serial": "/dev/does-not-exist-coex"}, InputContext())
    with caplog.at_level(logging.WARNING):
        adapter.open()
        assert adapter.poll(1.0) == [] and adapter.poll(7.0) == []
    assert sum("cannot open" in r.getMessage() for r in caplog.records) == 1
    # a loop:// port works: what is written comes back
    looped = NmeaInput({"serial": "loop://"}, InputContext())
    looped.open()
    looped._serial.write(nmea("HEHDT,12.5,T").encode())
    (nav,) = looped.poll(2.0)
    assert nav.heading == 12.5
    assert np.isclose(nav.time, 2.0)
    looped.close()
