"""Record a CoEx session with the real `lcm-logger`, play it back with the real `lcm-logplayer`,
and re-analyse it offline with `coex replay --lcm-log FILE`."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import signal
import subprocess
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import lcm
import numpy as np
import pytest

from coex_conformance import load_vectors
from coex_core import jsonfmt, wire
from coex_core.cli import main as coex_main
from coex_core.errors import PluginLoadError
from coex_core.messages import (
    FrameHeader,
    MapRoiRequest,
    Message,
    Subgrid,
    VehicleMode,
    VehicleStatus,
)
from coex_core.modality import Modality, ModalityReceiver, ModalitySender, Product
from coex_transports.lcm import LcmConfig, LcmTransport, decode_frame, encode_frame, is_frame_t
from coex_transports.lcm import replay as replay_mod
from coex_transports.lcm._types import map_level_t, vehicle_status_t
from coex_transports.lcm.products import vehicle_status_from_lcm
from coex_transports.lcm.replay import replay_log
from coex_transports.lcm.testing import TEST_UDPM_URL, ensure_multicast_route, unique_channel

BIN = Path(lcm.LCM_BIN_DIR)


@pytest.fixture(scope="module")
def multicast() -> Iterator[None]:
    undo = ensure_multicast_route()
    yield
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        undo()


# ------------------------------------------------------------------ a small test modality
class _TrackReceiver(ModalityReceiver):
    def __init__(self) -> None:
        self.rows: list[tuple[float, float, float, float]] = []

    def receive(self, message: Message, now: float) -> list[Product]:
        assert isinstance(message, VehicleStatus)
        self.rows.append((now, message.x, message.y, message.depth))
        return self.products()

    def poll(self, now: float) -> list[Message]:
        return []

    def products(self) -> list[Product]:
        if not self.rows:
            return []
        return [Product("track", "vehicle", len(self.rows), np.array(self.rows), {"columns": "t x y depth"})]


class _TrackSender(ModalitySender):
    def ingest(self, data: Any, now: float) -> None:
        raise NotImplementedError("topside-only test modality")

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        return []

    def handle(self, message: Message, now: float) -> list[Message]:
        return []


class TrackModality(Modality):
    """Test modality: the receiver turns VehicleStatus messages into a track array."""

    name = "track"
    messages = (VehicleStatus,)
    requests = (MapRoiRequest,)

    def sender(self, config: Mapping[str, Any] | None = None) -> ModalitySender:
        return _TrackSender()

    def receiver(self, config: Mapping[str, Any] | None = None) -> ModalityReceiver:
        return _TrackReceiver()


# ------------------------------------------------------------------ a CoEx session's frames
def _vector(kind: str) -> Any:
    v = next(v for v in load_vectors("messages") if v["type"] == kind)
    return jsonfmt.from_json({"type": kind, **v["fields"]})


def _status(i: int) -> VehicleStatus:
    return VehicleStatus(stamp=1000 + i, x=10.0 * i, y=-5.0 * i, depth=100.0 + i, altitude=20.0,
                         heading=90.0, speed=1.0, battery=80, mode=VehicleMode.SURVEY, faults=0)


def _session(n: int = 6) -> tuple[list[bytes], list[bytes]]:
    """Uplink frames (vehicle status first, then subgrids) and downlink frames (ROI requests)."""
    sub = _vector("Subgrid")
    assert isinstance(sub, Subgrid)
    up, down = [], []
    for i in range(n):
        messages: list[Message] = [_status(i), dataclasses.replace(sub, level=1, ix=i, iy=0, stamp=1000 + i)]
        up.append(wire.pack(messages, 256, FrameHeader(src=2, dst=1, seq=i, crc=True)))
        if i % 3 == 0:
            down.append(wire.pack([_vector("MapRoiRequest")], 256, FrameHeader(src=1, dst=2, seq=i)))
    return up, down


# ------------------------------------------------------------------ record with lcm-logger
def _wait_for_logger(path: Path, ready_channel: str, proc: subprocess.Popen[bytes]) -> None:
    """Publish on a probe channel until lcm-logger has written something (it is subscribed)."""
    probe = lcm.LCM(TEST_UDPM_URL)
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        assert proc.poll() is None, "lcm-logger exited early"
        probe.publish(ready_channel, b"ready?")
        time.sleep(0.1)
        if path.exists() and path.stat().st_size > 0:
            return
    raise AssertionError("lcm-logger did not start recording within 20 s")


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)


def test_record_with_lcm_logger_replay_offline_and_with_lcm_logplayer(
    multicast: None, tmp_path: Path
) -> None:
    up_ch, down_ch, ready = unique_channel("UP"), unique_channel("DOWN"), unique_channel("READY")
    path = tmp_path / "dive.lcmlog"
    logger = subprocess.Popen(
        [str(BIN / "lcm-logger"), f"--lcm-url={TEST_UDPM_URL}", f"--channel=({up_ch}|{down_ch}|{ready})",
         "--flush-interval=20", "--quiet", "--force", str(path)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )
    up, down = _session()
    vehicle = LcmTransport(LcmConfig(url=TEST_UDPM_URL, tx=up_ch, rx=down_ch))
    ship = LcmTransport(LcmConfig(url=TEST_UDPM_URL, tx=down_ch, rx=up_ch))
    try:
        _wait_for_logger(path, ready, logger)
        # the live session: every uplink frame reaches the ship, every downlink frame the vehicle
        downlink = iter(down)
        for i, frame in enumerate(up):
            vehicle.send(frame)
            assert ship.recv(timeout=5.0) == frame
            if i % 3 == 0:
                request = next(downlink)
                ship.send(request)
                assert vehicle.recv(timeout=5.0) == request
        time.sleep(0.3)  # > flush interval
    finally:
        vehicle.close()
        ship.close()
        _stop(logger)
    assert logger.returncode is not None

    # the log holds every frame, in order, as coex.frame_t on its channel
    events = [e for e in lcm.EventLog(str(path), "r") if is_frame_t(e.data)]
    assert [decode_frame(e.data).data for e in events if e.channel == up_ch] == up
    assert [decode_frame(e.data).data for e in events if e.channel == down_ch] == down

    # offline re-analysis: messages routed to the receiver of the modality that declares them
    out = tmp_path / "replay"
    summary = replay_log(path, out, modalities={"track": TrackModality()})
    assert summary["frames"] == len(up) + len(down)
    assert summary["messages_by_type"] == {"MapRoiRequest": len(down), "Subgrid": len(up), "VehicleStatus": len(up)}
    assert summary["routed"] == {"track": len(up)}
    assert summary["unrouted"] == {"Subgrid": len(up), "request": len(down)}
    assert summary["channels"] == {down_ch: len(down), up_ch: len(up)}
    assert summary["vehicle_status"]["stamp"] == 1000 + len(up) - 1
    track = np.load(out / "products" / "track" / "track-vehicle.npy")
    assert track.shape == (len(up), 4)
    assert np.allclose(track[:, 1], [10.0 * i for i in range(len(up))])
    assert np.all(np.diff(track[:, 0]) >= 0) and track[0, 0] > 1.6e9  # log times, in seconds
    assert json.loads((out / "summary.json").read_text())["frames"] == summary["frames"]
    assert summary["map_levels"][0]["level"] == 1 and summary["map_levels"][0]["subgrids"] == len(up)

    # lcm-logplayer puts the recorded frames back on the network; a new ship end receives them
    listener = LcmTransport(LcmConfig(url=TEST_UDPM_URL, tx=unique_channel(), rx=up_ch))
    player = subprocess.Popen(
        [str(BIN / "lcm-logplayer"), f"--lcm-url={TEST_UDPM_URL}", "--speed=20",
         f"--regexp={up_ch}", str(path)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )
    try:
        replayed = []
        deadline = time.monotonic() + 30
        while len(replayed) < len(up) and time.monotonic() < deadline:
            frame = listener.recv(timeout=0.5)
            if frame is not None:
                replayed.append(frame)
        player.wait(timeout=30)
    finally:
        listener.close()
        if player.poll() is None:
            player.kill()
            player.wait(timeout=10)
    assert player.returncode == 0, player.stderr.read() if player.stderr else ""
    assert replayed == up
    assert [m for f in replayed for m in wire.unpack(f) if isinstance(m, VehicleStatus)] == [
        _status(i) for i in range(len(up))
    ]


# ------------------------------------------------------------------ replay details (no network)
def _write_log(path: Path, up: list[bytes], extra: list[tuple[str, bytes]] = ()) -> None:  # type: ignore[assignment]
    log = lcm.EventLog(str(path), "w", overwrite=True)
    t = 1_700_000_000_000_000
    for i, frame in enumerate(up):
        log.write_event(t + i * 1_000_000, "COEX", encode_frame(frame, utime=t, origin=1))
    for j, (channel, data) in enumerate(extra):
        log.write_event(t + (len(up) + j) * 1_000_000, channel, data)
    log.close()


def test_replay_writes_decoded_lcm_types_and_counts_bad_events(tmp_path: Path) -> None:
    up, _ = _session(4)
    bad_coex = encode_frame(b"\xff\xff\xff\xff")  # a frame_t whose CoEx frame is invalid
    path = tmp_path / "dive.lcmlog"
    _write_log(path, up, [("COEX", bad_coex), ("COEX", encode_frame(b"x")[:-1]), ("POSE", b"other type")])
    summary = replay_log(path, tmp_path / "out", modalities={"track": TrackModality()})
    assert summary["events"] == len(up) + 3
    assert summary["frames"] == len(up) and summary["bad_events"] == 2
    assert summary["routed"] == {"track": len(up)}
    decoded = list(lcm.EventLog(str(tmp_path / "out" / "decoded.lcmlog"), "r"))
    statuses = [vehicle_status_from_lcm(vehicle_status_t.decode(e.data)) for e in decoded
                if e.channel == "COEX_VEHICLE_STATUS"]
    assert statuses == [_status(i) for i in range(len(up))]
    levels = [map_level_t.decode(e.data) for e in decoded if e.channel == "COEX_MAP_LEVEL"]
    assert [m.subgrids for m in levels] == [1, 2, 3, 4] and {m.level for m in levels} == {1}
    assert "decoded.lcmlog" in summary["files"] and "summary.json" in summary["files"]
    # a channel filter that matches a non-CoEx channel counts its events as bad
    only_pose = replay_log(path, None, channel="POSE", modalities={})
    assert only_pose["frames"] == 0 and only_pose["bad_events"] == 1


def test_replay_skips_unavailable_modalities_with_a_warning(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def load_modality(name: str) -> type[Modality]:
        if name == "sonar":
            raise PluginLoadError("coex.modalities plugin 'sonar' needs a missing module (sonarlib)")
        return TrackModality

    monkeypatch.setattr(replay_mod, "modality_names", lambda: ["sonar", "track"])
    monkeypatch.setattr(replay_mod.registry, "load_modality", load_modality)
    up, _ = _session(2)
    path = tmp_path / "dive.lcmlog"
    _write_log(path, up)
    with caplog.at_level(logging.WARNING):
        rc = coex_main(["replay", "--lcm-log", str(path), "--out", str(tmp_path / "out")])
    assert rc == 0
    assert "modality sonar unavailable" in caplog.text
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["modalities"] == ["track"] and "sonarlib" in summary["unavailable"]["sonar"]
    assert summary["routed"] == {"track": 2}
    assert (tmp_path / "out" / "products" / "track" / "track-vehicle.npy").exists()


def test_replay_cli_with_registered_modalities(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The real registry: whatever modalities load get the messages; the rest are listed."""
    up, _ = _session(3)
    path = tmp_path / "dive.lcmlog"
    _write_log(path, up)
    rc = coex_main(["replay", "--lcm-log", str(path), "--json"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == 3 and summary["messages_by_type"]["VehicleStatus"] == 3
    registered = set(replay_mod.modality_names())
    assert {"bathymetry", "imagery", "timeseries"} <= registered
    assert set(summary["modalities"]) | set(summary["unavailable"]) == registered
    assert summary["files"] == []  # nothing written without --out


def test_replay_cli_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert coex_main(["replay", "--lcm-log", str(tmp_path / "missing.lcmlog")]) == 2
    assert "no such LCM log" in capsys.readouterr().err
    empty = tmp_path / "empty.lcmlog"
    _write_log(empty, [], [("POSE", b"not coex")])
    assert coex_main(["replay", "--lcm-log", str(empty)]) == 1
    assert "0 CoEx frames" in capsys.readouterr().out


def test_replay_of_a_truncated_log_keeps_what_was_read(tmp_path: Path) -> None:
    up, _ = _session(5)
    path = tmp_path / "dive.lcmlog"
    _write_log(path, up)
    data = path.read_bytes()
    path.write_bytes(data[:-20])
    summary = replay_log(path, None, modalities={"track": TrackModality()})
    assert summary["frames"] == 4 and summary["routed"] == {"track": 4}


# ------------------------------------------------------------------ a real modality, end to end
def test_replay_reproduces_the_live_products_of_a_real_modality(tmp_path: Path) -> None:
    """A time-series session recorded through LcmTransport (file:// provider, both directions
    on one writer instance) replays, via the registry, into the same products topside had live."""
    from coex_plugins.timeseries import TimeSeriesModality, synth

    # the session runs on simulated time near the wall clock, as a live one would: replay gives
    # receivers the log's (wall-clock) event times as `now`, and stamps unwrap against it
    t0 = float(int(time.time()) - 2000)
    m, t = synth.dataset(duration=1200.0, t0=t0, jitter=0.2)
    modality = TimeSeriesModality()
    sender = modality.sender({"channels": [m.channel(), t.channel()], "block_samples": 256,
                              "max_latency": 120.0})
    live = modality.receiver()
    path = tmp_path / "dive.lcmlog"
    url = f"file://{path}?mode=w"
    up = LcmTransport(LcmConfig(url=url, tx="COEX_UP", rx="COEX_UP_IN", share="rec"))
    down = LcmTransport(LcmConfig(url=url, tx="COEX_DOWN", rx="COEX_DOWN_IN", share="rec"))
    step, now, sent = 60, t0, 0
    try:
        for i in range(0, m.times.size, step):
            now = float(m.times[min(i + step, m.times.size) - 1])
            sender.ingest({"methane": (m.times[i:i + step], m.values[i:i + step]),
                           "temperature": (t.times[i:i + step], t.values[i:i + step])}, now)
        for seq in range(300):
            now += 5.0
            messages = sender.fill(240, now)
            if messages:
                frame = wire.pack(messages, 256, FrameHeader(src=2, dst=1, seq=seq % 256))
                up.send(frame)
                sent += 1
                for message in wire.unpack(frame):
                    live.receive(message, now)
            requests = live.poll(now)
            if requests:
                down.send(wire.pack(requests, 256, FrameHeader(src=1, dst=2, seq=seq % 256)))
                for request in requests:
                    sender.handle(request, now)
    finally:
        up.close()
        down.close()
    assert sent >= 2

    summary = replay_log(path, tmp_path / "out")  # modalities from the entry points
    assert "timeseries" in summary["modalities"]
    assert summary["channels"]["COEX_UP"] == sent
    assert summary["routed"]["timeseries"] == summary["messages"] - summary["unrouted"].get("request", 0)
    want = {p.key: p for p in live.products()}
    got = summary["products"]["timeseries"]
    assert {p["key"] for p in got} == set(want) == {"methane", "temperature"}
    for key, product in want.items():
        arrays = np.load(tmp_path / "out" / "products" / "timeseries" / f"series-{key}.npz")
        assert np.array_equal(arrays["times"], product.data.times)
        assert np.array_equal(arrays["values"], product.data.values)
        assert product.data.times.size > 100
