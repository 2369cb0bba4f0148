"""``coex topside``'s USBL: the ship's tracking system read from its own serial line or UDP port
(``[usbl]`` of the topside file; :class:`coex_plugins.navigation.UsblInput`), its fixes fused with
each vehicle's received track into topside's drift estimate
(:class:`coex_plugins.navigation.Navigation`), which the console shows and applies (issue 56,
``docs/navigation.md``)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Any

__all__ = ["UsblFeed"]

log = logging.getLogger("coex.topside")


class UsblFeed:
    """The ``[usbl]`` table of a checked topside configuration, running: :meth:`attach` gives
    each console state the navigation, :meth:`poll` (after every step of the topside's loop)
    reads the fixes. A tracking system that is not there yet, or goes away, is retried by the
    input (every 5 s) while the console runs on."""

    def __init__(self, cfg: Any, clock: Callable[[], float]) -> None:
        from coex import InputContext
        from coex_plugins.navigation import Navigation, UsblInput

        table = dict(cfg.usbl or {})
        self.apply = bool(table.pop("apply", True))
        self.input = UsblInput(table, InputContext(cfg.origin_lat, cfg.origin_lon, str(cfg.base_dir), clock))
        self.navigation = Navigation(apply=self.apply)
        for vehicle in cfg.vehicle_ids():
            self.navigation.estimator(vehicle)
        self.fixes = 0

    def attach(self, states: Sequence[Any]) -> UsblFeed:
        for state in states:
            state.navigation = self.navigation
        return self

    def open(self) -> None:
        self.input.open()

    def close(self) -> None:
        self.input.close()

    def poll(self, now: float, states: Sequence[Any]) -> int:
        """Read the fixes that arrived; the number taken."""
        taken = 0
        from coex import Nav

        for item in self.input.poll(now):
            if isinstance(item, Nav) and self.navigation.fix(item) is not None:
                taken += 1
        if taken:
            self.fixes += taken
            for state in states:
                state.navigation_changed()
        return taken
