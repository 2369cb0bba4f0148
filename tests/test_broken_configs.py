"""The check is the daemon: every file of a corpus of broken configurations
(``tests/fixtures/broken-configs/``, the six of issue 51 among them) is refused by ``coex
config check`` and by the daemon it configures (``coex vehicle --config`` or ``coex topside
--config``) at start, with the same problems, each named by its key, and no traceback."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path
from typing import Any

import pytest

from coex_apps.console import cli as topside_cli
from coex_apps.vehicle.daemon import VehicleApp
from coex_core.cli import main

CORPUS = Path(__file__).resolve().parent / "fixtures" / "broken-configs"
FILES = sorted(CORPUS.glob("*.toml"))


def _expected(path: Path) -> tuple[str, str]:
    m = re.match(r"# expect: (\S+) \| (.+)", path.read_text().splitlines()[0])
    assert m, f"{path.name}: the first line must be '# expect: KEY | words'"
    return m.group(1), m.group(2).strip()


def _problems(text: str, path: Path) -> set[str]:
    """The problems a command printed about ``path``: ``FILE: KEY: text`` lines (the check's),
    or the daemon's ``coex ...: FILE: KEY: text`` / ``FILE: N problems:`` and indented lines."""
    out = set()
    for line in text.splitlines():
        line = re.sub(r"^coex (vehicle|topside): ", "", line)
        if line.startswith("  "):
            out.add(line.strip())
        elif line.startswith(f"{path}: ") and ": warning: " not in line and not re.match(
                rf"{re.escape(str(path))}: \d+ problems?:?$", line):
            out.add(line[len(f"{path}: "):])
    return out


def test_the_corpus_holds_the_six_of_issue_51() -> None:
    names = {p.stem for p in FILES}
    assert {"lcm-modem-port-76670", "mavlink-autonomy-port-99999", "lcm-autonomy-port-99999",
            "mavlink-input-udpinn", "store-in-missing-folder", "missing-role", "dest-own-id",
            "src-not-node-id", "slots-shorter-than-airtime"} <= names
    assert len(FILES) >= 20


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.stem)
def test_check_and_daemon_refuse_a_broken_configuration_alike(path: Path, capsys: pytest.CaptureFixture[str],
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    key, words = _expected(path)
    assert main(["config", "check", str(path)]) == 1
    check = _problems(capsys.readouterr().out, path)
    assert any(p.startswith(f"{key}: ") and words in p for p in check), check

    started: list[str] = []  # the daemon must refuse before it runs: if it got there, say so
    monkeypatch.setattr(VehicleApp, "run", lambda self: started.append("vehicle"))
    monkeypatch.setattr(topside_cli, "_serve", lambda app: started.append("topside") or app.close() or 0)
    raw: dict[str, Any] = tomllib.loads(path.read_text())
    role = raw.get("node", {}).get("role", "vehicle")  # coex vehicle, for a file that names none
    code = main([role, "--config", str(path)])
    err = capsys.readouterr().err
    assert not started, f"coex {role} started with {path.name}"
    assert code == 2, err
    assert "Traceback" not in err
    assert _problems(err, path) == check, err  # the same problems, every one
