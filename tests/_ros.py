"""A real ROS 1 master for the ROS tests: Debian's ``roscore`` on a free local port, and rospy in
the venv (``make ros``: scripts/ros.sh). Without either, the tests that need them are skipped with
the reason. Every process started here is killed on teardown (and with the test process, by
PR_SET_PDEATHSIG)."""

from __future__ import annotations

import importlib.util
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import xmlrpc.client
from pathlib import Path

from coex_transports.testing import free_port

ROOT = Path(__file__).resolve().parents[1]
PEER = ROOT / "tests" / "_ros_peer.py"

__all__ = ["PEER", "Roscore", "peer", "ros_entry_points", "ros_env", "why_no_ros"]


def why_no_ros() -> str | None:
    """Why the ROS tests cannot run here (None: they can)."""
    if shutil.which("roscore") is None:
        return ("no roscore on PATH: install Debian's ROS 1 (make install does it where apt-get can: "
                "scripts/system-deps.sh)")
    if importlib.util.find_spec("rospy") is None:
        return ("rospy is not importable from this Python: run `make ros` (scripts/ros.sh links "
                "Debian's rospy into the venv; the venv must be Python 3.11 like Debian's)")
    return None


def ros_entry_points() -> str | None:
    """Make the ``ros`` input and autonomy output findable as entry points when the installed
    metadata predates them (a venv installed from an older checkout, a git worktree): a small
    ``.dist-info`` holding them, taken from pyproject.toml, is put on ``sys.path``. Returns its
    directory (for a child process's PYTHONPATH), or None when not needed."""
    import tomllib
    from importlib import metadata

    groups = {"coex.inputs", "coex.autonomy"}
    root = Path(tempfile.gettempdir()) / f"coex-ros-eps-{os.getuid()}"
    if str(root) in sys.path:  # put there by an earlier call
        return str(root)
    if all("ros" in {ep.name for ep in metadata.entry_points(group=g)} for g in groups):
        return None
    eps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["entry-points"]
    info = root / "coex_ros_shim-0.0.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: coex-ros-shim\nVersion: 0.0\n")
    (info / "entry_points.txt").write_text("".join(f"[{g}]\nros = {eps[g]['ros']}\n\n" for g in sorted(groups)))
    if str(root) not in sys.path:
        sys.path.append(str(root))
    return str(root)


def _die_with_parent() -> None:
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    os.setsid()  # its own process group: roscore's children (rosmaster, rosout) go with it


def ros_env(master: str, home: Path, base: dict[str, str] | None = None) -> dict[str, str]:
    """An environment for ROS processes on loopback with logs under ``home``."""
    env = dict(os.environ if base is None else base)
    env.update(ROS_MASTER_URI=master, ROS_HOSTNAME="127.0.0.1", ROS_HOME=str(home),
               ROS_LOG_DIR=str(home / "log"), PYTHONUNBUFFERED="1")
    env.pop("ROS_IP", None)
    shim = ros_entry_points()
    if shim:
        env["PYTHONPATH"] = os.pathsep.join(p for p in (env.get("PYTHONPATH", ""), shim) if p)
    return env


class Roscore:
    """One ``roscore -p PORT`` (``start``/``stop``/``restart`` on the same port)."""

    def __init__(self, port: int | None = None) -> None:
        self.port = port or free_port()
        self.uri = f"http://127.0.0.1:{self.port}"
        self.dir = Path(tempfile.mkdtemp(prefix="coex-roscore-"))
        self.proc: subprocess.Popen[bytes] | None = None
        self.starts = 0

    def env(self) -> dict[str, str]:
        return ros_env(self.uri, self.dir)

    def start(self, timeout: float = 30.0) -> None:
        self.starts += 1
        logf = open(self.dir / f"roscore.{self.starts}.log", "wb")
        self.proc = subprocess.Popen(["roscore", "-p", str(self.port)], stdout=logf, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL, env=self.env(), cwd=self.dir,
                                     preexec_fn=_die_with_parent)
        logf.close()
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"roscore exited with {self.proc.returncode}: {self.log()}")
            if self.pid() is not None:
                return
            time.sleep(0.1)
        self.stop()
        raise RuntimeError(f"roscore did not answer on port {self.port} within {timeout} s: {self.log()}")

    def pid(self) -> int | None:
        """The master's PID as it says over XML-RPC (None while it does not answer)."""
        try:
            code, _, pid = xmlrpc.client.ServerProxy(self.uri).getPid("/coex_test")
            return int(pid) if code == 1 else None
        except OSError:
            return None

    def _children(self) -> list[int]:
        """roscore's children (rosmaster, rosout: roslaunch starts each in a session of its own)."""
        assert self.proc is not None
        out = []
        for stat in Path("/proc").glob("[0-9]*/stat"):
            try:
                fields = stat.read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == self.proc.pid:
                out.append(int(stat.parent.name))
        return out

    def stop(self) -> None:
        """Kill the master as a crash would (SIGKILL to roscore, rosmaster and rosout, by PID)."""
        if self.proc is not None:
            for pid in [*self._children(), self.proc.pid]:
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
            self.proc.wait(timeout=10)
            deadline = time.monotonic() + 10
            while self.pid() is not None and time.monotonic() < deadline:
                time.sleep(0.05)
        self.proc = None

    def restart(self) -> None:
        self.stop()
        self.start()

    def log(self) -> str:
        logs = sorted(self.dir.glob("roscore.*.log"))
        return logs[-1].read_text(errors="replace")[-2000:] if logs else ""

    def close(self) -> None:
        self.stop()
        shutil.rmtree(self.dir, ignore_errors=True)


def peer(args: list[str], env: dict[str, str], log: Path) -> subprocess.Popen[str]:
    """``tests/_ros_peer.py ARGS`` (its JSON lines on stdout), in its own process group."""
    return subprocess.Popen([sys.executable, str(PEER), *args], env=env, stdout=subprocess.PIPE,
                            stderr=open(log, "a"), text=True, preexec_fn=_die_with_parent)


def kill(proc: subprocess.Popen[str] | subprocess.Popen[bytes] | None) -> None:
    """Kill a process started here and its group; wait for it."""
    if proc is None or proc.poll() is not None:
        return
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
