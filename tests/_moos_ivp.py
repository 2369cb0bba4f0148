"""A real MOOS-IvP community for the tests: MOOSDB, pHelmIvP, uSimMarineV22 and pMarinePIDV22
built from ``../shared/vendor/moos-ivp`` (``build_ivp.sh``), with pCoex run from
``examples/moos/`` and a topside CoEx node on the same MOOSDB.

:func:`find_ivp` finds the binaries in ``$COEX_MOOS_IVP_BIN`` or the build cache
(``~/.cache/coex-moos-ivp/bin``), building them when the sources and a compiler are there (a file
lock keeps two pytest workers from building at once); otherwise the tests are skipped with the
reason. Everything listens on loopback; every process is killed when the test ends (and, on
Linux, when the test process dies).
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from coex_transports.moos.testing import die_with_parent

from ._moos import free_port

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
BUILD_SCRIPT = ROOT.parent / "shared" / "vendor" / "moos-ivp" / "build_ivp.sh"
APPS = ("MOOSDB", "pHelmIvP", "uSimMarineV22", "pMarinePIDV22", "pAntler")

__all__ = ["APPS", "Community", "Watcher", "find_ivp", "wait"]


def _cache() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "coex-moos-ivp"


def find_ivp() -> tuple[Path | None, str, bool]:
    """``(bin_dir, why_not, built_now)``: the directory holding every one of :data:`APPS`
    (``$COEX_MOOS_IVP_BIN``, else the build cache, built there with ``build_ivp.sh`` when
    missing), or None and the reason."""
    explicit = os.environ.get("COEX_MOOS_IVP_BIN")
    if explicit:
        d = Path(explicit)
        missing = [a for a in APPS if not os.access(d / a, os.X_OK)]
        return (d, "", False) if not missing else (None, f"COEX_MOOS_IVP_BIN={d} lacks {', '.join(missing)}", False)
    d = _cache() / "bin"
    if all(os.access(d / a, os.X_OK) for a in APPS):
        return d, "", False
    if not BUILD_SCRIPT.exists():
        return None, f"MOOS-IvP not built ({d}) and no {BUILD_SCRIPT} to build it from", False
    tools = [t for t in ("cmake", "g++", "make", "tar", "sha256sum") if shutil.which(t) is None]
    if tools:
        return None, f"MOOS-IvP not built ({d}) and {', '.join(tools)} missing to build it", False
    _cache().mkdir(parents=True, exist_ok=True)
    with open(_cache() / ".build.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another pytest worker may be building it
        if all(os.access(d / a, os.X_OK) for a in APPS):
            return d, "", False
        log = _cache() / "build_ivp.log"
        with open(log, "wb") as out:
            rc = subprocess.run(["bash", str(BUILD_SCRIPT)], stdout=out, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, timeout=3600).returncode
    if rc != 0 or not all(os.access(d / a, os.X_OK) for a in APPS):
        return None, f"building MOOS-IvP with {BUILD_SCRIPT} failed (exit {rc}; log {log})", True
    return d, "", True


def _session(sid: int) -> list[int]:
    """The processes of session ``sid`` (Linux /proc)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if len(fields) > 3 and int(fields[3]) == sid:  # state, ppid, pgrp, session
            out.append(int(stat.parent.name))
    return out


