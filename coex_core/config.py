"""The one configuration convention of CoEx plugins.

A sender's or receiver's configuration is a plain mapping (from TOML, JSON or code). Every
plugin declares its options with their defaults and merges with :func:`merged_config`: an
unknown key (a misspelling) is a :class:`~coex_core.errors.ConfigError` that names the key and
lists the known ones, never silently ignored.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from .errors import ConfigError

__all__ = ["merged_config"]


def merged_config(config: Mapping[str, Any] | None, defaults: Mapping[str, Any],
                  what: str = "") -> dict[str, Any]:
    """``defaults`` updated with ``config``; :class:`ConfigError` for a key not in ``defaults``
    (``what`` names the component in the message, e.g. ``"imagery sender"``)."""
    if config is not None and not isinstance(config, Mapping):
        raise ConfigError(f"{what or 'the'} configuration must be a mapping, "
                          f"got {type(config).__name__}")
    cfg = dict(defaults)
    for key, value in (config or {}).items():
        if key not in defaults:
            raise ConfigError(f"unknown {what + ' ' if what else ''}option {key!r} "
                              f"(known: {', '.join(sorted(map(str, defaults)))})")
        cfg[key] = value
    return cfg
