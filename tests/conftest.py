"""Shared test configuration."""

from __future__ import annotations

import os

from hypothesis import HealthCheck, settings

# a real MOOSDB for the MOOS tests, skipped with the reason when there is none (tests/_moos.py)
from ._moos import moosdb, moosdb_path  # noqa: F401

settings.register_profile(
    "ci", max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.register_profile("dev", max_examples=60, deadline=None)
settings.load_profile("ci" if os.environ.get("CI") else "dev")
