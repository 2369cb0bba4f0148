"""The ``coex`` command line.

The core provides ``coex plugins`` and ``coex spec``; every other sub-command (``demo``,
``bathy``, ``image``, ``timeseries``, ``send``, ``listen``, ``modem-sim``, ``topside``, ``replay``)
is contributed by a plugin through the ``coex.commands`` entry-point group: a function
``register(subparsers)`` that adds its parser and sets ``func`` to a callable taking the parsed
arguments and returning an exit code. The core imports no plugin.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Sequence
from typing import Any

from . import __version__
from .errors import CoexError
from .registry import CHECKER_GROUP, COMMAND_GROUP, available, entry_points

__all__ = ["main", "build_parser"]

log = logging.getLogger("coex")


def _cmd_plugins(args: argparse.Namespace) -> int:
    if args.action == "check":
        # the conformance kit registers its runner in coex.checkers (the core imports none)
        checkers = entry_points(CHECKER_GROUP)
        if not checkers:
            print("coex plugins check: no conformance kit installed (it registers in "
                  f"'{CHECKER_GROUP}'; reinstall coex)", file=sys.stderr)
            return 2
        check = next(iter(checkers.values())).load()
        return int(check(args.names, args.pytest_args or ()))
    if args.names:
        print("coex plugins: plugin names go with 'check' (coex plugins check NAME ...)", file=sys.stderr)
        return 2
    infos = available(check=True)
    if args.json:
        print(json.dumps([info.__dict__ for info in infos], indent=2))
        return 0
    print(f"{'kind':<10} {'name':<12} {'version':<10} {'status':<20} target")
    for info in infos:
        kind = {"coex.modalities": "modality", "coex.transports": "transport", "coex.inputs": "input",
                "coex.autonomy": "autonomy", "coex.detectors": "detector"}.get(info.group, info.group)
        line = f"{kind:<10} {info.name:<12} {info.version:<10} {info.status:<20} {info.target}"
        if info.error:
            line += f"  ({info.error})"
        print(line)
    return 0


def _cmd_spec(args: argparse.Namespace) -> int:
    from ._wire import spec as specgen

    if args.action == "decode":
        return specgen.serve_decoder(sys.stdin, sys.stdout)
    if args.action == "vectors":
        if not args.check_command:
            print("coex spec vectors: give --check-command CMD", file=sys.stderr)
            return 2
        if not specgen.vector_cases(args.vectors):
            print(f"coex spec vectors: no golden vectors in {args.vectors} (give --vectors DIR)", file=sys.stderr)
            return 2
        n, problems = _check_command(specgen, args.check_command, args.vectors, args.only)
        for p in problems[:50]:
            print(p)
        if len(problems) > 50:
            print(f"... and {len(problems) - 50} more")
        print(f"{n} vectors: {n - len(problems) if problems else n} agree, {len(problems)} difference(s) "
              f"({args.check_command})")
        return 1 if problems else 0

    if args.write_vectors:
        specgen.write_vectors(args.write_vectors)
        print(f"wrote the golden vectors to {args.write_vectors}")
        if not (args.check or args.write):
            return 0
    if args.check:
        stale = specgen.check_document(args.document)
        if stale:
            print(f"{args.document} is out of date; run: coex spec --write", file=sys.stderr)
            return 1
        print(f"{args.document} agrees with the construct definitions")
        return 0
    if args.write:
        specgen.write_document(args.document)
        print(f"wrote {args.document}")
        return 0
    print(specgen.render_tables())
    return 0


def _check_command(specgen: Any, command: str, directory: str,
                   only: list[str] | None = None) -> tuple[int, list[str]]:
    """Run another implementation's decoder on every vector (``coex spec vectors``), or on those
    whose names match one of the ``only`` patterns."""
    import fnmatch
    import shlex
    import subprocess

    cases = specgen.vector_cases(directory)
    if only:
        cases = [c for c in cases if any(fnmatch.fnmatchcase(c[0], pat) for pat in only)]
    if not cases:
        return 0, [f"no vectors in {directory}" + (f" match {' '.join(only)}" if only else "")]
    try:
        run = subprocess.run(shlex.split(command), input=specgen.vector_input(cases), capture_output=True,
                             text=True, timeout=600)
    except (OSError, subprocess.TimeoutExpired, ValueError) as exc:
        return len(cases), [f"could not run {command!r}: {exc}"]
    problems = []
    if run.returncode != 0:
        problems.append(f"{command!r} exited with {run.returncode}: {run.stderr.strip()[-300:]}")
    return len(cases), problems + specgen.compare_answers(cases, run.stdout)


def _default_vectors() -> str:
    """The repository's golden vectors (beside the package in a source checkout), else
    ``spec/vectors`` of the working directory."""
    from pathlib import Path

    here = Path(__file__).resolve().parents[1] / "spec" / "vectors"
    return str(here) if here.is_dir() else "spec/vectors"


def _command_word(argv: Sequence[str]) -> str | None:
    """The sub-command ``argv`` names (its first word that is not an option), or ``None`` when
    it names none or asks for the top-level help (every command is listed then). The top-level
    options (``-v``, ``--version``, ``-h``) take no value, so the first other word is the command."""
    for word in argv:
        if word in ("-h", "--help"):
            return None
        if not word.startswith("-"):
            return word
    return None


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The ``coex`` parser. With ``argv`` naming a sub-command that a plugin contributes, only
    that plugin's command is loaded (a ``coex`` call does not import every command: the demo's
    alone takes most of a second); without ``argv``, or when it names no contributed command,
    every command is registered (the top-level help lists them all)."""
    parser = argparse.ArgumentParser(
        prog="coex", description="CoEx: live science data from an underwater vehicle over an acoustic link."
    )
    parser.add_argument("--version", action="version", version=f"coexploration {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("plugins", help="list registered modalities and transports with their status; "
                       "'coex plugins check NAME ...' runs the conformance suite on installed modalities, together")
    p.add_argument("action", nargs="?", choices=["check"],
                   help="check: run the conformance suite on the named modality plugins, together")
    p.add_argument("names", nargs="*", metavar="NAME", help="modality plugins to check (entry-point names)")
    p.add_argument("--pytest-args", nargs=argparse.REMAINDER,
                   help="with check: further pytest arguments (e.g. -x -k node)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=_cmd_plugins)

    p = sub.add_parser("spec", help="print or regenerate the wire-format field tables; check another "
                       "implementation against the vectors ('coex spec vectors --check-command CMD')")
    p.add_argument("action", nargs="?", choices=["vectors", "decode"],
                   help="vectors: feed every vector to --check-command and report differences; "
                        "decode: the reference decoder of that protocol (lines on stdin, JSON out)")
    p.add_argument("--check-command", metavar="CMD",
                   help="with vectors: another implementation's decoder: reads 'message HEX', "
                        "'frame HEX' or 'cells JSON' lines, answers one JSON object per line (spec section 13)")
    p.add_argument("--only", action="append", metavar="PATTERN",
                   help="with vectors: only the vectors whose names match (shell-style, repeatable: "
                        "'cells/*', 'PredictedSubgrid/*', 'invalid/PredictedSubgrid*')")
    p.add_argument("--vectors", default=_default_vectors(), metavar="DIR",
                   help="the vectors (default: the repository's spec/vectors)")
    p.add_argument("--document", default="spec/wire-format.md", help="the spec document")
    p.add_argument("--write", action="store_true", help="rewrite the generated tables in the document")
    p.add_argument("--check", action="store_true", help="exit 1 if the document's tables are stale")
    p.add_argument("--write-vectors", metavar="DIR", help="regenerate the golden vectors into DIR")
    p.set_defaults(func=_cmd_spec)

    commands = entry_points(COMMAND_GROUP)  # sorted by name
    word = None if argv is None else _command_word(argv)
    loaded = [word] if word in commands else []
    _register(sub, [commands[name] for name in loaded])
    if word not in sub.choices:  # no command named, or its plugin did not add a parser by that name
        _register(sub, [ep for name, ep in commands.items() if name not in loaded])
    return parser


def _register(sub: Any, eps: Sequence[Any]) -> None:
    """Let each command plugin add its parser; a broken one becomes a command saying why."""
    for ep in eps:
        try:
            register = ep.load()
            register(sub)
        except Exception as exc:  # a broken or uninstallable plugin must not break the CLI
            log.debug("command plugin %s unavailable: %s", ep.name, exc)
            q = sub.add_parser(ep.name, help=f"(unavailable: {exc})")
            q.set_defaults(func=_unavailable(ep.name, exc))


def _unavailable(name: str, exc: Exception):  # type: ignore[no-untyped-def]
    def run(args: argparse.Namespace) -> int:
        print(f"coex {name} is unavailable: {exc}", file=sys.stderr)
        return 2

    return run


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except CoexError as exc:
        print(f"coex: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
