"""``coex modem-sim``: simulated Micromodem-2s on pseudo-terminals, joined by an acoustic channel.

    coex modem-sim --nodes 1,2 [--tcp-base 4001] [--link DIR] [--spacing 1000] [--loss 0.1] [--speed 1]

prints one line per modem (``modem 1: /dev/pts/7``, plus ``tcp 127.0.0.1:4001`` with
``--tcp-base``) and serves until interrupted or ``--duration`` seconds have passed. Point a driver
at a device path (``micromodem:///dev/pts/7?src=1``), at a TCP port
(``micromodem:socket://127.0.0.1:4001?src=1``), or WHOI's ``acomms`` library at the path.

``--link DIR`` also makes ``DIR/modem<N>`` a symbolic link to modem N's pseudo-terminal, the way
udev makes ``/dev/serial/by-id/...`` for a USB modem: a simulator stopped and started again
gets new pseudo-terminals behind the same names (the links go when it stops), so a configuration
that names the link sees the modem go away and come back.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence
from typing import Any

from coex_core.errors import ConfigError


def _nodes(text: str) -> list[int]:
    try:
        nodes = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a comma-separated list of node ids: {text!r}") from None
    if len(nodes) < 2 or len(set(nodes)) != len(nodes) or not all(1 <= n <= 127 for n in nodes):
        raise argparse.ArgumentTypeError("give at least two distinct node ids in 1..127")
    return nodes


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "modem-sim", help="simulated Micromodem-2s on pseudo-terminals (and TCP), joined acoustically",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--nodes", type=_nodes, default=[1, 2], help="node ids (= modem SRC), default 1,2")
    p.add_argument("--tcp-base", type=int, default=None, metavar="PORT",
                   help="also serve modem i on TCP port PORT+i (0-based) on 127.0.0.1")
    p.add_argument("--spacing", type=float, default=1000.0, help="metres between neighbouring nodes (a line)")
    p.add_argument("--loss", type=float, default=0.0, help="frame loss probability")
    p.add_argument("--ber", type=float, default=0.0, help="bit error rate")
    p.add_argument("--sound-speed", type=float, default=1500.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--speed", type=float, default=1.0, help="simulated seconds per real second")
    p.add_argument("--duration", type=float, default=None, help="stop after this many real seconds")
    p.add_argument("--link", metavar="DIR", default=None,
                   help="make DIR/modem<N> a symbolic link to modem N's pseudo-terminal (stable names "
                        "across restarts, like /dev/serial/by-id)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from coex_core.acoustic import AcousticChannel

    from .simulator import ModemNetwork, PtySimulator

    if args.speed <= 0:
        raise ConfigError("--speed must be positive")
    channel = AcousticChannel(loss=args.loss, bit_error_rate=args.ber, sound_speed=args.sound_speed,
                              seed=args.seed)
    positions: dict[int, Sequence[float]] = {n: (i * args.spacing, 0.0, 0.0) for i, n in enumerate(args.nodes)}
    network = ModemNetwork(positions, channel=channel)
    tcp = None if args.tcp_base is None else {n: args.tcp_base + i for i, n in enumerate(args.nodes)}
    sim = PtySimulator(network, tcp_ports=tcp, speed=args.speed)
    links = _links(args.link, sim.paths) if args.link else {}
    for n in args.nodes:
        line = f"modem {n}: {links.get(n, sim.paths[n])}"
        if n in links:
            line += f" -> {sim.paths[n]}"
        if n in sim.tcp_addresses:
            host, port = sim.tcp_addresses[n]
            line += f" tcp {host}:{port}"
        print(line, flush=True)
    sim.start()
    try:
        end = None if args.duration is None else time.monotonic() + args.duration
        while end is None or time.monotonic() < end:
            time.sleep(0.2 if end is None else max(0.0, min(0.2, end - time.monotonic())))
    except KeyboardInterrupt:
        pass
    finally:
        sim.stop()
        for path in links.values():
            try:
                os.unlink(path)
            except OSError:
                pass
    return 0


def _links(folder: str, paths: dict[int, str]) -> dict[int, str]:
    """``folder/modem<N>`` -> modem N's pseudo-terminal, each replaced atomically."""
    os.makedirs(folder, exist_ok=True)
    out = {}
    for n, target in paths.items():
        link = os.path.join(folder, f"modem{n}")
        tmp = f"{link}.{os.getpid()}.tmp"
        os.symlink(target, tmp)
        os.replace(tmp, link)
        out[n] = link
    return out


if __name__ == "__main__":  # pragma: no cover
    sys.exit(2)
