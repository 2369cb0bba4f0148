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

from coex_core.errors import ConfigError

from ..inputs.base import InputContext

__all__ = ["Autonomy", "check_autonomy_options"]


class Autonomy(abc.ABC):
    name: ClassVar[str] = ""
    #: name -> (default, description); ``...`` = required
    options: ClassVar[Mapping[str, tuple[Any, str]]] = {}

    def __init__(self, options: Mapping[str, Any], context: InputContext) -> None:
        problems = check_autonomy_options(type(self), options)
        if problems:
            raise ConfigError("; ".join(problems))
        self.config: dict[str, Any] = {k: v[0] for k, v in self.options.items() if v[0] is not ...}
        self.config.update(options)
        self.context = context

    @classmethod
    def check(cls, options: Mapping[str, Any]) -> list[str]:
        """Problems beyond unknown and missing keys, one sentence each naming the key."""
        return []

    def open(self) -> None:  # noqa: B027
        """Connect."""

    @abc.abstractmethod
    def submit(self, plan: Any, now: float) -> None:
        """Fly ``plan`` (a SurveyPlan) instead of whatever is flown now."""

    @abc.abstractmethod
    def poll(self, now: float) -> list[Any]:
        """SurveyReports since the last call (never blocks)."""

    def close(self) -> None:  # noqa: B027
        """Disconnect."""


def check_autonomy_options(cls: type[Autonomy], options: Mapping[str, Any]) -> list[str]:
    problems = [f"unknown option {k!r} for autonomy {cls.name!r} (known: {', '.join(sorted(cls.options))})"
                for k in options if k not in cls.options and k != "type"]
    problems += [f"autonomy {cls.name!r} needs option {k!r} ({desc})"
                 for k, (default, desc) in cls.options.items() if default is ... and k not in options]
    if not problems:
        problems += cls.check(options)
    return problems
