"""``coex demo``: a time-compressed replay of a nested survey (NUI dive 040) through the whole
CoEx stack and two simulated Micromodems. See :mod:`coex_apps.demo.dive`."""

from __future__ import annotations

from .dive import DemoConfig, DemoResult, run_demo

__all__ = ["DemoConfig", "DemoResult", "run_demo"]
