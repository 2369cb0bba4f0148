#!/usr/bin/env bash
# `make test` after lint and install: `make typecheck` (scripts/typecheck.sh) in the background
# beside `pytest -n 4` (the rest of the arguments are pytest's). Strict mypy is about 35 s of one
# core from a cold cache; pytest leaves CPU idle while tests wait on servers, browsers and
# daemons, so the two together take pytest's time. mypy runs at a lower priority (nice 10): it
# takes the CPU the tests leave idle instead of slowing the dives that start the run. Its output
# is printed after pytest's, and `make test` fails when either fails.
set -uo pipefail
venv=$1; shift
log=$(mktemp)
trap 'rm -f "$log"' EXIT
nice -n 10 bash scripts/typecheck.sh "$venv" >"$log" 2>&1 &
typecheck=$!
# one collection first, in this process alone: it compiles the tests (pytest's assertion
# rewriting, about 9 s of CPU) and the modules they import once and writes them (.pyc, see the
# Makefile on PYTHONDONTWRITEBYTECODE), instead of every worker doing all of it at once
"$venv/bin/pytest" --collect-only -q -p no:xdist -o addopts="" >/dev/null 2>&1 || true
"$venv/bin/pytest" -n 4 "$@"
tests=$?
wait "$typecheck"
types=$?
echo "== make typecheck (ran beside pytest): $([ $types -eq 0 ] && echo passed || echo FAILED)"
cat "$log"
[ $tests -eq 0 ] && [ $types -eq 0 ]
