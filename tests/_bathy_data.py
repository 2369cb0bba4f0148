"""Small simulated bathymetry data shared by the bathymetry tests (fixed seeds)."""

from __future__ import annotations

from functools import lru_cache
from typing import Any

from coex_plugins.bathymetry.sim import Seafloor, Survey, simulate_survey


@lru_cache(maxsize=4)
def small_survey(size: float = 64.0, beams: int = 96, seed: int = 1) -> tuple[Seafloor, Survey]:
    """A small survey: ``size`` metres square, two cars, 30 m altitude, swath-edge outliers."""
    floor = Seafloor.default(size=size, seed=seed, relief=0.5)
    survey = simulate_survey(floor, beams=beams, ping_rate=2.0, seed=seed + 1, outlier_fraction=0.004)
    return floor, survey


def survey_subgrids(size: float = 64.0, beams: int = 256, levels: int = 3) -> tuple[Any, list[Any]]:
    """A bathymetry sender fed :func:`small_survey`, and every Subgrid it sends (fill until idle)."""
    from coex_core.messages import Subgrid, SubgridMessage
    from coex_plugins.bathymetry import BathymetrySender

    _, survey = small_survey(size, beams)
    sender = BathymetrySender({"levels": levels})
    for t, xyz in survey.pings(batch=10):
        sender.ingest(xyz, t)
    now = float(survey.times[-1]) + 30.0
    out: list[Subgrid] = []
    for i in range(2000):
        batch = sender.fill(240, now + i)
        if not batch:
            break
        out.extend(m for m in batch if isinstance(m, SubgridMessage))
    return sender, out

