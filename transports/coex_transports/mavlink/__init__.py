"""CoEx frames over MAVLink 2: the ``TUNNEL`` binding (``spec/bindings/mavlink.md``).

* :class:`MavlinkTransport` - the ``mavlink:`` transport (UDP in/out, TCP, serial).
* :class:`TunnelCodec` - the sans-I/O codec under it (frames <-> MAVLink packets, ``now`` driven).
* :func:`split_frame`, :func:`parse_fragment`, :class:`Reassembler` - the fragmentation layer.

Only ``pymavlink.dialects.v20.common`` is imported, never ``pymavlink.mavutil`` (importing it
changes process-wide state).
"""

from __future__ import annotations

from ._fragment import (
    CHUNK_BYTES,
    FRAGMENT_HEADER_BYTES,
    FRAGMENT_VERSION,
    MAX_FRAGMENTS,
    MAX_FRAME_BYTES,
    TUNNEL_PAYLOAD_BYTES,
    Fragment,
    Reassembler,
    fragments_needed,
    parse_fragment,
    split_frame,
)
from .codec import (
    DEFAULT_COMPONENT_ID,
    DEFAULT_MTU,
    DEFAULT_SYSTEM_ID,
    PAYLOAD_TYPE,
    TunnelCodec,
    parse_tunnel,
)
from .transport import MavlinkEndpoint, MavlinkTransport, parse_mavlink_uri

__all__ = [
    "CHUNK_BYTES",
    "DEFAULT_COMPONENT_ID",
    "DEFAULT_MTU",
    "DEFAULT_SYSTEM_ID",
    "FRAGMENT_HEADER_BYTES",
    "FRAGMENT_VERSION",
    "MAX_FRAGMENTS",
    "MAX_FRAME_BYTES",
    "PAYLOAD_TYPE",
    "TUNNEL_PAYLOAD_BYTES",
    "Fragment",
    "MavlinkEndpoint",
    "MavlinkTransport",
    "Reassembler",
    "TunnelCodec",
    "fragments_needed",
    "parse_fragment",
    "parse_mavlink_uri",
    "parse_tunnel",
    "split_frame",
]
