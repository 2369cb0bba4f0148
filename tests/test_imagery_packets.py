"""Imagery: packet starts found by parsing JPEG 2000 packet headers (coex_plugins.imagery.packets).

The ground truth is OpenJPEG's PLT marker (``Encoded.packet_starts``)."""

from __future__ import annotations

import functools
import random
from pathlib import Path

import numpy as np
import pytest

from coex_core.errors import DecodeError
from coex_plugins.imagery import codec
from coex_plugins.imagery.codec import CodingParams
from coex_plugins.imagery.packets import PacketParser, packet_lengths, precinct_codeblocks
from coex_plugins.imagery.synth import seafloor

NUI040 = Path("/work/shared/data/nui040")
SIZES = ((640, 480), (300, 257), (37, 23), (1024, 768))


def ladder(layers: int) -> tuple[int, ...]:
    """``layers`` cumulative byte targets from 30 B to 20 KB (geometric)."""
    if layers == 1:
        return (20480,)
    out: list[int] = []
    for b in np.geomspace(30, 20480, layers):
        out.append(max(int(b), out[-1] + 1 if out else 1))
    return tuple(out)


#: four fixed layers, as many as the default quality marks give: the parser sees the stream those
#: give (calibration ends in a fixed-target encode, codec._encode) without its ~25 trial encodes a
#: stream, which these tests of the parser do not test (test_nui040_images_default_params keeps them)
FOUR_LAYERS = ladder(4)


@functools.cache
def image(w: int, h: int, colour: bool, kind: str, seed: int = 0) -> np.ndarray:
    if kind == "flat":
        shape = (h, w, 3) if colour else (h, w)
        return np.full(shape, 97 + seed, np.uint8)
    return seafloor(h, w, seed=seed, colour=colour)


def encode(w: int, h: int, colour: bool = False, kind: str = "sea", seed: int = 0, **kw: object) -> codec.Encoded:
    cp = CodingParams(grey=not colour, **kw)  # type: ignore[arg-type]
    return codec.encode_image(image(w, h, colour, kind, seed), cp)


def check(enc: codec.Encoded) -> None:
    starts = PacketParser(enc.params, enc.width, enc.height).parse(enc.body)
    assert starts.tolist() == enc.packet_starts.tolist()
    lengths = packet_lengths(enc.params, enc.width, enc.height, enc.body)
    assert lengths.sum() == len(enc.body)
    assert lengths.tolist() == np.diff(np.append(enc.packet_starts, len(enc.body))).tolist()


def _sample_configs(n: int) -> list[tuple]:
    """A seeded sample of the configuration space (every value of every axis appears)."""
    rng = random.Random(2024)
    axes = dict(size=SIZES, colour=(False, True), prog=("LRCP", "RLCP"), precincts=(0, 128, 256),
                irr=(True, False), res=tuple(range(1, 9)), layers=(1, 8, 18, 32))
    out = []
    for i in range(n):
        cfg = {k: (v[i % len(v)] if i < 8 else rng.choice(v)) for k, v in axes.items()}
        out.append((cfg["size"], cfg["colour"], cfg["prog"], cfg["precincts"], cfg["irr"], cfg["res"], cfg["layers"],
                    i))
    return out


@pytest.mark.parametrize(("size", "colour", "prog", "precincts", "irr", "res", "layers", "seed"), _sample_configs(48))
def test_starts_equal_plt_on_a_sample_of_configurations(size, colour, prog, precincts, irr, res, layers, seed) -> None:
    w, h = size
    check(encode(w, h, colour, seed=seed, progression=prog, precincts=precincts, irreversible=irr, resolutions=res,
                 layer_bytes=ladder(layers)))


@pytest.mark.parametrize("precincts", [0, 128, 256])
@pytest.mark.parametrize("res", range(1, 9))
def test_every_resolution_count_1024x768(res: int, precincts: int) -> None:
    enc = encode(1024, 768, seed=res, resolutions=res, precincts=precincts, layer_bytes=FOUR_LAYERS)
    assert enc.stream.resolutions == res
    check(enc)


@pytest.mark.parametrize("layers", [1, 8, 18, 32])
@pytest.mark.parametrize(("w", "h"), SIZES)
def test_default_params_every_size_and_layer_count(w: int, h: int, layers: int) -> None:
    check(encode(w, h, seed=layers, layer_bytes=ladder(layers)))


@pytest.mark.parametrize("colour", [False, True])
@pytest.mark.parametrize("prog", ["LRCP", "RLCP"])
@pytest.mark.parametrize("precincts", [0, 128, 256, 512])
def test_colour_and_grey_both_wavelets(colour: bool, prog: str, precincts: int) -> None:
    for irr in (True, False):
        check(encode(640, 480, colour, seed=3, progression=prog, precincts=precincts, irreversible=irr,
                     layer_bytes=FOUR_LAYERS))


