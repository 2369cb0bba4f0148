"""The ``moos`` transport against a real MOOSDB: the conformance suite, frames of every size to
and from an independent pymoos client, a MOOSDB restart, the registration replay, and
``coex send`` / ``coex listen`` over moos://."""

from __future__ import annotations

import os
import subprocess
import sys
import time
import tomllib
from collections.abc import Iterator
from importlib import metadata
from pathlib import Path
from typing import Any

import pytest

from coex_conformance import TransportFixtures, TransportTests
from coex_core.errors import ConfigError, FrameTooLarge
from coex_core.messages import FrameHeader, Opaque
from coex_core.registry import open_transport
from coex_core.wire import pack
from coex_transports.moos import MoosConfig, MoosTransport, parse_moos_uri

from ._moos import MoosDB, free_port, unique

REPO = Path(__file__).resolve().parents[1]
COEX = [str(Path(sys.executable).with_name("coex"))]


def _pair(db: MoosDB, **kw: Any) -> tuple[MoosTransport, MoosTransport]:
    cfg = MoosConfig(host="127.0.0.1", port=db.port, name=unique("pCoexA"), tx=unique("COEX_UP"),
                     rx=unique("COEX_DOWN"), **kw)
    a = MoosTransport(cfg)
    b = MoosTransport(cfg.swapped(unique("pCoexB")))
    assert a.connected and b.connected
    return a, b


class MoosFixtures(TransportFixtures):
    @pytest.fixture
    def transport_pair(self, moosdb: MoosDB) -> Iterator[tuple[MoosTransport, MoosTransport]]:
        a, b = _pair(moosdb)
        yield a, b
        a.close()
        b.close()


class TestMoosConformance(TransportTests, MoosFixtures):
    pass


# ------------------------------------------------------------------------------------ the URI


def test_uri() -> None:
    cfg = parse_moos_uri("moos://10.0.0.2:9001?name=pCoex2&tx=A_TX&rx=A_RX&mtu=512&queue=7&hold=0&timeout=1")
    assert (cfg.host, cfg.port, cfg.name, cfg.tx, cfg.rx, cfg.mtu, cfg.queue, cfg.hold, cfg.timeout) == \
        ("10.0.0.2", 9001, "pCoex2", "A_TX", "A_RX", 512, 7, 0.0, 1.0)
    assert parse_moos_uri("moos://") == MoosConfig()
    assert parse_moos_uri(MoosConfig(port=1234, name="x").uri) == MoosConfig(port=1234, name="x")
    assert parse_moos_uri("moos://h:1?warp=12.5").warp == 12.5  # the community's MOOSTimeWarp
    assert parse_moos_uri(MoosConfig(warp=4).uri) == MoosConfig(warp=4)
    for bad in ("moos://h:1?color=red", "moos://h:99999", "moos://h:1?tx=", "moos://h:1?name=a%20b",
                "moos://h:1/path", "lcm://h:1", "moos://h:1?mtu=0", "moos://h:1?hold=-1", "moos://h:1?warp=0",
                "moos://h:1?warp=nan", "moos://h:1?warp=500"):
        with pytest.raises(ConfigError):
            parse_moos_uri(bad)


def test_registered_in_pyproject() -> None:
    eps = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["entry-points"]["coex.transports"]
    assert eps["moos"] == "coex_transports.moos:MoosTransport"


def test_opens_without_moosdb_and_queues() -> None:
    t0 = time.monotonic()
    t = MoosTransport.from_uri(f"moos://127.0.0.1:{free_port()}?name=early&timeout=0.2")
    assert time.monotonic() - t0 < 2 and not t.connected
    t.send(b"kept")
    assert t.recv(timeout=0.1) is None and t.stats()["pending"] == 1
    with pytest.raises(FrameTooLarge):
        t.send(bytes(t.mtu + 1))
    t.close()


# ----------------------------------------------------------------- an independent pymoos client


def _sizes(mtu: int) -> list[int]:
    """Every size up to the MTU (2048 by default)."""
    return list(range(1, mtu + 1))


def _frame(size: int, salt: int) -> bytes:
    return bytes((i * 131 + size * 7 + salt) % 256 for i in range(size))


