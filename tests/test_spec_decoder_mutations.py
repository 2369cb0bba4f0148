"""The decoder written from spec/ alone (tests/test_spec_decoder.py) against the reference decoder
(`coex spec decode`, section 13.3) on inputs no vector holds: every valid vector with bits
flipped, cut short, lengthened or a byte inserted, under a fixed seed. Both must accept the same
inputs and decode them to the same fields; an input both reject may be rejected for different
words (section 13.2: an input that breaks several rules may be rejected for any of them). A
disagreement is a rule the reference checks and the document does not state (or states
otherwise): the document is incomplete there."""

from __future__ import annotations

import json
import random

from coex_core._wire import spec as specgen

from .test_spec_decoder import VECTORS, answer

CASES = [c for c in specgen.vector_cases(VECTORS) if c[1] in ("message", "frame")]


def _mutated(rng: random.Random, data: bytes) -> bytes:
    d = bytearray(data)
    op = rng.random()
    if op < 0.5 and d:
        for _ in range(rng.randint(1, 3)):
            i = rng.randrange(8 * len(d))
            d[i // 8] ^= 0x80 >> (i % 8)
    elif op < 0.7 and d:
        del d[rng.randrange(len(d)):]
    elif op < 0.85:
        d += bytes(rng.randrange(256) for _ in range(rng.randint(1, 3)))
    else:
        i = rng.randrange(len(d) + 1)
        d[i:i] = bytes([rng.randrange(256)])
    return bytes(d)


def test_the_document_s_decoder_and_the_reference_accept_the_same_mutated_inputs() -> None:
    rng = random.Random(54)
    disagreements = []
    rejected = 0
    for _ in range(1500):
        name, scope, hx, _ = rng.choice(CASES)
        mutated = _mutated(rng, bytes.fromhex(hx)).hex()
        reference = specgen.decode_line(f"{scope} {mutated}")
        ours = json.loads(answer(scope, mutated))
        if "error" in reference and "error" in ours:
            rejected += 1
            continue
        want = {"error": reference["error"]} if "error" in reference else reference
        disagreements += specgen.compare_answers([(f"{name} mutated", scope, mutated, want)], json.dumps(ours))
    assert disagreements == []
    assert 300 < rejected < 1400  # both accepted and rejected inputs were tried
