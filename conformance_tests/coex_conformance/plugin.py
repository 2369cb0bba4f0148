"""The pytest plugin (entry point ``pytest11: coex``): command-line options for the suite.

Kept cheap to import because pytest loads it in every run; disable with ``-p no:coex``.
"""

from __future__ import annotations

from typing import Any


def pytest_addoption(parser: Any) -> None:
    group = parser.getgroup("coex", "CoEx conformance suite")
    group.addoption("--coex-seed", type=int, default=None,
                    help="override the seed of the lossy links in the conformance suite")


def pytest_configure(config: Any) -> None:
    config.addinivalue_line("markers", "coex_conformance: a CoEx conformance test")
