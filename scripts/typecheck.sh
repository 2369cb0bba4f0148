#!/usr/bin/env bash
# `make typecheck`: strict mypy over every package (pyproject's [tool.mypy] files), then the
# sample plugin checked from its own directory as its author would run it. $1: the venv.
set -euo pipefail
venv=$(cd "$1" && pwd)
"$venv/bin/mypy"
cd examples/coex-sample-plugin && "$venv/bin/mypy" coex_sample_plugin tests
