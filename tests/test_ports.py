"""Ports handed to other processes (``coex_transports.testing.free_port``): below the kernel's
ephemeral range, reserved for the process that asked, free when given."""

from __future__ import annotations

import socket
import subprocess
import sys

from coex_transports import testing
from coex_transports.testing import free_port, port_holders


def test_a_port_is_below_the_ephemeral_range_free_and_never_given_twice() -> None:
    lo, _ = testing._ephemeral()
    ports = [free_port() for _ in range(20)]
    assert len(set(ports)) == 20
    assert all(testing.LOWEST <= p < lo for p in ports), ports
    for p in ports:  # free, TCP and UDP, without SO_REUSEADDR
        for kind in (socket.SOCK_STREAM, socket.SOCK_DGRAM):
            with socket.socket(socket.AF_INET, kind) as s:
                s.bind(("0.0.0.0", p))


def test_another_process_is_not_given_a_port_this_one_holds() -> None:
    mine = free_port()
    code = ("import sys; from coex_transports import testing as t; "
            f"print(t._lock({mine}), len({{t.free_port() for _ in range(200)}} & {{{mine}}}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["False", "0"]


def test_a_port_someone_binds_is_not_given_and_its_holder_is_named() -> None:
    base = free_port(3)
    assert all(p in testing._held for p in (base, base + 1, base + 2))
    testing._release(base + 1)
    with socket.socket() as s:
        s.bind(("127.0.0.1", base + 1))
        s.listen()
        assert port_holders(base + 1) == [f"127.0.0.1:{base + 1} -> 0.0.0.0:0 LISTEN"]
        # while it is bound, a block that would need it is not given
        assert not testing._bindable(base + 1)
    assert port_holders(base + 1) == []
