"""Fuzz the Micromodem NMEA parser: at least 10^6 mutated sentences.

Every input goes through ``nmea.parse`` and, when it parses, the typed parser of its sentence
type (``parse_cacst``, ``parse_cardp`` ...). An *escape* is any exception other than
:class:`~coex_transports.micromodem.nmea.NmeaError`. Half of the mutants get their checksum
recomputed so that the field parsers, not just the checksum check, see them. Every 8th batch of 64
inputs is also fed, as one byte stream, to a :class:`MicromodemDriver`, whose ``feed``/``poll``
must never raise at all.

Prints the inputs executed and the escapes; writes ``bench/results/fuzz_nmea.json``.

    python bench/fuzz_nmea.py [--inputs N] [--seed S] [--quick]
"""

from __future__ import annotations

import argparse
import json
import random
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

from coex_transports.micromodem import nmea
from coex_transports.micromodem.driver import DriverConfig, MicromodemDriver

T0 = 1735732800.0

TYPED: dict[str, Callable[[nmea.Sentence], Any]] = {
    "CYC": nmea.parse_cacyc, "DRQ": nmea.parse_cadrq, "RXD": nmea.parse_carxd, "ACK": nmea.parse_caack,
    "REV": nmea.parse_carev, "ERR": nmea.parse_caerr, "RDP": nmea.parse_cardp, "CST": nmea.parse_cacst,
    "XST": nmea.parse_caxst, "MPR": nmea.parse_campr,
}

TOKENS = ["", "0", "1", "-1", "255", "256", "99999999999999999999", "nan", "inf", "-inf", "1e999", "0x10",
          "ff", "FFFF", "abc", "1;2;3", ";", ";;", "1;0;", "0;9999;", "BAD_CRC", "INIT", "AUV", "NMEA",
          "DATA_TIMEOUT", "20250101", "19700101", "20250101120000.5", " ", "\t", "é"]


def seeds() -> list[bytes]:
    L = nmea.format_sentence
    frames = [nmea.FdpFrame(True, 3, b"abc"), nmea.FdpFrame(False, 256, b""), nmea.FdpFrame(True, 1, b"\x00")]
    return [
        L("CACYC", [0, 1, 2, 5, 0, 8]), L("CADRQ", ["120000", 1, 2, 0, 256, 1]),
        L("CARXD", [2, 1, 0, 1, bytes(range(64)).hex()]), L("CAMSG", ["BAD_CRC", 2]), L("CAACK", [2, 1, 1, 1]),
        L("CAREV", ["120000", "INIT", "2.0.27087"]), L("CAERR", ["120000", "DATA_TIMEOUT", 1, "late"]),
        nmea.format_cardp(2, 1, 5, False, (), frames), L("CAMPR", [2, 1, "0.6667"]),
        nmea.format_cacst(T0, mode=1, rate=5, src=2, dest=1, psk_error=3, packet_type=3, frames=8, bad_frames=2,
                          snr_in=9.5, snr_out=14.0, doppler=-0.3),
        nmea.format_caxst(T0, mode=0, rate=5, src=1, dest=2, ack=False, frames_expected=8, frames_sent=8,
                          packet_type=3, nbytes=2048),
        L("CACFG", ["info.part_number", "201005"]), L("CATXF", []), L("CATXP", []), L("CATMS", [0, "x"]),
        b"$CACFG,CST,1*35\r\n", b"$CACYC,0,0,8,0,0,1*52\r\n",
    ]


