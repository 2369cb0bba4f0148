"""Declared routing (coex_core.routing): modalities declare the type ids they own, a node routes
by id, refuses two modalities that claim one id, keeps legacy plugins working on their own,
and a deployment can remap third-party ids on the wire."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import pytest

from coex_core import wire
from coex_core.acoustic import AcousticChannel
from coex_core.channel import ChannelManager, LinkConfig, Schedule, StreamConfig
from coex_core.errors import ConfigError
from coex_core.messages import FrameHeader, ImageAck, Message, Opaque
from coex_core.modality import Modality, ModalityReceiver, ModalitySender, Product
from coex_core.node import Node
from coex_plugins.imagery import ImageryModality
from coex_runtime.runner import SimNetwork

VEHICLE, TOPSIDE = 2, 1


def nui() -> Schedule:
    return Schedule.simple([TOPSIDE, VEHICLE, VEHICLE, TOPSIDE, VEHICLE, VEHICLE], 20.0, 2.0)


class TagSender(ModalitySender):
    """Sends ``count`` messages of its data id, each carrying its tag; answers a request (its
    request id) by sending three more."""

    data_id = 0

    def __init__(self, data_id: int, count: int = 20) -> None:
        self.data_id, self.left, self.handled = data_id, count, []  # type: ignore[misc]

    def ingest(self, data: Any, now: float) -> None:
        pass

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        out: list[Message] = []
        while self.left and max_bytes >= 12:
            out.append(Opaque(self.data_id, self.left.to_bytes(4, "big") + bytes(4)))
            self.left -= 1
            max_bytes -= 12
        return out

    def handle(self, message: Message, now: float) -> list[Message]:
        self.handled.append(message)
        self.left += 3
        return []


class TagReceiver(ModalityReceiver):
    def __init__(self, request: Message | None = None) -> None:
        self.got: list[Message] = []
        self._request = request

    def receive(self, message: Message, now: float) -> list[Product]:
        self.got.append(message)
        return []

    def poll(self, now: float) -> list[Message]:
        out, self._request = ([self._request] if self._request is not None else []), None
        return out

    def products(self) -> list[Product]:
        return []


def modality(name: str, data: int, request: int, **attrs: Any) -> type[Modality]:
    class M(Modality):
        message_ids: ClassVar[tuple[int, ...]] = (data,)
        request_ids: ClassVar[tuple[int, ...]] = (request,)

        def sender(self, config: Mapping[str, Any] | None = None) -> ModalitySender:
            return TagSender(data)

        def receiver(self, config: Mapping[str, Any] | None = None) -> ModalityReceiver:
            return TagReceiver(Opaque(request, b"go"))

    M.name = name
    for k, v in attrs.items():
        setattr(M, k, v)
    return M


def pair(loss: float = 0.0) -> tuple[Node, Node, SimNetwork]:
    vehicle = Node(ChannelManager(VEHICLE, [LinkConfig(0, nui(), dst=TOPSIDE)]))
    topside = Node(ChannelManager(TOPSIDE, [LinkConfig(0, nui(), dst=VEHICLE)]))
    net = SimNetwork({0: AcousticChannel(loss=loss, seed=4)})
    net.add_node(vehicle, (0.0, 0.0, 100.0))
    net.add_node(topside, (10.0, 0.0, 0.0))
    return vehicle, topside, net


def attach(vehicle: Node, topside: Node, m: type[Modality], stream: int,
           ids: dict[int, int] | None = None) -> tuple[TagSender, TagReceiver]:
    s, r = m().sender(), m().receiver()
    vehicle.add_sender(m, s, StreamConfig(stream, m.name), ids=ids)
    topside.add_receiver(m, r, ids=ids)
    assert isinstance(s, TagSender) and isinstance(r, TagReceiver)
    return s, r


def test_two_third_party_modalities_share_a_node_and_each_gets_only_its_own_messages() -> None:
    vehicle, topside, net = pair(loss=0.2)
    ctd = modality("ctd", 200, 201)
    adcp = modality("adcp", 300, 301)
    s1, r1 = attach(vehicle, topside, ctd, 5)
    s2, r2 = attach(vehicle, topside, adcp, 6)
    net.run(1200.0)
    assert r1.got and r2.got
    assert {m.type_id for m in r1.got} == {200} and {m.type_id for m in r2.got} == {300}
    assert {m.type_id for m in s1.handled} == {201} and {m.type_id for m in s2.handled} == {301}
    assert vehicle.stats["rejected"] == 0 and topside.stats["rejected"] == 0


@pytest.mark.parametrize("side", ["sender", "receiver"])
def test_a_node_refuses_two_modalities_that_claim_one_id_naming_both(side: str) -> None:
    node = Node(ChannelManager(VEHICLE, [LinkConfig(0, nui(), dst=TOPSIDE)]))
    first, second = modality("ctd", 200, 201), modality("adcp", 200, 201)
    add = (lambda m, st: node.add_sender(m, m().sender(), StreamConfig(st, m.name))) if side == "sender" \
        else (lambda m, st: node.add_receiver(m, m().receiver()))
    add(first, 5)
    with pytest.raises(ConfigError, match=r"'ctd' and 'adcp' both claim .* type id 20[01]"):
        add(second, 6)


def test_a_built_in_type_claimed_twice_is_refused() -> None:
    class Copycat(Modality):
        name = "copycat"
        requests: ClassVar[tuple[type[Message], ...]] = (ImageAck,)

        def sender(self, config: Mapping[str, Any] | None = None) -> ModalitySender:
            return TagSender(200)

        def receiver(self, config: Mapping[str, Any] | None = None) -> ModalityReceiver:
            return TagReceiver()

    node = Node(ChannelManager(VEHICLE, [LinkConfig(0, nui(), dst=TOPSIDE)]))
    node.add_sender(ImageryModality, ImageryModality().sender(), StreamConfig(4, "images"))
    with pytest.raises(ConfigError, match="'imagery' and 'copycat' both claim request type id"):
        node.add_sender(Copycat, Copycat().sender(), StreamConfig(5, "copy"))


def test_an_id_outside_the_third_party_ranges_is_refused() -> None:
    bad = modality("bad", 10, 201)
    node = Node(ChannelManager(VEHICLE, [LinkConfig(0, nui(), dst=TOPSIDE)]))
    with pytest.raises(ConfigError, match="not a third-party type id"):
        node.add_receiver(bad, bad().receiver())


def test_a_plugin_listing_opaque_instead_of_its_ids_is_refused_with_the_upgrade() -> None:
    """The catch-all of 0.1 (``Opaque`` in ``messages``/``requests``, no ids) is gone: such a
    plugin is refused when added, with what to declare instead; the old ``opaque_*`` names are
    not read."""
    legacy = modality("legacy", 250, 251)
    legacy.message_ids = legacy.request_ids = ()  # type: ignore[misc]
    legacy.messages = legacy.requests = (Opaque,)  # type: ignore[misc]
    _vehicle, topside, _net = pair()
    with pytest.raises(ConfigError, match="list the third-party type ids in message_ids"):
        topside.add_receiver(legacy, legacy().receiver())
    old = modality("old", 250, 251)
    old.message_ids = old.request_ids = ()  # type: ignore[misc]
    old.opaque_messages = (250,)  # type: ignore[attr-defined]
    from coex_core.routing import declared_ids

    assert declared_ids(old, "messages") == frozenset()


def test_a_deployment_remaps_third_party_ids_on_the_wire() -> None:
    """Two plugins that chose the same ids share a node once the deployment remaps one: the
    wire carries the remapped ids, each plugin still sees its own."""
    vehicle, topside, net = pair()
    _s1, r1 = attach(vehicle, topside, modality("ctd", 200, 201), 5)
    s2, r2 = attach(vehicle, topside, modality("adcp", 200, 201), 6, ids={200: 4200, 201: 4201})
    on_wire: set[int] = set()
    poll = vehicle.poll

    def tapped(now: float) -> Any:
        txs = poll(now)
        for tx in txs:
            for f in tx.frames:
                on_wire.update(m.type_id for m in wire.unpack(f) if isinstance(m, Opaque))
        return txs

    vehicle.poll = tapped  # type: ignore[method-assign]
    net.run(900.0)
    assert on_wire == {200, 4200}
    assert {m.type_id for m in r1.got} == {200} and {m.type_id for m in r2.got} == {200}
    assert len(r1.got) >= 20 and len(r2.got) >= 20
    assert [m.type_id for m in s2.handled] == [201]
    assert vehicle.sender("adcp").inner is s2  # the plugin's own sender is inside the remap
    with pytest.raises(ConfigError, match="declares no third-party id 999"):
        topside.add_receiver(modality("x", 500, 501), TagReceiver(), ids={999: 4300})


def test_routine_requests_are_declared_not_guessed_from_class_names() -> None:
    """``routine`` lists the requests that do not expedite the stream: ImageAck for imagery;
    a third-party id for a plugin; nothing is routine because of its class name."""
    from coex_core.routing import routine_ids

    assert routine_ids(ImageryModality) == {wire.SPECS_BY_CLASS[ImageAck].type_id}
    ctd = modality("ctd", 200, 201, routine=(201,))
    assert routine_ids(ctd) == {201}
    assert routine_ids(modality("adcp", 300, 301)) == frozenset()
    node = Node(ChannelManager(VEHICLE, [LinkConfig(0, nui(), dst=TOPSIDE)]))
    node.add_sender(ctd, ctd().sender(), StreamConfig(5, "ctd"))
    frame = wire.pack([Opaque(201, b"ack")], 256, FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=1))
    node.receive(0, frame, 25.0)
    assert not node.manager.stream(5).expedite
    frame = wire.pack([Opaque(201, b"ack")], 256, FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=2))
    other = modality("adcp", 300, 301)
    node.add_sender(other, other().sender(), StreamConfig(6, "adcp"))
    node.receive(0, wire.pack([Opaque(301, b"go")], 256, FrameHeader(src=TOPSIDE, dst=VEHICLE, seq=2)), 26.0)
    assert node.manager.stream(6).expedite  # an operator request: answered in the next packet


def test_the_register_of_third_party_ids_is_consistent_with_the_plugins_that_use_them() -> None:
    """spec/third-party-ids.md: assigned ids are third-party ids outside the experimental block,
    no id twice, none retired; the example plugins declare exactly the ids registered for them;
    the guide's tutorial uses CoEx's example ids (its old 130, 131 are retired)."""
    import re
    from pathlib import Path

    from coex_conformance.sample import SampleModality
    from coex_core.routing import declared_ids
    from coex_sample_plugin import PingModality

    root = Path(__file__).resolve().parents[1]
    text = (root / "spec" / "third-party-ids.md").read_text()
    assigned = text.split("## Assigned ids", 1)[1].split("## Retired ids", 1)[0]
    retired = text.split("## Retired ids", 1)[1].split("## Experimental", 1)[0]
    rows = [(int(m[1]), m[2]) for m in re.finditer(r"^\| (\d+) \| ([\w-]+) \|", assigned, re.M)]
    ids = [i for i, _ in rows]
    assert rows and len(ids) == len(set(ids))
    assert all((96 <= i < 30000) for i in ids)
    gone = {int(i) for m in re.finditer(r"^\| ([\d, ]+) \|", retired, re.M) for i in m[1].split(",")}
    assert gone == {130, 131} and not gone & set(ids), "retired ids are never assigned again"
    by_plugin: dict[str, set[int]] = {}
    for i, name in rows:
        by_plugin.setdefault(name, set()).add(i)
    assert by_plugin["pings"] == declared_ids(PingModality, "messages") | declared_ids(PingModality, "requests")
    # the guide's tutorial holds CoEx's example ids, not a real plugin's (tests/test_plugin_guide.py builds it)
    assert "ctd" not in by_plugin
    assert "| 32600..32699 | examples in CoEx's documentation: the tutorial plugin `ctd`" in text
    assert "CAST, ACK = 32600, 32601" in (root / "docs" / "plugins.md").read_text()
    sample = declared_ids(SampleModality, "messages") | declared_ids(SampleModality, "requests")
    assert all(30000 <= i <= 32767 for i in sample) and "32700, 32701" in text


def _hooks(base: type) -> set[str]:
    """The public methods a base class declares (its hooks and the methods it calls them with)."""
    return {n for k in base.__mro__ if k is not object for n, v in vars(k).items()
            if callable(v) and not n.startswith("_")}


def test_the_remap_wrappers_declare_every_hook_and_delegate_nothing_else() -> None:
    """Each hook of ModalitySender / ModalityReceiver is defined by the remap wrapper itself
    (handed to ``inner``, ids translated): no ``__getattr__`` makes an optional hook look present
    or passes the plugin's own API through; that is on ``inner``."""
    from coex_core.remap import RemappedReceiver, RemappedSender

    assert _hooks(ModalitySender) - set(vars(RemappedSender)) == set()
    assert _hooks(ModalityReceiver) - set(vars(RemappedReceiver)) == set()
    assert "__getattr__" not in vars(RemappedSender) and "__getattr__" not in vars(RemappedReceiver)

    class Own(TagReceiver):
        def request_more(self) -> str:  # a plugin's own API
            return "more"

    inner = Own()
    outer = RemappedReceiver(inner, {200: 4200})
    assert not hasattr(outer, "request_more") and outer.inner is inner
    assert outer.products() == inner.products()


def test_a_modality_without_a_name_is_refused_by_the_node() -> None:
    """``Modality.name`` is required (declared on the base class, never guessed from the class's
    own name): a node refuses a modality that declares none, naming the class."""
    unnamed = modality("x", 300, 301)
    del unnamed.name
    node = Node(ChannelManager(VEHICLE, [LinkConfig(0, nui(), dst=TOPSIDE)]))
    with pytest.raises(ConfigError, match="declares no name"):
        node.add_sender(unnamed, TagSender(300), StreamConfig(5, "x"))
    with pytest.raises(ConfigError, match="declares no name"):
        node.add_receiver(unnamed, TagReceiver())
