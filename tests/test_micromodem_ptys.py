"""The in-process modem network can carry each host's NMEA through a real pseudo-terminal."""

from __future__ import annotations

import os

from coex_core.acoustic import AcousticChannel
from coex_transports.micromodem import ModemNetwork


def test_frames_cross_real_ptys_on_simulated_time() -> None:
    net = ModemNetwork({1: (0.0, 0.0, 0.0), 2: (1500.0, 0.0, 0.0)}, channel=AcousticChannel(seed=1), ptys=True)
    try:
        a = net.transport(1, dest=2, rate=5)
        b = net.transport(2, dest=1, rate=5)
        paths = net.pty_paths()
        assert set(paths) == {1, 2} and all(p.startswith("/dev/pts/") and os.path.exists(p) for p in paths.values())
        frames = [bytes([i]) * (40 + i) for i in range(3)]
        a.send_packet(frames, 5)
        got = [b.recv(timeout=120.0) for _ in frames]
        assert got == frames
        b.send(b"back")
        assert a.recv(timeout=120.0) == b"back"
    finally:
        net.close()
