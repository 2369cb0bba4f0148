"""A decoder of the subgrid codings written from spec/ alone (tests/spec_decoder/subgrids.py:
no CoEx import) agrees with every subgrid vector, the cells a receiver rebuilds from its parent
included, through `coex spec vectors --check-command` (wire-format.md 13.3); a copy of it with
one probability wrong does not."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DECODER = ROOT / "tests" / "spec_decoder" / "subgrids.py"
ONLY = ["cells/*", "PredictedSubgrid/*", "Subgrid/*", "invalid/PredictedSubgrid*", "invalid/predicted_*",
        "invalid/Subgrid*", "invalid/rice_*", "invalid/gradient*", "invalid/subgrid_*"]


def _check(command: str) -> subprocess.CompletedProcess[str]:
    args = [sys.executable, "-m", "coex_core.cli", "spec", "vectors", "--vectors", str(ROOT / "spec" / "vectors"),
            "--check-command", command]
    for pat in ONLY:
        args += ["--only", pat]
    return subprocess.run(args, capture_output=True, text=True, timeout=300, cwd=ROOT)


def test_the_independent_subgrid_decoder_imports_nothing_of_coex() -> None:
    tree = ast.parse(DECODER.read_text())
    names = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    names |= {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    assert not {m for m in names if m.split(".")[0].startswith("coex")}, names


def test_a_decoder_from_the_spec_alone_decodes_every_subgrid_vector() -> None:
    run = _check(f"{sys.executable} {DECODER}")
    assert run.returncode == 0, run.stdout + run.stderr
    summary = run.stdout.strip().splitlines()[-1]
    n = int(summary.split()[0])
    assert n >= 45 and f"{n} vectors: {n} agree, 0 difference(s)" in summary, summary


def test_the_check_catches_a_decoder_with_one_probability_wrong(tmp_path: Path) -> None:
    wrong = tmp_path / "wrong.py"
    wrong.write_text(
        "import sys\n"
        f"sys.path.insert(0, {str(DECODER.parent)!r})\n"
        "import subgrids\n"
        "subgrids.TABLES[0]['Z'][1] += 64\n"
        "raise SystemExit(subgrids.main())\n")
    run = _check(f"{sys.executable} {wrong}")
    assert run.returncode == 1 and "difference(s)" in run.stdout, run.stdout + run.stderr
    assert "PredictedSubgrid/parent_typical" in run.stdout or "cells/parent_nearest" in run.stdout
