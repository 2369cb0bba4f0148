"""``coex send`` / ``coex listen`` with ``--transport mavlink:...``: two processes over UDP loopback."""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from pathlib import Path

from coex_core.messages import FrameHeader, Opaque
from coex_core.wire import pack, unpack_frame
from coex_transports.testing import free_port as _free_port

COEX = [str(Path(sys.executable).with_name("coex"))]


def _wait_bound(port: int, proc: subprocess.Popen[str], limit: float = 20.0) -> None:
    """Wait until the listener holds the UDP port (binding it ourselves then fails)."""
    deadline = time.monotonic() + limit
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                return
        time.sleep(0.05)
    raise AssertionError("listener never bound its port")


def test_send_and_listen_over_mavlink_udp() -> None:
    port = _free_port()
    small = pack([Opaque(96, b"hello")], 256, FrameHeader(src=2, dst=1, seq=1))
    big = pack([Opaque(500, bytes(range(240)))] * 3, 2048, FrameHeader(src=2, dst=1, seq=2, crc=True))
    listener = subprocess.Popen(
        [*COEX, "listen", "--transport", f"mavlink:udpin:127.0.0.1:{port}?sysid=1", "--count", "2",
         "--timeout", "30"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        _wait_bound(port, listener)
        sender = subprocess.run(
            [*COEX, "send", "--transport", f"mavlink:udpout:127.0.0.1:{port}?sysid=2&compid=190",
             "--hex", small.hex(), "--hex", big.hex()],
            capture_output=True, text=True, timeout=60,
        )
        assert sender.returncode == 0, sender.stderr
        out, err = listener.communicate(timeout=60)
    finally:
        if listener.poll() is None:
            listener.kill()
            listener.wait()
    assert listener.returncode == 0, err
    lines = out.split()
    assert lines == [small.hex(), big.hex()]
    assert unpack_frame(bytes.fromhex(lines[1])) == unpack_frame(big)


def test_listen_times_out_with_exit_code_1() -> None:
    proc = subprocess.run(
        [*COEX, "listen", "--transport", f"mavlink:udpin:127.0.0.1:{_free_port()}", "--timeout", "0.5"],
        capture_output=True, text=True, timeout=60,
    )
    assert proc.returncode == 1 and proc.stdout == ""