@pytest.mark.parametrize("colour", [False, True])
@pytest.mark.parametrize("precincts", [0, 128, 256])
@pytest.mark.parametrize(("w", "h"), SIZES)
def test_flat_images_have_empty_packets(w: int, h: int, precincts: int, colour: bool) -> None:
    enc = encode(w, h, colour, kind="flat", precincts=precincts, layer_bytes=ladder(8))
    check(enc)


@pytest.mark.parametrize("prog", ["RPCL", "PCRL", "CPRL"])
@pytest.mark.parametrize("colour", [False, True])
@pytest.mark.parametrize(("w", "h"), [(640, 480), (300, 257), (37, 23)])
def test_other_progressions_one_precinct_per_resolution(prog: str, colour: bool, w: int, h: int) -> None:
    for irr in (True, False):
        check(encode(w, h, colour, seed=7, progression=prog, precincts=0, irreversible=irr, layer_bytes=FOUR_LAYERS))


def test_precinct_codeblocks_geometry() -> None:
    sp = codec.parse_params(codec.params_code("LRCP", 2, 1, True, False, 256))
    # 300 x 257: resolution 1 is the full image, precinct rows 0..255 and 256; its LH/HH band
    # rows end at 128 and the second precinct row maps to band rows 128..255: empty there.
    assert precinct_codeblocks(sp, 300, 257, 1, 0) == [(2, 2), (2, 2), (2, 2)]
    assert precinct_codeblocks(sp, 300, 257, 1, 2) == [(2, 1), (0, 0), (0, 0)]
    assert precinct_codeblocks(sp, 300, 257, 1, 3) == [(1, 1), (0, 0), (0, 0)]
    assert precinct_codeblocks(sp, 300, 257, 0, 0) == [(3, 3)]
    one = codec.parse_params(codec.params_code("LRCP", 1, 1, True, False, 0))
    assert precinct_codeblocks(one, 37, 23, 0, 0) == [(1, 1)]


# ------------------------------------------------------------------------------ incremental


@pytest.fixture(scope="module")
def enc() -> codec.Encoded:
    return encode(640, 480, seed=11)


def test_incremental_in_order_random_chunks_equals_all_at_once(enc: codec.Encoded) -> None:
    truth = enc.packet_starts
    for seed in range(5):
        rng = random.Random(seed)
        pp = PacketParser(enc.params, enc.width, enc.height, len(enc.body))
        buf, have = bytearray(len(enc.body)), np.zeros(len(enc.body), bool)
        pos, prev_known = 0, 1
        while pos < len(buf):
            n = rng.randint(1, 300)
            buf[pos:pos + n], have[pos:pos + n] = enc.body[pos:pos + n], True
            pos += n
            starts = pp.parse(buf, have)
            known = starts >= 0
            assert known.sum() >= prev_known and np.all(known[: known.sum()])  # a prefix
            assert starts[known].tolist() == truth[known].tolist()
            # every parsed packet's header was held (its data need not be)
            parsed = pp.header_bytes >= 0
            assert parsed.sum() == pp.parsed and np.all(starts[parsed] + pp.header_bytes[parsed] <= pos)
            prev_known = int(known.sum())
        assert pp.done and starts.tolist() == truth.tolist()


def test_incremental_fragments_in_random_order(enc: codec.Encoded) -> None:
    truth = enc.packet_starts
    rng = random.Random(5)
    frags = [(o, min(o + 57, len(enc.body))) for o in range(0, len(enc.body), 57)]
    rng.shuffle(frags)
    pp = PacketParser(enc.params, enc.width, enc.height)
    buf, have = bytearray(len(enc.body)), np.zeros(len(enc.body), bool)
    for a, b in frags:
        buf[a:b], have[a:b] = enc.body[a:b], True
        starts = pp.parse(buf, have)
        known = starts >= 0
        assert starts[known].tolist() == truth[known].tolist()
    assert starts.tolist() == truth.tolist()


def test_resumes_without_reparsing(enc: codec.Encoded, monkeypatch: pytest.MonkeyPatch) -> None:
    from coex_plugins.imagery import packets

    calls = []
    real = packets._read_header
    monkeypatch.setattr(packets, "_read_header", lambda *a: calls.append(1) or real(*a))
    pp = PacketParser(enc.params, enc.width, enc.height)
    buf, have = bytearray(len(enc.body)), np.zeros(len(enc.body), bool)
    steps = 0
    for o in range(0, len(buf), 64):
        buf[o:o + 64], have[o:o + 64] = enc.body[o:o + 64], True
        pp.parse(buf, have)
        steps += 1
    assert pp.done
    # each packet is parsed once, plus at most one interrupted attempt per call
    assert len(calls) <= pp.n_packets + steps


