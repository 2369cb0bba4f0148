"""The facade's modules are real files a plugin author's type checker finds: a third-party file
outside the repository's packages that imports every name of ``coex`` and of each ``coex.*``
module (and every ``coex.*`` import the README and the guides show) passes ``mypy --strict``;
no module of the facade is a ``sys.modules`` alias."""

from __future__ import annotations

import ast
import importlib
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FACADE = ROOT / "coex"
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
#: ``from coex.X import ...`` / ``import coex.X`` in a document's code
DOC_IMPORT = re.compile(r"^\s*(?:from\s+(coex\.\w+)\s+import\s+(.+)|import\s+(coex\.\w+))")
#: the modules the facade's docstring and the guides tell authors to import
TOLD = {"coex.messages", "coex.wire", "coex.errors", "coex.tracker", "coex.registry", "coex.state",
        "coex.routing", "coex.lcm", "coex.moos", "coex.ros"}


def facade_modules() -> list[str]:
    """``coex.X`` for every file of the facade package (its ``__init__`` aside)."""
    return sorted(f"coex.{p.stem}" for p in FACADE.glob("*.py") if p.stem != "__init__")


def doc_imports() -> tuple[set[str], list[str]]:
    """The ``coex.*`` modules the README's and the docs' code imports, and its import lines."""
    modules: set[str] = set()
    lines: list[str] = []
    for doc in DOCS:
        in_code = False
        for line in doc.read_text().splitlines():
            if line.lstrip().startswith("```"):
                in_code = not in_code
                continue
            m = DOC_IMPORT.match(line) if in_code else None
            if m:
                modules.add(m[1] or m[3])
                lines.append(line.strip())
    return modules, lines


def test_the_facade_sets_no_module_aliases() -> None:
    """``coex/__init__.py`` never writes ``sys.modules`` (its modules are files)."""
    tree = ast.parse((FACADE / "__init__.py").read_text())
    names = {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)} | {
        n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
    assert "modules" not in names and "sys" not in names


def test_every_facade_module_the_docs_name_is_a_file_with_an_explicit_all() -> None:
    named, _ = doc_imports()
    assert {"coex.messages", "coex.wire"} <= named
    files = facade_modules()
    assert sorted((named | TOLD) - set(files)) == [], "the docs name facade modules that are not files of coex/"
    for name in files:
        tree = ast.parse((ROOT / (name.replace(".", "/") + ".py")).read_text())
        declared = [n for n in tree.body if isinstance(n, ast.Assign)
                    and any(isinstance(t, ast.Name) and t.id == "__all__" for t in n.targets)]
        assert declared, f"{name} declares its __all__"
    import coex

    for name in sorted(TOLD - {"coex.lcm", "coex.moos", "coex.ros"}):  # those three load on demand
        mod = importlib.import_module(name)
        assert mod.__file__ is not None and Path(mod.__file__).parent == FACADE
        assert getattr(coex, name.split(".")[1]) is mod  # ``coex.messages`` after ``import coex``


def third_party_source() -> str:
    """A plugin author's module: every name of ``coex`` and of each facade module, imported as an
    author writes it (each under an alias of its own, so that equal names of two modules do not
    clash), the docs' own import lines, and a few uses whose types must agree."""
    import coex

    out = ["from __future__ import annotations", "",
           "from coex import " + ", ".join(f"{n} as _coex_{n}" for n in coex.__all__ if n != "__version__")]
    for name in facade_modules():
        mod = importlib.import_module(name)
        short = name.split(".")[1]
        out.append(f"from {name} import " + ", ".join(f"{n} as _{short}_{n}" for n in mod.__all__))
    out += ["import coex.messages", "import coex.wire",
            "from coex_conformance import ModalityFixtures, ModalityTests",
            "from coex_conformance.companions import Companion",
            "from coex_plugins.bathymetry.sender import BathymetrySender",
            "from coex_plugins.imagery.sender import ImagerySender", ""]
    out += sorted(set(doc_imports()[1]))
    out += ["",
            "def size(body: bytes) -> int:",
            "    return coex.wire.encoded_size(coex.messages.Opaque(32600, body))",
            "",
            "",
            "def final(state: _tracker_State) -> bool:",
            "    return state in _tracker_FINAL",
            "",
            "",
            "error: type[_coex_CoexError] = _errors_DecodeError",
            "saved: bytes = _state_dumps([1, 2.0, 'three'])",
            "",
            "",
            "# the built-in senders offer detectors the views their detectors declare (coex.Detector.view)",
            "def map_view(sender: BathymetrySender) -> _coex_MapView:",
            "    return sender.detector_view()",
            "",
            "",
            "def frame_view(sender: ImagerySender) -> _coex_ImageFrames:",
            "    return sender.detector_view()",
            "",
            "",
            "class Fixtures(ModalityFixtures):",
            "    pass",
            "",
            "",
            "def suite() -> tuple[type[ModalityTests], type[Companion]]:",
            "    return ModalityTests, Companion",
            ""]
    return "\n".join(out)


def test_third_party_code_importing_the_facade_passes_strict_mypy(tmp_path: Path) -> None:
    """``mypy --strict``, run where no project configuration is found (the CoEx modules it
    follows are not reported on), on a file outside the repository's packages and on the sample
    third-party plugin (``examples/coex-sample-plugin``, its detector included) finds every
    module and every name: no ``import-not-found``, no ``attr-defined``, nothing. The built-in
    plugins (no ``py.typed`` of their own yet) are read from their folder."""
    pytest.importorskip("mypy")
    (tmp_path / "coex_third_party.py").write_text(third_party_source())
    (tmp_path / "mypy.ini").write_text(f"[mypy]\nstrict = True\nfollow_imports = silent\n"
                                       f"mypy_path = {ROOT / 'plugins'}\n")
    sample = ROOT / "examples" / "coex-sample-plugin" / "coex_sample_plugin"
    r = subprocess.run([sys.executable, "-m", "mypy", "--config-file", "mypy.ini", "--cache-dir",
                        str(tmp_path / "cache"), "coex_third_party.py", str(sample)],
                       cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert "import-not-found" not in r.stdout, r.stdout
    assert r.returncode == 0, r.stdout + r.stderr
    assert "no issues found in 3 source files" in r.stdout, r.stdout
