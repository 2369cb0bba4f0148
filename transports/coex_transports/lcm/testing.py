"""Test helpers for the LCM transport: the loopback multicast check and unique channels (the
conformance fixtures are in ``tests/test_lcm_conformance.py``).

``udpm://`` with ``ttl=0`` keeps traffic on the host, but the kernel still needs a route for
multicast destinations. :func:`udpm_works` checks that an LCM instance hears its own multicast;
:func:`ensure_multicast_route` (root only) adds ``224.0.0.0/4 dev lo`` and turns multicast on
for ``lo`` when it does not, and returns an undo function.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
import uuid
from collections.abc import Callable

__all__ = [
    "TEST_UDPM_URL",
    "ensure_multicast_route",
    "unique_channel",
    "udpm_works",
]

#: udpm URL of the tests: LCM's default group, host-local (ttl=0).
TEST_UDPM_URL = "udpm://239.255.76.67:7667?ttl=0"


def unique_channel(prefix: str = "COEX_TEST") -> str:
    """A channel name no other test (or parallel test process) uses."""
    return f"{prefix}_{os.getpid()}_{uuid.uuid4().hex[:10]}"


def udpm_works(url: str = TEST_UDPM_URL, timeout: float = 1.0) -> bool:
    """Whether an LCM instance on ``url`` receives what it publishes (multicast is routed)."""
    import lcm

    try:
        instance = lcm.LCM(url)
    except Exception:
        return False
    channel = unique_channel("COEX_PROBE")
    got: list[bytes] = []
    instance.subscribe(channel, lambda _c, data: got.append(data))
    deadline = time.monotonic() + timeout
    while not got and time.monotonic() < deadline:
        instance.publish(channel, b"probe")
        instance.handle_timeout(100)
    return bool(got)


def ensure_multicast_route(url: str = TEST_UDPM_URL) -> Callable[[], None]:
    """Make ``udpm://`` work on this host; return a function that undoes what was changed.

    Does nothing when multicast already works. Otherwise, as root, runs
    ``ip link set lo multicast on`` and ``ip route add 224.0.0.0/4 dev lo`` (LCM's
    ``multicast-setup`` advice). Raises ``RuntimeError`` if multicast still does not work."""
    if udpm_works(url):
        return lambda: None
    ip = shutil.which("ip")
    if os.geteuid() != 0 or ip is None:
        raise RuntimeError(
            "LCM udpm:// needs a multicast route; as root run: "
            "ip link set lo multicast on && ip route add 224.0.0.0/4 dev lo"
        )
    subprocess.run([ip, "link", "set", "lo", "multicast", "on"], check=False, timeout=10)
    added = subprocess.run(
        [ip, "route", "add", "224.0.0.0/4", "dev", "lo"], check=False, timeout=10, capture_output=True
    ).returncode == 0
    if not udpm_works(url):
        raise RuntimeError("LCM udpm:// still fails after adding a multicast route on lo")

    def undo() -> None:
        if added:
            subprocess.run([ip, "route", "del", "224.0.0.0/4", "dev", "lo"], check=False, timeout=10)

    return undo