def _env() -> dict[str, str]:
    """The environment of pCoex: this checkout's sources first (a git worktree too)."""
    from ._moos import moos_entry_points

    env = dict(os.environ)
    extra = [str(ROOT / p) for p in ("", "transports", "runtime", "conformance_tests", "plugins", "apps")]
    shim = moos_entry_points()
    if shim is not None:
        extra.append(shim)
    env["PYTHONPATH"] = os.pathsep.join(extra + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    return env


class Community:
    """The example mission (``examples/moos/``) copied to ``work`` and run there: its
    ``coex_alpha.moos`` with another ``ServerPort`` and ``MOOSTimeWarp``, and the lines
    ``extra`` added to its pCoex block; ``coex.bhv`` as shipped."""

    def __init__(self, bin_dir: Path, work: Path, warp: float, extra: list[str]) -> None:
        self.bin = bin_dir
        self.warp = warp
        self.port = free_port()
        shutil.copytree(EXAMPLES / "moos", work / "moos")
        shutil.copytree(EXAMPLES / "deploy", work / "deploy")
        self.dir = work / "moos"
        self.mission = self.dir / "coex_alpha.moos"
        text = self.mission.read_text()
        text, n1 = re.subn(r"(?m)^ServerPort\s*=.*$", f"ServerPort   = {self.port}", text)
        text, n2 = re.subn(r"(?m)^MOOSTimeWarp\s*=.*$", f"MOOSTimeWarp = {warp:g}", text)
        for line in extra:  # a key of the pCoex block given again replaces it
            key = line.partition("=")[0].strip()
            text, n = re.subn(rf"(?m)^[ \t]*{re.escape(key)}[ \t]*=.*$", f"  {line}", text)
            if n == 0:
                text = re.sub(r"(?m)^(ProcessConfig = pCoex\s*\n\{\n)", lambda m, ln=line: m.group(1) + f"  {ln}\n",
                              text)
        assert (n1, n2) == (1, 1), "the example mission changed: update tests/_moos_ivp.py"
        self.mission.write_text(text)
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.starts: dict[str, int] = {}

    # ------------------------------------------------------------------ processes
    def start(self, name: str) -> subprocess.Popen[bytes]:
        """Start one application of the community (``pCoex``: ``coex vehicle --moos``)."""
        self.starts[name] = self.starts.get(name, 0) + 1
        log = open(self.dir / f"{name}.{self.starts[name]}.log", "wb")
        if name == "pCoex":
            cmd = [sys.executable, "-m", "coex_core.cli", "vehicle", "--moos", str(self.mission)]
            env = _env()
        else:
            cmd = [str(self.bin / name), self.mission.name, name]
            if name == "MOOSDB":
                cmd = [str(self.bin / name), self.mission.name, "--moos_suicide_disable"]
            env = dict(os.environ)
        p = subprocess.Popen(cmd, cwd=self.dir, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                             env=env, preexec_fn=die_with_parent)
        log.close()
        self.procs[name] = p
        return p

    def antler(self, bin_dir: Path) -> subprocess.Popen[bytes]:
        """The whole community as the example is run: ``pAntler coex_alpha.moos`` in the
        mission's directory (pCoex through ``./pCoex``, coex from this Python on PATH), in a
        process group of its own that :meth:`close` kills."""
        env = _env()
        env["PATH"] = os.pathsep.join([str(bin_dir), str(Path(sys.executable).parent), env.get("PATH", "")])
        log = open(self.dir / "pAntler.log", "wb")
        p = subprocess.Popen([str(bin_dir / "pAntler"), self.mission.name], cwd=self.dir, env=env, stdout=log,
                             stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)
        log.close()
        self.procs["pAntler"] = p
        return p

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        p = self.procs.pop(name, None)
        if p is not None and p.poll() is None:
            p.send_signal(sig)
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()

    def alive(self) -> list[str]:
        return [n for n, p in self.procs.items() if p.poll() is None]

    def log(self, name: str) -> str:
        logs = sorted(self.dir.glob(f"{name}.*.log"))
        return "".join(p.read_text(errors="replace")[-3000:] for p in logs[-1:])

    def close(self) -> None:
        if "pCoex" in self.procs:
            self.kill("pCoex", signal.SIGTERM)
        antler = self.procs.pop("pAntler", None)
        if antler is not None:
            # pAntler puts each application in a process group of its own, all in the session
            # this test made for pAntler: kill that session's processes
            for pid in _session(antler.pid):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            antler.wait(timeout=20)
        for name in list(self.procs):
            self.kill(name)


class Watcher:
    """The test's eyes and hands in the community: a MOOS client (warped like the community)
    that records every value of ``variables`` as ``(key, value, source, source_aux)``, the
    vehicle's track from NAV_X / NAV_Y, and posts like uPokeDB."""

    def __init__(self, port: int, warp: float, variables: list[str]) -> None:
        from coex_transports.moos import MoosClient

        self.client = MoosClient("127.0.0.1", port, "coex_test_watch", time_warp=warp)
        for v in variables:
            self.client.register(v, 0.0)
        self.lock = threading.Lock()
        self.mail: list[tuple[str, Any, str, str]] = []
        self.track: list[tuple[float, float]] = []
        self._x: float | None = None
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def start(self, timeout: float = 20.0) -> Watcher:
        assert self.client.connect(timeout), "the test's MOOS client did not connect"
        self.thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            self.client.wait_for_mail(0.2)
            for m in self.client.fetch():
                with self.lock:
                    self.mail.append((m.key, m.value, m.source, m.source_aux))
                    if m.key == "NAV_X" and m.is_double:
                        self._x = float(m.value)  # type: ignore[arg-type]
                    elif m.key == "NAV_Y" and m.is_double and self._x is not None:
                        self.track.append((self._x, float(m.value)))  # type: ignore[arg-type]

    def mark(self) -> int:
        """A position in the mail (for :meth:`since`)."""
        with self.lock:
            return len(self.mail)

    def since(self, mark: int, key: str | None = None) -> list[tuple[str, Any, str, str]]:
        with self.lock:
            return [m for m in self.mail[mark:] if key is None or m[0] == key]

    def track_mark(self) -> int:
        with self.lock:
            return len(self.track)

    def track_since(self, mark: int) -> list[tuple[float, float]]:
        with self.lock:
            return list(self.track[mark:])

    def where(self) -> tuple[float, float] | None:
        with self.lock:
            return self.track[-1] if self.track else None

    def post(self, var: str, value: Any) -> None:
        self.client.notify(var, value)
        assert self.client.flush(10.0), f"{var} not taken by MOOSDB"

    def close(self) -> None:
        self._stop.set()
        self.thread.join(timeout=5)
        self.client.close()


def wait(what: str, cond: Callable[[], Any], timeout: float, community: Community | None = None,
         poll: float = 0.05) -> Any:
    """Wait (at most ``timeout`` s) for ``cond()`` to be true; fail naming ``what`` (and any
    application of the community that died)."""
    end = time.monotonic() + timeout
    while True:
        got = cond()
        if got:
            return got
        if community is not None:
            dead = [n for n, p in community.procs.items() if p.poll() is not None]
            if dead:
                raise AssertionError(f"{', '.join(dead)} exited while waiting for {what}:\n"
                                     + "\n".join(community.log(n) for n in dead))
        if time.monotonic() > end:
            raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(poll)
