"""CoEx's public API: what integrators and plugin authors import.

::

    import coex

    node = coex.Node(coex.ChannelManager(1, [coex.LinkConfig(0, coex.Schedule.simple([1, 2], 20, 2))]))
    runner = coex.Runner(node, {0: coex.open_transport("micromodem:///dev/ttyUSB0?rate=5")})

Everything here is stable for a release; the modules behind it (``coex_core.*``,
``coex_transports.*``) may move. Layers: this facade re-exports the core (wire format, node,
channel manager, plugin bases, errors) and the transport layer (run loops, store); it imports no
modality plugin (load those by name with :func:`load_modality`).
"""

from __future__ import annotations

import sys

from coex_core import __version__, errors, messages, wire
from coex_core.acoustic import AcousticChannel
from coex_core.adapters import (
    FEEDS,
    Adapter,
    Autonomy,
    Image,
    Input,
    InputContext,
    Nav,
    Points,
    Samples,
    SurveyPlan,
    SurveyReport,
)
from coex_core.channel import (
    CONTROL_STREAM,
    Acked,
    BadFrame,
    ChannelManager,
    CommandResult,
    CommandUnanswered,
    Dropped,
    Event,
    LinkChanged,
    LinkConfig,
    LinkStats,
    ProductUpdated,
    Received,
    Rejected,
    Schedule,
    StreamConfig,
    TdmaSlot,
    Transmission,
)
from coex_core.config import merged_config
from coex_core.detect import Detector, Finding
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
from coex_core.messages import Frame, FrameHeader, Message
from coex_core.modality import Modality, ModalityReceiver, ModalitySender, Product
from coex_core.node import Node
from coex_core.registry import (
    available,
    check_transport_uri,
    load_detector,
    load_modality,
    load_transport,
    open_transport,
)
from coex_core.requests import RequestTracker
from coex_core.state import StateError, persistent
from coex_core.transport import Transport, UriInfo, parse_query
from coex_runtime.runner import RealClock, Runner, SimNetwork, SimulatedClock
from coex_runtime.store import NodeStore
from coex_transports.recovery import Health, ResilientTransport

# ``from coex.messages import Opaque``, ``coex.wire.pack``: the core's message, wire and error
# modules under the facade's name (the same module objects)
sys.modules.setdefault(__name__ + ".messages", messages)
sys.modules.setdefault(__name__ + ".wire", wire)
sys.modules.setdefault(__name__ + ".errors", errors)

__all__ = [
    "CONTROL_STREAM",
    "FEEDS",
    "AcousticChannel",
    "Acked",
    "Adapter",
    "Autonomy",
    "AuthenticationError",
    "BadFrame",
    "ChannelManager",
    "CoexError",
    "CommandResult",
    "CommandUnanswered",
    "ConfigError",
    "DecodeError",
    "Detector",
    "Dropped",
    "EncodeError",
    "Event",
    "Finding",
    "Frame",
    "FrameHeader",
    "FrameTooLarge",
    "Health",
    "Image",
    "Input",
    "InputContext",
    "LinkChanged",
    "LinkConfig",
    "LinkDown",
    "LinkStats",
    "Message",
    "Modality",
    "Nav",
    "ModalityReceiver",
    "ModalitySender",
    "Node",
    "NodeStore",
    "PluginLoadError",
    "Points",
    "PluginNotFound",
    "Product",
    "ProductUpdated",
    "RealClock",
    "Received",
    "Rejected",
    "RequestRejected",
    "RequestTracker",
    "ResilientTransport",
    "Runner",
    "Schedule",
    "Samples",
    "SimNetwork",
    "SimulatedClock",
    "StateError",
    "StreamConfig",
    "SurveyPlan",
    "SurveyReport",
    "TdmaSlot",
    "Transmission",
    "Transport",
    "TransportError",
    "TransportTimeout",
    "UriInfo",
    "__version__",
    "available",
    "check_transport_uri",
    "errors",
    "load_detector",
    "load_modality",
    "load_transport",
    "merged_config",
    "messages",
    "open_transport",
    "parse_query",
    "persistent",
    "wire",
]