def mutate(rng: random.Random, line: bytes) -> bytes:
    text = bytearray(line.rstrip(b"\r\n"))
    for _ in range(rng.randint(1, 3)):
        op = rng.randrange(8)
        if op == 0 and text:
            text[rng.randrange(len(text))] = rng.randrange(256)
        elif op == 1:
            text.insert(rng.randrange(len(text) + 1), rng.choice(b",;*$\r\n0123456789abcdefABCDEF\x00\xff"))
        elif op == 2 and len(text) > 1:
            del text[rng.randrange(len(text))]
        elif op == 3 and text:
            del text[rng.randrange(len(text)):]
        elif op == 4:  # replace one field with a hostile token
            body = bytes(text).split(b"*")[0]
            parts = body.split(b",")
            if len(parts) > 1:
                parts[rng.randrange(1, len(parts))] = rng.choice(TOKENS).encode("utf-8")
            text = bytearray(b",".join(parts))
        elif op == 5:  # drop or duplicate a field
            parts = bytes(text).split(b"*")[0].split(b",")
            i = rng.randrange(len(parts))
            if rng.random() < 0.5 and len(parts) > 1:
                del parts[i]
            else:
                parts.insert(i, parts[i])
            text = bytearray(b",".join(parts))
        elif op == 6:  # a long run
            i = rng.randrange(len(text) + 1)
            text[i:i] = bytes([rng.choice(b"0f;,")]) * rng.choice([10, 300, 5000, 9000])
        else:
            text += bytes(rng.randrange(256) for _ in range(rng.randint(1, 6)))
    if rng.random() < 0.5:  # give it a valid checksum so the field parsers are reached
        body = bytes(text).split(b"*")[0]
        if body.startswith(b"$"):
            body = body[1:]
        text = bytearray(b"$" + body + b"*" + nmea.checksum(body).encode())
    return bytes(text) + b"\r\n"


def run(inputs: int, seed: int) -> dict[str, Any]:
    rng = random.Random(seed)
    corpus = seeds()
    escapes: list[str] = []
    parsed = typed_ok = rejected = driver_feeds = 0
    driver = MicromodemDriver(DriverConfig(src=1))
    driver.start(T0)
    batch: list[bytes] = []
    t0 = time.perf_counter()
    for i in range(inputs):
        data = mutate(rng, rng.choice(corpus))
        try:
            s = nmea.parse(data)
            parsed += 1
            fn = TYPED.get(s.kind)
            if fn is not None:
                fn(s)
                typed_ok += 1
        except nmea.NmeaError:
            rejected += 1
        except Exception as exc:  # an escape
            if len(escapes) < 20:
                escapes.append(f"{type(exc).__name__}: {exc} <- {data[:120]!r}")
            else:
                escapes.append("")
        batch.append(data)
        if len(batch) == 64:
            if (i // 64) % 8 == 0:
                try:
                    driver.feed(b"".join(batch), T0 + i)
                    driver.poll(T0 + i)
                    driver.data_to_send()
                    driver_feeds += 1
                except Exception as exc:
                    escapes.append(f"driver {type(exc).__name__}: {exc}\n{traceback.format_exc()}")
            batch = []
    elapsed = time.perf_counter() - t0
    if driver.stats()["handler_errors"]:
        escapes.append(f"driver handler errors: {driver.stats()['handler_errors']}: {driver.stats()['last_error']}")
    return {
        "inputs": inputs, "seed": seed, "escapes": len(escapes), "escape_examples": [e for e in escapes if e][:20],
        "parsed": parsed, "typed_ok": typed_ok, "rejected": rejected, "driver_feeds": driver_feeds,
        "driver_stats": {k: v for k, v in driver.stats().items() if isinstance(v, int)},
        "seconds": round(elapsed, 2), "inputs_per_second": round(inputs / elapsed),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--inputs", type=int, default=1_000_000)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--quick", action="store_true", help="10^5 inputs")
    args = p.parse_args(argv)
    inputs = 100_000 if args.quick else args.inputs
    result = run(inputs, args.seed)
    print(f"inputs executed: {result['inputs']}")
    print(f"escapes: {result['escapes']}")
    print(f"parsed: {result['parsed']}  typed ok: {result['typed_ok']}  rejected: {result['rejected']}  "
          f"driver feeds: {result['driver_feeds']}")
    print(f"{result['seconds']} s, {result['inputs_per_second']} inputs/s")
    for e in result["escape_examples"]:
        print("  ", e)
    out = Path(__file__).parent / "results" / "fuzz_nmea.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    return 0 if result["escapes"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
