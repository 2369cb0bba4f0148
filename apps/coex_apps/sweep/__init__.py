"""``coex sweep``: many simulated dives (``coex demo``) on Dask, a local cluster by default or
an existing scheduler, with results as data (``dives.csv``, ``summary.json``) written as dives
finish. See docs/demo.md ("Sweeps on Dask")."""

from __future__ import annotations

from .conditions import (
           DEVELOPMENT_SEEDS,
           Condition,
           Overrides,
           fresh_seeds,
           grid,
           is_development_seed,
)
from .dive import DiveOutcome, DiveSpec, run_dive
from .results import DiveTable, summarise, wilson_interval
from .run import SweepResult, run_sweep

__all__ = ["DEVELOPMENT_SEEDS", "Condition", "DiveOutcome", "DiveSpec", "DiveTable", "Overrides",
           "SweepResult", "fresh_seeds", "grid", "is_development_seed", "run_dive", "run_sweep",
           "summarise", "wilson_interval"]
