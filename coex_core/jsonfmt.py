"""JSON forms of messages, used by the golden vectors and by ``messages.jsonl`` outputs.

``to_json(m)`` gives ``{"type": "Subgrid", <field>: <value>, ...}`` with enums as their names,
bytes as lowercase hex, bit masks as integers and nested entries as objects; ``from_json``
reverses it exactly. The form is specified in ``spec/wire-format.md`` section 13.1 (normative);
this module is its reference implementation, and a test decodes every vector to it from the
document alone (``tests/test_spec_decoder.py``).
"""

from __future__ import annotations

import dataclasses
import enum
import types
import typing
from typing import Any

from . import messages as _m
from .errors import DecodeError
from .messages import Message, Opaque

__all__ = ["from_json", "to_json", "message_class"]


def _plain(value: Any) -> Any:
    if isinstance(value, enum.Enum):
        return value.name
    if isinstance(value, bytes):
        return value.hex()
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    return value


def to_json(message: Message) -> dict[str, Any]:
    """A JSON-ready dict of the message, with its type name under ``"type"``."""
    out: dict[str, Any] = {"type": type(message).__name__}
    out.update(_plain(message))
    return out


def message_class(name: str) -> type[Message]:
    cls = getattr(_m, name, None)
    if not (isinstance(cls, type) and issubclass(cls, Message) and cls is not Message):
        raise DecodeError(f"unknown message type name {name!r}")
    return cls


def _typed(tp: Any, value: Any) -> Any:
    if value is None:
        return None
    origin = typing.get_origin(tp)
    if origin is typing.Union or origin is types.UnionType:
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return _typed(args[0], value)
    if origin is tuple:
        inner = typing.get_args(tp)[0]
        return tuple(_typed(inner, v) for v in value)
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return tp[value] if isinstance(value, str) else tp(value)
    if tp is bytes:
        return bytes.fromhex(value)
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        hints = typing.get_type_hints(tp, vars(_m))
        return tp(**{f.name: _typed(hints[f.name], value[f.name]) for f in dataclasses.fields(tp)})
    if tp is float and isinstance(value, int):
        return float(value)
    return value


def from_json(obj: dict[str, Any]) -> Message:
    """The message a :func:`to_json` dict describes."""
    data = dict(obj)
    cls = message_class(data.pop("type"))
    msg = _typed(cls, data)
    assert isinstance(msg, Message)
    return msg


_ = Opaque  # Opaque round-trips like any other message: {"type": "Opaque", "type_id": .., "body": hex}
