"""Modems that go away and come back, as processes: `coex vehicle` and `coex topside` from
configuration files, talking through `coex modem-sim` over TCP (``micromodem:socket://``) or over
pseudo-terminals named by stable links (``micromodem:///DIR/modem2``, like /dev/serial/by-id).
The simulator is killed (the plug pulled on both modems) and started again, twice: both daemons
stay up, reopen their modems by themselves, data flows again each time (the topside's series
keeps growing), the ship is told how long the vehicle's modem was down (LinkHealth), and the
logs say each change of state once instead of once per read. A modem missing at start is
waited for; with ``required = true`` it is an error at once."""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from ._modemsim import free_tcp_base
from ._procs import start, state, wait_for

pytest.importorskip("serial")

pytestmark = pytest.mark.slow

SLOT = 4.0  # seconds per TDMA slot (a rate-5 packet takes 3 s): a cycle of 24 s

CONFIG = """
[node]
role = "{role}"
id = {id}
peer = {peer}
store = "{role}.sqlite"

[[modems]]
uri = "{uri}"

[tdma]
slots = ["topside", "vehicle", "vehicle", "topside", "vehicle", "vehicle"]
slot_seconds = {slot}
guard = 0.5

[modalities.timeseries]
stream = 5
{options}

[modalities.survey]
stream = 7
priority = 90
{extra}
"""


def _config(folder: Path, role: str, uri: str, extra: str = "") -> Path:
    nid, peer = (2, 1) if role == "vehicle" else (1, 2)
    options = ('options = { channels = [{ name = "water_temperature", unit = "degC", lo = -2.0, hi = 40.0, '
               'resolution = 0.01 }], block_samples = 16, max_latency = 6.0 }') if role == "vehicle" else ""
    path = folder / f"{role}.toml"
    path.write_text(CONFIG.format(role=role, id=nid, peer=peer, uri=uri, slot=SLOT, options=options,
                                  extra=extra))
    return path


