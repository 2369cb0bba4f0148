"""What an autonomy output is: the bridge from accepted survey commands to the vehicle's own
autonomy (a MAVLink autopilot's mission, an LCM planner, the MOOS-IvP helm, or just a log).

An output is registered under the entry-point group ``coex.autonomy`` (a configuration file's
``[autonomy] type = "..."``). The daemon gives it each survey the vehicle accepted as a
:class:`~coex_plugins.survey.plan.SurveyPlan` (:meth:`Autonomy.submit`; a new plan replaces the
one being flown), polls it for what happened (:meth:`Autonomy.poll`:
:class:`~coex_plugins.survey.plan.SurveyReport` items: started, the waypoint it heads for,
completed, refused, stopped), and closes it on shutdown. Never blocking: an output that runs a
protocol (the MAVLink mission upload) advances it in :meth:`poll`.
"""

from __future__ import annotations

import abc
from collections.abc import Mapping
from typing import Any, ClassVar

from ..inputs.base import Adapter, adapter_problems

__all__ = ["Autonomy", "check_autonomy_options"]


class Autonomy(Adapter, abc.ABC):
    """An autonomy output (see the module docstring)."""

    kind: ClassVar[str] = "autonomy"

    @abc.abstractmethod
    def submit(self, plan: Any, now: float) -> None:
        """Fly ``plan`` (a SurveyPlan) instead of whatever is flown now."""

    @abc.abstractmethod
    def poll(self, now: float) -> list[Any]:
        """SurveyReports since the last call (never blocks)."""


def check_autonomy_options(cls: type[Autonomy], options: Mapping[str, Any]) -> list[str]:
    """Unknown and missing keys, then the output's own :meth:`Autonomy.check`."""
    return adapter_problems(cls, options)
