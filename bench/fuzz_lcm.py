"""Fuzz the LCM receive path: at least 10^6 mutated inputs through ``coex.frame_t`` decoding
and CoEx frame unpacking, and a share of them through the transport's LCM callback.

Seeds are ``coex.frame_t`` messages carrying the golden frames (``spec/vectors/frames.json``)
and frames of every message type's golden cases. Each input is one of:

* a raw mutation of the whole LCM message (fingerprint, utime, origin, length field, data):
  bit flips, random bytes, truncation, insertion, deletion, garbage, length-field rewrites;
* a mutated CoEx frame re-wrapped in a valid ``frame_t`` (valid LCM, corrupt CoEx), which
  reaches ``coex_core.wire.unpack_frame``.

An escape is any exception other than ``DecodeError`` from
``coex_transports.lcm.unpack_event`` (the receive path), or any exception at all from
``LcmTransport._on_message`` (the LCM callback, which must count bad input, never raise).

    python bench/fuzz_lcm.py [--inputs N] [--seed S] [--jobs J] [--quick]

With ``--jobs J`` the inputs are split over J processes (seeds ``S*1000 + j``); the run is
deterministic for a given (S, J).

Prints inputs executed and escapes; writes bench/results/fuzz_lcm.json.
"""

from __future__ import annotations

import argparse
import json
import logging
import random
import struct
import sys
import time
import traceback
from collections import Counter
from pathlib import Path

from coex_core import wire
from coex_core._wire._registry import SPECS_BY_ID
from coex_core.errors import DecodeError
from coex_core.messages import FrameHeader
from coex_transports.lcm import LcmConfig, LcmTransport, encode_frame, unpack_event

ROOT = Path(__file__).resolve().parents[1]
CALLBACK_SHARE = 10  # one input in this many also goes through the transport callback


def seed_frames() -> list[bytes]:
    frames = []
    vectors = ROOT / "spec" / "vectors" / "frames.json"
    if vectors.exists():
        frames += [bytes.fromhex(v["hex"]) for v in json.loads(vectors.read_text())["vectors"]]
    for spec in SPECS_BY_ID.values():
        for _, message in spec.cases():
            frames.append(wire.pack([message], 256, FrameHeader(src=2, dst=1, seq=7, crc=True)))
            frames.append(wire.pack([message], 256, FrameHeader(src=1, dst=2, seq=8)))
    return frames


def mutate(rng: random.Random, data: bytes) -> bytes:
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        op = rng.randrange(7)
        if op == 0 and b:  # flip a bit
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
        elif op == 1 and b:  # random byte
            b[rng.randrange(len(b))] = rng.randrange(256)
        elif op == 2 and b:  # truncate
            del b[rng.randrange(len(b)):]
        elif op == 3:  # insert
            b.insert(rng.randrange(len(b) + 1), rng.randrange(256))
        elif op == 4 and len(b) > 1:  # delete
            del b[rng.randrange(len(b))]
        elif op == 5:  # append garbage
            b += rng.randbytes(rng.randint(1, 8))
        else:  # duplicate a slice
            if b:
                i = rng.randrange(len(b))
                b[i:i] = b[i:i + rng.randint(1, 16)]
    return bytes(b)


def mutate_lcm(rng: random.Random, event: bytes) -> bytes:
    """Mutate a whole frame_t message; sometimes rewrite its length field only."""
    if rng.random() < 0.15 and len(event) >= 28:
        b = bytearray(event)
        length = rng.choice([-1, -(2**31), 2**31 - 1, 0, len(event) - 27, len(event) - 29,
                             rng.randrange(-1000, 1000)])
        b[24:28] = struct.pack(">i", length)
        return bytes(b)
    return mutate(rng, event)


