"""The CoEx wire format: encode/decode one message, pack/unpack one frame.

``spec/wire-format.md`` is the normative description; the construct definitions behind these
functions are the executable one, and the tests prove they agree.
"""

from __future__ import annotations

from ._wire._codec import (
    CRC_BYTES,
    FRAME_HEADER_BYTES,
    MAX_SIZES,
    crc16,
    decode,
    encode,
    encoded_size,
    header_size,
    pack,
    unpack,
    unpack_frame,
)
from ._wire._registry import MAX_MESSAGE_BYTES, SPECS_BY_CLASS, SPECS_BY_ID, THIRD_PARTY_RANGES
from ._wire.bathymetry import RESOLUTIONS as SUBGRID_RESOLUTIONS
from ._wire.bathymetry import VERTICAL_RESOLUTIONS as SUBGRID_VERTICAL_RESOLUTIONS
from ._wire.imagery import MAX_FRAGMENT_DATA as FRAGMENT_MAX_DATA
from ._wire.imagery import MAX_PACKET_MARKS as FRAGMENT_MAX_MARKS
from ._wire.imagery import NEAR_OFFSET_BITS as FRAGMENT_NEAR_OFFSET_BITS
from ._wire.imagery import SHORT_MAX_DATA as SHORT_FRAGMENT_MAX_DATA
from ._wire.imagery import SHORT_OFFSET_BITS as SHORT_FRAGMENT_OFFSET_BITS
from ._wire.imagery import SHORT_SLOT_BITS as SHORT_FRAGMENT_SLOT_BITS

__all__ = [
    "CRC_BYTES",
    "FRAGMENT_MAX_DATA",
    "FRAGMENT_MAX_MARKS",
    "FRAGMENT_NEAR_OFFSET_BITS",
    "SHORT_FRAGMENT_MAX_DATA",
    "SHORT_FRAGMENT_OFFSET_BITS",
    "SHORT_FRAGMENT_SLOT_BITS",
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


def message_types() -> dict[int, type]:
    """Every built-in message type by type id."""
    return {tid: spec.cls for tid, spec in sorted(SPECS_BY_ID.items())}


def type_id(message_cls: type) -> int:
    """The type id of a built-in message class."""
    return SPECS_BY_CLASS[message_cls].type_id