class _Nmea:
    """A water temperature sensor: an NMEA MTW sentence every 0.5 s on UDP."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.stop = threading.Event()
        self.t = threading.Thread(target=self._run, daemon=True)
        self.t.start()

    def _run(self) -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            i = 0
            while not self.stop.is_set():
                body = f"YXMTW,{10 + math.sin(i / 10):.2f},C"
                cs = 0
                for ch in body:
                    cs ^= ord(ch)
                s.sendto(f"${body}*{cs:02X}\r\n".encode(), ("127.0.0.1", self.port))
                i += 1
                self.stop.wait(0.5)


def _samples(http: str) -> int:
    chans = (state(http).get("series") or {}).get("channels") or []
    return sum(int(c.get("samples") or 0) for c in chans)


def _link(http: str) -> dict[str, Any]:
    links = (state(http).get("link") or {}).get("links") or []
    return links[0] if links else {}


@pytest.fixture
def folder(tmp_path: Path) -> Iterator[Path]:
    yield tmp_path


def _sim(kind: str, base: int, links: Path, log: Path, env: dict[str, str]) -> subprocess.Popen[str]:
    args = ["modem-sim", "--nodes", "1,2"]
    args += ["--tcp-base", str(base)] if kind == "tcp" else ["--link", str(links)]
    p, lines = start(args, env, log)
    wait_for("the modem simulator", lambda: lines.count("modem 2:") >= 1, 30, {"modem-sim": p})
    return p


def _kill(p: subprocess.Popen[str]) -> None:
    if p.poll() is None:
        p.send_signal(signal.SIGKILL)
        p.wait(timeout=10)


@pytest.mark.parametrize("kind", ["tcp", "pty"])
def test_modems_cut_and_restored_twice_and_data_flows_again_each_time(kind: str, folder: Path) -> None:
    base = free_tcp_base(2)
    udp = free_tcp_base(1, socket.SOCK_DGRAM)
    http_port = free_tcp_base(1)
    links = folder / "dev"
    if kind == "tcp":
        vuri = f"micromodem:socket://127.0.0.1:{base + 1}?src=2&dest=1&rate=5"
        turi = f"micromodem:socket://127.0.0.1:{base}?src=1&dest=2&rate=5"
    else:
        vuri = f"micromodem://{links}/modem2?src=2&dest=1&rate=5"
        turi = f"micromodem://{links}/modem1?src=1&dest=2&rate=5"
    vcfg = _config(folder, "vehicle", vuri, f'[[inputs]]\ntype = "nmea"\nudp = "127.0.0.1:{udp}"\n')
    tcfg = _config(folder, "topside", turi, f'[console]\nhttp = "127.0.0.1:{http_port}"\n')
    http = f"127.0.0.1:{http_port}"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    procs: dict[str, subprocess.Popen[str]] = {}
    sensor = _Nmea(udp)
    sim: subprocess.Popen[str] | None = None
    try:
        # both daemons start before their modems exist: they wait for them
        vp, vlog = start(["vehicle", "--config", str(vcfg)], env, folder / "vehicle.log")
        tp, tlog = start(["topside", "--config", str(tcfg)], env, folder / "topside.log")
        procs = {"vehicle": vp, "topside": tp}
        wait_for("the vehicle waiting for its modem", lambda: vlog.has("link 0 waiting for its modem"), 30, procs)
        wait_for("the console", lambda: state(http), 30, procs)
        sim = _sim(kind, base, links, folder / "sim.log", env)
        got = wait_for("series samples topside", lambda: _samples(http), 120, procs)
        for cut in (1, 2):
            _kill(sim)  # the plug pulled on both modems
            if kind == "pty":
                # as an unplugged USB serial device's node goes, so do the simulator's links (a
                # SIGKILLed simulator leaves them pointing at /dev/pts/N, which another process's
                # terminal may take meanwhile: opening it is not the modem coming back)
                for stale in links.glob("modem*"):
                    stale.unlink()
            wait_for(f"the vehicle to see modem loss {cut}", lambda c=cut: vlog.count("lost:") >= c, 30, procs)
            wait_for(f"topside to see modem loss {cut}", lambda c=cut: tlog.count("lost:") >= c, 30, procs)
            wait_for("the console to show its modem down",
                     lambda: (_link(http).get("topside_modem") or {}).get("up") is False, 30, procs)
            time.sleep(3.0)  # down for a while: both daemons keep running (checked by wait_for)
            sim = _sim(kind, base, links, folder / "sim.log", env)
            wait_for(f"the vehicle's modem back {cut}", lambda c=cut: vlog.count("back after") >= c + 1, 60, procs)
            before = got
            got = wait_for(f"data flowing again after cut {cut}",
                           lambda b=before: (n := _samples(http)) > b and n, 150, procs)
            # the ship knows how long the vehicle's modem was down
            wait_for("the vehicle's report of its outage",
                     lambda c=cut: ((_link(http).get("vehicle_modem") or {}).get("outages") or 0) >= c + 1, 150, procs)
        veh = _link(http)["vehicle_modem"]
        assert veh["up"] is True and veh["outages"] == 3  # absent at start, then two cuts
        assert veh["down_total"] >= veh["last_down"] >= 2
        own = _link(http)["topside_modem"]
        assert own["up"] is True and own["outages"] == 3
        for p in procs.values():
            p.send_signal(signal.SIGTERM)
        codes = {name: p.wait(timeout=30) for name, p in procs.items()}
        assert codes == {"vehicle": 0, "topside": 0}
        # quiet logs: one line per change of state, never one per read
        for lines in (vlog, tlog):
            assert lines.count("lost:") == 2 and lines.count("not there at start") == 1
            assert lines.count("back after") == 3
            assert lines.count("serial port failed") <= 2  # only in the "lost" lines
        wait_for("the vehicle's summary", lambda: vlog.has("coex vehicle: stopped"), 10)
        assert vlog.has("link 0: 3 outages")
    finally:
        sensor.stop.set()
        for p in procs.values():
            _kill(p)
        if sim is not None:
            _kill(sim)


def test_a_required_modem_missing_at_start_is_an_error(folder: Path) -> None:
    base = free_tcp_base(2)
    uri = f"micromodem:socket://127.0.0.1:{base + 1}?src=2&dest=1&rate=5"
    cfg = _config(folder, "vehicle", uri)
    text = cfg.read_text().replace(f'uri = "{uri}"', f'uri = "{uri}"\nrequired = true')
    cfg.write_text(text)
    p, lines = start(["vehicle", "--config", str(cfg)], dict(os.environ), folder / "vehicle.log")
    try:
        assert p.wait(timeout=60) == 2
        wait_for("the reason", lambda: lines.has("cannot open"), 10)
    finally:
        _kill(p)
