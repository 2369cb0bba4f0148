"""The shipped adapter suites (coex_conformance.InputTests / AutonomyTests) run on the built-in
inputs and autonomy outputs, the way a vehicle team runs them on its own: each built-in is a
fixtures class giving its class, working options and, where the source can be made to speak on
loopback, a feed of good data and of one bad item."""

from __future__ import annotations

import json
import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from coex_conformance import AutonomyFixtures, AutonomyTests, InputFixtures, InputTests
from coex_core.adapters import Autonomy, Input

from ._modemsim import free_tcp_base


def _udp_port() -> int:
    return free_tcp_base(1, socket.SOCK_DGRAM)


def _send_udp(port: int, data: bytes) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.sendto(data, ("127.0.0.1", port))


# ------------------------------------------------------------------------------- inputs
class DirectoryFixtures(InputFixtures):
    @pytest.fixture
    def input_class(self) -> type[Input]:
        from coex_plugins.inputs.directory import DirectoryInput

        return DirectoryInput

    @pytest.fixture
    def folder(self, tmp_path: Path) -> Path:
        d = tmp_path / "transmit"
        d.mkdir()
        return d

    @pytest.fixture
    def input_options(self, folder: Path) -> dict[str, Any]:
        return {"path": str(folder), "settle": 0.1} if "settle" in self._options() else {"path": str(folder)}

    @staticmethod
    def _options() -> Any:
        from coex_plugins.inputs.directory import DirectoryInput

        return DirectoryInput.options

    @pytest.fixture
    def feed(self, folder: Path) -> Callable[[Input], Any]:
        from PIL import Image

        def write(_: Input) -> None:
            img = (np.arange(64 * 48).reshape(48, 64) % 255).astype(np.uint8)
            Image.fromarray(img).save(folder / "a.part.png")
            (folder / "a.part.png").rename(folder / "frame_0001.png")

        return write

    @pytest.fixture
    def feed_bad(self, folder: Path) -> Callable[[Input], Any]:
        return lambda _: (folder / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\nnot an image")


class TestDirectoryInput(InputTests, DirectoryFixtures):
    pass


class PointsFixtures(InputFixtures):
    @pytest.fixture
    def input_class(self) -> type[Input]:
        from coex_plugins.inputs.points import PointsInput

        return PointsInput

    @pytest.fixture
    def folder(self, tmp_path: Path) -> Path:
        d = tmp_path / "points"
        d.mkdir()
        return d

    @pytest.fixture
    def input_options(self, folder: Path) -> dict[str, Any]:
        return {"path": str(folder)}

    @pytest.fixture
    def feed(self, folder: Path) -> Callable[[Input], Any]:
        def write(_: Input) -> None:
            xyz = np.random.default_rng(1).normal(size=(100, 3))
            np.save(folder / "tmp.npy", xyz)
            (folder / "tmp.npy").rename(folder / "ping_0001.npy")

        return write

    @pytest.fixture
    def feed_bad(self, folder: Path) -> Callable[[Input], Any]:
        return lambda _: (folder / "bad.npy").write_bytes(b"\x93NUMPY garbage")


class TestPointsInput(InputTests, PointsFixtures):
    pass


class NmeaFixtures(InputFixtures):
    @pytest.fixture
    def input_class(self) -> type[Input]:
        from coex_plugins.inputs.nmea import NmeaInput

        return NmeaInput

    @pytest.fixture
    def port(self) -> int:
        return _udp_port()

    @pytest.fixture
    def input_options(self, port: int) -> dict[str, Any]:
        return {"udp": f"127.0.0.1:{port}"}

    @staticmethod
    def _line(body: str) -> bytes:
        cs = 0
        for ch in body:
            cs ^= ord(ch)
        return f"${body}*{cs:02X}\r\n".encode()

    @pytest.fixture
    def feed(self, port: int) -> Callable[[Input], Any]:
        return lambda _: _send_udp(port, self._line("GPGGA,120000.00,4131.47,N,07040.27,W,1,08,0.9,-25.0,M,0.0,M,,"))

    @pytest.fixture
    def feed_bad(self, port: int) -> Callable[[Input], Any]:
        return lambda _: _send_udp(port, b"$GPGGA,garbage*00\r\n")


class TestNmeaInput(InputTests, NmeaFixtures):
    pass


class NmeaSamplesFixtures(NmeaFixtures):
    """The same input fed a water temperature: it gives ``Samples`` (with ``times``, not a
    ``time``), which the suite's item rule checks as a series."""

    @pytest.fixture
    def feed(self, port: int) -> Callable[[Input], Any]:
        return lambda _: _send_udp(port, self._line("YXMTW,12.5,C"))


class TestNmeaInputSamples(InputTests, NmeaSamplesFixtures):
    pass


class LcmFixtures(InputFixtures):
    @pytest.fixture
    def input_class(self) -> type[Input]:
        pytest.importorskip("lcm")
        from coex_plugins.inputs.lcm import LcmInput

        return LcmInput

    @pytest.fixture
    def url(self) -> str:
        return f"udpm://239.255.76.67:{_udp_port()}?ttl=0"

    @pytest.fixture
    def input_options(self, url: str) -> dict[str, Any]:
        return {"url": url, "nav_channel": "SUITE_NAV"}

    @pytest.fixture
    def feed(self, url: str) -> Callable[[Input], Any]:
        import lcm

        from coex_transports.lcm._types import nav_t

        def publish(_: Input) -> None:
            msg = nav_t()
            msg.utime = int(time.time() * 1e6)
            msg.x, msg.y, msg.depth = 1.0, 2.0, 30.0
            lcm.LCM(url).publish("SUITE_NAV", msg.encode())

        return publish

    @pytest.fixture
    def feed_bad(self, url: str) -> Callable[[Input], Any]:
        import lcm

        return lambda _: lcm.LCM(url).publish("SUITE_NAV", b"not a nav_t")


class TestLcmInput(InputTests, LcmFixtures):
    pass


class MavlinkInputFixtures(InputFixtures):
    @pytest.fixture
    def input_class(self) -> type[Input]:
        pytest.importorskip("pymavlink")
        from coex_plugins.inputs.mavlink import MavlinkInput

        return MavlinkInput

    @pytest.fixture
    def port(self) -> int:
        return _udp_port()

    @pytest.fixture
    def input_options(self, port: int) -> dict[str, Any]:
        return {"connection": f"udpin:127.0.0.1:{port}"}

    @pytest.fixture
    def feed(self, port: int) -> Iterator[Callable[[Input], Any]]:
        from pymavlink import mavutil

        conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)

        def send(_: Input) -> None:
            for _k in range(3):
                conn.mav.global_position_int_send(1000, int(41.5 * 1e7), int(-70.7 * 1e7), -30000, -30000,
                                                  0, 0, 0, 9000)
                time.sleep(0.05)

        yield send
        conn.close()

    @pytest.fixture
    def feed_bad(self, port: int) -> Iterator[Callable[[Input], Any]]:
        # a MAVLink 2 frame whose checksum is wrong (pymavlink reads it as BAD_DATA)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

        def send(_: Input) -> None:
            for _k in range(3):
                sock.sendto(bytes([0xFD, 9, 0, 0, 7, 1, 1, 0, 0, 0]) + bytes(9) + b"\xde\xad", ("127.0.0.1", port))
                time.sleep(0.05)

        yield send
        sock.close()