@pytest.fixture
def pymoos_peer(moosdb: MoosDB) -> Iterator[tuple[Any, str, str]]:
    """A pymoos client registered for ``up``; it writes ``down``."""
    pymoos = pytest.importorskip("pymoos", reason="pymoos not installed (`make moos` installs it into .venv)")
    up, down = unique("COEX_UP"), unique("COEX_DOWN")
    comms = pymoos.comms()
    comms.set_quiet(True)
    comms.set_on_connect_callback(lambda: comms.register(up, 0))
    comms.run("127.0.0.1", moosdb.port, unique("pymoos"))
    assert comms.wait_until_connected(5000)
    yield comms, up, down
    comms.close(True)


def _pymoos_collect(comms: Any, var: str, n: int, timeout: float = 20.0) -> list[bytes]:
    out: list[bytes] = []
    deadline = time.monotonic() + timeout
    while len(out) < n and time.monotonic() < deadline:
        msgs = [m for m in comms.fetch() if m.key() == var]
        assert all(m.is_binary() for m in msgs)
        out += [m.binary_data() for m in msgs]
        if len(out) < n:
            time.sleep(0.01)
    return out


def test_every_size_to_and_from_pymoos(moosdb: MoosDB, pymoos_peer: tuple[Any, str, str]) -> None:
    comms, up, down = pymoos_peer
    coex = MoosTransport(MoosConfig(host="127.0.0.1", port=moosdb.port, name=unique("pCoex"), tx=up, rx=down))
    try:
        sizes = _sizes(coex.mtu)
        # CoEx -> pymoos
        for start in range(0, len(sizes), 64):
            frames = [_frame(s, 1) for s in sizes[start:start + 64]]
            for f in frames:
                coex.send(f)
            assert _pymoos_collect(comms, up, len(frames)) == frames, f"sizes from {sizes[start]}"
        # pymoos -> CoEx (notify_binary: pymoos' notify(str) would cut at the first zero byte)
        for start in range(0, len(sizes), 64):
            frames = [_frame(s, 2) for s in sizes[start:start + 64]]
            for f in frames:
                assert comms.notify_binary(down, f, -1)
            got = [coex.recv(timeout=10) for _ in frames]
            assert got == frames, f"sizes from {sizes[start]}"
        assert coex.recv(timeout=0.3) is None
        assert coex.stats()["duplicates"] == 0 and coex.stats()["received"] == len(sizes)
    finally:
        coex.close()


# ------------------------------------------------------------------- restart and replay


def _wait(cond: Any, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.05)
    return bool(cond())


def test_moosdb_restart_loses_nothing_duplicates_nothing(moosdb_path: str) -> None:
    db = MoosDB(moosdb_path)
    db.start()
    try:
        a, b = _pair(db)
        a.send(b"up 0")
        b.send(b"down 0")
        assert b.recv(timeout=5) == b"up 0" and a.recv(timeout=5) == b"down 0"
        # b comes back seconds after a: a's frames must wait for b's registration (hold), or
        # MOOSDB would keep only the last one for b's replay
        b.client.retry = 3.0
        db.stop()  # SIGKILL
        a.send(b"up 1")  # possibly written to the dying connection: kept until MOOSDB confirms
        assert _wait(lambda: not a.connected and not b.connected)
        for i in (2, 3, 4):
            a.send(b"up %d" % i)
        b.send(b"down 1\x00\xff")
        db.start()  # same port
        assert [b.recv(timeout=15) for _ in range(4)] == [b"up %d" % i for i in (1, 2, 3, 4)]
        assert a.recv(timeout=15) == b"down 1\x00\xff"
        assert b.recv(timeout=1.5) is None and a.recv(timeout=0.5) is None  # nothing twice
        a.send(b"after")
        assert b.recv(timeout=5) == b"after"
        assert a.stats()["connects"] == 2 and b.stats()["connects"] == 2
        a.close()
        b.close()
    finally:
        db.close()


