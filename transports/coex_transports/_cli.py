"""``coex send`` and ``coex listen``: the generic transport command line every transport implements.

``coex send --transport URI --hex HEX [--hex HEX ...]`` sends each frame;
``coex listen --transport URI --count N --timeout S`` prints each received frame as one line of
lowercase hex and exits after N frames or S seconds (exit code 0 if N frames arrived, else 1);
once its transport is open it says so on standard error ("coex listen: listening on URI").
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

from coex_core.errors import ConfigError
from coex_core.registry import open_transport


def _hex(value: str) -> bytes:
    try:
        return bytes.fromhex(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not hexadecimal: {value!r}") from None


def register_send(sub: Any) -> None:
    p = sub.add_parser("send", help="send frames (hex) over a transport URI")
    p.add_argument("--transport", required=True, metavar="URI", help="e.g. micromodem:///dev/ttyUSB0?rate=5")
    p.add_argument("--hex", dest="frames", action="append", type=_hex, required=True, metavar="HEX",
                   help="one frame as hex; repeat for several")
    p.set_defaults(func=run_send)


def register_listen(sub: Any) -> None:
    p = sub.add_parser("listen", help="print frames received on a transport URI as hex lines")
    p.add_argument("--transport", required=True, metavar="URI")
    p.add_argument("--count", type=int, default=1, help="exit after this many frames (default 1)")
    p.add_argument("--timeout", type=float, default=10.0, help="exit after this many seconds (default 10)")
    p.set_defaults(func=run_listen)


def run_send(args: argparse.Namespace) -> int:
    with open_transport(args.transport) as transport:
        for frame in args.frames:
            transport.send(frame)
        transport.flush()  # declared on Transport (default: nothing to wait for)
    return 0


def run_listen(args: argparse.Namespace) -> int:
    if args.count < 1 or args.timeout < 0:
        raise ConfigError("--count must be >= 1 and --timeout >= 0")
    got = 0
    deadline = time.monotonic() + args.timeout
    with open_transport(args.transport) as transport:
        print(f"coex listen: listening on {args.transport}", file=sys.stderr, flush=True)
        while got < args.count:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            frame = transport.recv(timeout=min(left, 0.5))
            if frame is None:
                continue
            print(frame.hex(), flush=True)
            got += 1
    return 0 if got >= args.count else 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(2)
