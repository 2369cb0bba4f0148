"""Quality layers: each image's layers end where it first reaches each quality mark (dB)."""

from __future__ import annotations

import numpy as np
import pytest

from coex_core.errors import ConfigError
from coex_plugins.imagery import codec
from coex_plugins.imagery.synth import seafloor


def _layer_quality(enc: codec.Encoded) -> list[float]:
    lengths = list(np.diff(np.append(enc.packet_starts, len(enc.body))))
    return codec.layer_psnrs(enc.image, enc.params, enc.body, lengths)


@pytest.fixture(scope="module")
def image() -> np.ndarray:
    return seafloor(240, 320, seed=7)


def test_each_layer_is_the_first_to_reach_its_quality_mark(image: np.ndarray) -> None:
    cp = codec.CodingParams()
    assert cp.layer_psnr == codec.DEFAULT_LAYER_PSNR
    enc = codec.encode_image(image, cp)
    q = _layer_quality(enc)
    marks = list(cp.layer_psnr or ())
    assert 3 <= len(q) <= len(marks)
    # layer k reaches a mark at or above the k-th one (marks an earlier layer reaches are merged)
    kept = []
    for k, qk in enumerate(q):
        assert qk >= marks[k], (k, q)
        kept.append(max(m for m in marks if m <= qk))
    assert kept == sorted(set(kept))
    # and each layer is the first to reach its mark: the layer before falls short of it
    for k in range(1, len(q)):
        assert q[k - 1] < kept[k], (k, q)
    # and no fewer bytes would do: a little less for a layer's target (5 %, at least 3 B) falls
    # short of the mark it was made for (the first mark the layer before does not reach)
    sp = enc.stream
    targets = codec.quality_targets(enc.image, cp, sp.resolutions)
    assert len(targets) == sp.layers
    for k in range(len(q)):
        made_for = min(m for m in marks if k == 0 or m > q[k - 1])
        t = [*targets[:k], min(int(targets[k] * 0.95), targets[k] - 3)]
        if t[-1] < 1 or (k and t[-1] <= t[-2]):
            continue
        code = codec.params_code(sp.progression, sp.resolutions, len(t), sp.irreversible, False, sp.precincts)
        body, lengths = codec._encode_body(enc.image, code, t)
        assert codec.layer_psnrs(enc.image, code, body, lengths)[-1] < made_for, (k, made_for, q)

def test_byte_layers_when_asked_for(image: np.ndarray) -> None:
    cp = codec.CodingParams(layer_bytes=(100, 400, 1600))
    assert cp.layer_psnr == ()
    enc = codec.encode_image(image, cp)
    assert enc.stream.layers == 3
    assert codec.CodingParams.from_config({"layer_bytes": [50, 100]}).layer_psnr == ()
    assert codec.CodingParams.from_config({"layer_psnr": [22, 31.5]}).layer_psnr == (22.0, 31.5)
    assert codec.CodingParams.from_config({"layer_psnr": "none"}).layer_psnr == ()


def test_marks_beyond_reach_are_dropped() -> None:
    flat = np.full((64, 64), 90, np.uint8)  # any layer reproduces it: one layer
    enc = codec.encode_image(flat, codec.CodingParams())
    assert enc.stream.layers == 1
    assert codec.psnr(codec.decode_packets(enc.params, 64, 64, codec.split_packets(enc.body, enc.packet_starts)),
                      flat) >= codec.DEFAULT_LAYER_PSNR[-1]


@pytest.mark.parametrize("bad", [[30, 25], [5.0], [70], ["x"], list(range(10, 44))])
def test_bad_quality_marks_are_refused(bad: list) -> None:
    with pytest.raises(ConfigError):
        codec.CodingParams.from_config({"layer_psnr": bad})
