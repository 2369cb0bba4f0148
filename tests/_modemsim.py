"""`coex modem-sim` as a process for tests: two simulated Micromodem-2s on one acoustic channel
(real time), each on a local TCP port, for nodes that open ``micromodem:socket://`` URIs."""

from __future__ import annotations

import contextlib
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def free_tcp_base(n: int = 2, kind: int = socket.SOCK_STREAM) -> int:
    """A base port with ``n`` consecutive free ports (TCP; ``kind=socket.SOCK_DGRAM``: UDP)."""
    for _ in range(50):
        with socket.socket(socket.AF_INET, kind) as s:
            s.bind(("127.0.0.1", 0))
            base = int(s.getsockname()[1])
        if base + n >= 65000:
            continue
        try:
            for i in range(n):
                with socket.socket(socket.AF_INET, kind) as t:
                    t.bind(("127.0.0.1", base + i))
            return base
        except OSError:
            continue
    raise RuntimeError("no free ports")


@contextlib.contextmanager
def modem_sim(nodes: tuple[int, ...] = (1, 2), loss: float = 0.0) -> Iterator[dict[int, str]]:
    """Yields node id -> its modem's URI prefix (``micromodem:socket://127.0.0.1:PORT``)."""
    base = free_tcp_base(len(nodes))
    proc = subprocess.Popen([sys.executable, "-m", "coex_core.cli", "modem-sim", "--nodes",
                             ",".join(map(str, nodes)), "--tcp-base", str(base), "--loss", str(loss)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT)
    try:
        end = time.monotonic() + 30
        while time.monotonic() < end:  # its TCP ports accept connections
            try:
                for i in range(len(nodes)):
                    socket.create_connection(("127.0.0.1", base + i), timeout=1).close()
                break
            except OSError:
                if proc.poll() is not None:
                    out = proc.stdout.read() if proc.stdout else ""
                    raise RuntimeError(f"coex modem-sim exited: {out}") from None
                time.sleep(0.2)
        yield {n: f"micromodem:socket://127.0.0.1:{base + i}" for i, n in enumerate(nodes)}
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