def run(inputs: int, seed: int) -> dict[str, object]:
    rng = random.Random(seed)
    frames = seed_frames()
    events = [encode_frame(f, utime=1_700_000_000_000_000 + i, origin=i) for i, f in enumerate(frames)]
    logging.getLogger("coex_transports").setLevel(logging.CRITICAL)
    sink = LcmTransport(LcmConfig(url="memq://", tx="FUZZ_TX", rx="FUZZ_RX", queue=64))
    outcomes: Counter[str] = Counter()
    escapes: list[dict[str, str]] = []
    t0 = time.perf_counter()
    for n in range(inputs):
        k = rng.randrange(len(frames))
        if rng.random() < 0.6:
            data = encode_frame(mutate(rng, frames[k]), utime=rng.getrandbits(63), origin=rng.getrandbits(63))
        else:
            data = mutate_lcm(rng, events[k])
        try:
            unpack_event(data)
            outcomes["accepted"] += 1
        except DecodeError:
            outcomes["DecodeError"] += 1
        except Exception as exc:
            outcomes["escape"] += 1
            if len(escapes) < 20:
                escapes.append({"path": "unpack_event", "hex": data.hex(), "error": repr(exc),
                                "trace": traceback.format_exc(limit=3)})
        if n % CALLBACK_SHARE == 0:
            outcomes["callback"] += 1
            try:
                sink._on_message("FUZZ_RX", data)
            except Exception as exc:
                outcomes["escape"] += 1
                if len(escapes) < 20:
                    escapes.append({"path": "_on_message", "hex": data.hex(), "error": repr(exc),
                                    "trace": traceback.format_exc(limit=3)})
    seconds = time.perf_counter() - t0
    stats = dict(sink.stats())
    sink.close()
    return {
        "inputs": inputs,
        "escapes": outcomes["escape"],
        "accepted": outcomes["accepted"],
        "decode_errors": outcomes["DecodeError"],
        "callback_inputs": outcomes["callback"],
        "callback_bad": stats["bad"],
        "callback_queued": stats["received"],
        "seeds": len(frames),
        "seed": seed,
        "seconds": round(seconds, 2),
        "inputs_per_s": round(inputs / seconds) if seconds else None,
        "escape_examples": escapes,
    }


def _run_part(part: tuple[int, int]) -> dict[str, object]:
    return run(*part)


def run_parallel(inputs: int, seed: int, jobs: int) -> dict[str, object]:
    if jobs <= 1:
        return run(inputs, seed)
    import multiprocessing

    shares = [inputs // jobs + (1 if j < inputs % jobs else 0) for j in range(jobs)]
    t0 = time.perf_counter()
    with multiprocessing.get_context("spawn").Pool(jobs) as pool:
        parts = pool.map(_run_part, [(n, seed * 1000 + j) for j, n in enumerate(shares)])
    seconds = time.perf_counter() - t0
    out: dict[str, object] = {key: sum(int(p[key]) for p in parts)  # type: ignore[call-overload]
                              for key in ("inputs", "escapes", "accepted", "decode_errors",
                                          "callback_inputs", "callback_bad", "callback_queued")}
    out.update(seeds=parts[0]["seeds"], seed=seed, jobs=jobs, seconds=round(seconds, 2),
               inputs_per_s=round(inputs / seconds) if seconds else None,
               escape_examples=[e for p in parts for e in p["escape_examples"]][:20])  # type: ignore[attr-defined]
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="fuzz the LCM receive path")
    parser.add_argument("--inputs", type=int, default=1_000_000, help="mutated inputs (default 10^6)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--jobs", type=int, default=1, help="processes to split the inputs over")
    parser.add_argument("--quick", action="store_true", help="10^4 inputs, for a smoke run")
    args = parser.parse_args(argv)
    inputs = 10_000 if args.quick else args.inputs
    result = run_parallel(inputs, args.seed, args.jobs)
    out = ROOT / "bench" / "results" / "fuzz_lcm.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print(f"inputs executed: {result['inputs']}")
    print(f"escapes: {result['escapes']}")
    print(f"accepted: {result['accepted']}, DecodeError: {result['decode_errors']}, "
          f"through the LCM callback: {result['callback_inputs']} "
          f"({result['callback_bad']} counted bad, {result['callback_queued']} queued)")
    print(f"{result['seconds']} s, {result['inputs_per_s']} inputs/s; wrote {out.relative_to(ROOT)}")
    return 1 if result["escapes"] else 0


if __name__ == "__main__":
    sys.exit(main())
