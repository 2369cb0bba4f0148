"""The table of message types: type id, dataclass, construct body, and its golden-vector cases."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import construct as cs

from ..messages import Message

__all__ = [
    "MAX_MESSAGE_BYTES",
    "MessageSpec",
    "SPECS_BY_CLASS",
    "SPECS_BY_ID",
    "THIRD_PARTY_RANGES",
    "BUILTIN_RANGE",
    "RESERVED_RANGE",
    "register",
]

#: Every message fits in one Micromodem rate-5 sub-frame (256 B) after the frame header
#: (3 B) and the optional CRC (2 B): no message ever needs to cross a frame boundary.
MAX_MESSAGE_BYTES = 251

#: Type id 0 is the end-of-messages marker; 1..63 are built-in messages.
BUILTIN_RANGE = range(1, 64)
#: 64..95 are reserved for future built-in messages: receivers reject them.
RESERVED_RANGE = range(64, 96)
#: Third-party ranges: short form 96..127 (one byte) and long form 128..32767 (two bytes).
THIRD_PARTY_RANGES = (range(96, 128), range(128, 32768))


@dataclass(frozen=True)
class MessageSpec:
    """One message type.

    ``prefixed`` bodies carry a VarInt byte length (bodies that end in raw bytes or strings);
    other bodies are self-delimiting bit structures.
    """

    type_id: int
    cls: type[Message]
    body: cs.Construct
    prefixed: bool
    domain: str
    doc: str
    #: The largest possible message: its encoded size is the type's maximum, checked at import.
    largest: Callable[[], Message]
    #: Golden-vector cases: (name, message). At least three, with boundary values.
    cases: Callable[[], Sequence[tuple[str, Message]]] = field(default=lambda: ())

    @property
    def name(self) -> str:
        return self.cls.__name__


SPECS_BY_ID: dict[int, MessageSpec] = {}
SPECS_BY_CLASS: dict[type[Any], MessageSpec] = {}


def register(spec: MessageSpec) -> MessageSpec:
    if spec.type_id not in BUILTIN_RANGE:
        raise ValueError(f"built-in type id {spec.type_id} outside {BUILTIN_RANGE}")
    if spec.type_id in SPECS_BY_ID or spec.cls in SPECS_BY_CLASS:
        raise ValueError(f"type id {spec.type_id} or class {spec.name} registered twice")
    SPECS_BY_ID[spec.type_id] = spec
    SPECS_BY_CLASS[spec.cls] = spec
    return spec
