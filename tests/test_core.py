"""The core's contracts: no I/O modules, error hierarchy, registry, loopback, time stamps, CLI."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

import pytest

from coex_conformance import TransportFixtures, TransportTests
from coex_core import errors, registry
from coex_core.loopback import LoopbackLink, LoopbackTransport
from coex_core.timefmt import STAMP_MODULUS, to_stamp, unwrap
from coex_core.transport import parse_query

FORBIDDEN = ["serial", "pymavlink", "lcm", "socket", "threading", "asyncio", "glymur", "pywt", "rosbags",
             "coex_plugins", "coex_transports"]
#: Modules whose import in core source would mean reading a clock, sleeping or doing I/O.
FORBIDDEN_IMPORTS = {"time", "datetime", "socket", "threading", "asyncio", "serial", "subprocess", "select",
                     "selectors", "multiprocessing"}


def test_core_imports_no_io_module() -> None:
    code = (
        "import sys, json\n"
        "import coex_core, coex_core.wire, coex_core.modality, coex_core.transport, coex_core.loopback,"
        " coex_core.registry, coex_core.jsonfmt, coex_core.timefmt\n"
        "import pkgutil, importlib\n"
        "for m in pkgutil.walk_packages(coex_core.__path__, 'coex_core.'):\n"
        "    if m.name != 'coex_core.cli': importlib.import_module(m.name)\n"
        f"print(json.dumps([n for n in {FORBIDDEN!r} if n in sys.modules]))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert json.loads(out.stdout) == []


def test_core_source_never_imports_clock_or_io_modules() -> None:
    import ast
    from pathlib import Path

    import coex_core

    root = Path(coex_core.__file__).parent
    offenders = []
    for path in root.rglob("*.py"):
        if path.name == "cli.py":  # the command line is a front end, not protocol logic
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name.split(".")[0] for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module.split(".")[0]]
            offenders += [f"{path.relative_to(root)}: {n}" for n in names if n in FORBIDDEN_IMPORTS]
    assert offenders == []


def test_error_hierarchy() -> None:
    assert issubclass(errors.DecodeError, errors.CoexError)
    assert issubclass(errors.DecodeError, ValueError)
    assert issubclass(errors.PluginNotFound, LookupError)
    assert issubclass(errors.FrameTooLarge, errors.TransportError)
    for name in ("EncodeError", "ConfigError", "PluginNotFound", "RequestRejected"):
        assert issubclass(getattr(errors, name), errors.CoexError)


def test_registry_lists_builtin_and_third_party_plugins() -> None:
    infos = {(i.group, i.name): i for i in registry.available(check=True)}
    assert ("coex.transports", "loopback") in infos
    assert infos[("coex.transports", "loopback")].status == "ok"
    for name in ("bathymetry", "imagery", "timeseries"):
        assert ("coex.modalities", name) in infos
    for name in ("micromodem", "mavlink", "lcm"):
        assert ("coex.transports", name) in infos
    # the sample third-party plugin registers exactly like the built-ins
    assert infos[("coex.modalities", "pings")].status == "ok"
    from coex_sample_plugin import PingModality

    assert infos[("coex.modalities", "pings")].version == PingModality.version


def test_registry_errors_are_typed() -> None:
    with pytest.raises(errors.PluginNotFound, match="registered"):
        registry.load_modality("no-such-modality")
    with pytest.raises(errors.PluginNotFound):
        registry.open_transport("nosuchscheme://x")


def test_missing_extra_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    from importlib import metadata

    ep = metadata.EntryPoint("ghost", "coex_no_such_dependency_xyz:Thing [ghostly]", "coex.modalities")
    monkeypatch.setattr(registry, "_entry_points", lambda group: {"ghost": ep})
    with pytest.raises(errors.PluginLoadError, match=r"\[ghostly\]"):
        registry.load_modality("ghost")


def test_open_transport_by_uri_pairs_loopback_ends() -> None:
    a = registry.open_transport("loopback://pair-test?mtu=64&rate=1000")
    b = registry.open_transport("loopback://pair-test")
    assert isinstance(a, LoopbackTransport) and a.link is b.link and a.mtu == 64
    a.send(b"hello")
    assert b.recv(timeout=1.0) == b"hello"
    with pytest.raises(errors.ConfigError):
        registry.open_transport("loopback://x?bogus=1")


def test_coex_send_flushes_through_the_declared_transport_hook(monkeypatch: pytest.MonkeyPatch) -> None:
    """``Transport.flush`` is declared on the base (default: nothing to wait for) and ``coex
    send`` calls it after its frames, before closing; a transport that buffers overrides it."""
    import argparse

    from coex_core.transport import Transport
    from coex_transports import _cli

    link = LoopbackLink(mtu=64, bytes_per_s=1000)
    assert LoopbackTransport.flush is Transport.flush and link.a.flush() is None
    calls: list[int] = []

    class Buffering(LoopbackTransport):
        def flush(self) -> None:
            calls.append(self.link.in_flight())

    monkeypatch.setattr(_cli, "open_transport", lambda uri: Buffering(link, 0))
    assert _cli.run_send(argparse.Namespace(transport="loopback://x", frames=[b"ab", b"cd"])) == 0
    assert calls == [2]  # once, after both frames were handed over
    assert link.b.recv(timeout=1.0) == b"ab" and link.b.recv(timeout=1.0) == b"cd"


def test_parse_query_types_and_rejects() -> None:
    assert parse_query("rate=5&src=1&fdp=true", {"rate": int, "src": int, "fdp": bool}) == {
        "rate": 5, "src": 1, "fdp": True}
    with pytest.raises(errors.ConfigError):
        parse_query("rate=fast", {"rate": int})


def test_loopback_is_deterministic_and_lossy() -> None:
    def run(seed: int) -> list[int]:
        link = LoopbackLink(mtu=32, bytes_per_s=100, loss=0.5, seed=seed)
        got = []
        for i in range(200):
            link.a.send(bytes([i]))
        while (f := link.b.recv(timeout=10.0)) is not None:
            got.append(f[0])
        return got

    first = run(1)
    assert first == run(1) and first != run(2)
    assert 60 < len(first) < 140 and first == sorted(first)


def test_loopback_timing_follows_bytes_per_second() -> None:
    link = LoopbackLink(mtu=256, bytes_per_s=100, delay=0.5)
    link.a.send(bytes(100))
    link.a.send(bytes(50))
    assert link.b.recv(timeout=0.5) is None and link.now == pytest.approx(0.5)
    assert link.b.recv(timeout=10) == bytes(100) and link.now == pytest.approx(1.5)
    assert link.b.recv(timeout=10) == bytes(50) and link.now == pytest.approx(2.0)


def test_stamps_roll_over_to_the_nearest_time() -> None:
    t = 10 * STAMP_MODULUS + 1234.7
    assert to_stamp(t) == 1234
    assert unwrap(to_stamp(t), t + 5) == pytest.approx(t - 0.7)
    late = 3 * STAMP_MODULUS - 10.0  # stamp just before rollover, received just after it
    assert unwrap(to_stamp(late), 3 * STAMP_MODULUS + 20.0) == pytest.approx(late)


class LoopbackFixtures(TransportFixtures):
    @pytest.fixture
    def transport_pair(self):  # type: ignore[no-untyped-def]
        link = LoopbackLink(mtu=256, bytes_per_s=100.0)
        yield link.a, link.b
        link.a.close()
        link.b.close()


class TestLoopbackConformance(TransportTests, LoopbackFixtures):
    pass


def test_cli_plugins_and_spec_check() -> None:
    out = subprocess.run([sys.executable, "-m", "coex_core.cli", "plugins", "--json"], capture_output=True,
                         text=True, check=True)
    names = {p["name"] for p in json.loads(out.stdout)}
    assert {"loopback", "bathymetry", "micromodem", "pings"} <= names
    chk = subprocess.run([sys.executable, "-m", "coex_core.cli", "spec", "--check"], capture_output=True,
                         text=True)
    assert chk.returncode == 0, chk.stderr


def test_the_version_is_one_and_the_changelog_says_it(capsys: pytest.CaptureFixture[str]) -> None:
    """pyproject.toml and coex.__version__ give one version (the package's); CHANGELOG.md
    names it, and `coex --version` prints it."""
    import re
    import tomllib
    from pathlib import Path

    import coex
    from coex_core import __version__
    from coex_core.cli import build_parser

    root = Path(__file__).resolve().parents[1]
    declared = tomllib.loads((root / "pyproject.toml").read_text())["project"]["version"]
    assert declared == __version__ == coex.__version__
    assert re.fullmatch(r"\d+\.\d+\.\d+", declared)
    assert f"package version is {declared}" in (root / "CHANGELOG.md").read_text()
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--version"])
    assert f"coexploration {declared}" in capsys.readouterr().out


def test_a_coex_call_loads_only_the_command_it_names() -> None:
    """``coex NAME ...`` registers only NAME's plugin command (the core's own commands always):
    a short command does not import the demo. The top-level help, an unknown word and no argv
    register every command, so the help and argparse's "invalid choice" still list them all."""
    from coex_core.cli import _command_word, build_parser
    from coex_core.registry import COMMAND_GROUP, entry_points

    def names(argv: list[str] | None) -> set[str]:
        sub = next(a for a in build_parser(argv)._actions if isinstance(a, argparse._SubParsersAction))
        return set(sub.choices)

    every = {"plugins", "spec", *entry_points(COMMAND_GROUP)}
    assert {"demo", "operators", "config"} < every
    assert names(["operators", "add", "ana"]) == {"plugins", "spec", "operators"}
    assert names(["-v", "config", "check", "x.toml"]) == {"plugins", "spec", "config"}
    assert names(["spec", "--check"]) == {"plugins", "spec"}
    assert names(["--help", "demo"]) == names(["nosuch"]) == names([]) == names(None) == every
    assert _command_word(["-vv", "demo", "--quick"]) == "demo" and _command_word(["-h"]) is None
    code = ("import sys; from coex_core.cli import build_parser; build_parser(['operators', 'list']); "
            "print(sorted(m for m in sys.modules if m.startswith('coex_apps.demo')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out
