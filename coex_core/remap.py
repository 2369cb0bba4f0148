"""A modality whose third-party ids a deployment remapped (:mod:`coex_core.routing`): the plugin
speaks its own ids, the wire carries the remapped ones; these wrappers translate both ways.
``inner`` is the plugin's own sender or receiver (its state is what a node store saves).

Each wrapper declares every hook of its base class and hands it to ``inner`` (translating ids
where a message passes); nothing else is delegated: the plugin's own API (its request
methods, its data) is on ``inner``."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from typing import Any

from .messages import Message, Opaque
from .modality import ModalityReceiver, ModalitySender, Product
from .storage import Storage

__all__ = ["RemappedReceiver", "RemappedSender"]


def _translate(m: Message, table: Mapping[int, int]) -> Message:
    if isinstance(m, Opaque) and m.type_id in table:
        return Opaque(table[m.type_id], m.body)
    return m


class RemappedSender(ModalitySender):
    """A sender whose third-party ids a deployment remapped: it speaks its own ids, the wire
    carries the remapped ones (``inner`` is the plugin's sender: its state is saved)."""

    def __init__(self, inner: ModalitySender, to_wire: Mapping[int, int]) -> None:
        self.inner: ModalitySender = inner
        self.to_wire = dict(to_wire)
        self.from_wire = {b: a for a, b in self.to_wire.items()}

    def _out(self, ms: Iterable[Message]) -> list[Message]:
        return [_translate(m, self.to_wire) for m in ms]

    def ingest(self, data: Any, now: float) -> None:
        self.inner.ingest(data, now)

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        return self._out(self.inner.fill(max_bytes, now))

    def spare(self, max_bytes: int, now: float) -> list[Message]:
        return self._out(self.inner.spare(max_bytes, now))

    def handle(self, message: Message, now: float) -> list[Message]:
        return self._out(self.inner.handle(_translate(message, self.from_wire), now) or ())

    def pending_bytes(self) -> int:
        return self.inner.pending_bytes()

    def spare_bytes(self) -> int:
        return self.inner.spare_bytes()

    def ready_bytes(self, now: float) -> int:
        return self.inner.ready_bytes(now)

    def acked(self, message: Message, now: float) -> None:
        self.inner.acked(_translate(message, self.from_wire), now)

    def lost(self, message: Message, now: float) -> None:
        self.inner.lost(_translate(message, self.from_wire), now)

    def journal_form(self, data: Any) -> Any:
        return self.inner.journal_form(data)

    def focus(self, x: float, y: float, radius: float, now: float) -> int:
        return self.inner.focus(x, y, radius, now)

    def throughput(self, bytes_per_second: float, low: bool, now: float) -> None:
        self.inner.throughput(bytes_per_second, low, now)

    def detector_view(self) -> object | None:
        return self.inner.detector_view()

    def bind_peers(self, peer: Callable[[str], ModalitySender | None]) -> None:
        self.inner.bind_peers(peer)

    def peer(self, name: str) -> ModalitySender | None:
        return self.inner.peer(name)

    def attach_storage(self, storage: Storage) -> None:
        self.inner.attach_storage(storage)

    def sync_storage(self) -> None:
        self.inner.sync_storage()


class RemappedReceiver(ModalityReceiver):
    """The topside side of :class:`RemappedSender`."""

    def __init__(self, inner: ModalityReceiver, to_wire: Mapping[int, int]) -> None:
        self.inner: ModalityReceiver = inner
        self.to_wire = dict(to_wire)
        self.from_wire = {b: a for a, b in self.to_wire.items()}

    def receive(self, message: Message, now: float) -> list[Product]:
        return self.inner.receive(_translate(message, self.from_wire), now)

    def poll(self, now: float) -> list[Message]:
        return [_translate(m, self.to_wire) for m in self.inner.poll(now)]

    def products(self) -> list[Product]:
        return self.inner.products()

    def bind_command_ids(self, allocate: Callable[[], int]) -> None:
        self.inner.bind_command_ids(allocate)

    def next_command_id(self) -> int:
        return self.inner.next_command_id()

    def view(self, product: Product) -> Any:
        return self.inner.view(product)

    def supersedes(self, old: Message, new: Message) -> bool:
        return self.inner.supersedes(_translate(old, self.from_wire), _translate(new, self.from_wire))

    def attach_storage(self, storage: Storage) -> None:
        self.inner.attach_storage(storage)

    def sync_storage(self) -> None:
        self.inner.sync_storage()
