# CoEx developer entry points. `make demo` and `make test` work on a fresh machine: they create
# .venv/, install every package editable with all extras and the dev tools, and install the Debian
# packages that are missing (libopenjp2-7 for glymur, chromium for the browser tests, ROS 1 for
# the ros adapters), then let the venv import Debian's rospy (`make ros`, scripts/ros.sh).

PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.coex-installed
PYTEST_ARGS ?=
DEMO_ARGS ?=

# Python writes its compiled modules (.pyc) where it may: an environment that sets
# PYTHONDONTWRITEBYTECODE (some CI images and sandboxes do) makes every process compile every
# module it imports again, and the test suite starts about 160 Python processes (daemons, CLIs,
# workers), each paying 1-2 s of CPU for it (uv installs without .pyc). The .pyc files go to
# __pycache__/ (git-ignored) and the venv.
unexport PYTHONDONTWRITEBYTECODE

.PHONY: install demo test test-fast lint typecheck pytest moos ros bench clean

install: $(STAMP)

$(STAMP): pyproject.toml examples/coex-sample-plugin/pyproject.toml scripts/system-deps.sh scripts/ros.sh scripts/venv-install.sh
	@bash scripts/system-deps.sh
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@bash scripts/venv-install.sh $(VENV) -e ".[all,dev]" -e examples/coex-sample-plugin
	@bash scripts/ros.sh $(PY)
	@touch $(STAMP)
	@echo "CoEx installed in $(VENV)/ (activate with: . $(VENV)/bin/activate)"

demo: install
	$(VENV)/bin/coex demo $(DEMO_ARGS)

lint: install
	$(VENV)/bin/ruff check .

# strict mypy over every package (pyproject's [tool.mypy] files), then the sample plugin checked
# from its own directory as its author would run it
typecheck: install
	@bash scripts/typecheck.sh $(VENV)

# a real MOOSDB and pymoos for the MOOS tests, built from ../shared/vendor/moos when there is no
# MOOSDB on PATH; never fails (the tests needing them are skipped with the reason)
moos: install
	@bash scripts/moos.sh $(PY)

# the venv imports Debian's rospy (ROS modules only, after site-packages); never fails (the ROS
# tests are skipped with the reason)
ros: install
	@bash scripts/ros.sh $(PY)

# four workers on CI's two cores: the suite's tests wait on real servers, browsers, ROS and
# daemons about a quarter of the time, and the extra workers run while they wait (docs/testing.md)
pytest: install moos ros
	$(VENV)/bin/pytest -n 4 $(PYTEST_ARGS)

# everything: CI's target (.ci/run). pyproject's addopts give each test file whole to one worker
# (--dist loadfile) and tests/conftest.py starts the files with slow end-to-end tests first.
# `make typecheck` runs beside pytest (scripts/test.sh: about 35 s of one core, while the tests
# wait on servers); its output is printed after pytest's and either failing fails `make test`
test: lint install moos ros
	@bash scripts/test.sh $(VENV) $(PYTEST_ARGS)

# the quick loop while developing: lint, types and every test not marked slow (the whole demo
# dives, Chromium, ROS, MOOS-IvP, daemons on simulated modems run only in `make test`)
test-fast: lint typecheck install moos ros
	$(VENV)/bin/pytest -n 4 -m "not slow" $(PYTEST_ARGS)

bench: install
	@mkdir -p bench/results
	@set -e; for b in bench/*.py; do echo "== $$b"; $(PY) $$b; done

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache .hypothesis bench/results
