"""Deprecated: the run loops moved to the public :mod:`coex_transports.runner` (and the facade
``import coex``). This alias stays for one release."""

from __future__ import annotations

import warnings

from .runner import Clock, RealClock, Runner, SimNetwork, SimulatedClock, next_wakeup

warnings.warn("coex_transports._runner is deprecated: import Runner and SimNetwork from coex",
              DeprecationWarning, stacklevel=2)

__all__ = ["Clock", "RealClock", "Runner", "SimNetwork", "SimulatedClock", "next_wakeup"]
