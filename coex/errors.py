"""CoEx's errors: every one a :class:`CoexError`, the base to catch.

The public face of :mod:`coex_core.errors` (``from coex.errors import ...``): a module of its own, so
that a plugin author's type checker finds it; the names are the core's (the same objects).
"""

from __future__ import annotations

from coex_core.errors import (
    AuthenticationError,
    CoexError,
    ConfigError,
    DecodeError,
    EncodeError,
    FrameTooLarge,
    LinkDown,
    PluginLoadError,
    PluginNotFound,
    RequestRejected,
    TransportError,
    TransportTimeout,
)

__all__ = [
    "AuthenticationError",
    "CoexError",
    "ConfigError",
    "DecodeError",
    "EncodeError",
    "FrameTooLarge",
    "LinkDown",
    "PluginLoadError",
    "PluginNotFound",
    "RequestRejected",
    "TransportError",
    "TransportTimeout",
]
