"""Regenerate the committed LCM Python types from ``spec/bindings/*.lcm``.

Usage (from the repository root)::

    python transports/coex_transports/lcm/regen.py            # rewrite lcm/_types/
    python transports/coex_transports/lcm/regen.py --check    # exit 1 if _types/ is stale

It runs the ``lcm-gen`` that ships in the ``lcm`` wheel (``lcm.LCM_BIN_DIR``) with ``-p`` into a
temporary directory and copies the generated ``coex`` package verbatim into ``_types/``. The
.lcm types are flat (no nested user types), so the generated modules need no absolute imports
and work as the sub-package ``coex_transports.lcm._types``.

lcm-gen's Python is unannotated, so beside each generated ``<type>.py`` this writes a typing stub
``<type>.pyi`` (:func:`stub`) from the class's own ``__slots__``, ``__typenames__`` and
``__dimensions__``: a strict type checker then reads each field with its LCM type (``double`` a
``float``, ``byte[n]`` ``bytes``, other arrays sequences) and ``encode``/``decode`` typed. The
stubs are generated, never edited, and checked for staleness with the modules.
"""

from __future__ import annotations

import argparse
import ast
import filecmp
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
TYPES_DIR = HERE / "_types"
ROOT = HERE.parents[2]
BINDINGS_DIR = ROOT / "spec" / "bindings"
LCM_PACKAGE = "coex"

__all__ = ["BINDINGS_DIR", "TYPES_DIR", "find_lcm_gen", "generate", "stale_files", "stub", "main"]

#: the Python type of each LCM primitive, as lcm-gen's Python code holds it
_PRIMITIVES = {"int8_t": "int", "int16_t": "int", "int32_t": "int", "int64_t": "int", "byte": "int",
               "boolean": "bool", "float": "float", "double": "float", "string": "str"}


def find_lcm_gen() -> str:
    """Path of the ``lcm-gen`` executable of the installed ``lcm`` wheel (else from ``PATH``)."""
    try:
        import lcm

        candidate = os.path.join(lcm.LCM_BIN_DIR, "lcm-gen")
        if os.path.isfile(candidate) and os.access(candidate, os.X_OK):
            return candidate
    except ImportError:  # pragma: no cover - the lcm extra is required to regenerate
        pass
    found = shutil.which("lcm-gen")
    if not found:
        raise FileNotFoundError("lcm-gen not found: pip install 'coexploration[lcm]'")
    return found


def generate(out_dir: Path, bindings_dir: Path = BINDINGS_DIR) -> Path:
    """Run lcm-gen on every ``*.lcm`` file into ``out_dir``; return the generated package dir."""
    sources = sorted(str(p) for p in bindings_dir.glob("*.lcm"))
    if not sources:
        raise FileNotFoundError(f"no .lcm files in {bindings_dir}")
    subprocess.run(
        [find_lcm_gen(), "-p", "--ppath", str(out_dir), *sources],
        check=True,
        capture_output=True,
        timeout=60,
    )
    package = out_dir / LCM_PACKAGE
    if not package.is_dir():
        raise RuntimeError(f"lcm-gen did not create the {LCM_PACKAGE!r} package in {out_dir}")
    for module in sorted(package.glob("*.py")):
        if module.name != "__init__.py":
            module.with_suffix(".pyi").write_text(stub(module.read_text()))
    return package


def _field_type(typename: str, dims: list[object] | None) -> str:
    """The annotation of one field: its primitive (or type), in a sequence per dimension
    (``byte`` arrays are ``bytes``, as lcm-gen decodes them)."""
    base = _PRIMITIVES.get(typename, typename.rsplit(".", 1)[-1])
    depth = len(dims or [])
    if typename == "byte" and depth:
        base, depth = "bytes", depth - 1
    for _ in range(depth):
        base = f"Sequence[{base}]"
    return base


def stub(source: str) -> str:
    """The typing stub of one lcm-gen Python module (its class's fields from ``__slots__``,
    ``__typenames__`` and ``__dimensions__``; read with :mod:`ast`, never run)."""
    cls = next(n for n in ast.parse(source).body if isinstance(n, ast.ClassDef))
    declared: dict[str, ast.expr] = {}
    for node in cls.body:
        if isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Name):
            declared[node.targets[0].id] = node.value
    slots = ast.literal_eval(declared["__slots__"])
    typenames = ast.literal_eval(declared["__typenames__"])
    dims = ast.literal_eval(declared["__dimensions__"])
    name = cls.name
    fields = [f"    {field}: {_field_type(t, d)}" for field, t, d in zip(slots, typenames, dims, strict=True)]
    lines = ["# Typing stub of the lcm-gen module beside it, written by regen.py from the class's",
             "# __slots__, __typenames__ and __dimensions__. DO NOT MODIFY BY HAND.", ""]
    if any("Sequence[" in f for f in fields):
        lines.append("from collections.abc import Sequence")
    lines.append("from typing import BinaryIO")
    nested = sorted({t.rsplit(".", 1)[-1] for t in typenames if t not in _PRIMITIVES})
    lines += [f"from .{t} import {t}" for t in nested]
    lines += ["", "", f"class {name}:",
              "    __slots__: list[str]", "    __typenames__: list[str]",
              "    __dimensions__: list[list[int | str] | None]", *fields]
    lines += ["    def __init__(self) -> None: ...",
              "    def encode(self) -> bytes: ...",
              "    @staticmethod",
              f"    def decode(data: bytes | BinaryIO) -> {name}: ...",
              "    @staticmethod",
              "    def _get_packed_fingerprint() -> bytes: ...",
              "    def get_hash(self) -> int: ...", ""]
    return "\n".join(lines)


def _generated(package: Path) -> dict[str, Path]:
    return {p.name: p for p in sorted([*package.glob("*.py"), *package.glob("*.pyi")])}


def stale_files(types_dir: Path = TYPES_DIR, bindings_dir: Path = BINDINGS_DIR) -> list[str]:
    """Names of files in ``types_dir`` that differ from a fresh generation (missing, extra, changed)."""
    with tempfile.TemporaryDirectory() as tmp:
        fresh = _generated(generate(Path(tmp), bindings_dir))
        committed = _generated(types_dir)
        stale = sorted(set(fresh) ^ set(committed))
        for name in sorted(set(fresh) & set(committed)):
            if not filecmp.cmp(fresh[name], committed[name], shallow=False):
                stale.append(name)
        return sorted(stale)


def write(types_dir: Path = TYPES_DIR, bindings_dir: Path = BINDINGS_DIR) -> list[str]:
    """Regenerate ``types_dir``; return the file names written."""
    with tempfile.TemporaryDirectory() as tmp:
        fresh = _generated(generate(Path(tmp), bindings_dir))
        types_dir.mkdir(parents=True, exist_ok=True)
        for old in _generated(types_dir).values():
            if old.name not in fresh:
                old.unlink()
        for name, path in fresh.items():
            shutil.copyfile(path, types_dir / name)
        return sorted(fresh)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if the committed types are stale")
    parser.add_argument("--bindings", type=Path, default=BINDINGS_DIR, help="directory of .lcm files")
    parser.add_argument("--out", type=Path, default=TYPES_DIR, help="the _types directory")
    args = parser.parse_args(argv)
    if args.check:
        stale = stale_files(args.out, args.bindings)
        if stale:
            print(f"stale LCM types in {args.out}: {', '.join(stale)}; run: python {__file__}",
                  file=sys.stderr)
            return 1
        print(f"{args.out} agrees with {args.bindings}")
        return 0
    names = write(args.out, args.bindings)
    print(f"wrote {', '.join(names)} into {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
