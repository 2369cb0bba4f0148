"""Persistence: a vehicle and a topside process over LCM (UDP multicast on loopback), each with a
SQLite store, are killed with SIGKILL at random moments of a dive and restarted; in the end
nothing received is lost (topside's map, images and series equal the vehicle's) and the
restarts did not make the vehicle send again what topside had acknowledged."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from coex_core import wire
from coex_core.errors import DecodeError
from coex_core.messages import (
    FrameAck,
    ImageAck,
    ImageFragment,
    MapRoiRequest,
    SubgridMessage,
)
from coex_runtime.store import NodeStore
from coex_transports.lcm.testing import TEST_UDPM_URL, ensure_multicast_route, unique_channel

from ._faults import T0, VEHICLE, Dive, build_dive, images_complete, map_converged, series_complete
from ._persist_node import ACK_TIMEOUT, PACKET_SECONDS

ROOT = Path(__file__).resolve().parents[1]
#: dive seconds per wall-clock second: at 20 a loaded CI machine let a process read its socket
#: seconds late, beyond the 32-s ack timeout, and acks arrived after the frames counted as lost
SPEED = 10.0
MINUTES = 5  # of sensor data


def restored(db: Path, role: str) -> Any:
    def build() -> Any:
        d = build_dive(minutes=MINUTES, packet_seconds=PACKET_SECONDS, ack_timeout=ACK_TIMEOUT)
        return d.vehicle if role == "vehicle" else d.topside

    # a look at a store its process may be writing: read-only, the last committed snapshot whole
    store = NodeStore(db, read_only=True)
    try:
        return store.restore(build)
    finally:
        store.close()


def both(vdb: Path, tdb: Path) -> Dive:
    """The two nodes as their stores have them now, as a Dive for the fault suite's checks."""
    template = build_dive(minutes=MINUTES, packet_seconds=PACKET_SECONDS, ack_timeout=ACK_TIMEOUT)
    v, t = restored(vdb, "vehicle"), restored(tdb, "topside")
    return Dive(v, t, v.sender("bathymetry"), v.sender("imagery"), v.sender("timeseries"),
                t.receiver("bathymetry"), t.receiver("imagery"), t.receiver("timeseries"),
                series_data=template.series_data)


def converged(d: Dive) -> bool:
    return map_converged(d) and images_complete(d) and series_complete(d)


class Proc:
    def __init__(self, role: str, db: Path, uri: str, epoch: float, log: Path) -> None:
        self.args = [sys.executable, "-m", "tests._persist_node", "--role", role, "--db", str(db),
                     "--uri", uri, "--epoch", repr(epoch), "--speed", str(SPEED),
                     "--minutes", str(MINUTES)]
        self.log = log
        self.p: subprocess.Popen[bytes] | None = None
        self.start()

    def start(self) -> None:
        with self.log.open("ab") as f:
            self.p = subprocess.Popen(self.args, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT)

    def kill(self) -> None:
        assert self.p is not None and self.p.poll() is None, self.log.read_text()[-3000:]
        os.kill(self.p.pid, signal.SIGKILL)
        self.p.wait()

    def stop(self) -> int:
        assert self.p is not None
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGTERM)
            try:
                self.p.wait(120)  # its last snapshot, on a loaded machine
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait()
        return int(self.p.returncode)


@pytest.fixture(scope="module")
def lcm_uri() -> str:
    ensure_multicast_route()
    return f"lcm:{TEST_UDPM_URL}&channel={unique_channel('COEX_PERSIST')}"


