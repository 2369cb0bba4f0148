"""Behaviour of the time-series modality: overview, spikes first, bounds, requests, acks, CSV."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from coex_core import state, wire
from coex_core.errors import CoexError, ConfigError, RequestRejected
from coex_core.messages import (
    Message,
    TimeSeriesAck,
    TimeSeriesChannel,
    TimeSeriesChunk,
    TimeSeriesPart,
    TimeSeriesRequest,
    Wavelet,
)
from coex_core.registry import load_modality
from coex_core.timefmt import unwrap
from coex_plugins.timeseries import (
    InvalidSamples,
    Samples,
    TimeSeriesModality,
    TimeSeriesReceiver,
    TimeSeriesSender,
    synth,
)
from coex_plugins.timeseries.receiver import sample_series

T0 = 1_700_000_000.0


def _sender(series: list[synth.SynthSeries], **config: Any) -> TimeSeriesSender:
    return TimeSeriesSender({"channels": [s.channel() for s in series], **config})


def _feed(sender: TimeSeriesSender, series: list[synth.SynthSeries], batch: int = 60) -> float:
    n = series[0].times.size
    for i in range(0, n, batch):
        j = min(i + batch, n)
        sender.ingest({s.name: (s.times[i:j], s.values[i:j]) for s in series}, float(series[0].times[j - 1]))
    now = float(series[0].times[-1])
    sender.flush(now)
    return now


def _drain(sender: TimeSeriesSender, receiver: TimeSeriesReceiver, now: float,
           sent: list[Message] | None = None, budget: int = 251) -> float:
    for _ in range(10_000):
        for reply in receiver.poll(now):
            sender.handle(reply, now)
        out = sender.fill(budget, now)
        if not out:
            return now
        for m in out:
            assert wire.decode(wire.encode(m)) == m
            if sent is not None:
                sent.append(m)
            receiver.receive(m, now)
        now += 1.0
    raise AssertionError("the sender never went idle")


@pytest.fixture(scope="module")
def record() -> list[synth.SynthSeries]:
    return synth.dataset(duration=7200.0, t0=T0, seed=4)


def test_entry_point_loads_the_modality() -> None:
    assert load_modality("timeseries") is TimeSeriesModality


def test_overview_covers_every_channel_within_its_bound(record: list[synth.SynthSeries]) -> None:
    sender = _sender(record)
    rx = TimeSeriesReceiver()
    now = _drain(sender, rx, _feed(sender, record))
    for s in record:
        series = rx.series(s.name)
        assert series.unit == s.unit
        assert series.times.size == s.times.size
        np.testing.assert_allclose(series.times, s.times, atol=1e-6)
        err = np.abs(series.values - s.values)
        assert np.all(err <= series.bounds), f"{s.name}: error above the stated bound"
        # the overview is coarse (a few noise sigmas and more) but far from useless
        assert 0 < series.max_bound < 0.05 * (s.values.max() - s.values.min())
    assert sender.pending_bytes() == 0 and sender.unacked() == 0
    assert now > T0


def test_spikes_arrive_before_the_rest_of_the_overview(record: list[synth.SynthSeries]) -> None:
    methane = record[0]
    sender = _sender([methane])
    sent: list[Message] = []
    _drain(sender, TimeSeriesReceiver(), _feed(sender, [methane]), sent)
    total = sum(wire.encoded_size(m) for m in sent)
    rx = TimeSeriesReceiver()
    used = 0
    for m in sent:
        rx.receive(m, T0 + 7200)
        used += wire.encoded_size(m)
        series = rx.series("methane") if rx.products() and rx.bounds("methane") else None
        if series is None:
            continue
        got, _ = sample_series(series, np.array([sp.time for sp in methane.spikes]))
        idx = np.searchsorted(methane.times, [sp.time for sp in methane.spikes])
        above = got - methane.baseline[idx]
        if np.all(np.nan_to_num(above, nan=-1) >= 0.5 * np.array([sp.height for sp in methane.spikes])):
            break
    else:
        raise AssertionError("spikes never all visible")
    assert used < 0.5 * total, f"spikes visible only after {used} of {total} B"


def test_every_chunk_decodes_on_its_own(record: list[synth.SynthSeries]) -> None:
    sender = _sender(record[:1])
    sent: list[Message] = []
    _drain(sender, TimeSeriesReceiver(), _feed(sender, record[:1]), sent)
    chunks = [m for m in sent if isinstance(m, TimeSeriesChunk) and m.level == 0]
    assert len(chunks) >= 3
    for chunk in chunks:
        rx = TimeSeriesReceiver()  # no registration, nothing else
        products = rx.receive(chunk, T0 + 7200)
        assert products and products[0].data.times.size == chunk.count
        assert math.isfinite(products[0].data.max_bound)
        t0 = unwrap(chunk.start, T0 + 7200) + chunk.offset
        assert products[0].data.times[0] == pytest.approx(t0)


def test_lost_chunk_bound_uses_complete_prefix_and_recovers(record: list[synth.SynthSeries]) -> None:
    methane = record[0]
    sender = _sender([methane], max_latency=1e9)
    now = _feed(sender, [methane])
    rx = TimeSeriesReceiver()
    now = _drain(sender, rx, now)
    before = rx.bounds("methane")
    rx.request("methane", T0, T0 + 7200, 0.05)
    rx.request("methane", T0, T0 + 7200, 0.02)
    for m in rx.poll(now):
        sender.handle(m, now)
    refinements = [m for m in sender.fill(10_000, now) if isinstance(m, TimeSeriesChunk)]
    assert refinements and all(m.level >= 1 for m in refinements)
    lost, rest = refinements[0], refinements[1:]
    for m in rest:
        rx.receive(m, now)
    block = [b for b in rx.bounds("methane") if abs(b[0] - (unwrap(lost.start, now) + lost.offset)) < 1]
    assert block
    # the first refinement chunk is the first new pass of its block: without it the block keeps
    # the bound of its complete passes, although later passes of the block did arrive
    assert any((m.start, m.offset) == (lost.start, lost.offset) for m in rest)
    prefix_bound = next(b for b in before if b[0] == block[0][0])[2]
    assert block[0][2] == prefix_bound
    # the vehicle resends what was not acked, and then every bound meets the request
    for reply in rx.poll(now):
        sender.handle(reply, now)
    now = _drain(sender, rx, now + sender.retry_after)
    assert all(b <= 0.02 for _, _, b in rx.bounds("methane"))
    s = rx.series("methane")
    assert np.all(np.abs(s.values - methane.values) <= s.bounds)


def test_request_refines_only_the_window_and_never_resends_held_data(record: list[synth.SynthSeries]) -> None:
    methane = record[0]
    sender = _sender([methane], block_samples=1024)
    rx = TimeSeriesReceiver()
    now = _drain(sender, rx, _feed(sender, [methane]))
    before = {b[0]: b[2] for b in rx.bounds("methane")}
    req = rx.request("methane", T0 + 3000, T0 + 4000, 0.03)
    assert isinstance(req, TimeSeriesRequest) and req.max_error == pytest.approx(0.03)
    sent: list[Message] = []
    now = _drain(sender, rx, now, sent)
    assert sent and all(isinstance(m, TimeSeriesChunk) and m.level >= 1 for m in sent)
    after = rx.bounds("methane")
    for start, end, bound in after:
        if end >= T0 + 3000 and start <= T0 + 4001:
            assert bound <= 0.03
        else:
            assert bound == before[start]
    assert rx.pending_requests() == []
    # "finer detail": no max_error means four times finer than the worst bound held there
    worst = max(b for s, e, b in after if e >= T0 + 5000 and s <= T0 + 5500)
    req2 = rx.request("methane", T0 + 5000, T0 + 5500)
    assert req2.max_error == pytest.approx(worst / 4, rel=1e-6)
    _drain(sender, rx, now)
    assert max(b for s, e, b in rx.bounds("methane") if e >= T0 + 5000 and s <= T0 + 5500) <= worst / 4


def test_request_for_recent_data_closes_the_open_block(record: list[synth.SynthSeries]) -> None:
    methane = record[0]
    sender = _sender([methane], max_latency=1e9, spike_close=0)
    now = float(methane.times[999])
    sender.ingest(Samples("methane", methane.times[:1000], methane.values[:1000]), now)
    rx = TimeSeriesReceiver()
    _drain(sender, rx, now)
    assert not rx.bounds("methane") if rx.products() else True
    sender.handle(TimeSeriesRequest(1, 0, int(methane.times[900]) % 2**18, int(now) % 2**18, 0.05), now)
    rx2 = TimeSeriesReceiver()
    _drain(sender, rx2, now)
    assert rx2.bounds(0) and max(b for *_, b in rx2.bounds(0)) <= 0.05  # by id: rx2 missed the registration


def test_bad_requests_are_rejected_and_change_nothing(record: list[synth.SynthSeries]) -> None:
    sender = _sender(record)
    now = _feed(sender, record[:1] + record[1:])
    pending = sender.pending_bytes()
    bad = [
        TimeSeriesRequest(1, 7, 0, 10, 1.0),  # unknown channel
        TimeSeriesRequest(2, 0, 0, 10, 0.0001),  # below half the resolution (0.001 nM)
        TimeSeriesAck(9, True, ()),  # unknown channel
        TimeSeriesChannel(0, "x", "", 0.0, 1.0, 0.1),  # not a request
    ]
    for m in bad:
        with pytest.raises(RequestRejected):
            sender.handle(m, now)
    assert sender.pending_bytes() == pending
    rx = TimeSeriesReceiver()
    with pytest.raises(RequestRejected):
        rx.request("nothing", T0, T0 + 10, 1.0)
    _drain(sender, rx, now)
    with pytest.raises(RequestRejected):
        rx.request("methane", T0 + 10, T0, 1.0)
    with pytest.raises(RequestRejected):
        rx.request("methane", T0, T0 + 10, 0.0001)


def test_bad_samples_raise_and_lose_nothing(record: list[synth.SynthSeries]) -> None:
    methane = record[0]
    good = _sender([methane])
    t, v = methane.times[:2000], methane.values[:2000]
    good.ingest({"methane": (t, v)}, float(t[-1]))
    checked = _sender([methane])
    checked.ingest({"methane": (t, v)}, float(t[-1]))
    bad_batches: list[Any] = [
        {"methane": (t[-10:] + 100, v[-10:] + 5000.0)},  # above the channel's range
        {"methane": (t[:10], v[:10])},  # times go backwards
        {"methane": (t[-10:] + 100, v[-11:])},  # shape mismatch
        {"oxygen": (t[-10:] + 100, v[-10:])},  # unknown channel
        {"methane": (np.array([np.inf]), np.array([1.0]))},
        "not samples",
    ]
    for batch in bad_batches:
        with pytest.raises(InvalidSamples) as info:
            checked.ingest(batch, float(t[-1]))
        assert isinstance(info.value, CoexError)
    for s in (good, checked):
        s.flush(float(t[-1]))
    assert good.blocks("methane") == checked.blocks("methane")
    assert good.pending_bytes() == checked.pending_bytes() > 0


def test_irregular_times_and_gaps(record: list[synth.SynthSeries]) -> None:
    rng = np.random.default_rng(8)
    n = 3000
    t = T0 + np.cumsum(rng.uniform(0.6, 1.4, n))  # irregular, mean period 1 s
    t = np.concatenate([t[:1200], t[1500:] + 5000.0])  # a long gap: a new block starts after it
    v = 10 + np.sin((t - T0) / 300.0)
    v[100:110] = np.nan  # dropouts are interpolated inside a block
    sender = TimeSeriesSender({"channels": [{"name": "o2", "unit": "umol/kg", "lo": 0, "hi": 400,
                                             "resolution": 0.001}]})
    sender.ingest(Samples("o2", t, v), float(t[-1]))
    sender.flush(float(t[-1]))
    blocks = sender.blocks("o2")
    assert len(blocks) >= 2 and blocks[1][0] >= t[1199] + 4000
    assert all(abs(p - 1.0) <= 0.02 for _, _, p in blocks)
    rx = TimeSeriesReceiver()
    _drain(sender, rx, float(t[-1]))
    rx.request("o2", float(t[0]), float(t[-1]), 0.002)
    _drain(sender, rx, float(t[-1]) + 10)
    s = rx.series("o2")
    ok = np.isfinite(v)
    got, bound = sample_series(s, t[ok])
    # on a grid of the mean period, each sample moves by at most half a period: slope * 0.5 s
    slope = 1 / 300.0
    assert np.all(np.abs(got - v[ok]) <= bound + slope * 0.5 + 1e-9)
    inside_gap = sample_series(s, np.array([t[1199] + 2000.0]))[0]
    assert np.isnan(inside_gap).all()


def test_unacked_chunks_are_resent_and_acked_ones_are_not(record: list[synth.SynthSeries]) -> None:
    sender = _sender(record[:1], retry_after=60.0)
    now = _feed(sender, record[:1])
    first = sender.fill(10_000, now)
    assert isinstance(first[0], TimeSeriesChannel) and len(first) > 2
    assert sender.fill(10_000, now + 10) == []
    again = sender.fill(10_000, now + 61)
    assert again == first
    rx = TimeSeriesReceiver()
    for m in again:
        rx.receive(m, now + 61)
    acks = rx.poll(now + 61)
    assert acks and all(isinstance(a, TimeSeriesAck) for a in acks)
    for a in acks:
        sender.handle(a, now + 62)
    assert sender.fill(10_000, now + 500) == [] and sender.pending_bytes() == 0
    # a duplicate is acked again (its first ack may have been lost) but changes no product
    assert rx.receive(again[1], now + 600) == []
    re_ack = rx.poll(now + 600)
    assert isinstance(re_ack[0], TimeSeriesAck) and re_ack[0].parts == (
        TimeSeriesPart(again[1].start, again[1].offset, again[1].level, 0),)


def test_latency_closes_blocks_so_the_overview_flows(record: list[synth.SynthSeries]) -> None:
    methane = record[0]
    sender = _sender([methane], max_latency=300.0)
    sender.ingest(Samples("methane", methane.times[:200], methane.values[:200]), float(methane.times[199]))
    assert sender.blocks("methane") == []
    out = sender.fill(251, float(methane.times[0]) + 301)
    assert any(isinstance(m, TimeSeriesChunk) and m.count == 200 for m in out)


def test_fill_respects_small_budgets(record: list[synth.SynthSeries]) -> None:
    sender = _sender(record[:1], block_samples=512)
    now = _feed(sender, record[:1])
    for budget in (0, 12, 13, 30, 64):
        out = sender.fill(budget, now)
        assert sum(wire.encoded_size(m) for m in out) <= budget


def test_csv_export(tmp_path: Any, record: list[synth.SynthSeries]) -> None:
    sender = _sender(record)
    rx = TimeSeriesReceiver()
    _drain(sender, rx, _feed(sender, record))
    text = rx.to_csv(tmp_path / "r.csv", times=record[0].times[:5])
    lines = (tmp_path / "r.csv").read_text().splitlines()
    assert text.splitlines() == lines
    assert lines[0] == "time,methane,temperature,methane_bound,temperature_bound"
    row = lines[1].split(",")
    assert float(row[0]) == pytest.approx(T0)
    assert abs(float(row[1]) - record[0].values[0]) <= float(row[3])
    assert abs(float(row[2]) - record[1].values[0]) <= float(row[4])
    assert len(lines) == 6


def test_invalid_configuration() -> None:
    base = {"name": "m", "lo": 0, "hi": 1, "resolution": 0.1}
    for config in ({"channels": [{**base, "hi": -1}]}, {"channels": [{**base, "resolution": 0}]},
                   {"channels": [base, base]}, {"channels": [{"name": "m"}]}, {"wavelet": "sym99"},
                   {"block_samples": 8}, {"block_samples": 5000}, {"retry_after": -1}, {"alert_fraction": 1.5},
                   {"bogus": 1}):
        with pytest.raises(ConfigError):
            TimeSeriesSender(config)
    with pytest.raises(ConfigError):
        TimeSeriesReceiver({"request_retry": 0})


def test_receiver_retries_unsatisfied_requests() -> None:
    rx = TimeSeriesReceiver({"request_retry": 50.0, "request_tries": 3})
    rx.receive(TimeSeriesChannel(0, "m", "nM", 0.0, 10.0, 0.001), T0)
    assert isinstance(rx.poll(T0)[0], TimeSeriesAck)
    req = rx.request(0, T0, T0 + 100, 0.01)
    assert rx.poll(T0) == [req]
    assert rx.poll(T0 + 10) == []
    assert rx.poll(T0 + 60) == [req]
    assert rx.poll(T0 + 120) == [req]
    assert rx.poll(T0 + 200) == []  # gave up after three tries


def test_receiver_survives_any_wire_valid_chunk() -> None:
    """Chunks that are valid on the wire but carry nonsense never make the receiver raise."""
    rng = np.random.default_rng(12)
    rx = TimeSeriesReceiver()
    for i in range(250):
        count = int(rng.integers(1, 4097))
        partial = bool(rng.integers(0, 2))
        first = int(rng.integers(0, 8000)) if partial else None
        end = int(rng.integers(1, 8193)) if partial else None
        data = rng.integers(0, 256, int(rng.integers(0, 60)), dtype=np.uint8).tobytes()
        chunk = TimeSeriesChunk(int(rng.integers(0, 3)), int(rng.integers(0, 50)), 0.0, 1.0, count,
                                list(Wavelet)[int(rng.integers(0, 4))], int(rng.integers(0, 4)),
                                bool(rng.integers(0, 2)), int(rng.integers(0, 256)), int(rng.integers(0, 256)),
                                first, end, data)
        assert wire.decode(wire.encode(chunk)) == chunk
        rx.receive(chunk, T0 + i)
    rx.poll(T0 + 500)
    for p in rx.products():
        assert p.kind == "series"
    assert rx.ignored > 0


def test_a_spike_closes_its_block_early_so_the_alert_is_prompt() -> None:
    methane = synth.methane(duration=7200.0, t0=T0, seed=4)
    sender = _sender([methane], max_latency=3600.0, spike_close=60.0)
    rx = TimeSeriesReceiver()
    first_seen: dict[int, float] = {}
    for i in range(0, methane.times.size, 10):
        now = float(methane.times[min(i + 10, methane.times.size) - 1])
        sender.ingest(Samples("methane", methane.times[i:i + 10], methane.values[i:i + 10]), now)
        _drain(sender, rx, now)
        for k, sp in enumerate(methane.spikes):
            if k not in first_seen and any(s <= sp.time <= e for s, e, _ in rx.bounds("methane")):
                first_seen[k] = now
    assert len(first_seen) == len(methane.spikes)
    for k, sp in enumerate(methane.spikes):
        # the spike's own samples, 60 s of tail and one 10 s batch; not the 3600 s latency
        assert first_seen[k] - sp.time <= sp.width + 60 + 10 + 5, (k, first_seen[k] - sp.time)
    # and only spikes close blocks early: the rest still closes after max_latency
    assert len(sender.blocks("methane")) <= 2 + 2 * len(methane.spikes)


def test_dives_longer_than_the_stamp_period() -> None:
    """Stamps repeat every 2^18 s (72.8 h); blocks of an 80 h dive stay apart even when a late
    block starts on the very stamp of an early one (4096 s blocks: 2^18 s is 64 of them)."""
    period = 64.0
    t = T0 + period * np.arange(int(80 * 3600 / period))
    v = 5 + np.sin((t - T0) / 20000.0)
    sender = TimeSeriesSender({"channels": [{"name": "o2", "lo": 0, "hi": 20, "resolution": 0.01,
                                             "period": period}], "block_samples": 64, "max_latency": 1e9})
    rx = TimeSeriesReceiver()
    for i in range(0, t.size, 30):
        now = float(t[min(i + 30, t.size) - 1])
        sender.ingest(Samples("o2", t[i:i + 30], v[i:i + 30]), now)
        _drain(sender, rx, now)
    sender.flush(float(t[-1]))
    _drain(sender, rx, float(t[-1]))
    want = [start for start, _, _ in sender.blocks("o2")]
    got = [start for start, _, _ in rx.bounds("o2")]
    assert len(want) > 65 and got == pytest.approx(want)
    assert want[64] - want[0] == 2**18
    s = rx.series("o2")
    assert np.all(np.abs(s.values - v) <= s.bounds)


def test_spare_work_refines_the_series_below_the_overview(record: list[synth.SynthSeries]) -> None:
    """Spare capacity (``spare``) sends refinement passes, newest block first, that topside
    decodes into a series within a smaller stated bound, still true against the samples; the
    background (``fill``) never sends them."""
    methane = record[0]
    sender = _sender([methane])
    rx = TimeSeriesReceiver()
    now = _drain(sender, rx, _feed(sender, [methane]))
    overview = rx.series(methane.name).max_bound
    assert sender.fill(251, now + 1.0) == []  # the background is done
    assert sender.spare_bytes() > 0
    for i in range(400):
        out = sender.spare(251, now + 2.0 + i)
        assert sum(wire.encoded_size(m) for m in out) <= 251
        for m in out:
            rx.receive(m, now + 2.0 + i)
        for reply in rx.poll(now + 2.0 + i):
            sender.handle(reply, now + 2.0 + i)
        if not out:
            break
    series = rx.series(methane.name)
    assert series.max_bound < overview / 3
    assert np.all(np.abs(series.values - methane.values) <= series.bounds)
    assert sender.fill(251, now + 1000.0) == []


def test_a_done_block_keeps_only_its_place_and_bound(record: list[synth.SynthSeries]) -> None:
    """Once a block has no pass left to make and topside acknowledged all its chunks, the sender
    drops its samples, reconstruction, pass codes and chunks: nothing can need them (acked
    chunks are never sent again), and the vehicle's saved state, written before every
    transmission, no longer grows with the length of the dive (the soak: 10 of the vehicle's
    13 MB after 23 hours). Its place and bound stay; a request over it sends nothing."""
    methane = record[0]
    sender = _sender([methane])
    rx = TimeSeriesReceiver()
    now = _drain(sender, rx, _feed(sender, [methane]))
    blocks = sender.blocks(methane.name)
    assert len(blocks) >= 2 and not any(b.done for b in sender._channels[0].blocks)  # more passes to make
    overview_state = len(state.dumps(sender))
    for i in range(2000):  # spare capacity until every pass is made and acknowledged
        t = now + 1.0 + i
        out = sender.spare(251, t)
        for m in out:
            rx.receive(m, t)
        for reply in rx.poll(t):
            sender.handle(reply, t)
        if not out and sender.spare_bytes() == 0:
            break
    now += 2001.0
    assert all(b.done for b in sender._channels[0].blocks)
    assert sender.blocks(methane.name) == blocks
    held = {s: b for s, _, b in rx.bounds(methane.name)}
    assert [(s, b) for s, _, b in sender.bound(methane.name)] == [(s, held[s]) for s, *_ in blocks]
    assert max(held.values()) <= methane.channel()["resolution"] / 2 * (1 + 1e-6)
    assert len(state.dumps(sender)) < overview_state / 10
    # a request over done blocks: nothing to send, nothing broken
    rx.request(methane.name, blocks[0][0], blocks[-1][0] + 10.0, methane.channel()["resolution"] / 2)
    assert _drain(sender, rx, now) == now and sender.fill(251, now) == [] and sender.spare(251, now) == []
    # saved and restored as it is; new samples still flow
    again = state.loads(state.dumps(sender))
    assert again.blocks(methane.name) == blocks and again.bound(methane.name) == sender.bound(methane.name)
    later = methane.times[-1] + 1.0 + np.arange(600.0)
    again.ingest(Samples(methane.name, later, np.full(600, float(methane.values[-1]))), float(later[-1]))
    again.flush(float(later[-1]))
    assert len(again.blocks(methane.name)) == len(blocks) + 1 and again.fill(251, float(later[-1]))


def test_topside_keeps_each_pass_in_the_narrowest_integer_codes(record: list[synth.SynthSeries]) -> None:
    """Topside keeps every pass of the dive's blocks and saves them in every snapshot: their codes
    are held in the narrowest integer type (mostly int8), not int64, with the same series, before
    and after a save and restore (the saved receiver is a third of the size on this record)."""
    methane = record[0]
    sender = _sender([methane])
    rx = TimeSeriesReceiver()
    now = _drain(sender, rx, _feed(sender, [methane]))
    for i in range(2000):
        out = sender.spare(251, now + 1.0 + i)
        for m in out:
            rx.receive(m, now + 1.0 + i)
        for reply in rx.poll(now + 1.0 + i):
            sender.handle(reply, now + 1.0 + i)
        if not out and sender.spare_bytes() == 0:
            break
    codes = [p.codes for ch in rx._channels.values() for b in ch.blocks.values()
             for parts in b.passes.values() for p in parts.values()]
    assert codes and max(c.itemsize for c in codes) <= 2
    assert sum(c.itemsize == 1 for c in codes) > len(codes) / 2
    series = rx.series(methane.name)
    assert np.all(np.abs(series.values - methane.values) <= series.bounds)
    again = state.loads(state.dumps(rx)).series(methane.name)
    assert np.array_equal(again.values, series.values) and np.array_equal(again.bounds, series.bounds)


def test_keep_archives_old_blocks_to_csv_and_bounds_memory(tmp_path: Any, record: list[synth.SynthSeries]) -> None:
    """With ``keep`` and ``out_dir`` topside holds a window of each series in memory (and in its
    saved state) and appends every older block to ``series_<name>.csv``: together they hold
    every sample the vehicle sent, within its bound; a chunk of an archived block is acked and
    not taken; the archive and the window survive a save and restore."""
    sender = _sender(record)
    rx = TimeSeriesReceiver({"keep": 1800.0, "out_dir": str(tmp_path)})
    whole = TimeSeriesReceiver()  # the same messages, every block kept
    sent: list[Message] = []
    now = _drain(sender, rx, _feed(sender, record), sent)
    for m in sent:
        whole.receive(m, now)
    for s in record:
        path = rx.archive_path(s.name)
        assert path is not None and path.exists()
        assert path.read_text().splitlines()[0] == "time,value,bound,block_start"
        live = rx.series(s.name)
        newest = live.times.max()
        assert live.times.min() >= newest - 1800.0 - 1300.0  # a window (blocks of at most 1200 s)
        assert live.times.size < s.times.size / 2
        held = rx.held(s.name)
        np.testing.assert_allclose(held.times, s.times, atol=1e-3)
        assert np.all(np.abs(held.values - s.values) <= held.bounds + 1e-6)
        assert [round(a, 3) for a, _, _ in rx.bounds(s.name)] == [round(a, 3) for a, _, _ in whole.bounds(s.name)]
    assert len(state.dumps(rx)) < len(state.dumps(whole)) / 2
    # a chunk of an archived block again: acked, not taken, nothing changes
    first = next(m for m in sent if isinstance(m, TimeSeriesChunk))
    before, late = rx.held(record[0].name).times.size, rx.archived_late
    rx.poll(now)
    assert rx.receive(first, now) == []
    assert rx.archived_late == late + 1 and any(isinstance(a, TimeSeriesAck) and a.parts for a in rx.poll(now))
    again = state.loads(state.dumps(rx))
    assert again.keep == 1800.0 and again.held(record[0].name).times.size == before
    with pytest.raises(ConfigError, match="out_dir"):
        TimeSeriesReceiver({"keep": 600})
    with pytest.raises(ConfigError, match="keep: -1 is not above 0 s"):
        TimeSeriesReceiver({"keep": -1, "out_dir": str(tmp_path)})


def test_a_receiver_saved_before_the_archive_loads_with_every_block_kept(record: list[synth.SynthSeries]) -> None:
    """Version 1 of the saved receiver (no ``keep``): upgraded, it keeps every block as before."""
    sender = _sender(record[:1])
    rx = TimeSeriesReceiver()
    _drain(sender, rx, _feed(sender, record[:1]))
    bounds = rx.bounds(record[0].name)
    for k in ("keep", "out_dir", "_archived", "_archived_floor", "archived_late"):
        delattr(rx, k)
    blob = state.dumps(rx).replace(b'"timeseries.Receiver":2', b'"timeseries.Receiver":1')
    back = state.loads(blob)
    assert back.keep is None and back.out_dir is None and back.archived_late == 0
    assert back.bounds(record[0].name) == bounds
