"""Small simulated bathymetry data shared by the bathymetry tests (fixed seeds)."""

from __future__ import annotations

from functools import lru_cache

from coex_plugins.bathymetry.sim import Seafloor, Survey, simulate_survey


@lru_cache(maxsize=4)
def small_survey(size: float = 64.0, beams: int = 96, seed: int = 1) -> tuple[Seafloor, Survey]:
    """A small survey: ``size`` metres square, two cars, 30 m altitude, swath-edge outliers."""
    floor = Seafloor.default(size=size, seed=seed, relief=0.5)
    survey = simulate_survey(floor, beams=beams, ping_rate=2.0, seed=seed + 1, outlier_fraction=0.004)
    return floor, survey