def test_kill_and_restart_both_sides_at_random_moments(tmp_path: Path, lcm_uri: str) -> None:
    rng = random.Random(2026)
    vdb, tdb = tmp_path / "vehicle.sqlite", tmp_path / "topside.sqlite"
    epoch = time.time() + 2.0  # both processes import and build before the dive starts
    procs = {"vehicle": Proc("vehicle", vdb, lcm_uri, epoch, tmp_path / "vehicle.log"),
             "topside": Proc("topside", tdb, lcm_uri, epoch, tmp_path / "topside.log")}
    kills: list[tuple[str, float]] = []
    try:
        # six crashes during the first 400 s of the dive, mostly alternating sides, at random
        # moments, each side down for a random 4-30 dive seconds
        moments = sorted(rng.uniform(20.0, 400.0) / SPEED for _ in range(int(os.environ.get("COEX_KILLS", "6"))))
        for i, m in enumerate(moments):
            role = ("vehicle", "topside")[i % 2] if rng.random() < 0.7 else ("topside", "vehicle")[i % 2]
            wait = epoch + m - time.time()
            if wait > 0:
                time.sleep(wait)
            procs[role].kill()
            kills.append((role, round(T0 + (time.time() - epoch) * SPEED, 1)))
            time.sleep(rng.uniform(4.0, 30.0) / SPEED)
            procs[role].start()
        # then until everything has arrived: on an idle machine within about 1500 dive seconds;
        # a loaded one runs the processes late and they miss slots, so the bound is generous (the
        # loop ends as soon as everything is there)
        deadline = epoch + 9000.0 / SPEED
        while True:
            time.sleep(4.0)
            d = both(vdb, tdb)
            if converged(d) or time.time() > deadline:
                break
    finally:
        codes = {role: p.stop() for role, p in procs.items()}
    d = both(vdb, tdb)
    logs = {role: (tmp_path / f"{role}.log").read_text()[-2000:] for role in procs}
    assert os.environ.get("COEX_KILLS") or ({r for r, _ in kills} == {"vehicle", "topside"} and len(kills) == 6)
    assert codes == {"vehicle": 0, "topside": 0}, logs
    assert map_converged(d), ("map", kills, logs)
    assert images_complete(d), ("images", kills, logs)
    assert series_complete(d), ("series", kills, logs)

    # the topside's journal has every frame it received, and after every restart the vehicle did
    # not send again a map subgrid that topside had acknowledged (the vehicle's journal has what
    # it sent and the acks it got), nor much more image data than the images need
    store = NodeStore(tdb, read_only=True)
    try:
        starts = int(store.get("starts_topside") or 0)
        received = store.count("rx")
    finally:
        store.close()
    assert starts == 1 + sum(r == "topside" for r, _ in kills)
    assert received > 60  # frames (fewer since subgrids are predicted from their parents)
    store = NodeStore(vdb, read_only=True)
    try:
        rows = list(store.journal())
    finally:
        store.close()
    by_seq: dict[int, tuple[set[Any], float]] = {}  # seq -> the subgrids its frame carried, when it went
    acked: set[Any] = set()
    sent = again = again_asked = again_late = image_bytes = image_again = 0
    held: dict[int, list[tuple[int, int]]] = {}  # image id -> byte ranges topside acked
    # (level, ix, iy) -> journal row of the newest request covering it; key -> row of its last send
    requested: dict[tuple[int, int, int], int] = {}
    last_tx: dict[Any, int] = {}
    # key -> (when its newest ack came, what the acked copy was, when that copy went)
    acked_at: dict[Any, tuple[float, str, float]] = {}
    sent_as: dict[Any, str] = {}  # key -> the copy last sent
    unasked: list[str] = []  # how each unasked re-send came about (for the failure message)
    for r in rows:
        if r.kind not in ("rx", "tx"):
            continue
        try:
            frame = wire.unpack_frame(r.data)
        except DecodeError:
            continue
        if r.kind == "tx":
            keys = {(msg.level, msg.ix, msg.iy, msg.stamp) for msg in frame.messages if isinstance(msg, SubgridMessage)}
            for msg in frame.messages:
                if isinstance(msg, ImageFragment):
                    image_bytes += len(msg.data)
                    a, b = msg.offset, msg.offset + len(msg.data)
                    image_again += sum(max(0, min(b, e) - max(a, s)) for s, e in held.get(msg.image_id, []))
            sent += len(keys)
            for msg in frame.messages:
                k = (msg.level, msg.ix, msg.iy, msg.stamp) if isinstance(msg, SubgridMessage) else None
                if k is None:
                    continue
                if k in acked:
                    again += 1
                    # topside asked for it since it last went (a request race: it asked before the
                    # ack of an earlier copy was heard, or after a restart lost it)
                    t, data, went = acked_at.get(k, (-1.0, "", -1.0))
                    if requested.get(k[:3], -1) > last_tx.get(k, -1):
                        again_asked += 1
                    elif t - went > ACK_TIMEOUT:
                        # the ack came after the ack timeout of the copy it acknowledged: the
                        # vehicle had given that copy up as lost and queued it again by then (as
                        # after any loss; a loaded machine runs the processes that late)
                        again_late += 1
                    elif len(unasked) < 12:
                        unasked.append(f"{k} seq {frame.header.seq} at {r.t:.1f}: acked at {t:.1f} (sent at "
                                       f"{went:.1f}), {'same' if data == repr(msg) else 'other'} content")
                sent_as[k] = repr(msg)
                last_tx[k] = r.id
            by_seq[frame.header.seq] = (keys, r.t)
            continue
        for msg in frame.messages:
            if isinstance(msg, MapRoiRequest):
                for i in range(msg.w * msg.h):
                    requested[(msg.level, msg.x0 + i % msg.w, msg.y0 + i // msg.w)] = r.id
            if isinstance(msg, ImageAck):
                held[msg.image_id] = [(0, msg.contiguous), *((g.start, g.end) for g in msg.ranges)]
            if isinstance(msg, FrameAck) and msg.node == VEHICLE:
                for e in msg.entries:
                    for bit in range(8):
                        if e.frames >> bit & 1:
                            keys, went = by_seq.get((e.seq + bit) % 256, (set(), r.t))
                            for k in keys:
                                acked.add(k)
                                acked_at[k] = (r.t, sent_as.get(k, ""), went)
    need = sum(tx.goal for tx in d.images.images.values())
    print(f"kills {kills}; {sent} subgrids sent, {again} of them after topside had acked them "
          f"({again_asked} asked for again by topside, {again_late} after an ack that came later than "
          f"the ack timeout); "
          f"{image_bytes} image bytes sent for {need}, {image_again} of them after topside had "
          f"acked them; unasked re-sends: {unasked[:6]}")
    assert sent > 200
    # the vehicle re-sends on its own (spare work) only what it did not hear acknowledged; what
    # topside asks for again after a restart (a request race) it sends, as asked
    # (what it had given up before the ack came, it sent again, as after a loss: counted, not
    # asserted, as it depends on how late the machine runs the processes)
    unasked_again = again - again_asked - again_late
    assert unasked_again <= 0.02 * sent, (f"{unasked_again} of {sent} subgrids sent again unasked", unasked)
    # a topside killed between two snapshots forgets what it received since, and asks again
    # (more when spare traffic fills the link): bounded, not zero
    assert again_asked <= 0.10 * sent, f"{again_asked} of {sent} subgrids asked for again after their ack"
    # what was sent but not yet acked when a side died goes again (as after a loss); what topside
    # had acked does not
    # (how much unacked data goes again depends on how late the processes run: not asserted)
    assert image_again <= 0.02 * image_bytes, f"{image_again} image bytes sent again after their ack"
    assert image_bytes >= need
