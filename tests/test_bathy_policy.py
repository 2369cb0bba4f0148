"""Sending policy, region requests with implicit acks, gap filling, and the exchange under loss."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from coex_conformance.harness import LinkedPair, run_until
from coex_core import wire
from coex_core.errors import RequestRejected
from coex_core.messages import (
    MapMetadata,
    MapRoiReply,
    MapRoiRequest,
    Subgrid,
    SubgridMessage,
    VehicleMode,
    VehicleStatus,
)
from coex_core.timefmt import to_stamp
from coex_plugins.bathymetry import BathymetryReceiver, BathymetrySender

from ._bathy_data import small_survey

LEVELS = 3


def _loaded_sender(**cfg: object) -> tuple[BathymetrySender, float]:
    _, survey = small_survey(48.0, 128)
    sender = BathymetrySender({"levels": LEVELS, **cfg})
    for t, xyz in survey.pings(batch=10):
        sender.ingest(xyz, t)
    return sender, float(survey.times[-1])


def _bump(sender: BathymetrySender, x: float, y: float, t: float) -> None:
    """New soundings 0.4 m above the current cell mean at (x, y): a real change, not an outlier."""
    blk = sender.map.block(0, int(x // 8), int(y // 8))
    assert blk is not None
    z = float(blk.mean[int(y) % 8, int(x) % 8]) + 0.4
    sender.ingest(np.array([[x, y, z]] * 6), t)


def _drain(sender: BathymetrySender, now: float, budget: int = 240, step: float = 1.0) -> list[Subgrid]:
    out: list[Subgrid] = []
    for i in range(5000):
        batch = sender.fill(budget, now + i * step)
        subs = [m for m in batch if isinstance(m, SubgridMessage)]
        out.extend(subs)
        if not subs and (sender.pending_bytes() == 0 or step == 0):
            break
    return out


def test_nothing_is_sent_until_quiet_for_send_delay_then_coarsest_level_first() -> None:
    sender, last = _loaded_sender()
    early = sender.fill(240, last + 5.0)
    assert isinstance(early[0], MapMetadata) and early[0].pending > 0
    recent = {k for k, st in sender.inventory().items() if st > last + 5.0 - 20.0}
    assert recent, "the last lines of the survey are not quiet yet"
    early_subs = _drain(sender, last + 5.0, step=0.0)
    assert early_subs and all(s.stamp <= last + 5.0 - 20.0 for s in early_subs)
    assert not recent & {(s.level, s.ix, s.iy) for s in early_subs}
    sender, last = _loaded_sender()
    remaining = set(sender.inventory())
    sent: list[Subgrid] = []
    for i in range(1000):
        subs = [m for m in sender.fill(240, last + 21.0 + i) if isinstance(m, SubgridMessage)]
        if not subs:
            break
        # Each packet starts with the coarsest level still unsent; leftover room may take a
        # smaller, finer subgrid (whole subgrids that fit), never a coarser one later.
        assert subs[0].level == max(k[0] for k in remaining)
        remaining -= {(s.level, s.ix, s.iy) for s in subs}
        sent.extend(subs)
    assert not remaining
    assert all(sender.last_transmitted((s.level, s.ix, s.iy)) is not None for s in sent)
    assert sender.last_transmitted((0, 999, 999)) is None
    keys = [(s.level, s.ix, s.iy) for s in sent]
    assert len(keys) == len(set(keys)), "each subgrid is sent once"
    assert set(keys) == set(sender.inventory())


def test_fill_answers_whole_subgrids_within_the_budget() -> None:
    sender, last = _loaded_sender()
    assert sender.fill(11, last + 30.0) == []
    for budget in (12, 40, 64, 100, 251):
        out = sender.fill(budget, last + 30.0)
        assert sum(wire.encoded_size(m) for m in out) <= budget


def test_a_changed_subgrid_is_sent_again_once_quiet_and_only_it() -> None:
    sender, last = _loaded_sender()
    _drain(sender, last + 21.0)
    t2 = last + 1000.0
    _bump(sender, 3.2, 4.1, t2)
    assert not [m for m in sender.fill(240, t2 + 10.0) if isinstance(m, SubgridMessage)]
    again = _drain(sender, t2 + 21.0)
    assert sorted((s.level, s.ix, s.iy) for s in again) == [(k, 0, 0) for k in range(LEVELS)]
    assert all(s.stamp == to_stamp(t2) for s in again)


def _synced(loss: float = 0.0) -> tuple[BathymetrySender, BathymetryReceiver, float]:
    sender, last = _loaded_sender()
    receiver = BathymetryReceiver({"levels": LEVELS, "auto_fill": False})
    now = last + 21.0
    for sg in _drain(sender, now):
        receiver.receive(sg, now)
    return sender, receiver, now + 100.0


def _request(receiver: BathymetryReceiver, level: int, now: float) -> MapRoiRequest:
    receiver.request_region(level, -2, -2, 6, 6)
    reqs = receiver.poll(now)
    assert len(reqs) == 1 and isinstance(reqs[0], MapRoiRequest)
    return reqs[0]


def test_region_request_with_current_stamps_resends_nothing() -> None:
    sender, receiver, now = _synced()
    req = _request(receiver, 0, now)
    assert any(h is not None for h in req.held)
    replies = sender.handle(req, now)
    # nothing newer; the region's subgrids beyond the survey (negative indices) are awaited
    unsurveyed = sum(1 for i in range(36) if not math.isfinite(sender.subgrid_time((0, -2 + i % 6, -2 + i // 6))))
    assert unsurveyed > 0
    assert replies == [MapRoiReply(req.request_id, 0, 0, unsurveyed)]
    assert not [m for m in sender.fill(240, now) if isinstance(m, SubgridMessage)]
    receiver.receive(replies[0], now)
    (region,) = receiver.active_regions()  # it stands on the vehicle: waiting, not answered
    assert region.waiting == unsurveyed and not region.done
    assert receiver.poll(now + 600.0) == []  # not asked again while it stands


def test_a_request_over_surveyed_ground_with_current_stamps_closes() -> None:
    sender, receiver, now = _synced()
    receiver.request_region(0, 0, 0, 4, 4)
    (req,) = receiver.poll(now)
    replies = sender.handle(req, now)
    assert replies == [MapRoiReply(req.request_id, 0, 0, 0)]
    receiver.receive(replies[0], now)
    assert receiver.active_regions() == []


def test_region_request_resends_only_missing_and_newer_subgrids() -> None:
    sender, receiver, now = _synced()
    held0 = receiver.holdings(0)
    inside = sorted(k for k in held0 if -2 <= k[0] < 4 and -2 <= k[1] < 4)
    missing = inside[0]
    assert receiver.forget(0, *missing)
    t2 = now + 10.0
    newer_key = inside[-1]
    x = (newer_key[0] * 8 + 3.5) * 1.0
    y = (newer_key[1] * 8 + 3.5) * 1.0
    _bump(sender, x, y, t2)
    req = _request(receiver, 0, t2 + 1.0)
    (reply,) = sender.handle(req, t2 + 1.0)
    assert isinstance(reply, MapRoiReply) and reply.queued == 2
    out = [m for m in sender.fill(240, t2 + 2.0) if isinstance(m, SubgridMessage)]
    assert sorted((s.ix, s.iy) for s in out if s.level == 0)[:2] == sorted([missing, newer_key])
    assert {(s.level, s.ix, s.iy) for s in out[:2]} == {(0, *missing), (0, *newer_key)}


def test_requested_subgrids_go_out_ahead_of_background() -> None:
    sender, last = _loaded_sender()
    receiver = BathymetryReceiver({"levels": LEVELS, "auto_fill": False})
    receiver.request_region(0, 1, 1, 1, 1)
    (req,) = receiver.poll(last + 21.0)
    sender.handle(req, last + 21.0)
    out = [m for m in sender.fill(240, last + 21.0) if isinstance(m, SubgridMessage)]
    assert (out[0].level, out[0].ix, out[0].iy) == (0, 1, 1)
    assert out[1].level == LEVELS - 1  # then the background, coarsest first


def test_gap_filling_sends_exactly_what_topside_lacks() -> None:
    sender, receiver, now = _synced()
    dropped = sorted(receiver.holdings(0))[::3]
    for k in dropped:
        assert receiver.forget(0, *k)
    xs = [k[0] for k in sender.inventory() if k[0] == 0]
    keys = [k[1:] for k in sender.inventory() if k[0] == 0]
    x0, y0 = min(k[0] for k in keys), min(k[1] for k in keys)
    w, h = max(k[0] for k in keys) - x0 + 1, max(k[1] for k in keys) - y0 + 1
    regions = receiver.request_gaps(0, x0, y0, w, h)
    assert len(regions) == -(-w // 16) * -(-h // 16) and xs  # 16 x 16 subgrids per gap request
    reqs = receiver.poll(now)
    queued = 0
    for r in reqs:
        assert isinstance(r, MapRoiRequest) and r.fill_gaps and r.have is not None
        assert wire.decode(wire.encode(r)) == r
        queued += sender.handle(r, now)[0].queued  # type: ignore[attr-defined]
    assert queued == len(dropped)
    out = _drain(sender, now)
    assert sorted((s.ix, s.iy) for s in out) == sorted(dropped)


def test_a_requested_subgrid_acked_meanwhile_is_not_sent_again_unless_newer() -> None:
    """Topside asks for two subgrids it lacks while copies are still on the way; the ack of a
    copy answers its request (the ack arrives after the request), unless the map has a newer
    version of it by then."""
    sender, receiver, now = _synced()
    keys = sorted(k for k in receiver.holdings(0) if min(k) >= 0)[:2]
    copies = {k: sender.build((0, *k)) for k in keys}
    for k in keys:
        assert receiver.forget(0, *k)
    receiver.request_gaps(0, min(k[0] for k in keys), min(k[1] for k in keys), 16, 16)
    for r in receiver.poll(now):
        sender.handle(r, now)
    plain, newer = keys
    sender.acked(copies[plain], now + 5.0)  # the copy in flight arrived: nothing to resend
    x, y = newer[0] * 8 + 3.5, newer[1] * 8 + 3.5
    _bump(sender, x, y, now + 6.0)  # the other subgrid changed before its copy was acked
    sender.acked(copies[newer], now + 7.0)
    sender.acked(sender.metadata(now), now + 7.0)  # not a subgrid: ignored
    out = [(s.level, s.ix, s.iy) for s in _drain(sender, now + 30.0) if s.level == 0]
    assert (0, *plain) not in out
    assert out.count((0, *newer)) == 1  # once: as requested, not again as a changed subgrid


def test_the_newest_gap_request_for_a_region_wins() -> None:
    """An older copy of a gap request delivered late (the channel re-sent it) queues nothing;
    a newer gap request saying topside now holds what an earlier one asked for unqueues it."""
    sender, receiver, now = _synced()
    k1, k2 = sorted(k for k in receiver.holdings(0) if min(k) >= 0)[:2]
    x0, y0 = min(k1[0], k2[0]), min(k1[1], k2[1])
    w, h = max(k1[0], k2[0]) - x0 + 1, max(k1[1], k2[1]) - y0 + 1

    def gap(rid: int, lacking: set[tuple[int, int]]) -> MapRoiRequest:
        have = 0
        for i in range(w * h):
            have = (have << 1) | ((x0 + i % w, y0 + i // w) not in lacking)
        return MapRoiRequest(rid, 0, x0, y0, w, h, True, (), have)

    assert sender.handle(gap(250, {k1, k2}), now)[0].queued == 2  # type: ignore[attr-defined]
    assert sender.handle(gap(3, {k2}), now + 30.0)[0].queued == 1  # type: ignore[attr-defined]
    assert sender.handle(gap(250, {k1, k2}), now + 40.0)[0].queued == 0  # type: ignore[attr-defined]
    assert sender.stale_requests == 1
    out = [(s.ix, s.iy) for s in _drain(sender, now + 41.0, step=0) if s.level == 0]
    assert out == [k2]
    # long after, or far older ids, a request is new again
    assert sender.handle(gap(250, {k1}), now + 400.0)[0].queued == 1  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    "request_",
    [
        MapRoiRequest(1, 9, 0, 0, 1, 1, False, (None,)),  # level beyond the map
        MapRoiRequest(1, 0, 0, 0, 1000, 1000, True, (), 0),  # absurd area
        MapRoiRequest(1, 0, 0, 0, 2, 2, False, (None,)),  # one stamp for four subgrids
        MapRoiRequest(1, 0, 0, 0, 2, 2, True, (), None),  # gap filling without a bitmap
        MapRoiRequest(1, 0, 8190, 0, 16, 1, True, (), 0),  # outside the addressable map
        VehicleStatus(0, 0.0, 0.0, 0.0, None, 0.0, 0.0, 0, VehicleMode.IDLE, 0),
    ],
)
def test_absurd_or_foreign_requests_are_rejected_and_change_nothing(request_: object) -> None:
    sender, last = _loaded_sender()
    before = (list(sender._queue), sender.inventory())
    with pytest.raises(RequestRejected):
        sender.handle(request_, last)  # type: ignore[arg-type]
    assert (list(sender._queue), sender.inventory()) == before


def test_receiver_rejects_absurd_regions() -> None:
    receiver = BathymetryReceiver({"levels": LEVELS})
    with pytest.raises(RequestRejected):
        receiver.request_region(7, 0, 0, 1, 1)
    with pytest.raises(RequestRejected):
        receiver.request_region(0, 0, 0, 10_000, 10_000)


def test_receiver_keeps_the_newest_version_and_ages() -> None:
    sender, receiver, now = _synced()
    key = sorted(receiver.holdings(0))[0]
    stamp = receiver.holdings(0)[key]
    sg = sender.build((0, *key))
    assert sg is not None
    older = dataclasses.replace(sg, stamp=stamp - 50)
    assert receiver.receive(older, now) == []
    assert receiver.holdings(0)[key] == stamp
    age = receiver.age(0, *key, now)
    assert age is not None and age > 100.0
    assert receiver.age(0, 999, 999, now) is None


def test_roi_and_ack_exchange_converges_under_loss() -> None:
    sender, last = _loaded_sender()
    receiver = BathymetryReceiver({"levels": LEVELS, "auto_fill": False, "request_timeout": 30.0})
    pair = LinkedPair(sender, receiver, loss=0.4, seed=11, round_seconds=5.0)
    pair.now = last + 21.0
    for _ in range(300):  # stream the background over the lossy link, no requests
        pair.step()
        if sender.pending_bytes() == 0:
            break
    want = {(ix, iy): st for (lv, ix, iy), st in sender.inventory().items() if lv == 0}
    assert receiver.holdings(0) != want, "with 40% loss some subgrids must be missing"
    # Data changes on the vehicle after topside got its copy: the stamps make it re-sent.
    before = sender.inventory()
    _bump(sender, 20.5, 20.5, pair.now)
    assert sender.inventory() != before
    pair.now += 25.0
    want = {(ix, iy): st for (lv, ix, iy), st in sender.inventory().items() if lv == 0}
    xs = [k[0] for k in want]
    ys = [k[1] for k in want]
    regions = receiver.request_region(0, min(xs), min(ys), max(xs) - min(xs) + 1, max(ys) - min(ys) + 1)

    def done() -> bool:
        return receiver.holdings(0) == want and all(r.done for r in regions)

    run_until(pair, done, 2000)
    assert any(r.sends > 1 for r in regions), "lost requests or replies were retried"
    assert any(isinstance(m, MapRoiReply) and m.queued == 0 for m in pair.received_messages)
    assert math.isfinite(pair.now)


def test_config_outside_the_wire_tables_is_a_config_error() -> None:
    from coex_core.errors import ConfigError

    for cfg in ({"resolution": 0.3}, {"vertical_resolution": 0.07}, {"subgrid_side": 16}, {"bogus": 1}):
        with pytest.raises(ConfigError):
            BathymetrySender(cfg)


def test_elevations_beyond_the_wire_range_are_skipped_not_a_crash() -> None:
    sender = BathymetrySender({"vertical_resolution": 0.01, "levels": 2})
    deep = np.array([[1.5, 1.5, -6000.0]] * 5)  # 600,000 cm: beyond 20 signed bits
    ok = np.array([[20.5, 20.5, -50.0]] * 5)
    sender.ingest(np.vstack([deep, ok]), 0.0)
    out = [m for m in sender.fill(240, 30.0) if isinstance(m, SubgridMessage)]
    assert {(m.level, m.ix, m.iy) for m in out} == {(1, 1, 1), (0, 2, 2)}
    assert (0, 0, 0) in sender.unsendable


def test_poll_paces_requests_and_auto_fill_runs_once_per_map_change() -> None:
    receiver = BathymetryReceiver({"levels": LEVELS})
    meta = MapMetadata(stamp=500, resolution=1.0, vertical_resolution=0.1, subgrid_side=8, levels=LEVELS,
                       origin_lat=0.0, origin_lon=0.0, x_min=-256, y_min=0, x_max=256, y_max=256, pending=0)
    receiver.receive(meta, 1000.0)
    first = receiver.poll(1000.0)
    assert 0 < len(first) <= 4 and all(isinstance(r, MapRoiRequest) and r.fill_gaps for r in first)
    assert [r.level for r in first] == sorted((r.level for r in first), reverse=True)  # type: ignore[attr-defined]
    total = len(first)
    while batch := receiver.poll(1001.0):
        total += len(batch)
    assert total == len(receiver.active_regions()) > 4
    for region in receiver.active_regions():  # the vehicle has nothing for any of them
        assert region.request_id is not None
        receiver.receive(MapRoiReply(region.request_id, region.level, 0), 1002.0)
    assert receiver.active_regions() == []
    receiver.receive(meta, 2000.0)  # same map, nothing was missing: no new round
    assert receiver.poll(2000.0) == []
    receiver.receive(MapMetadata(**{**{f: getattr(meta, f) for f in meta.__slots__}, "stamp": 900}), 2001.0)
    assert receiver.poll(2001.0)  # the map changed: gaps are checked again


def test_a_reply_to_an_earlier_copy_of_a_retried_request_closes_the_region() -> None:
    """On a TDMA link the vehicle's answer often comes back after topside retried the request
    under a new id (the retry timer is shorter than a cycle). Matching the answer only to the
    newest id left regions open forever, retried every minute with every answer discarded (seen
    in the demo: 1 m gaps that were asked for and never filled)."""
    receiver = BathymetryReceiver({"levels": LEVELS, "auto_fill": False})
    region = receiver.request_area(0, 0.0, 0.0, 20.0, 20.0, fill_gaps=True)[0]
    first = receiver.poll(0.0)
    assert len(first) == 1 and isinstance(first[0], MapRoiRequest)
    retry = receiver.poll(receiver.request_timeout + 1.0)  # no answer yet: retried, new id
    assert len(retry) == 1 and isinstance(retry[0], MapRoiRequest)
    assert retry[0].request_id != first[0].request_id
    # the answer to the first copy arrives now: the vehicle queued 3 subgrids
    receiver.receive(MapRoiReply(first[0].request_id, 0, 3), 70.0)
    assert receiver.active_regions() == [region]
    assert receiver.poll(71.0) == []  # it waits for them instead of asking again at once
    # then an answer to the first copy saying nothing more: the region is done
    receiver.receive(MapRoiReply(first[0].request_id, 0, 0), 200.0)
    assert receiver.active_regions() == []
    assert receiver.poll(10_000.0) == []
