"""What the vehicle writes to its disk in an hour, as the kernel counts it.

The vehicle daemon (:class:`coex_apps.vehicle.daemon.VehicleApp` from its TOML configuration,
its SQLite store on a real disk) runs the soak's load (``bench/soak_faults.py``'s simulated
sensors: the 256 m site surveyed with a 96-beam multibeam again and again, **a camera image every
5 minutes**, two sensor channels at 1 Hz, navigation every 10 s) at **the documented TDMA**
(``docs/deploy.md``: the NUI cycle of 6 x 20 s slots, rate 5) over two simulated Micromodem-2s
(20 % frame loss) to a topside that writes nothing (no store, no products), on a simulated clock.
Nothing else in the process writes to a disk, so the process's ``write_bytes`` in
``/proc/self/io`` (the bytes it sent to the storage layer: what the flash sees, counted when a
page is dirtied) is the vehicle's. Measured each simulated hour, with:

* what the store did (rows journaled by kind, snapshots, what the snapshots wrote as content:
  ``NodeStore.stats``);
* ``write_bytes`` taken around each of the store's calls (journal rows by kind, snapshots, the
  map's spilled tiles, small values), so it says what dominates; the WAL checkpoints (SQLite
  copies the WAL's pages into the file once it holds ``WAL_PAGES`` of them, then syncs both) are
  run by the bench when SQLite would run them, after the call whose commit filled the WAL, and
  counted apart.

The clock is simulated (a day in minutes): SQLite syncs the WAL and the file at every checkpoint,
so pages are written back at the same points whatever the speed, and the count per simulated hour
is the count per hour of a real dive (a page dirtied twice before it is written back counts once:
between two checkpoints the WAL only grows, and the file is only written by a checkpoint).

    python bench/disk_writes.py [--hours 3] [--quick] [--dir DIR]

``--quick``: one simulated hour of the soak's lighter load (a 64 m site, 32 beams, 64 x 96
images). JSON in ``bench/results/disk_writes.json`` (``disk_writes-quick.json``).
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

if str(Path(__file__).resolve().parent) not in sys.path:
    sys.path.append(str(Path(__file__).resolve().parent))

from soak_faults import KEY, TOPSIDE, TOPSIDE_URI, VEHICLE, VEHICLE_URI, SimSensors, _inline

from coex_apps.console.cli import topside_from_config
from coex_apps.vehicle.config import load
from coex_apps.vehicle.daemon import VehicleApp
from coex_core.acoustic import AcousticChannel
from coex_runtime.store import WAL_PAGES, NodeStore, SqliteStorage
from coex_transports.micromodem.simulator import ModemNetwork, SimLoop
from coex_transports.recovery import ResilientTransport

ROOT = Path(__file__).resolve().parents[1]
HOUR = 3600.0


def write_bytes() -> int:
    """This process's ``write_bytes`` (``/proc/self/io``)."""
    for line in Path("/proc/self/io").read_text().splitlines():
        if line.startswith("write_bytes:"):
            return int(line.split()[1])
    raise RuntimeError("no write_bytes in /proc/self/io")


def _wal_frames(path: Path) -> int:
    """The frames the WAL of ``path`` holds now (``mxFrame`` of the wal-index header in the
    ``-shm`` file; the WAL file itself keeps its size when SQLite starts it again)."""
    try:
        with open(f"{path}-shm", "rb") as f:
            head = f.read(20)
    except OSError:
        return 0
    return int.from_bytes(head[16:20], sys.byteorder) if len(head) == 20 else 0


