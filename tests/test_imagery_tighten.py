"""The packet writer (coex_plugins.imagery.packets.write_packets) and layers tightened to their
quality marks (coex_plugins.imagery.tighten)."""

from __future__ import annotations

import os
import warnings

import numpy as np
import pytest

from coex_plugins.imagery import codec
from coex_plugins.imagery.codec import CodingParams
from coex_plugins.imagery.packets import (
    CodeBlock,
    CodeBlocks,
    LayerWriter,
    PacketParser,
    code_blocks,
    packet_lengths,
    write_packets,
)
from coex_plugins.imagery.synth import sand_ripples, seafloor


def _layers(enc: codec.Encoded) -> list[float]:
    lengths = list(np.diff(np.append(enc.packet_starts, len(enc.body))))
    return codec.layer_psnrs(enc.image, enc.params, enc.body, lengths)


@pytest.mark.parametrize(("w", "h", "colour", "cp"), [
    (160, 120, False, CodingParams(tighten=False)),
    (300, 257, True, CodingParams(grey=False, tighten=False)),
    (128, 96, False, CodingParams(layer_bytes=(30, 60, 120, 240, 480, 900, 1600), precincts=0)),
    (200, 150, False, CodingParams(progression="RLCP", precincts=128, tighten=False)),
    (37, 23, False, CodingParams(irreversible=False, resolutions=3, tighten=False)),
    (640, 480, False, CodingParams(tighten=False)),  # the dive frames' size, the default coding
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


@pytest.mark.parametrize(("w", "h", "colour", "cp"), [
    (640, 480, False, CodingParams(tighten=False)),  # the dive frames' size: 13 precincts a layer
    (300, 257, True, CodingParams(grey=False, tighten=False)),
    (128, 96, False, CodingParams(layer_bytes=(30, 60, 120, 240, 480, 900, 1600), precincts=0)),
])
def test_the_layer_writer_gives_the_packets_of_write_packets(w: int, h: int, colour: bool, cp: CodingParams) -> None:
    """The one-layer writer of the tightening's trials (each precinct's packet remembered):
    the same packets as write_packets for each layer's allocation, and for trials that take
    bytes off, cut inside a pass or leave out one code-block's contribution, asked in any order
    and again (issue 55)."""
    enc = codec.encode_image(seafloor(h, w, seed=7, colour=colour), cp)
    blocks = code_blocks(enc.params, w, h, enc.body)
    sp = enc.stream
    one = codec.parse_params(codec.params_code(sp.progression, sp.resolutions, 1, sp.irreversible, sp.colour,
                                               sp.precincts))
    writer = LayerWriter(sp, w, h, blocks)
    rng = np.random.default_rng(5)
    trials = []
    for k in range(blocks.layers):
        alloc = blocks.allocation(k)
        trials.append(alloc)
        for cb in [list(alloc)[int(i)] for i in rng.choice(len(alloc), min(6, len(alloc)), replace=False)]:
            n, nb = alloc[cb]
            trials.append({**alloc, cb: (n, max(1, nb - int(rng.integers(1, 40))))})  # cut inside a pass
            trials.append({c: a for c, a in alloc.items() if c != cb})  # left to the next layer
    seen = set()
    for trial in [*trials, *trials[::-1]]:
        expected, lengths = write_packets(one, w, h, [trial], blocks)
        got = writer.packets(trial)
        assert b"".join(got) == expected and [len(p) for p in got] == lengths
        seen.add(expected)
    assert len(seen) > blocks.layers  # the trials are different bodies, not one body many times
    cb = next(iter(blocks.allocation(0)))
    with pytest.raises(ValueError, match="no pass"):
        writer.packets({cb: (0, 3)})


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


# ------------------------------------------------------------------ truncation of written bodies


def _layer_decodes(enc_params: int, w: int, h: int, body: bytes) -> tuple[list[int], list[np.ndarray], list[np.ndarray]]:
    """For each layer k of a body: where it ends (whole packets), the decode of the body cut
    there (what topside shows, :func:`codec.decode_packets`) and OpenJPEG's own decode of the
    whole body limited to k layers (``Jp2k.layer``), the independent reference."""
    sp = codec.parse_params(enc_params)
    starts = PacketParser(enc_params, w, h).parse(body)
    order = codec.packet_order(sp, w, h)
    cs, _ = codec.assemble(enc_params, w, h, codec.split_packets(body, starts))
    path = os.path.join(codec._scratch(), "layers.j2k")
    with open(path, "wb") as fh:
        fh.write(cs)
    ends, cut, reference = [], [], []
    try:
        for k in range(1, sp.layers + 1):
            last = int(np.nonzero(order[:, 0] < k)[0].max())
            end = codec.packet_end(starts, len(body), last)
            ends.append(end)
            cut.append(codec.decode_packets(enc_params, w, h, codec.split_packets(body, starts, end)))
            j = codec._glymur().Jp2k(path)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                if k < sp.layers:
                    j.layer = k
                reference.append(np.asarray(j[:], np.uint8))
    finally:
        os.unlink(path)
    return ends, cut, reference


def _cut_inside_passes(blocks: CodeBlocks) -> list[dict[CodeBlock, tuple[int, int]]]:
    """OpenJPEG's allocations with every layer but the last ending halfway into the last pass
    of each contribution the next layer carries on with another pass."""
    allocs = [blocks.allocation(k) for k in range(blocks.layers)]
    for k in range(blocks.layers - 1):
        for cb, (n, nb) in list(allocs[k].items()):
            _, b_prev = allocs[k - 1].get(cb, (0, 0)) if k else (0, 0)
            if blocks.cum[cb][k + 1][0] > n and nb - b_prev >= 2:
                allocs[k][cb] = (n, b_prev + (nb - b_prev) // 2)
    return allocs


@pytest.mark.parametrize(("w", "h", "colour", "cp"), [
    (160, 120, False, CodingParams(layer_bytes=(60, 200, 600, 1500, 3000), layer_psnr=(), tighten=False)),
    (120, 90, True, CodingParams(grey=False, layer_bytes=(80, 300, 900, 2500), layer_psnr=(), precincts=0)),
    (100, 75, False, CodingParams(irreversible=False, precincts=128,
                                  layer_bytes=(50, 150, 450, 1200), layer_psnr=())),
])
def test_layers_ending_inside_passes_decode_cut_at_each_layer_end(w: int, h: int, colour: bool, cp: CodingParams) -> None:
    """The writer's bodies whose layers end inside a coding pass (LRCP: a layer's end is a prefix
    holding that layer and those before, nothing of later ones): cut at each layer's end they
    decode, to what OpenJPEG decodes of the whole body limited to those layers, and a layer
    cut short shows less than OpenJPEG's own layer did; every packet boundary decodes."""
    img = seafloor(h, w, seed=5, colour=colour)
    enc = codec.encode_image(img, cp)
    blocks = code_blocks(enc.params, w, h, enc.body)
    allocs = _cut_inside_passes(blocks)
    cut_short = sum(a != blocks.allocation(k) for k, a in enumerate(allocs))
    assert cut_short == blocks.layers - 1  # the test exercises cuts inside passes in every layer but the last
    body, lengths = write_packets(enc.stream, w, h, allocs, blocks)
    again = code_blocks(enc.params, w, h, body)
    assert again.data == blocks.data  # the same codewords: only where the layers end moved (and headers)
    assert [again.allocation(k) for k in range(again.layers)] == allocs
    assert packet_lengths(enc.params, w, h, body).tolist() == lengths
    ends, cut, reference = _layer_decodes(enc.params, w, h, body)
    _, openjpeg_cut, _ = _layer_decodes(enc.params, w, h, enc.body)
    assert ends[-1] == len(body)
    for k in range(blocks.layers):
        np.testing.assert_array_equal(cut[k], reference[k], err_msg=f"layer {k + 1}")
        if k < blocks.layers - 1:
            assert codec.psnr(cut[k], img) < codec.psnr(openjpeg_cut[k], img)
            assert codec.psnr(cut[k], img) > codec.psnr(cut[k - 1], img) if k else codec.psnr(cut[k], img) > 20
    np.testing.assert_array_equal(cut[-1], openjpeg_cut[-1])  # the whole body: the same image
    starts = np.concatenate([[0], np.cumsum(lengths[:-1])]).astype(np.int64)
    for i in range(1, len(starts) + 1):
        shown = codec.decode_packets(enc.params, w, h, codec.split_packets(body, starts, codec.packet_end(
            starts, len(body), i - 1)))
        assert shown.shape == img.shape


def test_a_tightened_body_decodes_cut_at_each_layer_end_to_its_mark(textured: np.ndarray) -> None:
    """The sender's tightened body: the writer gives it back byte for byte, and cut at each
    layer's end it decodes to what OpenJPEG decodes of the whole body limited to those layers,
    at or above the layer's mark."""
    tight = codec.encode_image(textured)
    h, w = textured.shape
    blocks = code_blocks(tight.params, w, h, tight.body)
    body, lengths = write_packets(tight.stream, w, h, [blocks.allocation(k) for k in range(blocks.layers)], blocks)
    assert body == tight.body
    assert lengths == np.diff(np.append(tight.packet_starts, len(tight.body))).tolist()
    ends, cut, reference = _layer_decodes(tight.params, w, h, tight.body)
    assert ends == [tight.layer_end(k) for k in range(1, tight.stream.layers + 1)]
    q = [codec.psnr(c, textured) for c in cut]
    marks = codec.DEFAULT_LAYER_PSNR
    for k in range(tight.stream.layers):
        np.testing.assert_array_equal(cut[k], reference[k], err_msg=f"layer {k + 1}")
        assert any(m <= q[k] < m + 1.0 for m in marks), (k, q)  # at its mark, not a dB past it
    assert q == sorted(q)
