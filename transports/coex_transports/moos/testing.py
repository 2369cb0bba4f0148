"""A real MOOSDB for tests and benchmarks: found on PATH or where ``make moos`` builds it, and
run on a local port (:class:`MoosDB`: start, stop with a signal, restart on the same port). The
port comes from :func:`coex_transports.testing.free_port`: reserved for the process that asked,
below the kernel's ephemeral range, so nobody takes it while the MOOSDB is down for a restart.

``make moos`` (a step of ``make test``) runs ``../shared/vendor/moos/build_moos.sh``, which
builds MOOSDB under ``$WORK`` (default ``~/.cache/coex-moos``). :func:`find_moosdb` says where it
is, or why there is none (the MOOS tests are then skipped with that reason, the soak benchmark
leaves its MOOSDB fault out).
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from pathlib import Path

from coex_transports.testing import free_port, port_holders

__all__ = ["MoosDB", "die_with_parent", "find_moosdb", "free_port"]


def _build_dirs() -> list[Path]:
    """Where ``build_moos.sh`` builds: ``$WORK`` if set, and its default."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    dirs = [Path(base) / "coex-moos"]
    if os.environ.get("WORK"):  # build_moos.sh's own variable
        dirs.insert(0, Path(os.environ["WORK"]))
    return dirs


def find_moosdb() -> tuple[str | None, str]:
    """The MOOSDB executable (``$COEX_MOOSDB``, PATH, then the ``make moos`` build), or ``None``
    and why not."""
    explicit = os.environ.get("COEX_MOOSDB")
    if explicit:
        if os.access(explicit, os.X_OK):
            return explicit, ""
        return None, f"COEX_MOOSDB={explicit} is not an executable"
    found = shutil.which("MOOSDB")
    if found:
        return found, ""
    candidates = [d / "core-moos" / "build" / "bin" / "MOOSDB" for d in _build_dirs()]
    for built in candidates:
        if os.access(built, os.X_OK):
            return str(built), ""
    built = candidates[0]
    repo = Path(__file__).resolve().parents[3]
    shared = repo.parent / "shared" / "vendor" / "moos" / "build_moos.sh"
    how = ("run `make moos`" if shared.exists() else
           f"no {shared} to build it from; install MOOSDB (github.com/themoos/core-moos) on PATH")
    return None, f"MOOSDB not found (not on PATH, not at {built}): {how}"


def die_with_parent() -> None:
    """In the child: on Linux, get SIGKILL when the test process dies (no MOOSDB left behind
    when pytest itself is killed)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


class MoosDB:
    """One MOOSDB process on a local port (``start``/``stop``/``restart`` on the same port)."""

    def __init__(self, exe: str, port: int | None = None, community: str = "coex_test") -> None:
        self.exe = exe
        self.port = port or free_port()
        self.community = community
        self.dir = Path(tempfile.mkdtemp(prefix="coex-moosdb-"))
        self.proc: subprocess.Popen[bytes] | None = None
        self.starts = 0

    def start(self, timeout: float = 10.0) -> None:
        mission = self.dir / "test.moos"
        mission.write_text(f"ServerHost = localhost\nServerPort = {self.port}\nCommunity = {self.community}\n")
        self.starts += 1
        logf = open(self.dir / f"moosdb.{self.starts}.log", "wb")
        # --moos_suicide_disable: no suicide-monitoring channel (a multicast socket CI may lack)
        self.proc = subprocess.Popen(
            [self.exe, str(mission), f"--moos_port={self.port}", "--moos_suicide_disable"],
            stdout=logf, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, cwd=self.dir,
            preexec_fn=die_with_parent,
        )
        logf.close()
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                held = port_holders(self.port)
                why = f" (port {self.port} held by: {'; '.join(held)})" if held else ""
                raise RuntimeError(f"MOOSDB exited with {self.proc.returncode}{why}: {self.log()}")
            if self._listening():
                return
            time.sleep(0.05)
        self.stop()
        raise RuntimeError(f"MOOSDB did not listen on port {self.port} within {timeout} s: {self.log()}")

    def _listening(self) -> bool:
        # look at the kernel's table rather than connecting (a bare connection makes MOOSDB log
        # a protocol error)
        try:
            lines = Path("/proc/net/tcp").read_text().splitlines()[1:]
            lines += Path("/proc/net/tcp6").read_text().splitlines()[1:]
        except OSError:
            with socket.socket() as s:
                s.settimeout(0.5)
                return s.connect_ex(("127.0.0.1", self.port)) == 0
        want = f":{self.port:04X}"
        return any(f.split()[1].endswith(want) and f.split()[3] == "0A" for f in lines)

    def stop(self, sig: int = signal.SIGKILL) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.proc = None

    def restart(self) -> None:
        self.stop()
        self.start()

    def log(self) -> str:
        logs = sorted(self.dir.glob("moosdb.*.log"))
        return logs[-1].read_text(errors="replace")[-2000:] if logs else ""

    def close(self) -> None:
        self.stop()
        shutil.rmtree(self.dir, ignore_errors=True)
