"""Quality layers that end at fewer bytes than OpenJPEG's: the vehicle's choice of what each layer
holds (spec/payloads.md 3.2: nothing on the wire says how layers are formed).

OpenJPEG ends a layer at whole coding passes, chosen by one rate-distortion slope for every
code-block. On a small or finely textured image one pass of a 64 x 64 code-block of the finest
band is 100 to 200 bytes, so the layer that first reaches a quality mark can overshoot it by a
fifth of a dB: 35.22 dB for a 35 dB mark on one 160 x 120 frame, 180 bytes past the layer
allocation just below (34.69 dB). :func:`tighten` takes the encoded body apart (its packets'
contributions, :func:`.packets.code_blocks`), and for each layer, largest contributions first,
tries leaving a code-block's contribution to the next layer or cutting it short inside a pass
(a decoder reads the rest of the codeword as 1 bits, T.800 C.3.4; the next layer brings the rest
of the pass), keeping what still reaches the layer's mark with fewer bytes, measured by
decoding. It writes the body again with :func:`.packets.write_packets`. A layer only ever loses
bytes to the next one, so every layer still reaches its mark and the whole body is the same
codeword; only where the layers end moves. The search is bounded (:data:`DECODES` decodes per
layer, fewer on large images) and deterministic."""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ._stream import StreamParams, params_code, parse_params
from .packets import CodeBlock, CodeBlocks, LayerWriter, code_blocks, packet_lengths, write_packets

__all__ = ["DECODES", "Quality", "decodes_for", "tighten"]

#: How a layer's quality is measured: the PSNR (dB) of the image decoded from a body's packets
#: (its params code and its packets); the codec gives it (:func:`.codec.layer_psnrs` measures
#: the same way).
Quality = Callable[[int, Sequence[bytes | None]], float]

#: Decodes per layer on a small image; a large one gets fewer (:func:`decodes_for`).
DECODES = 160
#: A layer within this of its mark is left as it is (there is next to nothing to gain).
SLACK_DB = 0.005
#: Near a quality mark the PSNR grows by about this many dB per e-fold of bytes (6 dB per
#: doubling): what a layer's excess over its mark is worth in bytes.
DB_PER_E = 6.02 / float(np.log(2.0))
#: Tightened bodies of the last images, by content (an image encoded again is not searched again).
_CACHE: dict[bytes, tuple[bytes, list[int]]] = {}
_CACHE_MAX = 64

Allocation = dict[CodeBlock, tuple[int, int]]