def test_stored_frame_replayed_on_registration_is_ignored(moosdb: MoosDB, pymoos_peer: tuple[Any, str, str]) -> None:
    comms, _, down = pymoos_peer
    assert comms.notify_binary(down, b"stale frame", -1)
    time.sleep(0.3)
    # MOOSDB really replays it: a second pymoos client that registers receives it ...
    pymoos = pytest.importorskip("pymoos")
    other = pymoos.comms()
    other.set_quiet(True)
    other.set_on_connect_callback(lambda: other.register(down, 0))
    other.run("127.0.0.1", moosdb.port, unique("pymoos2"))
    try:
        assert other.wait_until_connected(5000)
        assert _pymoos_collect(other, down, 1, timeout=5) == [b"stale frame"]
    finally:
        other.close(True)
    # ... but a CoEx end that registers now does not take it for a new frame
    coex = MoosTransport(MoosConfig(host="127.0.0.1", port=moosdb.port, name=unique("pCoex"),
                                    tx=unique("UNUSED"), rx=down))
    try:
        assert coex.recv(timeout=1.0) is None
        assert coex.stats()["replays_ignored"] == 1
        assert comms.notify_binary(down, b"fresh frame", -1)
        assert coex.recv(timeout=5) == b"fresh frame"
    finally:
        coex.close()


def test_own_frames_and_strings_are_not_frames(moosdb: MoosDB) -> None:
    var = unique("COEX_BOTH")
    a = MoosTransport(MoosConfig(host="127.0.0.1", port=moosdb.port, name=unique("a"), tx=var, rx=var))
    b = MoosTransport(MoosConfig(host="127.0.0.1", port=moosdb.port, name=unique("b"), tx=var, rx=var))
    a.send(b"one variable, both ways")
    assert b.recv(timeout=5) == b"one variable, both ways"
    assert a.recv(timeout=0.5) is None and a.stats()["own"] == 1
    s_var = unique("COEX_STR")
    c = MoosTransport(MoosConfig(host="127.0.0.1", port=moosdb.port, name=unique("c"), rx=s_var))
    c.client.notify(s_var, "a string is not a frame")  # the variable is now a string one
    assert c.recv(timeout=0.5) is None
    a.close()
    b.close()
    c.close()


# --------------------------------------------------------------------- coex send / coex listen


@pytest.fixture
def moos_entry_point(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> dict[str, str]:
    """The environment for ``coex`` with the ``moos`` transport registered: an installed
    distribution registers it once installed from this pyproject.toml; a checkout run against
    an older editable install gets the same entry point from a throw-away dist-info."""
    env = dict(os.environ)
    if "moos" not in {ep.name for ep in metadata.entry_points(group="coex.transports")}:
        info = tmp_path / "coex_moos_checkout-0.dist-info"
        info.mkdir()
        (info / "METADATA").write_text("Metadata-Version: 2.1\nName: coex-moos-checkout\nVersion: 0\n")
        (info / "entry_points.txt").write_text(
            "[coex.transports]\nmoos = coex_transports.moos:MoosTransport\n")
        monkeypatch.syspath_prepend(str(tmp_path))
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(tmp_path), env.get("PYTHONPATH")]))
    return env


def test_open_transport_by_uri(moosdb: MoosDB, moos_entry_point: dict[str, str]) -> None:
    t = open_transport(f"moos://127.0.0.1:{moosdb.port}?name={unique('uri')}")
    assert isinstance(t, MoosTransport) and t.connected
    t.close()


def test_send_and_listen_over_moos(moosdb: MoosDB, moos_entry_point: dict[str, str]) -> None:
    up, down = unique("COEX_UP"), unique("COEX_DOWN")
    small = pack([Opaque(96, b"hello")], 256, FrameHeader(src=2, dst=1, seq=1))
    big = pack([Opaque(500, bytes(range(240)))] * 3, 2048, FrameHeader(src=2, dst=1, seq=2, crc=True))
    base = f"moos://127.0.0.1:{moosdb.port}"
    listener = subprocess.Popen(
        [*COEX, "listen", "--transport", f"{base}?name={unique('listen')}&rx={up}&tx={down}",
         "--count", "2", "--timeout", "60"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=moos_entry_point,
    )
    try:
        # the sender holds its frames until the listener has registered (hold=), then waits for
        # MOOSDB to take them before it exits (flush)
        sender = subprocess.run(
            [*COEX, "send", "--transport", f"{base}?name={unique('send')}&tx={up}&rx={down}&hold=45",
             "--hex", small.hex(), "--hex", big.hex()],
            capture_output=True, text=True, timeout=90, env=moos_entry_point,
        )
        assert sender.returncode == 0, sender.stderr
        out, err = listener.communicate(timeout=90)
    finally:
        if listener.poll() is None:
            listener.kill()
            listener.wait()
    assert listener.returncode == 0, err
    assert out.split() == [small.hex(), big.hex()]
