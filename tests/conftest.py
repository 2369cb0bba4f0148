"""Shared test configuration."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest
from hypothesis import HealthCheck, settings

# a real MOOSDB for the MOOS tests, skipped with the reason when there is none (tests/_moos.py)
from ._dives import codestreams_shared
from ._moos import moosdb, moosdb_path  # noqa: F401

settings.register_profile(
    "ci", max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.register_profile("dev", max_examples=60, deadline=None)
settings.load_profile("ci" if os.environ.get("CI") else "dev")


#: the files that take longest, longest first (CPU seconds of a run at 2026-12-07's fourth pass,
#: docs/testing.md): they start first, on every worker, and the short files fill in behind them
LONGEST = ("tests/test_demo.py", "tests/test_demo_eye.py", "tests/test_demo_fleet.py", "tests/test_console_browser.py",
           "tests/test_soak_faults.py", "tests/test_imagery_packets.py", "tests/test_navigation_demo.py")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The longest files (:data:`LONGEST`, in that order) run first, then the other files
    holding a test marked ``slow`` (in their order), then every other file (in its order).
    With ``--dist loadfile --no-loadscope-reorder`` (pyproject's addopts) each file goes whole
    to one of the ``-n 3`` workers in this order, so the long end-to-end files start at once,
    the short ones fill in after, and the workers finish together instead of one running a
    long file at the end. Nothing is skipped: only the order changes."""
    def path(item: pytest.Item) -> str:
        return item.nodeid.split("::", 1)[0]

    slow = {path(item) for item in items if item.get_closest_marker("slow") is not None}

    def rank(item: pytest.Item) -> tuple[int, int]:
        p = path(item)
        return (0, LONGEST.index(p)) if p in LONGEST else (1 if p in slow else 2, 0)

    items.sort(key=rank)  # stable: each file stays in one piece


@pytest.fixture
def shared_codestreams(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, int]]:
    """Image codings shared by the run's dives (``tests/_dives.py`` ``codestreams_shared``) while
    the test runs: a test that runs a dive (or reads a ``shared_dive``) marks itself
    ``@pytest.mark.usefixtures("shared_codestreams")``; a module fixture running a dive runs it
    inside ``codestreams_shared`` itself."""
    with codestreams_shared(tmp_path_factory) as counts:
        yield counts
