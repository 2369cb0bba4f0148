"""The plugin author's guide works as written: the out-of-tree package in docs/plugins.md is
copied to a temporary directory, installed, passes its own conformance tests, and passes
`coex plugins check ctd pings`: two out-of-tree plugins in one node, with every built-in one."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "docs" / "plugins.md"
FILE = re.compile(r"<!-- file: (?P<path>[^ ]+) -->\n```[a-z]*\n(?P<body>.*?)\n```", re.S)


def guide_files() -> dict[str, str]:
    files = {m["path"]: m["body"] + "\n" for m in FILE.finditer(GUIDE.read_text())}
    assert {"coex-ctd/pyproject.toml", "coex-ctd/coex_ctd/__init__.py", "coex-ctd/tests/test_conformance.py"} <= set(files)
    assert "CAST, ACK = 130, 131  # spec/third-party-ids.md" in files["coex-ctd/coex_ctd/__init__.py"]
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