class TestMavlinkInput(InputTests, MavlinkInputFixtures):
    pass


# ------------------------------------------------------------------------- autonomy outputs
class LogFixtures(AutonomyFixtures):
    @pytest.fixture
    def autonomy_class(self) -> type[Autonomy]:
        from coex_plugins.autonomy.log import LogAutonomy

        return LogAutonomy

    @pytest.fixture
    def autonomy_options(self, tmp_path: Path) -> dict[str, Any]:
        return {"file": str(tmp_path / "plans.jsonl")}

    @pytest.fixture
    def peer(self) -> str | None:
        return None

    @pytest.fixture
    def patience(self) -> float:
        return 30.0


class TestLogAutonomy(AutonomyTests, LogFixtures):
    def test_the_plan_is_in_the_file(self, autonomy_options: dict[str, Any], context: Any) -> None:
        from coex_conformance import survey_plan
        from coex_plugins.autonomy.log import LogAutonomy

        out = LogAutonomy(autonomy_options, context)
        out.open()
        out.submit(survey_plan(3), 10.0)
        out.close()
        line = json.loads(Path(autonomy_options["file"]).read_text().splitlines()[0])
        assert line["survey_id"] == 3


class SimFixtures(AutonomyFixtures):
    @pytest.fixture
    def autonomy_class(self) -> type[Autonomy]:
        from coex_plugins.autonomy.sim import SimAutonomy

        return SimAutonomy

    @pytest.fixture
    def autonomy_options(self) -> dict[str, Any]:
        return {"speed": 10.0}

    @pytest.fixture
    def peer(self) -> str | None:
        return "flies"

    @pytest.fixture
    def patience(self) -> float:
        return 20.0  # a 30 m line at the plan's 1 m/s: done in 30 s of `now`, which runs on the wall clock


