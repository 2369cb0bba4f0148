"""CoEx over MOOS: the ``moos`` transport and a native client of the MOOS wire protocol.

* :class:`MoosTransport` (URI ``moos://HOST:PORT?name=pCoex&tx=COEX_TX&rx=COEX_RX``) carries
  each CoEx frame as one binary MOOS variable, for vehicles whose modem is run by a MOOS
  application (``docs/moos.md``).
* :class:`MoosClient`: a MOOS client in pure Python (no pymoos, no libMOOS), which the MOOS
  inputs and autonomy build on: ``register``, ``notify``, ``fetch``, reconnects by itself.
"""

from __future__ import annotations

from .client import (
    MAX_TIME_WARP,
    MoosClient,
    MoosMessage,
    MoosProtocolError,
    RawMessage,
    decode_packet,
    encode_packet,
)
from .transport import DEFAULT_PORT, MoosConfig, MoosTransport, parse_moos_uri

__all__ = [
    "DEFAULT_PORT",
    "MAX_TIME_WARP",
    "MoosClient",
    "MoosConfig",
    "MoosMessage",
    "MoosProtocolError",
    "MoosTransport",
    "RawMessage",
    "decode_packet",
    "encode_packet",
    "parse_moos_uri",
]
