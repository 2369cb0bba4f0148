"""The quality calibration's cost (issue 55): each trial encode is made once, known by the byte
limits OpenJPEG's rate control gives its layers (codec.rate_limits), and the calibration is the
one every trial encoded and decoded would give; the PSNR of uint8 images in integers."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest

from coex import DecodeError
from coex_plugins.imagery import codec
from coex_plugins.imagery.codec import CodingParams
from coex_plugins.imagery.synth import sand_ripples, seafloor


def _limits(img: np.ndarray, code: int, targets: Sequence[int]) -> tuple[int, ...]:
    h, w = img.shape[:2]
    return codec.rate_limits(img.size, codec._stream_targets(code, w, h, targets), codec._main_header(code, w, h)[1])


def _code(layers: int) -> int:
    return codec.params_code("LRCP", 6, layers, True, False, codec.DEFAULT_PRECINCTS)


def test_each_layer_of_an_encode_stays_within_its_rate_limit_and_reaches_it_at_times() -> None:
    img = seafloor(120, 160, seed=5)
    exact = 0
    for targets in ([3], [40], [300], [2500], [3, 9], [40, 90, 900], [25, 400, 401, 5000], [200, 3000, 2999 + 3]):
        code = _code(len(targets))
        _body, lengths = codec._encode_body(img, code, targets)
        lim = _limits(img, code, targets)
        order = codec.packet_order(codec.parse_params(code), 160, 120)[:, 0]
        ends = np.cumsum(lengths)
        for k, limit in enumerate(lim):
            used = int(ends[np.nonzero(order <= k)[0].max()])
            assert used <= limit, (targets, k, used, limit)
            exact += used == limit
    assert exact >= 1  # the limits are OpenJPEG's to the byte, not a loose bound


def test_targets_whose_last_limit_lies_between_an_encodes_bytes_and_its_own_limit_encode_alike() -> None:
    img = sand_ripples(120, 160, seed=2)
    checked = 0
    for done in ([], [12], [60, 700]):
        code = _code(len(done) + 1)
        for t in (150, 900, 2600):
            if done and t <= done[-1] + 40:
                continue
            body, _ = codec._encode_body(img, code, [*done, t])
            top = _limits(img, code, [*done, t])[-1]
            floor = done[-1] + 1 if done else 1
            below = [u for u in range(t - 1, max(floor, t - 400), -1)
                     if len(body) <= _limits(img, code, [*done, u])[-1] < top]
            for u in below[:: max(1, len(below) // 4)]:
                assert codec._encode_body(img, code, [*done, u])[0] == body, (done, t, u)
                checked += 1
            # and a limit below the encode's bytes is another encode (the rule is not vacuous)
            under = next(u for u in range(t - 1, floor, -1) if _limits(img, code, [*done, u])[-1] < len(body))
            assert codec._encode_body(img, code, [*done, under])[0] != body
    assert checked >= 6


class _EveryTrial(codec._Trials):
    """Every trial encoded and decoded, and every probe layer decoded (the calibration before
    issue 55)."""

    def _find(self, code: int, limits: tuple[int, ...]) -> None:
        return None

    def layer_qualities(self, code: int, targets: Sequence[int], enough: float) -> list[float]:
        return super().layer_qualities(code, targets, float("inf"))


@pytest.mark.parametrize(("img", "marks"), [
    (seafloor(120, 160, seed=11), (20.0, 25.0, 30.0, 35.0, 40.0)),
    (sand_ripples(150, 200, seed=54001), (25.0, 30.0, 35.0, 40.0)),
    (seafloor(96, 128, seed=4, colour=True), (20.0, 25.0, 30.0, 35.0)),
])
def test_the_calibration_is_the_one_every_trial_gives_with_fewer_encodes(img: np.ndarray,
                                                                        marks: tuple[float, ...]) -> None:
    cp = CodingParams(layer_psnr=marks, grey=img.ndim == 2)
    res = codec._feasible_resolutions(img.shape[0], img.shape[1], cp.resolutions)
    fast, slow = codec._Trials(img, None, None), _EveryTrial(img, None, None)
    targets = codec._calibrate(fast, cp, res)
    assert targets == codec._calibrate(slow, cp, res)
    assert fast.encodes < slow.encodes, (fast.encodes, slow.encodes)
    # the final encode is the trial's (no encode left to do), and it is what OpenJPEG makes
    code = codec.params_code(cp.progression, res, len(targets), cp.irreversible, img.ndim == 3, cp.precincts)
    made = fast.known(code, targets)
    assert made is not None and made == codec._encode_body(img, code, targets)


def test_a_residual_calibrates_alike_too() -> None:
    original = seafloor(96, 128, seed=8)
    base = np.clip(original.astype(np.int16) + 9, 0, 255).astype(np.uint8)
    data = codec.residual(original, base)
    cp = CodingParams(layer_psnr=(30.0, 35.0))
    assert (codec._calibrate(codec._Trials(data, base, original), cp, 6)
            == codec._calibrate(_EveryTrial(data, base, original), cp, 6))


def test_psnr_of_uint8_images_in_integers_is_the_float_one_to_the_bit() -> None:
    rng = np.random.default_rng(3)
    for shape in ((480, 640), (7, 5), (32, 48, 3)):
        a = rng.integers(0, 256, shape, dtype=np.uint8)
        b = np.clip(a.astype(np.int16) + rng.integers(-40, 41, shape), 0, 255).astype(np.uint8)
        d = a.astype(np.float64) - b.astype(np.float64)
        assert codec.psnr(a, b) == 10.0 * float(np.log10(255.0**2 / float(np.mean(d * d))))
        assert codec.psnr(a, b.astype(np.float64)) == codec.psnr(a, b)  # the general path agrees
    assert codec.psnr(a, a) == float("inf")
    assert codec.psnr(np.zeros((4, 4), np.uint8), np.full((4, 4), 255, np.uint8)) == 0.0


def test_decodes_run_in_the_callers_thread_whatever_the_encodes_use(monkeypatch: pytest.MonkeyPatch) -> None:
    import glymur
    from glymur.lib import openjp2

    img = seafloor(64, 96, seed=1)
    enc = codec.encode_image(img, CodingParams(layer_bytes=(200, 800)))
    packets = codec.split_packets(enc.body, enc.packet_starts)
    before = glymur.get_option("lib.num_threads")
    seen: list[int] = []
    real = openjp2.codec_set_threads

    def spy(codec_: object, n: int) -> object:
        seen.append(n)
        return real(codec_, n)

    try:
        codec.set_threads(0)
        single = codec.decode_packets(enc.params, enc.width, enc.height, packets)
        codec.set_threads(2)
        if glymur.get_option("lib.num_threads") != 2:
            pytest.skip("this OpenJPEG has no thread support")
        monkeypatch.setattr(openjp2, "codec_set_threads", spy)
        pooled = codec.decode_packets(enc.params, enc.width, enc.height, packets)
        assert seen == [0]  # decoded in the caller's thread
        assert glymur.get_option("lib.num_threads") == 2  # the encodes keep their threads
        assert np.array_equal(pooled, single)
    finally:
        monkeypatch.undo()
        codec.set_threads(before)


@pytest.mark.parametrize("colour", [False, True])
def test_the_decode_gives_the_pixels_of_glymurs_reader(tmp_path: Path, colour: bool) -> None:
    import glymur

    img = seafloor(96, 128, seed=6, colour=colour)
    code = codec.params_code("LRCP", 5, 3, True, colour, codec.DEFAULT_PRECINCTS)
    body, lengths = codec._encode_body(img, code, [150, 900, 4000])
    ends = np.cumsum(lengths)
    packets: list[bytes | None] = [body[int(e) - n:int(e)] for e, n in zip(ends, lengths, strict=True)]
    rng = np.random.default_rng(4)
    for keep in (len(packets), len(packets) // 2, 3):
        some = [p if rng.random() < 0.8 else None for p in packets[:keep]]
        cs, _ = codec.assemble(code, 128, 96, some)
        path = tmp_path / "x.j2k"
        path.write_bytes(cs)
        ours = codec.decode_codestream(cs)
        theirs = np.asarray(glymur.Jp2k(str(path))[:], np.uint8)
        assert ours.shape == theirs.shape == img.shape and ours.dtype == np.uint8
        assert np.array_equal(ours, theirs)
        assert np.array_equal(codec.decode_codestream(cs, reduce=1), np.asarray(glymur.Jp2k(str(path))[::2, ::2]))
    for bad in (cs[: len(cs) // 3] + b"\xff\xd9", b"\xff\x4f\xff\x51 not a codestream"):
        with pytest.raises(DecodeError):
            codec.decode_codestream(bad)


@pytest.mark.parametrize("img", [sand_ripples(120, 160, seed=7), seafloor(96, 128, seed=4, colour=True)])
def test_a_run_of_trials_that_change_nothing_is_made_from_its_last(img: np.ndarray) -> None:
    """Where trials leave the image below a mark as the bracket's lower end left it, the last
    trial of that run is made first and tells the others (issue 55): the same targets and final
    body as the search that makes each in turn, with fewer encodes (these two images have such
    runs)."""
    cp = CodingParams(layer_psnr=(20.0, 25.0, 30.0, 35.0, 40.0), grey=img.ndim == 2)
    res = codec._feasible_resolutions(img.shape[0], img.shape[1], cp.resolutions)
    ahead, step = codec._Trials(img, None, None), codec._Trials(img, None, None)
    targets = codec._calibrate(ahead, cp, res)
    assert targets == codec._calibrate(step, cp, res, ahead=False)
    assert ahead.encodes < step.encodes, (ahead.encodes, step.encodes)
    code = codec.params_code(cp.progression, res, len(targets), cp.irreversible, img.ndim == 3, cp.precincts)
    assert ahead.known(code, targets) == step.known(code, targets) == codec._encode_body(img, code, targets)


def test_an_image_coded_twice_is_the_same_codestream_and_the_dives_share_it(
        tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    """The coding is deterministic: the same pixels and parameters, calibrated afresh, give the
    same bytes. That is what lets the test dives share their codings (``tests/_dives.py``
    ``codestreams_shared``): the second coding of an image is read from the run's shared
    directory, equal to OpenJPEG's in every field."""
    from ._dives import codestreams_shared

    img = seafloor(96, 128, seed=6)
    cp = CodingParams(layer_psnr=(25.0, 30.0, 35.0), grey=True)
    coded = []
    for _ in range(2):
        monkeypatch.setattr(codec, "_TARGETS", {})  # calibrated again, not remembered
        coded.append(codec.encode_image(img, cp))
    with codestreams_shared(tmp_path_factory) as counts:
        coded += [codec.encode_image(img, cp), codec.encode_image(img, cp)]
    assert counts == {"encodes": 1, "reused": 1}
    first = coded[0]
    for enc in coded[1:]:
        assert enc.body == first.body and enc.packet_starts.tolist() == first.packet_starts.tolist()
        assert (enc.params, enc.width, enc.height, enc.grey) == (first.params, first.width, first.height, first.grey)
        assert np.array_equal(enc.image, first.image)
