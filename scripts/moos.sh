#!/usr/bin/env bash
# `make moos`: build a real MOOSDB and pymoos for the MOOS tests, from the MOOS sources in
# ../shared/vendor/moos (core-moos, python-moos; their build_moos.sh builds under $WORK, default
# ~/.cache/coex-moos, a few seconds once built), and install the pymoos wheel into the venv.
# Never fails the build: without the sources or the tools it says why, and the MOOS tests that
# need MOOSDB or pymoos are skipped with that reason (tests/_moos.py); every other test runs.
# Usage: scripts/moos.sh [VENV_PYTHON]   Env: MOOS_VENDOR (default ../shared/vendor/moos), WORK
set -u
PY=${1:-.venv/bin/python}
VENDOR=${MOOS_VENDOR:-../shared/vendor/moos}
WORK=${WORK:-${XDG_CACHE_HOME:-$HOME/.cache}/coex-moos}
export WORK
say() { echo "moos: $*"; }
have_pymoos() { "$PY" -c 'import pymoos' >/dev/null 2>&1; }

if command -v MOOSDB >/dev/null 2>&1 && have_pymoos; then
  say "MOOSDB on PATH ($(command -v MOOSDB)) and pymoos installed"; exit 0
fi
if [ ! -f "$VENDOR/build_moos.sh" ]; then
  say "no $VENDOR/build_moos.sh (the MOOS sources): MOOS tests needing MOOSDB/pymoos will be skipped"; exit 0
fi
for tool in cmake g++ make patch; do
  if ! command -v "$tool" >/dev/null 2>&1; then
    say "$tool is missing, cannot build MOOSDB/pymoos: the MOOS tests needing them will be skipped"; exit 0
  fi
done
# build pymoos for the venv's own Python (the wheel is tied to its version)
BASE_PY=$("$PY" -c 'import sys; print(sys._base_executable)' 2>/dev/null) || BASE_PY=python3
mkdir -p "$WORK"
LOG=$WORK/build.log
say "building MOOSDB and pymoos from $VENDOR under $WORK (log: $LOG)"
if ! PYTHON=$BASE_PY bash "$VENDOR/build_moos.sh" >"$LOG" 2>&1; then
  tail -n 15 "$LOG" | sed 's/^/  | /'
  say "build failed (see $LOG): the MOOS tests needing MOOSDB/pymoos will be skipped"; exit 0
fi
say "MOOSDB: $WORK/core-moos/build/bin/MOOSDB"
WHEEL=$(ls -t "$WORK"/dist/pymoos-*.whl 2>/dev/null | head -n 1)
STAMP=$(dirname "$PY")/../.pymoos-wheel
# the wheel is rebuilt (not byte for byte) on every run: reinstall only when the sources changed
SUM="$(basename "${WHEEL:-none}") $(cat "$WORK/core-moos/src/.src-sha256" "$WORK/python-moos/.src-sha256" 2>/dev/null | tr '\n' ' ')"
if [ -n "$WHEEL" ] && { ! have_pymoos || [ "$(cat "$STAMP" 2>/dev/null)" != "$SUM" ]; }; then
  if "$PY" -m pip install -q --disable-pip-version-check --no-deps --force-reinstall "$WHEEL"; then
    echo "$SUM" > "$STAMP"; say "pymoos installed from $WHEEL"
  else
    say "could not install $WHEEL into $PY (another Python version? remove $WORK/venv and run again)"
  fi
elif have_pymoos; then
  say "pymoos already installed"
fi
exit 0
