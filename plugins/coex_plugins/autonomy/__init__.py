"""Autonomy outputs: the bridge from an accepted survey to the vehicle's own autonomy.

Built-in outputs (entry-point group ``coex.autonomy``; ``docs/autonomy.md``):

* ``log`` (the default): logs each plan in words, optionally one JSON line per plan to a file;
* ``sim``: a simulated vehicle that flies the plan at a constant speed (examples and tests);
* ``mavlink``: uploads the plan as a MAVLink mission (ArduSub, PX4) with pymavlink and starts it;
* ``lcm``: publishes a ``coex.survey_request_t`` for an LCM planner and reads its
  ``coex.survey_state_t`` answers;
* ``moos``: updates the MOOS-IvP helm's ``BHV_Waypoint`` and reads its ``WPT_INDEX`` /
  ``WPT_STAT`` (``docs/moos.md``);
* ``ros``: publishes a ``nav_msgs/Path`` for a ROS 1 planner and reads its answers on a
  ``std_msgs/String`` progress topic.

:func:`open_autonomy` builds one from a configuration table (``[autonomy] type = "..."``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from coex import Autonomy, check_autonomy_options

__all__ = ["DEFAULT", "GROUP", "Autonomy", "check_autonomy_options", "load_autonomy", "open_autonomy"]

#: the entry-point group of autonomy outputs
GROUP = "coex.autonomy"
#: the output a vehicle configuration without ``[autonomy]`` (or without its ``type``) gets
DEFAULT = "log"


def load_autonomy(name: str) -> type[Autonomy]:
    """The :class:`Autonomy` subclass registered as ``name`` (PluginNotFound, PluginLoadError)."""
    from coex import registry

    cls = registry.load(GROUP, name)
    if not (isinstance(cls, type) and issubclass(cls, Autonomy)):
        from coex import PluginLoadError

        raise PluginLoadError(f"{GROUP} plugin {name!r} is not an Autonomy subclass")
    return cls


def open_autonomy(table: Mapping[str, Any] | None, context: Any) -> Autonomy:
    """Build (not open) the output a configuration table names: ``type`` picks it (default
    :data:`DEFAULT`), the other keys are its options (ConfigError names a bad one)."""
    table = dict(table or {})
    name = str(table.pop("type", DEFAULT))
    return load_autonomy(name)(table, context)
