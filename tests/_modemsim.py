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

from coex_transports.testing import free_port

ROOT = Path(__file__).resolve().parents[1]


def free_tcp_base(n: int = 2, kind: int = socket.SOCK_STREAM) -> int:
    """A base port with ``n`` consecutive free ports (TCP and UDP, whatever ``kind``), reserved
    for this process (:func:`coex_transports.testing.free_port`)."""
    del kind  # both are checked free
    return free_port(n)


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
