"""Fuzz the wire decoders: at least 10^6 mutated inputs across all message types and frames.

Prints the number of inputs executed and the number of escapes: any exception other than
DecodeError, or a decode slower than 10 ms. Writes bench/results/fuzz_wire.json.

    python bench/fuzz_wire.py [--inputs N] [--seed S] [--quick]
"""

from __future__ import annotations

import argparse
import json
import random
import sys
import time
from pathlib import Path

from coex_core import wire
from coex_core._wire._registry import SPECS_BY_ID
from coex_core.errors import DecodeError
from coex_core.messages import FrameHeader

SLOW_S = 0.010


def seeds() -> list[bytes]:
    out = []
    for spec in SPECS_BY_ID.values():
        for _, m in spec.cases():
            data = wire.encode(m)
            out.append(data)
            out.append(wire.pack([m], 256, FrameHeader(src=2, dst=1, seq=7, crc=True)))
    return out


def mutate(rng: random.Random, data: bytes) -> bytes:
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        op = rng.randrange(6)
        if op == 0 and b:  # flip a bit
            i = rng.randrange(len(b))
            b[i] ^= 1 << rng.randrange(8)
        elif op == 1 and b:  # random byte
            b[rng.randrange(len(b))] = rng.randrange(256)
        elif op == 2 and b:  # truncate
            del b[rng.randrange(len(b)):]
        elif op == 3:  # insert
            b.insert(rng.randrange(len(b) + 1), rng.randrange(256))
        elif op == 4 and len(b) > 1:  # delete
            del b[rng.randrange(len(b))]
        else:  # append garbage
            b += bytes(rng.randrange(256) for _ in range(rng.randint(1, 8)))
    return bytes(b)


def _cpu_time(fn: object, data: bytes) -> float:
    t0 = time.process_time()
    try:
        fn(data)  # type: ignore[operator]
    except Exception:
        pass
    return time.process_time() - t0


def run(n: int, seed: int) -> dict[str, object]:
    rng = random.Random(seed)
    corpus = seeds()
    escapes: list[str] = []
    slow = 0
    decoded = 0
    worst = 0.0
    start = time.perf_counter()
    for i in range(n):
        data = mutate(rng, rng.choice(corpus))
        fn = wire.decode if i % 2 == 0 else wire.unpack_frame
        # CPU time of this process: other processes on a shared machine do not count against a decode
        t0 = time.process_time()
        try:
            fn(data)
            decoded += 1
        except DecodeError:
            pass
        except Exception as exc:  # an escape: anything but DecodeError
            if len(escapes) < 20:
                escapes.append(f"{type(exc).__name__}: {exc} on {data.hex()}")
            else:
                escapes.append("...")
        dt = time.process_time() - t0
        if dt > SLOW_S:
            # a decode is deterministic: time it again and keep the fastest of three, so that a
            # page fault or a busy machine is not blamed on the decoder
            dt = min(dt, *(_cpu_time(fn, data) for _ in range(2)))
        worst = max(worst, dt)
        if dt > SLOW_S:
            slow += 1
            if len(escapes) < 20:
                escapes.append(f"slow decode ({dt * 1000:.1f} ms CPU) of {data.hex()}")
        if (i + 1) % 100000 == 0:
            print(f"  {i + 1} inputs, {len(escapes)} exceptions, {slow} slow", flush=True)
    return {
        "inputs": n,
        "seed": seed,
        "valid_after_mutation": decoded,
        "exception_escapes": len([e for e in escapes if not e.startswith("slow")]),
        "slow_escapes": slow,
        "escapes": len([e for e in escapes if not e.startswith("slow")]) + slow,
        "worst_decode_ms": round(worst * 1000, 3),
        "seconds": round(time.perf_counter() - start, 1),
        "examples": escapes[:20],
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--inputs", type=int, default=1_000_000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="10^4 inputs")
    args = ap.parse_args()
    n = 10_000 if args.quick else args.inputs
    result = run(n, args.seed)
    print(f"fuzz_wire: {result['inputs']} inputs executed, {result['escapes']} escapes "
          f"({result['exception_escapes']} exceptions, {result['slow_escapes']} slower than 10 ms), "
          f"worst decode {result['worst_decode_ms']} ms, {result['seconds']} s")
    out = Path(__file__).resolve().parent / "results"
    out.mkdir(exist_ok=True)
    (out / "fuzz_wire.json").write_text(json.dumps(result, indent=2))
    return 0 if result["escapes"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
