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

import pytest

pytest.register_assert_rewrite("coex_conformance.modality", "coex_conformance.transport", "coex_conformance.wire")

from .fixtures import ModalityFixtures, TransportFixtures  # noqa: E402
from .harness import LinkedPair, run_until  # noqa: E402
from .modality import ModalityTests  # noqa: E402
from .transport import TransportTests  # noqa: E402
from .wire import WireVectorTests, load_vectors, vectors_dir  # noqa: E402

__all__ = [
    "LinkedPair",
    "ModalityFixtures",
    "ModalityTests",
    "TransportFixtures",
    "TransportTests",
    "WireVectorTests",
    "load_vectors",
    "run_until",
    "vectors_dir",
]