class Counted:
    """``write_bytes`` taken around the store's calls, by what the call did (a call made inside
    another, a tile spilled while a snapshot is built, counts for itself alone)."""

    def __init__(self) -> None:
        self.bytes: dict[str, int] = {}
        self.calls: dict[str, int] = {}
        self._saved: list[tuple[Any, str, Any]] = []
        self._inner: list[int] = []  # per call in progress: what the calls inside it wrote

    def wrap(self, owner: Any, name: str, what: Callable[[tuple[Any, ...]], str]) -> None:
        inner = getattr(owner, name)
        counted = self

        def call(*args: Any, **kwargs: Any) -> Any:
            before = write_bytes()
            counted._inner.append(0)
            try:
                return inner(*args, **kwargs)
            finally:
                total = write_bytes() - before
                own = total - counted._inner.pop()
                if counted._inner:
                    counted._inner[-1] += total
                key = what(args)
                counted.bytes[key] = counted.bytes.get(key, 0) + own
                counted.calls[key] = counted.calls.get(key, 0) + 1
                if not counted._inner:
                    counted.checkpoint(args[0])

        self._saved.append((owner, name, inner))
        setattr(owner, name, call)

    def checkpoint(self, owner: Any) -> None:
        """SQLite's checkpoint, as it would run it (the WAL has ``WAL_PAGES`` pages), counted
        apart: the store's connection checkpoints no more by itself here (:meth:`install`)."""
        path = getattr(owner, "path", None)
        db = getattr(owner, "db", None)
        if path is None or db is None or getattr(owner, "read_only", False):
            return
        if _wal_frames(Path(path)) < WAL_PAGES or db.in_transaction:
            return
        before = write_bytes()
        db.execute("PRAGMA wal_checkpoint(PASSIVE)")
        key = "checkpoints (the WAL's pages into the file, each once)"
        self.bytes[key] = self.bytes.get(key, 0) + write_bytes() - before
        self.calls[key] = self.calls.get(key, 0) + 1

    def install(self) -> None:
        self.wrap(NodeStore, "record_rx", lambda a: "journal: received frames")
        self.wrap(NodeStore, "record_tx", lambda a: "journal: sent frames")
        self.wrap(NodeStore, "record_input", lambda a: f"journal: {a[1]} inputs")
        self.wrap(NodeStore, "snapshot", lambda a: "snapshots")
        self.wrap(NodeStore, "set", lambda a: "small values (meta)")
        self.wrap(NodeStore, "delete", lambda a: "small values (meta)")
        self.wrap(SqliteStorage, "put", lambda a: "the map's spilled tiles")

    def remove(self) -> None:
        for owner, name, inner in reversed(self._saved):
            setattr(owner, name, inner)
        self._saved.clear()


def run(hours: float, work: Path, *, light: bool, seed: int = 1, say: Callable[[str], Any] = print) -> dict[str, Any]:
    net = ModemNetwork({TOPSIDE: (300.0, 400.0, 0.0), VEHICLE: (0.0, 0.0, 500.0)},
                       channel=AcousticChannel(loss=0.2, seed=seed))
    t0 = net.now
    loop = SimLoop(net, max_step=1.0)
    from soak import sensor_series

    series = sensor_series(hours * HOUR, seed, t0)
    (work / "coex.key").write_text(KEY)
    channels = "[" + ", ".join(_inline(s.channel()) for s in series) + "]"
    common = """
[tdma]
slots = ["topside", "vehicle", "vehicle", "topside", "vehicle", "vehicle"]
slot_seconds = 20
guard = 2
[modalities.bathymetry]
stream = 3
priority = 40
[modalities.imagery]
stream = 4
priority = 30
[modalities.timeseries]
stream = 5
priority = 20
"""
    (work / "vehicle.toml").write_text(f"""
[node]
role = "vehicle"
id = {VEHICLE}
peer = {TOPSIDE}
command_key_file = "coex.key"
store = "vehicle.sqlite"
[[modems]]
uri = "{VEHICLE_URI}"
[status]
interval = 10
""" + common.replace("priority = 40\n", "priority = 40\noptions = { send_delay = 20.0 }\n") + f"""
options = {{ channels = {channels} }}
""")
    (work / "topside.toml").write_text(f"""
[node]
role = "topside"
id = {TOPSIDE}
peer = {VEHICLE}
command_key_file = "coex.key"
store = false
[[modems]]
uri = "{TOPSIDE_URI}"
[console]
http = "127.0.0.1:0"
""" + common)

    def link(uri: str) -> ResilientTransport:
        return ResilientTransport(uri, name="link 0", clock=lambda: net.now, sleep=net.run_for, opener=net.open_uri)

    clock = lambda: net.now  # noqa: E731
    vehicle = VehicleApp(load(work / "vehicle.toml", "vehicle"), clock=clock, transports={0: link(VEHICLE_URI)})
    load_kw: dict[str, Any] = dict(site=64.0, beams=32, image=(64, 96)) if light else {}
    sensors = SimSensors(vehicle.context, start=t0, end=t0 + hours * HOUR, seed=seed, series=series, nav=True,
                         **load_kw)
    vehicle.add_input(sensors, key="sensors (simulated)")
    vehicle.open()
    topside = topside_from_config(str(work / "topside.toml"), clock, transports={0: link(TOPSIDE_URI)})
    loop.runners.extend([vehicle.runner, topside.runner])
    store = vehicle.store
    store.db.execute("PRAGMA wal_autocheckpoint=0")  # checkpoints run (and are counted) by Counted
    counted = Counted()
    counted.install()
    samples: list[dict[str, Any]] = []
    last: dict[str, Any] = {"io": write_bytes(), "stats": dict(store.stats), "bytes": {}, "calls": {}, "wall": time.perf_counter()}

    def sample(now: float) -> None:
        io = write_bytes()
        st = dict(store.stats)
        d = {k: st[k] - last["stats"].get(k, 0) for k in st}
        by = {k: v - last["bytes"].get(k, 0) for k, v in counted.bytes.items()}
        calls = {k: v - last["calls"].get(k, 0) for k, v in counted.calls.items()}
        s = {"hour": round((now - t0) / HOUR, 3), "write_mb": round((io - last["io"]) / 1e6, 2),
             "store_mb": round(sum(p.stat().st_size for p in work.glob("vehicle.sqlite*")) / 1e6, 2),
             "rows": {k: d[k] for k in ("rx", "tx", "input")}, "snapshots": d["snapshots"],
             "snapshot_content_mb": round(d["snapshot_bytes"] / 1e6, 2),
             "state_mb_each": round(d["state_bytes"] / max(d["snapshots"], 1) / 1e6, 2),
             "by_call_mb": {k: round(v / 1e6, 2) for k, v in sorted(by.items(), key=lambda kv: -kv[1])},
             "calls": calls, "images": vehicle.counts["images"], "wall_s": round(time.perf_counter() - last["wall"], 1)}
        samples.append(s)
        last.update(io=io, stats=st, bytes=dict(counted.bytes), calls=dict(counted.calls), wall=time.perf_counter())
        top = ", ".join(f"{k} {v}" for k, v in list(s["by_call_mb"].items())[:4])
        say(f"hour {s['hour']:g}: {s['write_mb']} MB written (store {s['store_mb']} MB); {top}; "
            f"{s['snapshots']} snapshots, rows {s['rows']}; {s['wall_s']} s")

    loop.every(HOUR, sample, start=t0 + HOUR)
    try:
        loop.run(t0 + hours * HOUR + 1.0)
    finally:
        counted.remove()
        vehicle.close()
        topside.close()
    return {"samples": samples}


