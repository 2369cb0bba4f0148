"""The exception hierarchy of CoEx.

Every exception CoEx raises on purpose derives from :class:`CoexError`. Several also derive from
the built-in exception that best describes them, so callers that do not know CoEx still catch them
(``except ValueError`` catches a :class:`DecodeError`).
"""

from __future__ import annotations

from typing import Any

__all__ = [
    "CoexError",
    "ConfigError",
    "DecodeError",
    "EncodeError",
    "PluginLoadError",
    "PluginNotFound",
    "TransportError",
    "TransportTimeout",
    "LinkDown",
    "FrameTooLarge",
    "RequestRejected",
    "AuthenticationError",
]


class CoexError(Exception):
    """Base class of every error CoEx raises on purpose."""


class DecodeError(CoexError, ValueError):
    """Received bytes are not a valid CoEx message or frame.

    This is the *only* exception that :func:`coex_core.wire.decode` and
    :func:`coex_core.wire.unpack` raise, whatever bytes they are given: the peer (or the channel)
    was at fault, not the caller.

    ``reason`` is the error word of ``spec/wire-format.md`` section 13 naming the rule the input
    breaks (``"truncated"``, ``"canonical"``, ``"empty region"`` ...): the wire codec always
    gives one for any bytes it is given; other decoders (a plugin's body codec) may leave it ``None``.
    """

    def __init__(self, *args: object, reason: str | None = None) -> None:
        super().__init__(*args)
        self.reason = reason


class EncodeError(CoexError, ValueError):
    """A message cannot be encoded: a value out of its specified range, or too large a body."""


class ConfigError(CoexError, ValueError):
    """A configuration value (URI, option, schedule, queue setting) is invalid.

    ``problems``: each problem with the key it names, when a validator collected several
    (:class:`coex_core.config.Problems`); empty otherwise."""

    problems: tuple[Any, ...] = ()


class PluginNotFound(CoexError, LookupError):
    """No modality or transport is registered under that name."""


class PluginLoadError(CoexError, ImportError):
    """A registered plugin could not be imported, usually because an optional extra is missing."""


class TransportError(CoexError, OSError):
    """A transport failed to send or receive."""


class TransportTimeout(TransportError, TimeoutError):
    """A transport operation timed out."""


class LinkDown(TransportError):
    """A transport's device or stream is gone for now and being reopened: what was offered is not
    sent (the protocol's acks recover it once the link is back). The run loop counts these
    quietly instead of logging each one."""


class FrameTooLarge(TransportError, EncodeError):
    """A frame larger than the transport's MTU was offered for sending."""


class RequestRejected(CoexError, ValueError):
    """A request (ROI, goal, window, command) is out of bounds and was refused."""


class AuthenticationError(CoexError, PermissionError):
    """A command failed authentication (bad tag, replayed counter, or missing trailer)."""
