"""Shared test configuration."""

from __future__ import annotations

import os

import pytest
from hypothesis import HealthCheck, settings

# a real MOOSDB for the MOOS tests, skipped with the reason when there is none (tests/_moos.py)
from ._moos import moosdb, moosdb_path  # noqa: F401

settings.register_profile(
    "ci", max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.register_profile("dev", max_examples=60, deadline=None)
settings.load_profile("ci" if os.environ.get("CI") else "dev")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Files holding a test marked ``slow`` run first (in their order; every other file after,
    in its order). With ``--dist loadfile`` (pyproject's addopts) each file goes whole to one
    of the ``-n 3`` workers, so the long end-to-end files start at once, the short ones fill
    in after, and the two workers finish together instead of one running a slow file at the
    end. Nothing is skipped: only the order changes."""
    def path(item: pytest.Item) -> str:
        return item.nodeid.split("::", 1)[0]

    slow = {path(item) for item in items if item.get_closest_marker("slow") is not None}
    items.sort(key=lambda item: path(item) not in slow)  # stable: each file stays in one piece
