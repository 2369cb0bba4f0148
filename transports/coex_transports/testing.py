"""Local ports for tests and benchmarks that hand a port to another process (a MOOSDB, a modem
simulator, a daemon) or bind it again later (a server restarted on its port).

The usual way, binding port 0 and closing the socket, gives a port from the kernel's ephemeral
range (``/proc/sys/net/ipv4/ip_local_port_range``, 32768-60999 on Linux), which is free only
until someone else is given it: the kernel hands the same range out to every ``bind(("", 0))``
(servers, browsers, daemons, the other test workers picking their own ports) and to the local end
of every outgoing connection. A port left free for a moment (between the pick and the child's
bind, or while a server is down to be restarted on it) can be taken, and the child then fails
("Error binding to listen socket"): seen with four pytest workers on two cores.

:func:`free_port` instead gives ports *below* the ephemeral range, which the kernel never hands
out on its own, so only an explicit bind can take them; and each port given is reserved for the
life of the process that asked, by a lock on a file named after it (``/tmp/coex-ports-UID/``,
whatever the process's ``TMPDIR``): every caller on the machine (each xdist worker, another checkout's test
run, a benchmark) skips a port another process holds. A port is also checked free (TCP and UDP,
without ``SO_REUSEADDR``, so a connection of an earlier user still in TIME_WAIT counts as taken).
"""

from __future__ import annotations

import errno
import fcntl
import os
import random
import socket
import tempfile
from pathlib import Path

__all__ = ["free_port", "port_holders"]

#: the lowest port :func:`free_port` gives (ports below are left to services)
LOWEST = 20000

_held: dict[int, int] = {}  # port -> the descriptor of its lock file, held until this process ends


def _ephemeral() -> tuple[int, int]:
    try:
        lo, hi = map(int, Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
        return lo, hi
    except (OSError, ValueError):
        return 32768, 60999  # Linux's default


def _candidates() -> range:
    lo, hi = _ephemeral()
    if lo - LOWEST >= 1000:
        return range(LOWEST, lo)
    return range(hi + 1, 65536)  # a range reaching down to LOWEST: above it


def _lock(port: int) -> bool:
    # one directory for every process of the machine, whatever its TMPDIR (a test may give a
    # child process a TMPDIR of its own)
    d = (Path("/tmp") if Path("/tmp").is_dir() else Path(tempfile.gettempdir())) / f"coex-ports-{os.getuid()}"
    d.mkdir(exist_ok=True)
    fd = os.open(d / str(port), os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        os.close(fd)
        if exc.errno in (errno.EWOULDBLOCK, errno.EACCES):
            return False
        raise
    _held[port] = fd
    return True


def _release(port: int) -> None:
    fd = _held.pop(port, None)
    if fd is not None:
        os.close(fd)  # closing the descriptor drops the lock


def _bindable(port: int) -> bool:
    for kind in (socket.SOCK_STREAM, socket.SOCK_DGRAM):
        with socket.socket(socket.AF_INET, kind) as s:
            try:
                s.bind(("0.0.0.0", port))
            except OSError:
                return False
    return True


def free_port(n: int = 1) -> int:
    """A port on this machine (the first of ``n`` consecutive ones) that nothing binds, TCP or
    UDP, reserved for this process until it ends: no other caller of :func:`free_port` is given
    it, and the kernel never gives it to anyone (below the ephemeral range). Hand it to a child
    process, or close a server on it and bind it again: nobody else takes it meanwhile."""
    ports = _candidates()
    span = len(ports) - n
    start = random.Random(os.getpid() ^ int.from_bytes(os.urandom(4), "little")).randrange(span)
    for i in range(span):
        base = ports[(start + i) % span]
        got: list[int] = []
        for p in range(base, base + n):
            if p in _held or not _lock(p):
                break
            got.append(p)
            if not _bindable(p):
                break
        else:
            return base
        for p in got:
            _release(p)
    raise RuntimeError(f"no {n} free consecutive ports in {ports.start}-{ports.stop - 1}")


_TCP_STATES = {"01": "ESTABLISHED", "02": "SYN_SENT", "03": "SYN_RECV", "04": "FIN_WAIT1", "05": "FIN_WAIT2",
               "06": "TIME_WAIT", "07": "CLOSE", "08": "CLOSE_WAIT", "09": "LAST_ACK", "0A": "LISTEN",
               "0B": "CLOSING"}


def port_holders(port: int) -> list[str]:
    """The TCP sockets bound to local ``port`` now, from the kernel's tables (Linux), as
    ``"local -> remote STATE"``: why a server could not bind it. Empty when none (or no
    ``/proc``)."""
    out: list[str] = []
    want = f":{port:04X}"
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            f = line.split()
            if len(f) > 3 and f[1].endswith(want):
                out.append(f"{_address(f[1])} -> {_address(f[2])} {_TCP_STATES.get(f[3], f[3])}")
    return out


def _address(hexed: str) -> str:
    host, port = hexed.split(":")
    if len(host) == 8:
        ip = socket.inet_ntop(socket.AF_INET, bytes.fromhex(host)[::-1])
    else:  # four little-endian 32-bit words
        raw = b"".join(bytes.fromhex(host[i:i + 8])[::-1] for i in range(0, 32, 8))
        ip = socket.inet_ntop(socket.AF_INET6, raw)
    return f"{ip}:{int(port, 16)}"
