"""The wire format's codec: ``encode`` / ``decode`` one message, ``pack`` / ``unpack`` a frame,
``encoded_size`` (what a sender's ``fill`` counts against its budget), and the format's limits.

The public face of :mod:`coex_core.wire` (``from coex.wire import ...``): a module of its own, so
that a plugin author's type checker finds it; the names are the core's (the same objects).
"""

from __future__ import annotations

from coex_core.wire import (
    CRC_BYTES,
    FRAGMENT_MAX_DATA,
    FRAGMENT_MAX_MARKS,
    FRAGMENT_NEAR_OFFSET_BITS,
    FRAME_HEADER_BYTES,
    MAX_MESSAGE_BYTES,
    MAX_SIZES,
    SUBGRID_RESOLUTIONS,
    SUBGRID_VERTICAL_RESOLUTIONS,
    THIRD_PARTY_RANGES,
    crc16,
    decode,
    encode,
    encoded_size,
    header_size,
    message_types,
    pack,
    type_id,
    unpack,
    unpack_frame,
)

__all__ = [
    "CRC_BYTES",
    "FRAGMENT_MAX_DATA",
    "FRAGMENT_MAX_MARKS",
    "FRAGMENT_NEAR_OFFSET_BITS",
    "FRAME_HEADER_BYTES",
    "MAX_MESSAGE_BYTES",
    "MAX_SIZES",
    "SUBGRID_RESOLUTIONS",
    "SUBGRID_VERTICAL_RESOLUTIONS",
    "THIRD_PARTY_RANGES",
    "crc16",
    "decode",
    "encode",
    "encoded_size",
    "header_size",
    "message_types",
    "pack",
    "type_id",
    "unpack",
    "unpack_frame",
]
