"""Out-of-core storage for a modality's large state (a day-long map), as a sans-I/O contract.

A modality whose state can outgrow memory (the bathymetry map of a 100 km² survey) keeps what it
is not working on in a :class:`Storage`: named byte strings it writes and reads back. The core
never opens a file: whoever runs the node gives each modality its storage with
:meth:`Node.attach_storage <coex_core.node.Node.attach_storage>`. A node with a store
(``coex_runtime.store.NodeStore.storage``) backs it with the node's SQLite file; without one,
:class:`MemoryStorage` keeps the bytes in memory (and in the node's saved state).

The contract, which a storage implements and a modality may rely on:

* ``put(key, data)`` then ``get(key)`` returns ``data``; a key never put returns ``None``;
* what was put is saved with the node's next snapshot, together: a node restored from a snapshot
  sees its storage exactly as it was at that snapshot (what was put after it is discarded), so
  a restored modality and its storage always agree and the journal replayed after the snapshot
  counts nothing twice;
* before every snapshot the node calls each modality's ``sync_storage()``: the modality writes to
  its storage whatever it holds in memory that the storage does not have yet.

Keys are short strings (a modality's own names, e.g. ``"tile/12/-3"``). A modality's storage is a
:meth:`child <Storage.child>` of the node's, so two modalities never see each other's keys.
"""

from __future__ import annotations

import abc

from .state import persistent

__all__ = ["MemoryStorage", "Storage"]


class Storage(abc.ABC):
    """Named byte strings that outlive memory (see the module docstring for the contract)."""

    @abc.abstractmethod
    def get(self, key: str) -> bytes | None:
        """The bytes last put under ``key`` (None: never put)."""

    @abc.abstractmethod
    def put(self, key: str, data: bytes) -> None:
        """Keep ``data`` under ``key`` (replacing what was there)."""

    @abc.abstractmethod
    def keys(self, prefix: str = "") -> list[str]:
        """Every key put, that starts with ``prefix``, in no particular order."""

    @abc.abstractmethod
    def nbytes(self) -> int:
        """Bytes the storage holds for these keys (what is on disk, for a disk storage)."""

    def child(self, prefix: str) -> Storage:
        """The part of this storage under ``prefix`` (a modality's own namespace)."""
        return _Child(self, prefix)

    def same_keys(self, other: Storage | None) -> bool:
        """Whether ``other`` holds exactly this storage's keys: the same object, or the same
        part (:meth:`child`) of the same storage, as a node attaching its storage again gives
        (a modality then has nothing to move). The default: the same object."""
        return other is self


class _Child(Storage):
    def __init__(self, parent: Storage, prefix: str) -> None:
        self.parent, self.prefix = parent, prefix

    def get(self, key: str) -> bytes | None:
        return self.parent.get(self.prefix + key)

    def put(self, key: str, data: bytes) -> None:
        self.parent.put(self.prefix + key, data)

    def keys(self, prefix: str = "") -> list[str]:
        n = len(self.prefix)
        return [k[n:] for k in self.parent.keys(self.prefix + prefix)]

    def nbytes(self) -> int:
        # the parent's share of this prefix (an estimate is enough for reports)
        return sum(len(self.get(k) or b"") for k in self.keys())

    def child(self, prefix: str) -> Storage:
        return _Child(self.parent, self.prefix + prefix)

    def same_keys(self, other: Storage | None) -> bool:
        return other is self or (isinstance(other, _Child) and other.prefix == self.prefix
                                 and self.parent.same_keys(other.parent))


@persistent("core.MemoryStorage")
class MemoryStorage(Storage):
    """A storage in memory: the default of a modality that is given none (tests, a short
    demo). It is saved with the modality's state, so a restored node finds it as it was."""

    def __init__(self) -> None:
        self.data: dict[str, bytes] = {}

    def get(self, key: str) -> bytes | None:
        return self.data.get(key)

    def put(self, key: str, data: bytes) -> None:
        self.data[key] = bytes(data)

    def keys(self, prefix: str = "") -> list[str]:
        return [k for k in self.data if k.startswith(prefix)]

    def nbytes(self) -> int:
        return sum(len(v) for v in self.data.values())