def decodes_for(width: int, height: int) -> int:
    """The decode budget per layer: :data:`DECODES` up to about 200 x 150 pixels, then fewer in
    proportion to the pixels (a decode costs about that much more), at least 12."""
    return int(max(12, min(DECODES, DECODES * 30000 // max(1, width * height))))


def tighten(code: int, width: int, height: int, body: bytes, marks: Sequence[float], quality: Quality,
            key: bytes, budget: int | None = None) -> tuple[bytes, list[int]]:
    """``body`` (a ``width x height`` image coded with ``code``) with each layer ending at fewer
    bytes where it still reaches its mark, the largest of ``marks`` its own decode reaches, as
    ``quality`` measures it. ``key`` names what ``quality`` measures against (the image, and for
    a crop its base and reference): with the rest of the arguments it keys the cache of the last
    results. Returns the body and its packet lengths."""
    key = hashlib.blake2b(b"".join([key, code.to_bytes(4, "big"), width.to_bytes(4, "big"),
                                    height.to_bytes(4, "big"), body, repr(tuple(marks)).encode(),
                                    repr(budget).encode()]), digest_size=16).digest()
    hit = _CACHE.get(key)
    if hit is None:
        hit = _tighten(code, width, height, body, marks, quality, budget)
        if len(_CACHE) >= _CACHE_MAX:
            del _CACHE[next(iter(_CACHE))]
        _CACHE[key] = hit
    return hit[0], list(hit[1])


def _tighten(code: int, w: int, h: int, body: bytes, marks: Sequence[float], quality: Quality,
             budget: int | None) -> tuple[bytes, list[int]]:
    sp = parse_params(code)
    blocks = code_blocks(sp, w, h, body)
    allocs = [blocks.allocation(layer) for layer in range(sp.layers)]
    one_code = params_code(sp.progression, sp.resolutions, 1, sp.irreversible, sp.colour, sp.precincts)
    one = parse_params(one_code)
    per_layer = decodes_for(w, h) if budget is None else budget
    writer = LayerWriter(one, w, h, blocks)

    def measure(alloc: Allocation) -> tuple[int, float]:
        """Body bytes and PSNR of the image decoded from ``alloc`` (as one layer: the decode of
        every layer up to one is that of their union; its packets as :func:`write_packets`
        writes them, each precinct's written once for each set of contributions)."""
        packets: list[bytes | None] = list(writer.packets(alloc))
        return sum(len(p) for p in packets if p is not None), quality(one_code, packets)

    changed = False
    for layer in range(sp.layers):
        n_cur, q = measure(allocs[layer])
        mark = max((m for m in marks if m <= q), default=None)
        if mark is None or q < mark + SLACK_DB:
            continue
        # a layer stays below the next mark: the next layer is the first to reach that one
        ceiling = min((m for m in marks if m > q), default=float("inf"))
        prev = allocs[layer - 1] if layer else {}
        nxt = allocs[layer + 1] if layer + 1 < sp.layers else None
        cur, n_cur = _search(allocs[layer], n_cur, q, prev, nxt, mark, ceiling, per_layer, measure)
        if cur is not allocs[layer]:
            allocs[layer], changed = cur, True
    if not changed:
        starts = _lengths(sp, w, h, body, blocks)
        return body, starts
    return write_packets(sp, w, h, allocs, blocks)


def _search(start: Allocation, n_start: int, q_start: float, prev: Allocation, nxt: Allocation | None, mark: float,
            ceiling: float, budget: int, measure: Any) -> tuple[Allocation, int]:
    """The fewest bytes from ``start`` (between ``prev`` and it) still reaching ``mark`` (and
    not ``ceiling``: a layer's decode may gain by a cut, never past the next mark). Each
    round takes the layer's contributions, largest first, and tries taking off their last
    bytes: about what the layer's excess quality is worth (:data:`DB_PER_E` dB per e-fold of
    bytes near a mark), half and twice that, or all of a contribution when that is no more
    (left to the next layer); the option with the fewest bytes that still reaches the mark is
    kept. Rounds repeat while one helps and the budget lasts."""
    cur, n_cur, q_cur, left = start, n_start, q_start, budget
    improved = True
    while improved and left > 0:
        improved = False
        sizes = sorted(((nb - prev.get(cb, (0, 0))[1], cb) for cb, (n, nb) in cur.items()
                        if (n, nb) != prev.get(cb, (0, 0))), reverse=True)
        for size, cb in sizes:
            if left <= 0:
                break
            n1, b1 = cur[cb]
            n0, b0 = prev.get(cb, (0, 0))
            # cut inside a pass only where the next layer adds a pass to this code-block (it
            # brings the rest of this one), or where nothing follows
            can_cut = nxt is None or nxt.get(cb, (0, 0))[0] > n1
            excess = max(1, round(n_cur * min(q_cur - mark, 10.0) / DB_PER_E))  # inf: identical
            removals = sorted({min(size, r) for r in (2 * excess, excess, max(1, excess // 2))}, reverse=True)
            best: tuple[int, float, Allocation] | None = None
            for r in removals:
                whole = r >= size
                if not whole and not can_cut:
                    continue
                trial = dict(cur)
                if whole and n0 == 0:
                    del trial[cb]
                else:
                    trial[cb] = (n0, b0) if whole else (n1, b1 - r)
                n, q = measure(trial)
                left -= 1
                if mark <= q < ceiling and n < n_cur and (best is None or n < best[0]):
                    best = (n, q, trial)
                    break  # the largest removal that works (they are tried largest first)
                if left <= 0:
                    break
            if best is not None:
                n_cur, q_cur, cur = best
                improved = True
    return cur, n_cur


def _lengths(sp: StreamParams, w: int, h: int, body: bytes, blocks: CodeBlocks) -> list[int]:
    """The packet lengths of an unchanged body."""
    return [int(v) for v in packet_lengths(sp, w, h, body)]
