"""Subgrid coding: exact round trip through the wire, size model, self-containment under loss."""

from __future__ import annotations

import random

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from coex_core import wire
from coex_core.errors import DecodeError
from coex_core.messages import (
    FrameHeader,
    PredictedSubgrid,
    Subgrid,
    SubgridContext,
    SubgridEncoding,
)
from coex_core.predicted import decode_predicted
from coex_plugins.bathymetry import (
    BathymetrySender,
    decode_subgrid,
    decode_subgrid_units,
    encode_subgrid,
    size_2022,
    subgrid_bits,
)

from ._bathy_data import survey_subgrids

ABSENT = np.iinfo(np.int64).min


def _encode(q: np.ndarray, present: np.ndarray, **kw: object) -> Subgrid:
    return encode_subgrid(q, present, level=1, ix=-3, iy=7, stamp=1000, resolution=1.0,
                          vertical_resolution=0.1, **kw)  # type: ignore[arg-type]


@st.composite
def blocks(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray]:
    side = draw(st.sampled_from([2, 4, 8, 8, 16]))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    ii, jj = np.mgrid[0:side, 0:side]
    base = draw(st.integers(-400_000, 400_000))
    noise = draw(st.sampled_from([0.0, 0.4, 2.0, 20.0]))
    slope = draw(st.floats(-40, 40))
    q = np.rint(base + slope * ii - 0.5 * slope * jj + rng.normal(0, noise, (side, side))).astype(np.int64)
    if draw(st.booleans()):
        q[rng.integers(side), rng.integers(side)] += draw(st.integers(-3000, 3000))  # a spike
    present = rng.random((side, side)) < draw(st.sampled_from([1.0, 0.7, 0.2, 0.0]))
    return q, present


@given(blocks())
def test_every_encoding_roundtrips_exactly_through_the_wire(block: tuple[np.ndarray, np.ndarray]) -> None:
    q, present = block
    for enc in SubgridEncoding:
        try:
            sg = _encode(q, present, encodings=(enc,))
        except ValueError:
            continue  # this encoding cannot code the block (e.g. too wide); another one can
        data = wire.encode(sg)
        assert len(data) == (subgrid_bits(sg) + 7) // 8
        back = wire.decode(data)
        assert back == sg
        units = decode_subgrid_units(back)
        np.testing.assert_array_equal(units[present], q[present])
        assert (units[~present] == ABSENT).all()
    if q.shape[0] == 16 and present.any() and np.ptp(q[present]) >= 64:
        return  # 256 rough cells may not fit one message; the sender only uses sides up to 8
    best = _encode(q, present)
    sizes = []
    for enc in SubgridEncoding:
        try:
            sizes.append(subgrid_bits(_encode(q, present, encodings=(enc,))))
        except ValueError:
            pass
    assert subgrid_bits(best) == min(sizes)


def test_each_encoding_wins_where_it_should() -> None:
    ii, jj = np.mgrid[0:8, 0:8]
    full = np.ones((8, 8), bool)
    flat = np.full((8, 8), -3000)
    assert _encode(flat, full).encoding == SubgridEncoding.OFFSET and _encode(flat, full).width == 0
    plane = -3000 + 7 * ii + 3 * jj
    assert _encode(plane, full).encoding == SubgridEncoding.PLANE
    rng = np.random.default_rng(0)
    walk = -3000 + np.cumsum(rng.integers(-1, 2, 64)).reshape(8, 8)
    walk[1::2] = walk[1::2, ::-1]  # a smooth serpentine path that no plane fits
    assert _encode(walk, full).encoding == SubgridEncoding.DELTA


def test_decode_gives_metres_and_nan() -> None:
    q = np.arange(16).reshape(4, 4) - 5000
    present = np.ones((4, 4), bool)
    present[0, 0] = False
    z = decode_subgrid(_encode(q, present))
    assert np.isnan(z[0, 0])
    assert z[3, 3] == pytest.approx((15 - 5000) * 0.1)


def test_size_2022_is_one_or_two_bytes_per_cell() -> None:
    full = np.ones((8, 8), bool)
    assert size_2022(full, np.zeros((8, 8))) == 80
    wide = np.zeros((8, 8))
    wide[0, 0] = 400
    assert size_2022(full, wide) == 144


def _survey_subgrids(levels: int = 3) -> tuple[BathymetrySender, list[Subgrid | PredictedSubgrid]]:
    return survey_subgrids(64.0, 256, levels)  # type: ignore[return-value]


def test_a_lost_subgrid_leaves_every_other_subgrid_decodable() -> None:
    sender, subgrids = _survey_subgrids()
    assert len(subgrids) > 50
    frames = []
    batch: list[Subgrid | PredictedSubgrid] = []
    for sg in subgrids:
        if sum(wire.encoded_size(m) for m in [*batch, sg]) > 250:
            frames.append((batch, wire.pack(batch, 256, FrameHeader(src=2, dst=1))))
            batch = []
        batch.append(sg)
    frames.append((batch, wire.pack(batch, 256, FrameHeader(src=2, dst=1))))
    rng = random.Random(5)
    lost = set(rng.sample(range(len(frames)), len(frames) // 3))
    for k, (sent, frame) in enumerate(frames):
        if k in lost:
            continue
        got = wire.unpack(frame)
        assert list(got) == sent
        for sg in got:
            # nothing acknowledged: every subgrid is coded on its own (a Subgrid, or a
            # PredictedSubgrid from its own base)
            if isinstance(sg, PredictedSubgrid):
                assert sg.context == SubgridContext.NONE
                cells = decode_predicted(sg)
            else:
                assert isinstance(sg, Subgrid)
                cells = decode_subgrid(sg)
            blk = sender.map.block(sg.level, sg.ix, sg.iy)
            assert blk is not None
            expect = np.where(blk.count > 0, np.rint(blk.mean / 0.1) * 0.1, np.nan)
            np.testing.assert_allclose(cells, expect, atol=1e-9, equal_nan=True)


def test_a_corrupted_subgrid_is_a_decode_error_not_a_crash() -> None:
    _, subgrids = _survey_subgrids()
    rng = random.Random(2)
    for sg in subgrids[:40]:
        data = bytearray(wire.encode(sg))
        for _ in range(5):
            bad = bytearray(data)
            bad[rng.randrange(1, len(bad))] ^= 1 << rng.randrange(8)
            try:
                wire.decode(bytes(bad))
            except DecodeError:
                pass
        with pytest.raises(DecodeError):
            wire.decode(bytes(data[:-1]) if data[-1] else bytes(data[:-2]))
