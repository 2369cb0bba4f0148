"""Fuzzing the receive path of whole nodes: random bytes and mutated real frames (bit flips,
truncation, splices) go into a vehicle and a topside node with all three modalities attached.
Nothing may raise, and a valid frame afterwards is still used."""

from __future__ import annotations

from functools import lru_cache

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from coex_core.acoustic import AcousticChannel
from coex_core.messages import Opaque

from ._faults import T0, TOPSIDE, VEHICLE, Dive, build_dive, run_sim

KEY = b"fuzzing-key-of-at-least-16-bytes"


@lru_cache(maxsize=1)
def real_frames() -> tuple[tuple[int, bytes], ...]:
    """(sender node, frame) of a short dive, both directions."""
    dive = build_dive()
    net = run_sim(dive, AcousticChannel(seed=1), T0 + 300.0)
    return tuple((nid, f) for nid, tx in net.transmissions for f in tx.frames)


def fresh() -> Dive:
    return build_dive(crc=False)


@st.composite
def mutated(draw: st.DrawFn) -> bytes:
    frames = real_frames()
    _, base = draw(st.sampled_from(frames))
    kind = draw(st.sampled_from(["flip", "truncate", "splice", "random", "insert"]))
    data = bytearray(base)
    if kind == "flip":
        for _ in range(draw(st.integers(1, 8))):
            i = draw(st.integers(0, len(data) * 8 - 1))
            data[i // 8] ^= 1 << (i % 8)
    elif kind == "truncate":
        data = data[: draw(st.integers(0, len(data)))]
    elif kind == "splice":
        _, other = draw(st.sampled_from(frames))
        cut = draw(st.integers(0, min(len(data), len(other))))
        data = data[:cut] + bytearray(other[cut:])
    elif kind == "insert":
        at = draw(st.integers(0, len(data)))
        data[at:at] = draw(st.binary(min_size=1, max_size=16))
    else:
        data = bytearray(draw(st.binary(max_size=300)))
    return bytes(data)


DIVE = None


def dive() -> Dive:
    global DIVE
    if DIVE is None:
        DIVE = fresh()
    return DIVE


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(mutated(), min_size=1, max_size=5))
def test_mutated_frames_never_crash_a_node(frames: list[bytes]) -> None:
    d = dive()
    for i, f in enumerate(frames):
        d.vehicle.receive(0, f, T0 + 400.0 + i)
        d.topside.receive(0, f, T0 + 400.0 + i)
    d.vehicle.events()
    d.topside.events()


def test_nodes_still_work_after_the_fuzz() -> None:
    # the same nodes the fuzz test used (or fresh ones when run alone), then real frames again
    d = dive()
    before = d.topside.stats["messages"]
    for nid, f in real_frames():
        (d.topside if nid == VEHICLE else d.vehicle).receive(0, f, T0 + 500.0)
    assert d.topside.stats["messages"] > before
    assert any(name == "bathymetry" for name, _ in d.topside.products())


def test_keyed_vehicle_survives_garbage_with_trailers() -> None:
    from coex_core.channel import ChannelManager, LinkConfig
    from coex_core.node import Node

    from ._faults import schedule

    v = Node(ChannelManager(VEHICLE, [LinkConfig(0, schedule(), rate=5, dst=TOPSIDE)], command_key=KEY))
    for _, f in real_frames():
        v.receive(0, f, 1.0)
    # a frame of a third-party request with a trailer-like tail of garbage
    from coex_core import wire
    from coex_core.messages import AuthTrailer, FrameHeader

    frame = wire.pack([Opaque(120, b"x"), AuthTrailer(5, bytes(8))], 64, FrameHeader(src=TOPSIDE, dst=VEHICLE))
    v.receive(0, frame, 2.0)
    topside_frames = sum(1 for nid, _ in real_frames() if nid == TOPSIDE)
    assert v.stats["frames"] == len(real_frames()) + 1
    # topside's unsigned commands and the forged trailer: rejected, counted, never raised
    assert 2 <= v.stats["unauthenticated"] <= topside_frames + 1
