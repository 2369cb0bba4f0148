"""The packet writer (coex_plugins.imagery.packets.write_packets) and layers tightened to their
quality marks (coex_plugins.imagery.tighten)."""

from __future__ import annotations

import numpy as np
import pytest

from coex_plugins.imagery import codec
from coex_plugins.imagery.codec import CodingParams
from coex_plugins.imagery.packets import PacketParser, code_blocks, packet_lengths, write_packets
from coex_plugins.imagery.synth import sand_ripples, seafloor


def _layers(enc: codec.Encoded) -> list[float]:
    lengths = list(np.diff(np.append(enc.packet_starts, len(enc.body))))
    return codec.layer_psnrs(enc.image, enc.params, enc.body, lengths)


@pytest.mark.parametrize(("w", "h", "colour", "cp"), [
    (160, 120, False, CodingParams(tighten=False)),
    (300, 257, True, CodingParams(grey=False, tighten=False)),
    (128, 96, False, CodingParams(layer_bytes=(30, 60, 120, 240, 480, 900, 1600), precincts=0)),
    (200, 150, False, CodingParams(progression="RLCP", precincts=128, tighten=False)),
])
def test_the_writer_gives_back_openjpegs_packets_byte_for_byte(w: int, h: int, colour: bool, cp: CodingParams) -> None:
    enc = codec.encode_image(seafloor(h, w, seed=3, colour=colour), cp)
    blocks = code_blocks(enc.params, enc.width, enc.height, enc.body)
    assert blocks.layers == enc.stream.layers and blocks.data
    body, lengths = write_packets(enc.stream, enc.width, enc.height,
                                  [blocks.allocation(k) for k in range(blocks.layers)], blocks)
    assert body == enc.body
    assert lengths == packet_lengths(enc.params, enc.width, enc.height, enc.body).tolist()


def test_the_writer_refuses_a_layer_that_adds_bytes_but_no_pass() -> None:
    enc = codec.encode_image(seafloor(96, 128, seed=4), CodingParams(tighten=False))
    blocks = code_blocks(enc.params, enc.width, enc.height, enc.body)
    cb, (n, nb) = next((cb, a) for cb, a in blocks.allocation(0).items() if a[1] > 2)
    cut = {**blocks.allocation(0), cb: (n, nb - 2)}  # ends inside its last pass: fine
    body, lengths = write_packets(enc.stream, enc.width, enc.height, [cut, blocks.allocation(1)], blocks)
    sp = enc.stream
    two = codec.params_code(sp.progression, sp.resolutions, 2, sp.irreversible, sp.colour, sp.precincts)
    assert packet_lengths(two, enc.width, enc.height, body).tolist() == lengths
    with pytest.raises(ValueError, match="no pass"):
        write_packets(enc.stream, enc.width, enc.height, [cut, {**blocks.allocation(0)}], blocks)


@pytest.fixture(scope="module")
def textured() -> np.ndarray:
    """A small textured frame, where one pass of a code-block is a large step in quality."""
    return np.ascontiguousarray(sand_ripples(480, 640, seed=11)[::4, ::4])


def test_tightened_layers_end_at_fewer_bytes_and_still_reach_their_marks(textured: np.ndarray) -> None:
    loose = codec.encode_image(textured, CodingParams(tighten=False))
    tight = codec.encode_image(textured)
    assert tight.params == loose.params  # the same parameters on the wire: only where layers end moves
    q_loose, q_tight = _layers(loose), _layers(tight)
    marks = codec.DEFAULT_LAYER_PSNR
    saved = 0
    for k in range(tight.stream.layers):
        # each layer still reaches the mark the loose one was made for, and not the next one
        mark = max(m for m in marks if m <= q_loose[k])
        assert mark <= q_tight[k] < min((m for m in marks if m > mark), default=np.inf), (k, q_loose, q_tight)
        end_loose, end_tight = loose.layer_end(k + 1), tight.layer_end(k + 1)
        assert end_tight <= end_loose
        saved += end_loose - end_tight
    assert saved > 0
    # the receiver finds every packet by parsing the headers, as for OpenJPEG's bodies
    starts = PacketParser(tight.params, tight.width, tight.height).parse(tight.body)
    assert starts.tolist() == tight.packet_starts.tolist()
    # and a crop (one layer to its goal) is tightened too
    crop = codec.encode_residual(textured[:60, :80], np.full((60, 80), 128, np.uint8),
                                 CodingParams(precincts=0, layer_psnr=(33.0,)))
    loose_crop = codec.encode_residual(textured[:60, :80], np.full((60, 80), 128, np.uint8),
                                       CodingParams(precincts=0, layer_psnr=(33.0,), tighten=False))
    assert len(crop.body) <= len(loose_crop.body)
    assert codec.psnr(codec.decode_packets(crop.params, 80, 60, codec.split_packets(crop.body, crop.packet_starts)),
                      textured[:60, :80]) >= 33.0
