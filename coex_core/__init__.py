"""CoEx core: the wire format, the sans-I/O protocol logic and the plugin contracts.

The core never sleeps, never reads a clock and never opens a socket: time enters as ``now``
and bytes leave as return values. Transports and runners (outside this package) do the I/O.
"""

from __future__ import annotations

from . import errors, messages, wire
from .errors import (
    CoexError,
    ConfigError,
    DecodeError,
    EncodeError,
    PluginLoadError,
    PluginNotFound,
    RequestRejected,
    TransportError,
)
from .messages import Frame, FrameHeader, Message
from .modality import Modality, ModalityReceiver, ModalitySender, Product
from .transport import Transport

__version__ = "0.2.0"

__all__ = [
    "CoexError",
    "ConfigError",
    "DecodeError",
    "EncodeError",
    "Frame",
    "FrameHeader",
    "Message",
    "Modality",
    "ModalityReceiver",
    "ModalitySender",
    "PluginLoadError",
    "PluginNotFound",
    "Product",
    "RequestRejected",
    "Transport",
    "TransportError",
    "__version__",
    "errors",
    "messages",
    "wire",
]
