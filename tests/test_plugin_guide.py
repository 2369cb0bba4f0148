"""The plugin author's guide works as written: the out-of-tree package in docs/plugins.md is
copied to a temporary directory, installed, passes its own conformance tests, and passes
`coex plugins check ctd pings`: two out-of-tree plugins in one node, with every built-in one."""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from coex_transports.testing import free_port as _free_port

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "docs" / "plugins.md"
FILE = re.compile(r"<!-- file: (?P<path>[^ ]+) -->\n```[a-z]*\n(?P<body>.*?)\n```", re.S)


def guide_files() -> dict[str, str]:
    files = {m["path"]: m["body"] + "\n" for m in FILE.finditer(GUIDE.read_text())}
    assert {"coex-ctd/pyproject.toml", "coex-ctd/coex_ctd/__init__.py", "coex-ctd/tests/test_conformance.py"} <= set(files)
    assert "CAST, ACK = 32600, 32601  # CoEx's example ids" in files["coex-ctd/coex_ctd/__init__.py"]
    return files


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """The guide's package written out and installed (pip, into a directory of its own)."""
    tmp = tmp_path_factory.mktemp("guide")
    for rel, body in guide_files().items():
        path = tmp / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(body)
    site = tmp / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                    "--disable-pip-version-check", "--target", str(site), str(tmp / "coex-ctd")],
                   check=True, capture_output=True, text=True)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(site), env.get("PYTHONPATH", "")])
    return {"env": env, "project": str(tmp / "coex-ctd")}  # type: ignore[dict-item]


def run(args: list[str], installed: dict, cwd: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, *args], env=installed["env"], cwd=cwd, capture_output=True,
                          text=True, timeout=600)


def test_the_guides_package_installs_and_passes_its_own_conformance_tests(installed: dict) -> None:
    r = run(["-m", "pytest", "-q", "-p", "no:cacheprovider", "tests"], installed, installed["project"])
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
    assert re.search(r"\b2\d passed\b", r.stdout), r.stdout[-500:]


def test_two_out_of_tree_plugins_pass_coex_plugins_check_together(installed: dict) -> None:
    """`ctd` (from the guide) and `pings` (examples/coex-sample-plugin) in one node with every
    built-in modality: the whole suite passes for both."""
    r = run(["-m", "coex_core.cli", "plugins", "check", "ctd", "pings"], installed, installed["project"])
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
    assert "coex plugins check: the conformance suite on ctd, pings, together" in r.stdout
    assert re.search(r"\b\d+ passed\b", r.stdout) and " failed" not in r.stdout


def test_plugins_check_names_a_plugin_without_conformance_inputs(installed: dict) -> None:
    r = run(["-m", "coex_core.cli", "plugins", "check", "no-such-plugin"], installed, installed["project"])
    assert r.returncode == 2
    assert "plugin 'no-such-plugin' registers no conformance inputs" in r.stderr


EXAMPLE = re.compile(r"<!-- example: (?P<path>[^ ]+) -->\n```[a-z]*\n(?P<body>.*?)\n```", re.S)


def test_the_guides_transport_passes_the_transport_conformance_tests(tmp_path: Path) -> None:
    """Section 7's UDP transport and its test, as written (on two free ports), pass
    TransportTests; its URI parser refuses what it should, opening nothing."""
    examples = {m["path"]: m["body"] + "\n" for m in EXAMPLE.finditer(GUIDE.read_text())}
    assert set(examples) == {"coex_udp.py", "test_udp.py"}
    a, b = _free_port(), _free_port()
    (tmp_path / "coex_udp.py").write_text(examples["coex_udp.py"])
    (tmp_path / "test_udp.py").write_text(examples["test_udp.py"].replace("47001", str(a)).replace("47002", str(b)))
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), env.get("PYTHONPATH", "")])
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "test_udp.py"], env=env,
                       cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
    assert re.search(r"\b\d+ passed\b", r.stdout) and " failed" not in r.stdout
    check = subprocess.run([sys.executable, "-c", (
        "from coex import ConfigError\n"
        "from coex_udp import UdpTransport as U\n"
        "assert U.check_uri('udp://10.0.0.2:5000?listen=5001&mtu=64').mtu == 64\n"
        "for bad in ('udp://10.0.0.2:5000', 'udp://10.0.0.2:5000?listen=5001&mtu=0', "
        "'udp://10.0.0.2:5000?listen=5001&speed=3', 'udp://10.0.0.2?listen=1', 'tcp://h:1?listen=2'):\n"
        "    try:\n"
        "        U.check_uri(bad)\n"
        "    except ConfigError:\n"
        "        continue\n"
        "    raise SystemExit(bad)\n")], env=env, capture_output=True, text=True, timeout=60)
    assert check.returncode == 0, check.stdout + check.stderr


def test_every_coex_name_the_guide_uses_is_in_the_facade() -> None:
    """docs/plugins.md names `coex.X` (and imports `from coex import ...`): each is exported by
    the public facade, so an author never needs coex_core."""
    import coex

    text = GUIDE.read_text()
    names = set(re.findall(r"\bcoex\.([A-Za-z_]\w*)", text))
    for block in re.findall(r"from coex import \(?([^)]*?)\)?\n(?:\n|[a-z])", text):
        names.update(n.strip() for n in block.replace("\n", ",").split(",") if n.strip())
    names -= {"messages", "wire", "modalities", "transports", "conformance", "commands", "detectors"}  # modules, entry-point groups
    # section 7's table of what a transport author imports from coex
    table = text.split("What a transport author imports", 1)[1].split("\n\n", 2)[1]
    for row in table.splitlines()[2:]:
        names.update(re.findall(r"`(\w+)", row.split("|")[1]))
    names.discard("coex")
    assert {"parse_query", "UriInfo", "LinkDown", "persistent", "DecodeError", "EncodeError", "TransportTimeout",
            "FrameTooLarge", "load_transport", "Health"} <= names
    # coex.lcm, coex.moos, coex.ros: the facade's middleware modules, not loaded by import coex
    missing = sorted(n for n in names if not hasattr(coex, n) and importlib.util.find_spec(f"coex.{n}") is None)
    assert not missing, f"the guide names coex.{missing} which the facade does not export"
    assert "coex_core" not in re.sub(r"`coex_core[^`]*`", "", text.split("## 9.", 1)[0]).replace(
        "(`coex_core.*`)", ""), "the guide (before its upgrade notes) imports nothing from coex_core"
