"""``coex demo``: a time-compressed replay of a nested survey (NUI dive 040) through the whole
CoEx stack and two simulated Micromodems. See :mod:`coex_apps.demo.dive`."""

from __future__ import annotations

from .config import DEVELOPMENT_SEEDS
from .dive import DemoConfig, DemoResult, run_demo

# DEVELOPMENT_SEEDS: the seeds issue 50 developed the eye, referee and operator on; `coex sweep`
# never draws them (coex_apps.sweep.conditions.is_development_seed)
__all__ = ["DEVELOPMENT_SEEDS", "DemoConfig", "DemoResult", "run_demo"]