class TestSimAutonomy(AutonomyTests, SimFixtures):
    def _reports(self, out: Autonomy, start: float, seconds: float, *, realtime: bool,
                 until: Callable[[list[Any]], bool]) -> list[Any]:
        """The sim takes its time from ``now`` alone (it reads no clock, coex_plugins.autonomy.sim):
        the kit runs ``now`` ahead for it instead of following the wall clock, as for a flying
        peer, so its 30 m line at 1 m/s is flown in no real time (was 30 s asleep). The kit's
        rules on what it reports are checked as before."""
        return super()._reports(out, start, seconds, realtime=False, until=until)


class MavlinkSilentFixtures(AutonomyFixtures):
    @pytest.fixture
    def autonomy_class(self) -> type[Autonomy]:
        pytest.importorskip("pymavlink")
        from coex_plugins.autonomy.mavlink import MavlinkAutonomy

        return MavlinkAutonomy

    @pytest.fixture
    def autonomy_options(self) -> dict[str, Any]:
        return {"connection": f"udpout:127.0.0.1:{_udp_port()}", "heartbeat": 0.0}  # nobody listens


class TestMavlinkAutonomySilent(AutonomyTests, MavlinkSilentFixtures):
    pass


class MavlinkFlyingFixtures(MavlinkSilentFixtures):
    @pytest.fixture
    def port(self) -> int:
        return _udp_port()

    @pytest.fixture
    def autonomy_options(self, port: int) -> dict[str, Any]:
        return {"connection": f"udpout:127.0.0.1:{port}"}

    @pytest.fixture
    def peer(self, port: int) -> Iterator[str]:
        from coex_plugins.autonomy.mavpeer import MissionPeer

        with MissionPeer(f"udpin:127.0.0.1:{port}", fly_interval=0.5):
            yield "flies"

    @pytest.fixture
    def patience(self) -> float:
        return 30.0


class TestMavlinkAutonomyFlying(AutonomyTests, MavlinkFlyingFixtures):
    pass


class LcmSilentFixtures(AutonomyFixtures):
    @pytest.fixture
    def autonomy_class(self) -> type[Autonomy]:
        pytest.importorskip("lcm")
        from coex_plugins.autonomy.lcm import LcmAutonomy

        return LcmAutonomy

    @pytest.fixture
    def autonomy_options(self) -> dict[str, Any]:
        return {"url": f"udpm://239.255.76.67:{_udp_port()}?ttl=0"}


class TestLcmAutonomySilent(AutonomyTests, LcmSilentFixtures):
    pass


# -------------------------------------------------------------- the suites catch what they say
class _Broken(Input):
    name = "broken"
    feeds = ("status",)
    options = {"mode": ("", "what is wrong with it")}

    def poll(self, now: float) -> list[Any]:
        from coex_core.adapters import Points

        if self.config["mode"] == "blocks":
            time.sleep(2.5)
        if self.config["mode"] == "wrong_items":
            return [Points(now, np.zeros((1, 3)))]
        return []


class _Lying(Autonomy):
    name = "lying"
    options = {"mode": ("", "what is wrong with it")}

    def submit(self, plan: Any, now: float) -> None:
        self.plan = plan

    def poll(self, now: float) -> list[Any]:
        from coex_core.adapters import SurveyReport
        from coex_core.messages import SurveyReason, SurveyState

        if self.config["mode"] == "accepted":
            return [SurveyReport(self.plan.survey_id, SurveyState.ACCEPTED, now)]
        if now > 1100 and self.config["mode"] == "refused":  # a silent peer read as a refusal
            return [SurveyReport(self.plan.survey_id, SurveyState.REJECTED, now, SurveyReason.AUTONOMY_REFUSED)]
        return []


@pytest.mark.parametrize("mode", ["blocks", "wrong_items"])
def test_the_input_suite_catches_a_broken_input(mode: str, tmp_path: Path) -> None:
    from coex_core.adapters import InputContext

    ctx = InputContext(0, 0, str(tmp_path))
    suite = InputTests()
    with pytest.raises(AssertionError):
        if mode == "blocks":
            suite.test_poll_never_blocks_and_close_is_harmless_twice(_Broken, {"mode": mode}, ctx)
        else:
            suite.test_what_it_reads_comes_as_the_items_it_feeds(_Broken, {"mode": mode}, ctx, lambda _: None)


@pytest.mark.parametrize("mode", ["accepted", "refused"])
def test_the_autonomy_suite_catches_a_lying_output(mode: str, tmp_path: Path) -> None:
    from coex_core.adapters import InputContext

    with pytest.raises(AssertionError, match="never ACCEPTED" if mode == "accepted" else "AUTONOMY_NO_ANSWER"):
        AutonomyTests().test_reports_are_about_its_plans_in_the_states_an_output_may_report(
            _Lying, {"mode": mode}, InputContext(0, 0, str(tmp_path)), "silent", 300.0)
