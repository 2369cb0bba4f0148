"""A time-series chunk whose coefficient range overlaps one already held of its pass is refused
(adding both would count the overlap twice: spec/payloads.md section 2.4)."""

from __future__ import annotations

import dataclasses

import numpy as np

from coex_core.messages import TimeSeriesChannel, TimeSeriesChunk
from coex_plugins.timeseries import TimeSeriesModality, codec
from coex_plugins.timeseries.conformance import companion


def test_an_overlapping_chunk_of_a_pass_is_refused_not_added_twice() -> None:
    c = companion()
    sender = TimeSeriesModality().sender(c.sender_config())
    for t, data in c.sample_inputs():
        sender.ingest(data, t)
    now = c.sample_inputs()[-1][0] + 1000.0
    msgs = []
    for i in range(400):
        msgs += sender.fill(240, now + i)
    receiver = TimeSeriesModality().receiver()
    for m in msgs:
        if isinstance(m, TimeSeriesChannel):
            receiver.receive(m, now)
    whole = next(m for m in msgs if isinstance(m, TimeSeriesChunk) and m.first is None and m.level == 0
                 and not m.samples)
    receiver.receive(whole, now)
    (name,) = [n for n in ("methane", "temperature") if receiver.bounds(n)][:1]
    before = receiver.series(name).values.copy()
    ignored = receiver.ignored
    overlap = dataclasses.replace(whole, first=1, end=3, data=codec.encode_codes(np.array([5, -5]), 0))
    assert receiver.receive(overlap, now) == []
    assert receiver.ignored == ignored + 1
    assert np.array_equal(before, receiver.series(name).values)
