"""CoEx's public API: what integrators and the authors of plugins, inputs and autonomy outputs import.

::

    import coex

    node = coex.Node(coex.ChannelManager(1, [coex.LinkConfig(0, coex.Schedule.simple([1, 2], 20, 2))]))
    runner = coex.Runner(node, {0: coex.open_transport("micromodem:///dev/ttyUSB0?rate=5")})

Everything here is stable for a release; the modules behind it (``coex_core.*``,
``coex_transports.*``, ``coex_runtime.*``) may move. Layers: this facade re-exports the core
(wire format, messages, node, channel manager, the bases of modalities, inputs, autonomy outputs
and detectors, storage, state registration, stamps, subgrid coding, errors) and the runtime (run
loops, store, the transport that comes back); it imports no plugin (load those by name with
:func:`load_modality`) and no application. The built-in plugins import only this package.

Modules of the facade, each a file of its own with an explicit ``__all__`` (so that a plugin
author's type checker finds ``from coex.messages import Opaque``): :mod:`coex.messages`,
:mod:`coex.wire`, :mod:`coex.errors`, :mod:`coex.tracker`, :mod:`coex.registry` and
:mod:`coex.state` re-export the core's modules of those names (the same objects),
:mod:`coex.routing` what a node routes to a modality (for tools like the conformance kit);
:mod:`coex.lcm`, :mod:`coex.moos` and :mod:`coex.ros` give what an input or autonomy output for
those middlewares needs from their transports (imported on demand: ``import coex`` loads none).
"""

from __future__ import annotations

from coex_core import __version__
from coex_core.acoustic import AcousticChannel, GilbertElliott
from coex_core.adapters import (
    FEEDS,
    Adapter,
    Autonomy,
    Image,
    Input,
    InputContext,
    Item,
    Nav,
    Points,
    PositionAid,
    Samples,
    SurveyPlan,
    SurveyReport,
    adapter_check,
    adapter_problems,
    check_autonomy_options,
    check_options,
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
from coex_core.config import Problem, Problems, merged_config
from coex_core.detect import Detector, Finding, ImageFrame, ImageFrames, MapView
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
from coex_core.jsonfmt import from_json, to_json
from coex_core.loopback import Bernoulli, LoopbackLink, LossModel, RoundTrip, WireEvent
from coex_core.messages import Frame, FrameHeader, Message
from coex_core.modality import Modality, ModalityReceiver, ModalitySender, Product
from coex_core.node import Node
from coex_core.predicted import (
    ContextMismatch,
    SubgridParent,
    decode_predicted,
    decode_predicted_units,
    encode_predicted,
    parent_from_rows,
    parent_from_values,
    region_digest,
    subgrid_units,
    units_rows,
)
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
from coex_core.storage import MemoryStorage, Storage
from coex_core.subgrid import decode_subgrid, decode_subgrid_units, encode_subgrid, subgrid_bits
from coex_core.timefmt import STAMP_MODULUS, to_stamp, unwrap
from coex_core.transport import Transport, UriInfo, parse_query
from coex_runtime.peers import SILENT_CYCLES, PeerSilence, PeerWatch
from coex_runtime.runner import RealClock, Runner, SimNetwork, SimulatedClock
from coex_runtime.store import NodeStore, StoreError
from coex_transports.recovery import Health, ResilientTransport

from . import errors, messages, registry, routing, state, tracker, wire

__all__ = [
    "Acked",
    "AcousticChannel",
    "Adapter",
    "AuthenticationError",
    "Autonomy",
    "BadFrame",
    "Bernoulli",
    "CONTROL_STREAM",
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
    "FEEDS",
    "Finding",
    "Frame",
    "FrameHeader",
    "FrameTooLarge",
    "GilbertElliott",
    "Health",
    "Image",
    "ImageFrame",
    "ImageFrames",
    "Input",
    "InputContext",
    "Item",
    "LinkChanged",
    "LinkConfig",
    "LinkDown",
    "LinkStats",
    "LoopbackLink",
    "LossModel",
    "MapView",
    "MemoryStorage",
    "Message",
    "Modality",
    "ModalityReceiver",
    "ModalitySender",
    "Nav",
    "Node",
    "NodeStore",
    "PeerSilence",
    "PeerWatch",
    "PluginLoadError",
    "PluginNotFound",
    "Points",
    "Problem",
    "Problems",
    "Product",
    "ProductUpdated",
    "RealClock",
    "Received",
    "Rejected",
    "RequestRejected",
    "RequestTracker",
    "ResilientTransport",
    "RoundTrip",
    "Runner",
    "SILENT_CYCLES",
    "STAMP_MODULUS",
    "Samples",
    "Schedule",
    "SimNetwork",
    "SimulatedClock",
    "StateError",
    "Storage",
    "StoreError",
    "StreamConfig",
    "PositionAid",
    "SurveyPlan",
    "SurveyReport",
    "TdmaSlot",
    "Transmission",
    "Transport",
    "TransportError",
    "TransportTimeout",
    "UriInfo",
    "WireEvent",
    "adapter_check",
    "adapter_problems",
    "available",
    "check_autonomy_options",
    "check_options",
    "check_transport_uri",
    "ContextMismatch",
    "SubgridParent",
    "decode_predicted",
    "decode_predicted_units",
    "decode_subgrid",
    "decode_subgrid_units",
    "encode_predicted",
    "encode_subgrid",
    "parent_from_rows",
    "parent_from_values",
    "region_digest",
    "subgrid_units",
    "units_rows",
    "errors",
    "from_json",
    "load_detector",
    "load_modality",
    "load_transport",
    "merged_config",
    "messages",
    "open_transport",
    "parse_query",
    "persistent",
    "registry",
    "routing",
    "state",
    "subgrid_bits",
    "to_json",
    "to_stamp",
    "tracker",
    "unwrap",
    "wire",
    "__version__",
]
