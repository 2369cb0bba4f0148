"""Fuzz the receive path of the MAVLink binding with mutated inputs.

Every input goes through :meth:`TunnelCodec.receive`, as a UDP datagram or as a piece of a
TCP/serial stream (alternately, into two long-lived codecs, so parser and reassembly state carry
over from input to input). Inputs come from three mutators, seeded with real packets (multi-
fragment CoEx frames, single-fragment frames, heartbeats, other messages):

* ``bytes``: bit flips, interesting bytes (0x00, 0xFD, 0xFE, 0xFF, 0x80, 128, 129), inserts,
  deletions, duplications, truncations and splices of concatenated packets (CRCs mostly break);
* ``fields``: TUNNEL messages re-packed by pymavlink with a valid CRC but mutated fields
  (payload_length 0..255, fragment header bytes, payload_type, targets, non-zero tails);
* ``random``: uniformly random bytes.

An *escape* is any exception leaving ``receive`` or any broken invariant: a frame above the MTU,
more partial frames than ``max_partial``, more buffered chunk bytes than ``max_partial * mtu``,
or a parser holding more than one maximal MAVLink packet after a call.

Usage: ``.venv/bin/python bench/fuzz_mavlink.py [--inputs N] [--seed S] [--quick]``; prints the
numbers and writes ``bench/results/fuzz_mavlink.json``. Exit code 1 if anything escaped.
"""

from __future__ import annotations

import argparse
import json
import random
import re
import sys
import time
import traceback
from collections import Counter, deque
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from coex_transports.mavlink import PAYLOAD_TYPE, TunnelCodec, split_frame

MTU = 2048
MAX_PARTIAL = 8
MAX_PACKET = 10 + 255 + 2 + 13  # MAVLink 2 header, payload, CRC, signature
INTERESTING = [0x00, 0xFD, 0xFE, 0xFF, 0x80, 0x7F, 128, 129, 1, 0x10, 0xC0, 0xE5]


def seed_packets(rng: random.Random) -> list[bytes]:
    sender = TunnelCodec(system_id=7, component_id=1, heartbeat_interval=1.0)
    packets: list[bytes] = []
    for size in (0, 1, 40, 124, 125, 300, 900, 2048):
        packets += sender.encode(rng.randbytes(size))
    packets.append(sender.heartbeat())
    mav = mavlink2.MAVLink(None, 3, 1)
    packets.append(bytes(mav.param_request_list_encode(0, 0).pack(mav)))
    packets.append(bytes(mav.heartbeat_encode(2, 3, 0, 0, 4).pack(mav, force_mavlink1=True)))
    return packets


class Mutator:
    def __init__(self, rng: random.Random) -> None:
        self.rng = rng
        self.seeds = seed_packets(rng)
        self.mav = mavlink2.MAVLink(None, 9, 2)

    def bytes_level(self) -> bytes:
        r = self.rng
        start = r.randrange(len(self.seeds))
        data = bytearray(b"".join(self.seeds[start:start + r.randint(1, 4)]))
        for _ in range(r.randint(1, 8)):
            op = r.randrange(7)
            pos = r.randrange(len(data)) if data else 0
            if op == 0 and data:
                data[pos] ^= 1 << r.randrange(8)
            elif op == 1 and data:
                data[pos] = r.choice(INTERESTING)
            elif op == 2:
                data[pos:pos] = r.randbytes(r.randint(1, 16))
            elif op == 3 and data:
                del data[pos:pos + r.randint(1, 16)]
            elif op == 4 and data:
                n = r.randint(1, 32)
                data[pos:pos] = data[pos:pos + n]
            elif op == 5 and data:
                del data[r.randrange(len(data) + 1):]
            else:
                other = r.choice(self.seeds)
                cut = r.randrange(len(other) + 1)
                data[pos:pos] = other[cut:]
        return bytes(data)

    def field_level(self) -> bytes:
        r = self.rng
        frame = r.randbytes(r.choice([0, 3, 50, 124, 200, 600, 2048, 2100]))
        payloads = split_frame(frame, r.randrange(256)) if len(frame) <= 31620 else [b""]
        out = []
        for payload in r.sample(payloads, k=min(len(payloads), r.randint(1, 4))):
            p = bytearray(payload)
            length = len(p)
            for _ in range(r.randint(0, 3)):
                op = r.randrange(6)
                if op == 0:
                    length = r.randrange(256)
                elif op == 1 and p:
                    p[r.randrange(min(4, len(p)))] = r.choice([*INTERESTING, r.randrange(256)])
                elif op == 2:
                    p = p[: r.randrange(len(p) + 1)]
                    length = len(p)
                elif op == 3:
                    p += r.randbytes(r.randint(1, 8))
                elif op == 4 and p:
                    p[r.randrange(len(p))] = r.randrange(256)
            p = p[:128]
            body = list(p) + [0] * (128 - len(p))
            if r.random() < 0.1:
                body[r.randrange(128)] = r.randrange(1, 256)  # dirt after payload_length
            ptype = PAYLOAD_TYPE if r.random() < 0.9 else r.randrange(65536)
            target = (0, 0) if r.random() < 0.8 else (r.randrange(3), r.randrange(3))
            msg = self.mav.tunnel_encode(target[0], target[1], ptype, length, body)
            out.append(bytes(msg.pack(self.mav)))
            self.mav.seq = (self.mav.seq + 1) % 256
        return b"".join(out)

    def random_bytes(self) -> bytes:
        return self.rng.randbytes(self.rng.randint(0, 300))

    def next(self) -> tuple[str, bytes]:
        x = self.rng.random()
        if x < 0.6:
            return "bytes", self.bytes_level()
        if x < 0.9:
            return "fields", self.field_level()
        return "random", self.random_bytes()


