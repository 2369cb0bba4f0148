"""The CoEx conformance suite: run it against your own modality or transport plugin.

Usage (fsspec style): subclass a fixtures class and a test class, in a module pytest collects::

    from coex_conformance import ModalityFixtures, ModalityTests

    class MyFixtures(ModalityFixtures):
        @pytest.fixture
        def modality(self): return MyModality()
        ...

    class TestMyModality(ModalityTests, MyFixtures):
        pass

Test classes have no ``Test`` prefix, so pytest never collects them where they are defined.
Golden wire vectors ship with the package (:func:`vectors_dir`).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:  # what a plugin author's type checker sees; at run time each loads on first use
    from .adapters import AutonomyFixtures, AutonomyTests, InputFixtures, InputTests, survey_plan
    from .fixtures import ModalityFixtures, TransportFixtures
    from .harness import LinkedPair, run_until
    from .modality import ModalityTests
    from .transport import TransportTests
    from .wire import WireVectorTests, load_vectors, vectors_dir

pytest.register_assert_rewrite("coex_conformance.adapters", "coex_conformance.modality", "coex_conformance.transport", "coex_conformance.wire")

# Imported on first use: pytest imports this package for its plugin in every run, so it stays cheap.
_LAZY = {
    "AutonomyFixtures": "adapters",
    "AutonomyTests": "adapters",
    "InputFixtures": "adapters",
    "InputTests": "adapters",
    "survey_plan": "adapters",
    "ModalityFixtures": "fixtures",
    "TransportFixtures": "fixtures",
    "LinkedPair": "harness",
    "run_until": "harness",
    "ModalityTests": "modality",
    "TransportTests": "transport",
    "WireVectorTests": "wire",
    "load_vectors": "wire",
    "vectors_dir": "wire",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(name)

__all__ = [
    "AutonomyFixtures",
    "AutonomyTests",
    "InputFixtures",
    "InputTests",
    "LinkedPair",
    "ModalityFixtures",
    "ModalityTests",
    "TransportFixtures",
    "TransportTests",
    "WireVectorTests",
    "load_vectors",
    "run_until",
    "survey_plan",
    "vectors_dir",
]