def test_a_hole_stops_parsing_and_filling_it_resumes(enc: codec.Encoded) -> None:
    truth, body = enc.packet_starts, enc.body
    k = len(truth) // 2
    hdr = PacketParser(enc.params, enc.width, enc.height)
    hdr.parse(body)
    s = int(truth[k])
    have = np.ones(len(body), bool)
    have[s] = False  # the first header byte of packet k
    buf = bytearray(body)
    buf[s] = 0xA5  # whatever is there must not be read
    pp = PacketParser(enc.params, enc.width, enc.height)
    starts = pp.parse(buf, have)
    assert pp.parsed == k
    assert starts[: k + 1].tolist() == truth[: k + 1].tolist() and np.all(starts[k + 1:] == -1)
    assert pp.parse(buf, have).tolist() == starts.tolist()  # stays stopped
    buf[s], have[s] = body[s], True
    assert pp.parse(buf, have).tolist() == truth.tolist()


def test_a_hole_in_the_last_header_byte_and_one_in_packet_data(enc: codec.Encoded) -> None:
    truth, body = enc.packet_starts, enc.body
    pp0 = PacketParser(enc.params, enc.width, enc.height)
    pp0.parse(body)
    hb = pp0.header_bytes
    # a packet with a header of several bytes and some data after it
    ends = np.append(truth[1:], len(body))
    k = int(np.flatnonzero((hb > 2) & (ends - truth > hb + 2))[0])
    s, h = int(truth[k]), int(hb[k])
    have = np.ones(len(body), bool)
    have[s + h - 1] = False  # the header's last byte
    pp = PacketParser(enc.params, enc.width, enc.height)
    assert pp.parse(body, have)[k + 1] == -1 and pp.parsed == k
    have[s + h - 1] = True
    have[s + h: int(ends[k])] = False  # only the code-block data is missing: not needed
    assert pp.parse(body, have).tolist() == truth.tolist()


# ------------------------------------------------------------------------------ malformed


def _fits(starts: np.ndarray, total: int) -> bool:
    known = starts[starts >= 0]
    return bool(np.all(known <= total) and np.all(np.diff(known) >= 0))


@pytest.mark.parametrize("precincts", [0, 256])
@pytest.mark.parametrize("colour", [False, True])
def test_random_garbage_raises_or_stays_inside(precincts: int, colour: bool) -> None:
    rng = np.random.default_rng(precincts + colour)
    code = codec.params_code("LRCP", 7, 18, True, colour, precincts)
    outcomes = set()
    for trial in range(300):
        n = int(rng.integers(0, 3000))
        kind = trial % 3
        if kind == 0:
            data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        elif kind == 1:
            data = bytes([0xFF]) * n
        else:
            data = rng.choice(np.array([0, 0xFF, 0x80, 0x7F], np.uint8), n).tobytes()
        have = rng.random(n) < 0.9 if trial % 2 else None
        pp = PacketParser(code, 640, 480)
        try:
            starts = pp.parse(data, have)
        except DecodeError:
            outcomes.add("error")
            with pytest.raises(DecodeError):  # and stays failed
                pp.parse(data, have)
            continue
        outcomes.add("stopped")
        assert _fits(starts, n)
    assert "error" in outcomes


def test_truncated_padded_and_corrupted_bodies(enc: codec.Encoded) -> None:
    body = enc.body
    for cut in (1, 2, 10, len(body) // 2, len(body) - 1):
        with pytest.raises(DecodeError):
            packet_lengths(enc.params, enc.width, enc.height, body[:cut])
    with pytest.raises(DecodeError):
        packet_lengths(enc.params, enc.width, enc.height, body + b"\x00")
    with pytest.raises(DecodeError):
        packet_lengths(enc.params, enc.width, enc.height, b"")
    rng = np.random.default_rng(1)
    for _ in range(200):
        bad = bytearray(body)
        for i in rng.integers(0, len(body), 3):
            bad[i] = int(rng.integers(0, 256))
        try:
            starts = PacketParser(enc.params, enc.width, enc.height).parse(bad)
        except DecodeError:
            continue
        assert _fits(starts, len(bad))


def test_bad_arguments() -> None:
    code = codec.params_code("LRCP", 7, 18, True, False, 256)
    pp = PacketParser(code, 640, 480, 100)
    with pytest.raises(DecodeError):
        pp.parse(bytes(99))
    with pytest.raises(DecodeError):
        PacketParser(code, 640, 480).parse(bytes(10), np.ones(9, bool))
    with pytest.raises(DecodeError):
        PacketParser(code, 40, 30)  # 7 resolutions impossible
    with pytest.raises(DecodeError):
        PacketParser(7 << 10, 640, 480)


# ------------------------------------------------------------------------------ real images


@pytest.mark.skipif(not list(NUI040.glob("*.tiff")), reason="no NUI dive-040 images at /work/shared/data/nui040")
def test_nui040_images_default_params() -> None:
    import tifffile

    files = sorted(NUI040.glob("*.tiff"))
    for f in files:
        enc = codec.encode_image(tifffile.imread(f), CodingParams())
        check(enc)
