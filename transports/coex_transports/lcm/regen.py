"""Regenerate the committed LCM Python types from ``spec/bindings/*.lcm``.

Usage (from the repository root)::

    python transports/coex_transports/lcm/regen.py            # rewrite lcm/_types/
    python transports/coex_transports/lcm/regen.py --check    # exit 1 if _types/ is stale

It runs the ``lcm-gen`` that ships in the ``lcm`` wheel (``lcm.LCM_BIN_DIR``) with ``-p`` into a
temporary directory and copies the generated ``coex`` package verbatim into ``_types/``. The
.lcm types are flat (no nested user types), so the generated modules need no absolute imports
and work as the sub-package ``coex_transports.lcm._types``.
"""

from __future__ import annotations

import argparse
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

__all__ = ["BINDINGS_DIR", "TYPES_DIR", "find_lcm_gen", "generate", "stale_files", "main"]


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
    return package


def _generated(package: Path) -> dict[str, Path]:
    return {p.name: p for p in sorted(package.glob("*.py"))}


def stale_files(types_dir: Path = TYPES_DIR, bindings_dir: Path = BINDINGS_DIR) -> list[str]:
    """Names of files in ``types_dir`` that differ from a fresh generation (missing, extra, changed)."""
    with tempfile.TemporaryDirectory() as tmp:
        fresh = _generated(generate(Path(tmp), bindings_dir))
        committed = {p.name: p for p in sorted(types_dir.glob("*.py"))}
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
        for old in types_dir.glob("*.py"):
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
