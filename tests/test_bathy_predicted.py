"""Subgrids predicted from what topside holds (PredictedSubgrid, spec/payloads.md 1.6 to 1.10):
exact round trips of every predictor, the sender predicting only from parents frame acks
confirmed, and the receiver setting aside a subgrid whose parent cells it lacks (or holds in
another version) until they come, never rebuilding it wrong."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from coex_core import state, wire
from coex_core.messages import MapRoiRequest, PredictedSubgrid, SubgridContext, SubgridMessage
from coex_core.predicted import (
    ABSENT,
    ContextMismatch,
    SubgridParent,
    context_check,
    decode_predicted_units,
    encode_predicted,
)
from coex_plugins.bathymetry import BathymetryReceiver, BathymetrySender

from ._bathy_data import small_survey

LEVELS = 3


def _parent(rng: np.random.Generator, holes: float = 0.0) -> SubgridParent:
    a, b = np.indices((8, 8))
    z = -5000 + 6 * a - 3 * b + rng.integers(-4, 5, (8, 8))
    return SubgridParent(z, rng.random((8, 8)) >= holes)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), ix=st.integers(-8192, 8191), iy=st.integers(-8192, 8191),
       holes=st.sampled_from([0.0, 0.2]), partial=st.booleans(), scale=st.sampled_from([1, 4, 60, 3000]))
def test_every_predictor_and_shift_round_trips_exactly(seed: int, ix: int, iy: int, holes: float, partial: bool,
                                                      scale: int) -> None:
    rng = np.random.default_rng(seed)
    parent = _parent(rng, holes)
    qx, qy = ix & 1, iy & 1
    i, j = np.indices((8, 8))
    q = parent.z[qy * 4 + i // 2, qx * 4 + j // 2] + rng.integers(-scale, scale + 1, (8, 8))
    present = rng.random((8, 8)) > 0.3 if partial else np.ones((8, 8), bool)
    if not present.any():
        present[3, 3] = True
    for context in SubgridContext:
        for predictor in range(4):
            for shift in range(4):
                got = encode_predicted(q, present, level=0, ix=ix, iy=iy, stamp=9, resolution=1.0,
                                       vertical_resolution=0.1, parent=parent, only=(context, predictor, shift))
                if got is None:  # no parent cell near the quarter, or too many bits
                    continue
                sg, bits = got
                data = wire.encode(sg)
                assert len(data) == (bits + 7) // 8
                back = wire.decode(data)
                assert back == sg
                z = decode_predicted_units(back, parent if context == SubgridContext.PARENT else None)
                np.testing.assert_array_equal(z == ABSENT, ~present)
                np.testing.assert_array_equal(z[present], q[present])


def test_a_parent_subgrid_needs_the_parent_cells_it_was_predicted_from() -> None:
    rng = np.random.default_rng(4)
    parent = _parent(rng)
    q = np.repeat(np.repeat(parent.z[4:, :4], 2, 0), 2, 1) + 1
    sg, _ = encode_predicted(q, np.ones((8, 8), bool), level=0, ix=4, iy=3, stamp=1, resolution=1.0,
                             vertical_resolution=0.1, parent=parent, standalone=False)  # type: ignore[misc]
    assert sg.context == SubgridContext.PARENT and sg.check == context_check(parent, 0, 1)
    with pytest.raises(ContextMismatch):
        decode_predicted_units(sg, None)
    inside = SubgridParent(parent.z.copy(), parent.present)
    inside.z[5, 1] += 1  # in the quarter's check region (rows 2..7, columns 0..5)
    with pytest.raises(ContextMismatch):
        decode_predicted_units(sg, inside)
    outside = SubgridParent(parent.z.copy(), parent.present)
    outside.z[0, 7] += 50  # outside it: the subgrid does not depend on it
    np.testing.assert_array_equal(decode_predicted_units(sg, outside), q)


def _sender() -> tuple[BathymetrySender, float]:
    _, survey = small_survey(48.0, 128)
    sender = BathymetrySender({"levels": LEVELS})
    for t, xyz in survey.pings(batch=10):
        sender.ingest(xyz, t)
    return sender, float(survey.times[-1]) + 30.0


def _drain(sender: BathymetrySender, receiver: BathymetryReceiver, now: float, ack: bool) -> list[SubgridMessage]:
    out: list[SubgridMessage] = []
    for i in range(3000):
        got = sender.fill(240, now + i)
        if not got:
            break
        for m in got:
            receiver.receive(wire.decode(wire.encode(m)), now + i)
            if ack:
                sender.acked(m, now + i)
            if isinstance(m, SubgridMessage):
                out.append(m)
    return out


def _map_units(sender: BathymetrySender, key: tuple[int, int, int]) -> np.ndarray:
    blk = sender.map.block(*key)
    assert blk is not None
    return np.where(blk.count > 0, np.rint(np.where(blk.count > 0, blk.mean, 0.0) / 0.1), np.nan)


def _held_units(receiver: BathymetryReceiver, key: tuple[int, int, int]) -> np.ndarray:
    held = receiver._held_block(*key)
    assert held is not None, key
    return np.where(np.isfinite(held), np.rint(held / 0.1), np.nan)


def test_the_sender_predicts_from_a_parent_only_once_an_ack_says_topside_holds_it() -> None:
    sender, now = _sender()
    receiver = BathymetryReceiver({"levels": LEVELS, "auto_fill": False})
    blind = _drain(sender, receiver, now, ack=False)
    assert blind and not [m for m in blind if isinstance(m, PredictedSubgrid) and m.context == SubgridContext.PARENT]

    sender, now = _sender()
    receiver = BathymetryReceiver({"levels": LEVELS, "auto_fill": False})
    sent = _drain(sender, receiver, now, ack=True)
    parent = [m for m in sent if isinstance(m, PredictedSubgrid) and m.context == SubgridContext.PARENT]
    assert len(parent) > len(sent) // 2
    assert sum(wire.encoded_size(m) for m in sent) < 0.85 * sum(wire.encoded_size(m) for m in blind)
    assert receiver.set_aside == 0
    for key in sender.inventory():  # every level rebuilt exactly as the vehicle's map quantises it
        np.testing.assert_array_equal(_held_units(receiver, key), _map_units(sender, key))


def _raise(sender: BathymetrySender, key: tuple[int, int, int], cells: list[tuple[int, int]], t: float) -> None:
    """New soundings 0.6 m above level-0 cells ``(i, j)`` of subgrid ``key``: a real change."""
    for i, j in cells:
        x, y = 8 * key[1] + j + 0.5, 8 * key[2] + i + 0.5
        z = float(_map_units(sender, key)[i, j]) * 0.1 + 0.6
        sender.ingest(np.array([[x, y, z]] * 40), t)
    sender.map.flush(force=True)


def test_a_newer_parent_overtaking_its_child_sets_the_child_aside_until_it_is_sent_again() -> None:
    """A child's new version is predicted from the parent version topside acknowledged; then
    the parent changes next to the child (a neighbouring subgrid's new soundings, within the
    child's check region) and that newer parent reaches topside first: the check fails, the
    child is set aside (not held, not rebuilt wrong: topside keeps the version it had); a region
    request brings it again, coded from what the vehicle now knows topside holds."""
    sender, now = _sender()
    receiver = BathymetryReceiver({"levels": LEVELS, "auto_fill": False})
    _drain(sender, receiver, now, ack=True)
    key, sibling, pkey = (0, 2, 2), (0, 3, 2), (1, 1, 1)
    t = now + 5000.0
    _raise(sender, key, [(3, 3)], t)  # the child changes, so does its parent there
    parent_v2 = sender.build(pkey)
    assert parent_v2 is not None
    receiver.receive(parent_v2, t + 30.0)
    sender.fill(240, t + 30.0)  # the background sends the new versions; topside acknowledges them
    sender.acked(parent_v2, t + 31.0)
    child = sender.build(key)
    assert isinstance(child, PredictedSubgrid) and child.context == SubgridContext.PARENT
    _raise(sender, sibling, [(3, 0)], t + 40.0)  # next to the child: in its check region
    parent_v3 = sender.build(pkey)
    assert parent_v3 is not None and parent_v3 != parent_v2
    later = t + 100.0
    receiver.receive(parent_v3, later)  # overtakes the child
    held_before = receiver.holdings(0)[(key[1], key[2])]
    assert receiver.receive(child, later) == []
    assert receiver.waiting() == [key] and receiver.set_aside == 1
    assert receiver.holdings(0)[(key[1], key[2])] == held_before < child.stamp  # the old version, not a wrong one
    receiver.request_region(0, key[1], key[2], 1, 1)
    (req,) = receiver.poll(later)
    assert isinstance(req, MapRoiRequest)
    sender.handle(req, later)
    again = [m for m in sender.fill(240, later + 1.0) if isinstance(m, SubgridMessage)]
    sg = next(m for m in again if (m.level, m.ix, m.iy) == key)
    receiver.receive(wire.decode(wire.encode(sg)), later + 1.0)
    assert receiver.waiting() == []
    np.testing.assert_array_equal(_held_units(receiver, key), _map_units(sender, key))


def test_a_child_lost_after_a_restart_goes_again_though_its_parent_was_acknowledged_since() -> None:
    """Issue 51 (the kill -9 loop's map that never converged): a change goes out as a new parent
    and a new child in one fill (the child coded on its own: the new parent is not acknowledged
    yet); the parent's frame arrives and is acknowledged, the child's is lost, and the vehicle
    restarts from its saved state before the loss is known. The child's current build is then
    predicted from the acknowledged parent, another message than the lost one, and the sender
    no longer knows the lost message's version (not saved): the loss must still send the child
    again, or topside keeps its old version for good (the background sends a subgrid only when
    it changes)."""
    sender, now = _sender()
    receiver = BathymetryReceiver({"levels": LEVELS, "auto_fill": False})
    _drain(sender, receiver, now, ack=True)
    key, pkey = (0, 2, 2), (1, 1, 1)
    t = now + 5000.0
    _raise(sender, key, [(3, 3)], t)
    sent: list[SubgridMessage] = []
    for i in range(60):  # the background, once the change is quiet
        sent += [m for m in sender.fill(240, t + i) if isinstance(m, SubgridMessage)]
    child = next(m for m in sent if (m.level, m.ix, m.iy) == key)
    assert any((m.level, m.ix, m.iy) == pkey for m in sent)
    assert not (isinstance(child, PredictedSubgrid) and child.context == SubgridContext.PARENT)
    for m in sent:  # every frame arrives and is acknowledged but the child's
        if m is not child:
            receiver.receive(wire.decode(wire.encode(m)), t + 61.0)
            sender.acked(m, t + 62.0)
    restored = state.loads(state.dumps(sender))  # the restart (the node's store saves this state)
    assert isinstance(restored, BathymetrySender)
    rebuilt = restored.build(key)
    assert isinstance(rebuilt, PredictedSubgrid) and rebuilt.context == SubgridContext.PARENT
    restored.lost(child, t + 80.0)  # the loss, known after the restart
    again = [m for m in restored.spare(240, t + 81.0) if isinstance(m, SubgridMessage)]
    assert [(m.level, m.ix, m.iy) for m in again] == [key]
    receiver.receive(wire.decode(wire.encode(again[0])), t + 82.0)
    np.testing.assert_array_equal(_held_units(receiver, key), _map_units(restored, key))


def test_a_child_set_aside_is_rebuilt_when_its_parent_arrives() -> None:
    sender, now = _sender()
    receiver = BathymetryReceiver({"levels": LEVELS, "auto_fill": False})
    sent = _drain(sender, receiver, now, ack=True)
    child = next(m for m in sent if isinstance(m, PredictedSubgrid) and m.context == SubgridContext.PARENT
                 and m.level == 0)
    parent = next(m for m in sent if (m.level, m.ix, m.iy) == (1, child.ix >> 1, child.iy >> 1))
    fresh = BathymetryReceiver({"levels": LEVELS, "auto_fill": False})
    for m in sent:  # what arrived at a receiver that lost the parent's level but for that one
        if m.level == 2:
            fresh.receive(m, now)
    assert fresh.receive(child, now) == []
    assert fresh.waiting() == [(0, child.ix, child.iy)]
    products = fresh.receive(parent, now + 1.0)
    assert {p.key for p in products} == {"level-1", "level-0"}
    assert fresh.waiting() == [] and fresh.resolved == 1
    np.testing.assert_array_equal(_held_units(fresh, (0, child.ix, child.iy)),
                                  _map_units(sender, (0, child.ix, child.iy)))


def test_topside_saying_it_lacks_a_parent_stops_predictions_from_it() -> None:
    sender, now = _sender()
    receiver = BathymetryReceiver({"levels": LEVELS, "auto_fill": False})
    _drain(sender, receiver, now, ack=True)
    key = (0, 2, 2)
    child = sender.build(key)
    assert isinstance(child, PredictedSubgrid) and child.context == SubgridContext.PARENT
    # a gap request at level 1 that says topside holds nothing (it lost its state, say)
    sender.handle(MapRoiRequest(7, 1, 1, 1, 1, 1, True, (), have=0), now + 4000.0)
    again = sender.build(key)
    assert again is not None and not (isinstance(again, PredictedSubgrid) and again.context == SubgridContext.PARENT)


def test_what_topside_holds_survives_a_saved_and_restored_sender() -> None:
    sender, now = _sender()
    receiver = BathymetryReceiver({"levels": LEVELS, "auto_fill": False})
    _drain(sender, receiver, now, ack=True)
    restored = state.loads(state.dumps(sender))
    assert isinstance(restored, BathymetrySender)
    built = restored.build((0, 2, 2))
    assert isinstance(built, PredictedSubgrid) and built.context == SubgridContext.PARENT
    assert built == dataclasses.replace(sender.build((0, 2, 2)))  # type: ignore[type-var]


def test_lcm_map_summaries_rebuild_predicted_subgrids_from_their_parents() -> None:
    pytest.importorskip("lcm")
    from coex_transports.lcm.products import MapLevelSummary

    sender, now = _sender()
    receiver = BathymetryReceiver({"levels": LEVELS, "auto_fill": False})
    sent = _drain(sender, receiver, now, ack=True)
    assert any(isinstance(m, PredictedSubgrid) and m.context == SubgridContext.PARENT for m in sent)
    summary = MapLevelSummary()
    for m in sent:
        summary.add(m)
    for level in range(LEVELS):
        grid, _, _ = sender.map.grid(level)
        lv = summary.summary(level)
        assert lv.resolution == 2.0**level and lv.subgrids == len(receiver.holdings(level))
        assert lv.z_min == pytest.approx(np.rint(np.nanmin(grid) / 0.1) * 0.1)
        assert lv.z_max == pytest.approx(np.rint(np.nanmax(grid) / 0.1) * 0.1)


def test_a_round_trip_with_acks_tells_the_sender_each_frames_fate() -> None:
    """RoundTrip(acks=True): every message of a frame that arrived and whose ack came back is
    acknowledged to the sender; every message of a lost frame (or of a lost ack) is lost."""
    from coex_core.loopback import Bernoulli, RoundTrip

    class Recorder(BathymetrySender):
        def __init__(self) -> None:
            super().__init__({"levels": LEVELS})
            self.fates: list[tuple[str, object]] = []

        def acked(self, message: object, now: float) -> None:  # type: ignore[override]
            self.fates.append(("acked", message))
            super().acked(message, now)  # type: ignore[arg-type]

        def lost(self, message: object, now: float) -> None:  # type: ignore[override]
            self.fates.append(("lost", message))
            super().lost(message, now)  # type: ignore[arg-type]

    _, survey = small_survey(48.0, 128)
    sender = Recorder()
    for t, xyz in survey.pings(batch=10):
        sender.ingest(xyz, t)
    receiver = BathymetryReceiver({"levels": LEVELS, "auto_fill": False})
    link = RoundTrip(sender, receiver, down=Bernoulli(0.3, 5), up=Bernoulli(0.3, 6),
                     now=float(survey.times[-1]) + 30.0, acks=True)
    for _ in range(40):
        link.step()
    by_id = {id(m): fate for fate, m in sender.fates}
    sent = [e for e in link.events if e.direction == "down"]
    assert sent and len(by_id) == len({id(e.message) for e in sent})  # each message told once
    assert {by_id[id(e.message)] for e in sent if e.lost} == {"lost"}
    arrived = [by_id[id(e.message)] for e in sent if not e.lost]
    assert "acked" in arrived and "lost" in arrived  # some acks were lost on the way up
    quiet = RoundTrip(BathymetrySender({"levels": LEVELS}), BathymetryReceiver({"levels": LEVELS}))
    assert quiet.acks is False  # by default the sender is told nothing (as before)


def test_the_largest_predicted_subgrid_takes_the_most_bytes_one_can() -> None:
    """The size the spec gives for type 20 (its largest vector) is the true maximum: NONE (the
    longest header) with coded cells within a few bits of the 1536 allowed (bytes round up)."""
    from coex_core._wire._subgrid_code import CodedCells, encode_cells, table_for
    from coex_core._wire.bathymetry import _LARGEST_PREDICTED as largest
    from coex_core.predicted import HEADER_BITS

    bits = len(encode_cells(largest.side, CodedCells(None, largest.cells.residuals), largest.shift,
                            table_for(False, largest.level)))
    assert 1536 - 3 <= bits <= 1536
    assert len(wire.encode(largest)) == (HEADER_BITS[SubgridContext.NONE] + 1536 + 7) // 8 == wire.MAX_SIZES[
        "PredictedSubgrid"]