def check(codec: TunnelCodec, frames: list[bytes]) -> str | None:
    if any(not isinstance(f, bytes) or len(f) > MTU for f in frames):
        return "frame above the MTU or not bytes"
    if len(codec.reassembler) > MAX_PARTIAL:
        return f"{len(codec.reassembler)} partial frames held"
    if codec.reassembler.buffered_bytes > MAX_PARTIAL * MTU:
        return f"{codec.reassembler.buffered_bytes} B buffered"
    if codec._parser.buf_len() > MAX_PACKET:
        return f"parser holds {codec._parser.buf_len()} B"
    return None


class ReasonCounter(deque):  # type: ignore[type-arg]
    """``TunnelCodec.errors`` replacement that also tallies every rejection by its reason."""

    def __init__(self, tally: Counter[str]) -> None:
        super().__init__(maxlen=4)
        self.tally = tally

    def append(self, err: Any) -> None:
        text = re.sub(r"^from \d+/\d+: ", "", str(err))
        text = re.sub(r"\(\d+ B\)", "", text)
        key = re.split(r"[0-9]", text, maxsplit=1)[0].strip(" :(,")
        self.tally[key[:60]] += 1
        super().append(err)


def new_codec(tally: Counter[str]) -> TunnelCodec:
    codec = TunnelCodec(system_id=1, component_id=191, mtu=MTU, max_partial=MAX_PARTIAL,
                        reassembly_timeout=2.0, heartbeat_interval=0)
    codec.errors = ReasonCounter(tally)
    return codec


def _add(totals: Counter[str], codecs: dict[bool, TunnelCodec]) -> None:
    for c in codecs.values():
        totals.update(c.counters)
        totals.update({f"reassembly_{k}": v for k, v in c.reassembler.stats().items()
                       if k not in ("partial", "buffered_bytes")})


def run(n_inputs: int, seed: int) -> dict[str, Any]:
    rng = random.Random(seed)
    mut = Mutator(rng)
    reasons: Counter[str] = Counter()
    totals: Counter[str] = Counter()
    codecs = {True: new_codec(reasons), False: new_codec(reasons)}
    now = 0.0
    executed = escapes = frames_out = 0
    by_kind: dict[str, int] = {"bytes": 0, "fields": 0, "random": 0}
    examples: list[dict[str, str]] = []
    t0 = time.perf_counter()
    for i in range(n_inputs):
        kind, data = mut.next()
        datagram = (i & 1) == 0
        codec = codecs[datagram]
        now += rng.random() * 0.1
        executed += 1
        by_kind[kind] += 1
        try:
            frames = codec.receive(data, now, datagram=datagram)
            problem = check(codec, frames)
            frames_out += len(frames)
        except Exception:
            problem = traceback.format_exc(limit=3)
        if problem is not None:
            escapes += 1
            if len(examples) < 10:
                examples.append({"kind": kind, "datagram": str(datagram), "input": data.hex(),
                                 "problem": problem})
        if i % 50_000 == 49_999:
            _add(totals, codecs)
            codecs = {True: new_codec(reasons), False: new_codec(reasons)}
    elapsed = time.perf_counter() - t0
    _add(totals, codecs)
    return {
        "inputs_executed": executed,
        "escapes": escapes,
        "frames_delivered": frames_out,
        "inputs_by_mutator": by_kind,
        "seconds": round(elapsed, 2),
        "inputs_per_second": round(executed / elapsed) if elapsed else None,
        "seed": seed,
        "codec_counters": dict(sorted(totals.items())),
        "rejections_by_reason": dict(reasons.most_common()),
        "escape_examples": examples,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--inputs", type=int, default=1_000_000, help="mutated inputs (default 10^6)")
    ap.add_argument("--seed", type=int, default=20261122)
    ap.add_argument("--quick", action="store_true", help="20,000 inputs (a smoke run)")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results" / "fuzz_mavlink.json")
    args = ap.parse_args(argv)
    n = 20_000 if args.quick else args.inputs
    result = run(n, args.seed)
    result["target_inputs"] = 1_000_000
    result["target_met"] = result["inputs_executed"] >= 1_000_000 and result["escapes"] == 0
    result["quick"] = bool(args.quick)
    print(f"inputs executed: {result['inputs_executed']:,}")
    print(f"escapes:         {result['escapes']}")
    print(f"frames delivered (valid or re-CRCed mutants): {result['frames_delivered']:,}")
    print(f"by mutator:      {result['inputs_by_mutator']}")
    print(f"time:            {result['seconds']} s ({result['inputs_per_second']:,} inputs/s)")
    print(f"delivered frames / fragments received: {result['codec_counters'].get('frames_received', 0):,}"
          f" / {result['codec_counters'].get('fragments_received', 0):,}")
    print("rejections by reason (top 12):")
    for reason, n in list(result["rejections_by_reason"].items())[:12]:
        print(f"  {n:>9,}  {reason}")
    for ex in result["escape_examples"][:3]:
        print("escape:", ex["kind"], ex["input"][:80], ex["problem"].splitlines()[-1])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 1 if result["escapes"] else 0


if __name__ == "__main__":
    sys.exit(main())