def _tmpfs(path: Path) -> bool:
    """Whether ``path`` is on a file system in memory (the longest mount point above it)."""
    best, kind = "", ""
    for line in Path("/proc/mounts").read_text().splitlines():
        parts = line.split()
        if len(parts) > 2 and str(path.resolve()).startswith(parts[1]) and len(parts[1]) > len(best):
            best, kind = parts[1], parts[2]
    return kind in ("tmpfs", "ramfs")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--hours", type=float, default=3.0)
    p.add_argument("--quick", action="store_true", help="one simulated hour of the lighter load")
    p.add_argument("--dir", metavar="DIR", help="work in DIR (a real disk: tmpfs counts nothing) and keep it")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    hours = 1.0 if args.quick else args.hours
    work = Path(args.dir) if args.dir else Path(tempfile.mkdtemp(prefix="coex-disk-writes-"))
    if _tmpfs(work):
        print(f"{work} is on a tmpfs, where write_bytes counts nothing: give --dir on a real disk")
        return 2
    work.mkdir(parents=True, exist_ok=True)
    print(f"vehicle disk writes: {hours:g} simulated hours in {work}", flush=True)
    try:
        r = run(hours, work, light=args.quick, say=lambda t: print(t, flush=True))
    finally:
        if not args.dir:
            shutil.rmtree(work, ignore_errors=True)
    s = r["samples"]
    steady = s[1:] or s  # the first hour fills the vehicle's image bound: from hour 1 on
    r["write_mb_per_hour"] = round(sum(x["write_mb"] for x in steady) / len(steady), 1)
    r["date"] = time.strftime("%Y-%m-%d")
    r["command"] = "python bench/disk_writes.py" + (" --quick" if args.quick else f" --hours {hours:g}")
    out = ROOT / "bench" / "results"
    out.mkdir(parents=True, exist_ok=True)
    path = out / ("disk_writes-quick.json" if args.quick else "disk_writes.json")
    path.write_text(json.dumps(r, indent=1))
    print(f"vehicle writes {r['write_mb_per_hour']} MB per simulated hour (write_bytes; from hour "
          f"{steady[0]['hour'] - 1:g}); {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
