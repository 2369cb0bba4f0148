"""Declared routing: which modality a received message belongs to, by wire type id.

A modality declares the messages it owns (:class:`~coex_core.modality.Modality`):

* ``messages`` / ``requests``: built-in message types (each has a type id, spec section 5);
* ``message_ids`` / ``request_ids``: third-party type ids (96..32767), carried as
  :class:`~coex_core.messages.Opaque`;
* ``routine``: the requests (types or ids) that do not expedite its stream (acks of data).

A :class:`~coex_core.node.Node` routes each received message by its type id to the one modality
that claimed it, and refuses, when a modality is added, a second modality that claims an id
already claimed (a :class:`~coex_core.errors.ConfigError` naming both).

A plugin written before ids were declared lists ``Opaque`` in ``messages`` (or ``requests``)
and declares no ids: it receives the third-party messages that no modality claims (one such
plugin per node and direction).

A deployment may **remap** a modality's third-party ids on the wire (two plugins that chose
the same id, or an id the register assigns differently): ``Node.add_sender(..., ids={200: 4200})``
and the same on the other node. The plugin keeps using its own ids; the node translates
(:mod:`coex_core.remap`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from ._wire._registry import SPECS_BY_CLASS, THIRD_PARTY_RANGES
from .errors import ConfigError
from .messages import Message, Opaque

#: a Modality subclass (this module is below coex_core.modality, which uses it)
Modality = Any

__all__ = ["Routes", "check_remap", "declared_ids", "routine_ids", "third_party", "type_id"]

_KINDS = {"messages": ("messages", "message_ids"), "requests": ("requests", "request_ids")}


def third_party(tid: int) -> bool:
    return any(tid in r for r in THIRD_PARTY_RANGES)


def type_id(m: Message) -> int | None:
    """The wire type id of ``m`` (None: not a wire message)."""
    if isinstance(m, Opaque):
        return int(m.type_id)
    spec = SPECS_BY_CLASS.get(type(m))
    return None if spec is None else spec.type_id


def _own_ids(cls: type[Modality], raw: Iterable[Any], what: str) -> tuple[int, ...]:
    try:
        ids = tuple(int(i) for i in raw or ())
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"modality {_name(cls)}: {what}_ids must be type ids (integers): {exc}") from exc
    for i in ids:
        if not third_party(i):
            raise ConfigError(f"modality {_name(cls)}: {what} id {i} is not a third-party type id "
                              "(96..32767, spec section 5)")
    return ids


def declared_ids(cls: type[Modality], kind: str) -> frozenset[int]:
    """Wire type ids a modality owns: ``kind`` ``"messages"`` (its sender emits them) or
    ``"requests"`` (its receiver emits them): the built-in types of ``messages`` / ``requests``
    and the third-party ids of ``message_ids`` / ``request_ids`` (declared on
    :class:`~coex_core.modality.Modality`)."""
    types_attr, ids_attr = _KINDS[kind]
    types = cls.messages if kind == "messages" else cls.requests
    ids = {SPECS_BY_CLASS[t].type_id for t in types if t in SPECS_BY_CLASS}
    if Opaque in tuple(types):
        raise ConfigError(f"modality {_name(cls)}: Opaque in {types_attr} is not a declaration: list the "
                          f"third-party type ids in {ids_attr} (the catch-all of 0.1 is gone)")
    ids.update(_own_ids(cls, cls.message_ids if kind == "messages" else cls.request_ids, kind[:-1]))
    return frozenset(ids)


def routine_ids(cls: type[Modality]) -> frozenset[int]:
    """Requests of a modality that are routine (``routine``: types or third-party ids)."""
    out: set[int] = set()
    for r in tuple(cls.routine or ()):
        if isinstance(r, type):
            spec = SPECS_BY_CLASS.get(r)
            if spec is None:
                raise ConfigError(f"modality {_name(cls)}: routine type {r.__name__} is not a wire message")
            out.add(spec.type_id)
        else:
            out.add(int(r))
    return frozenset(out)


def _name(cls: type[Any]) -> str:
    return str(getattr(cls, "name", cls.__name__))


def check_remap(cls: type[Modality], ids: Mapping[int, int] | None) -> dict[int, int]:
    """A deployment's remap of ``cls``'s third-party ids (own id -> wire id), checked."""
    if not ids:
        return {}
    own = set(_own_ids(cls, cls.message_ids, "message")) | set(_own_ids(cls, cls.request_ids, "request"))
    out: dict[int, int] = {}
    for a, b in dict(ids).items():
        try:
            a, b = int(a), int(b)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"modality {_name(cls)}: id remap {a!r} -> {b!r} is not two integers") from exc
        if a not in own:
            raise ConfigError(f"modality {_name(cls)} declares no third-party id {a} to remap "
                              f"(it declares {sorted(own) or 'none'})")
        if not third_party(b):
            raise ConfigError(f"modality {_name(cls)}: remapped id {b} is not a third-party type id (96..32767)")
        out[a] = b
    if len(set(out.values())) != len(out):
        raise ConfigError(f"modality {_name(cls)}: two ids remapped to one wire id: {out}")
    return out


@dataclass
class Routes:
    """One node's routing table for one direction: wire type id -> owner."""

    kind: str
    owners: dict[int, Any] = field(default_factory=dict)
    names: dict[int, str] = field(default_factory=dict)

    def claim(self, name: str, cls: type[Modality], ids: Iterable[int], slot: Any) -> None:
        """Claim ``ids`` for ``slot`` (modality ``name``); :class:`ConfigError` naming both
        modalities when one is claimed already. Nothing is claimed unless all are free."""
        ids = sorted(set(ids))
        for i in ids:
            if i in self.owners:
                raise ConfigError(
                    f"modalities {self.names[i]!r} and {name!r} both claim {self.kind[:-1]} type id {i}"
                    f"{' (a third-party id: remap one in the deployment configuration)' if third_party(i) else ''}")
        for i in ids:
            self.owners[i] = slot
            self.names[i] = name

    def owner(self, m: Message) -> Any:
        tid = type_id(m)
        return self.owners.get(tid) if tid is not None else None
