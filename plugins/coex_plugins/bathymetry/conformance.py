"""The bathymetry modality's conformance inputs (entry point ``coex.conformance: bathymetry``):
what ``coex plugins check bathymetry`` and the suite's two-node tests run it on, and what its own
conformance tests use (one source of truth)."""

from __future__ import annotations

from functools import lru_cache
from typing import Any

from coex import ModalityReceiver, ModalitySender
from coex_conformance.companions import Companion

BATHY_LEVELS = 3


@lru_cache(maxsize=1)
def _survey() -> Any:
    from .sim import Seafloor, simulate_survey

    floor = Seafloor.default(size=48.0, seed=1, relief=0.5)
    return simulate_survey(floor, beams=64, ping_rate=2.0, seed=2, outlier_fraction=0.004)


def bathy_inputs() -> list[tuple[float, Any]]:
    return list(_survey().pings(batch=20))


def bathy_converged(sender: ModalitySender, receiver: ModalityReceiver) -> bool:
    """Topside holds every subgrid version the sender's quadtree holds."""
    from . import BathymetryReceiver, BathymetrySender

    assert isinstance(sender, BathymetrySender) and isinstance(receiver, BathymetryReceiver)
    held = {level: receiver.holdings(level) for level in range(BATHY_LEVELS)}
    return all(held[lv].get((ix, iy)) == st for (lv, ix, iy), st in sender.inventory().items())


def companion() -> Companion:
    """Entry point ``coex.conformance: bathymetry``."""
    from . import BathymetryModality

    return Companion("bathymetry", BathymetryModality, bathy_inputs, bathy_converged,
                     lambda: {"levels": BATHY_LEVELS}, lambda: {"levels": BATHY_LEVELS})
