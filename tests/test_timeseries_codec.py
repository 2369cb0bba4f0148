"""The time-series wavelet code: transforms, passes and the coefficient bit code."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from coex_core.messages import Wavelet
from coex_plugins.timeseries import codec


def test_codes_bracket_values() -> None:
    for v in np.geomspace(1e-5, 1e3, 97):
        f, c = codec.floor_code(float(v)), codec.ceil_code(float(v))
        assert codec.code_value(f) <= v * (1 + 1e-12)
        assert codec.code_value(c) >= v * (1 - 1e-12)
        assert c - f in (0, 1)
    assert codec.floor_code(0.0) == 0 and codec.ceil_code(1e9) == 255


@pytest.mark.parametrize("wavelet", list(Wavelet))
@pytest.mark.parametrize("count", [1, 2, 7, 64, 1000, 4096])
def test_transform_is_perfect(wavelet: Wavelet, count: int) -> None:
    x = np.random.default_rng(count).normal(size=count).cumsum()
    flat = codec.analyse(x, wavelet)
    assert flat.size == codec.layout(count, wavelet).total
    np.testing.assert_allclose(codec.synthesise(flat, count, wavelet), x, atol=1e-9)


def _random_codes(rng: np.random.Generator, n: int, density: float, scale: float) -> np.ndarray:
    codes = np.zeros(n, dtype=np.int64)
    idx = rng.random(n) < density
    codes[idx] = np.rint(rng.laplace(0, scale, idx.sum())).astype(np.int64)
    return codes


@pytest.mark.parametrize("seed", range(8))
def test_coefficient_code_roundtrip(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 3000))
    codes = _random_codes(rng, n, float(rng.uniform(0.001, 1.0)), float(rng.choice([0.5, 3, 200, 1e5])))
    n_approx = int(rng.integers(0, min(n, 30) + 1))
    for dpcm in (False, True):
        data = codec.encode_codes(codes, n_approx, dpcm=dpcm)
        np.testing.assert_array_equal(codec.decode_codes(data, n, n_approx), codes)
    assert codec.encoded_bits(codes) == pytest.approx(8 * len(codec.encode_codes(codes)), abs=7)


def test_coefficient_code_edge_cases() -> None:
    for codes in (np.zeros(1, dtype=np.int64), np.zeros(500, dtype=np.int64), np.array([-1]),
                  np.array([0, 0, 0, 2**40]), np.arange(-50, 50)):
        data = codec.encode_codes(codes)
        np.testing.assert_array_equal(codec.decode_codes(data, codes.size), codes)


def test_coefficient_code_rejects_malformed() -> None:
    codes = np.array([0, 3, 0, -7, 0, 0, 1, 0], dtype=np.int64)
    data = codec.encode_codes(codes)
    with pytest.raises(codec.CodeError):
        codec.decode_codes(b"", 8)
    for k in range(1, len(data)):
        try:
            out = codec.decode_codes(data[:k], 8)
        except codec.CodeError:
            continue
        assert not np.array_equal(out, codes)  # a shorter prefix never passes as the original
    with pytest.raises(codec.CodeError):
        codec.decode_codes(data, 5)  # an index beyond the range
    with pytest.raises(codec.CodeError):
        codec.decode_codes(data + b"\x00", 8)  # a whole byte of padding is not canonical
    with pytest.raises(codec.CodeError):
        codec.decode_codes(codec.encode_codes(codes, 4, dpcm=True), 8, 4, allow_dpcm=False)
    rng = np.random.default_rng(5)
    for _ in range(300):  # random garbage raises CodeError or decodes; nothing else
        junk = rng.integers(0, 256, int(rng.integers(1, 40)), dtype=np.uint8).tobytes()
        try:
            codec.decode_codes(junk, int(rng.integers(1, 100)), 3)
        except codec.CodeError:
            pass


@pytest.mark.parametrize("wavelet", [Wavelet.HAAR, Wavelet.BIOR22, Wavelet.BIOR44])
def test_make_pass_meets_target_and_states_bound(wavelet: Wavelet) -> None:
    rng = np.random.default_rng(1)
    x = np.cumsum(rng.normal(0, 0.05, 1500)) + rng.normal(0, 0.01, 1500)
    x[700:705] += 5.0
    recon = np.zeros_like(x)
    previous = np.inf
    for target in (1.0, 0.1, 0.02, 0.004):
        p, recon = codec.make_pass(x, recon, target, wavelet)
        achieved = float(np.max(np.abs(x - recon)))
        assert achieved <= target
        assert achieved <= codec.code_value(p.error)
        assert codec.code_value(p.error) <= target * 2 ** (1 / 8) + 1e-12
        assert achieved < previous
        previous = achieved


def test_passes_sum_to_the_reconstruction() -> None:
    rng = np.random.default_rng(2)
    x = np.sin(np.linspace(0, 9, 800)) + rng.normal(0, 0.02, 800)
    recon = np.zeros_like(x)
    flat = np.zeros(codec.layout(x.size, Wavelet.BIOR44).total)
    direct = np.zeros(x.size)
    kinds = []
    for target in (0.5, 0.05, 0.01, 0.002):
        p, recon = codec.make_pass(x, recon, target, Wavelet.BIOR44)
        kinds.append(p.samples)
        if p.samples:
            direct += p.coefficients()
        else:
            flat += p.coefficients()
        np.testing.assert_allclose(codec.synthesise(flat, x.size, Wavelet.BIOR44) + direct, recon, atol=1e-9)
    # coarse passes are wavelet passes; near the noise level coding samples wins
    assert kinds[0] is False and kinds[-1] is True


def test_split_pass_pieces_fit_cover_and_decode_alone() -> None:
    rng = np.random.default_rng(3)
    codes = _random_codes(rng, 4133, 0.3, 40.0)
    lay_approx = 12
    pieces = codec.split_pass(codes, lay_approx, 100)
    assert len(pieces) > 5
    pos = 0
    for first, end, data in pieces:
        assert first == pos and end > first and len(data) <= 100
        got = codec.decode_codes(data, end - first, lay_approx, allow_dpcm=first == 0)
        np.testing.assert_array_equal(got, codes[first:end])
        pos = end
    assert pos == codes.size


@given(
    codes=st.lists(st.one_of(st.integers(-3, 3), st.integers(-(2**40), 2**40)), min_size=1, max_size=300),
    n_approx=st.integers(0, 40),
    dpcm=st.booleans(),
)
def test_coefficient_code_roundtrip_property(codes: list[int], n_approx: int, dpcm: bool) -> None:
    arr = np.array(codes, dtype=np.int64)
    data = codec.encode_codes(arr, n_approx, dpcm=dpcm)
    np.testing.assert_array_equal(codec.decode_codes(data, arr.size, n_approx), arr)
