"""Vehicle input adapters on files: ``directory`` (images) and ``points`` (soundings), their
shared watcher, and the ``coex.inputs`` registrations in pyproject.toml."""

from __future__ import annotations

import importlib
import json
import logging
import math
import os
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest

from coex import (
    FEEDS,
    Image,
    Input,
    InputContext,
    Options,
    Points,
    check_options,
)
from coex_core.errors import ConfigError
from coex_plugins.inputs._files import as_pixels
from coex_plugins.inputs.directory import DirectoryInput
from coex_plugins.inputs.points import PointsInput
from coex_plugins.options import compass_from_enu_yaw, yaw_of_quaternion

ROOT = Path(__file__).resolve().parents[1]
OLD = time.time() - 3600.0  # an mtime that has long settled


def entry_points() -> dict[str, str]:
    doc = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return doc["project"]["entry-points"]["coex.inputs"]


def load(value: str) -> type[Input]:
    target = value.split("[")[0].strip()
    module, _, attr = target.partition(":")
    return getattr(importlib.import_module(module), attr)


# --------------------------------------------------------------------------- registrations
def test_every_adapter_is_registered_with_its_extra_and_loads() -> None:
    eps = entry_points()
    assert set(eps) == {"directory", "points", "rosbag", "ros", "lcm", "mavlink", "nmea", "moos"}
    extras = {name: value.split("[")[1].rstrip("] ") if "[" in value else "" for name, value in eps.items()}
    assert extras == {"directory": "imagery", "points": "bathymetry", "rosbag": "bathymetry",
                      "lcm": "lcm", "mavlink": "mavlink", "nmea": "nmea", "moos": "", "ros": ""}
    extras_defined = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    for name, value in eps.items():
        cls = load(value)
        assert issubclass(cls, Input) and cls.name == name
        assert cls.feeds and set(cls.feeds) <= set(FEEDS)
        assert all(o.doc for o in Options.of(cls.options).values())  # each option declared with its doc
        assert extras[name] in extras_defined or not extras[name]  # moos, ros (Debian's rospy): no extra


def test_unknown_and_missing_options_are_named() -> None:
    with pytest.raises(ConfigError, match="needs option 'path'"):
        DirectoryInput({}, InputContext())
    with pytest.raises(ConfigError, match="unknown option 'paht'"):
        DirectoryInput({"path": "x", "paht": "y"}, InputContext())
    with pytest.raises(ConfigError, match="settle: -1 is below 0 s"):
        DirectoryInput({"path": "x", "settle": -1}, InputContext())
    assert check_options(DirectoryInput, {"path": "x", "existing": "yes"}) == [
        "existing: true or false, got 'yes'"]
    assert check_options(PointsInput, {"path": "x", "type": "points"}) == []


def test_every_problem_of_an_adapters_options_is_reported_together_with_its_key(tmp_path: Path) -> None:
    """An adapter's options are checked by the one collector: every unknown and missing option at
    once, in one ConfigError (the adapter) or under the input's key (the deployment file)."""
    from coex_apps.vehicle.config import check

    with pytest.raises(ConfigError) as err:
        DirectoryInput({"paht": "y", "setle": 1}, InputContext())
    text = str(err.value)
    assert "unknown option 'paht'" in text and "unknown option 'setle'" in text and "needs option 'path'" in text
    f = tmp_path / "v.toml"
    f.write_text('[node]\nrole = "vehicle"\nid = 2\nstore = false\n[[modems]]\nuri = "loopback://p"\n'
                 '[[inputs]]\ntype = "directory"\npaht = "y"\nsetle = 1\n')
    _, problems = check(f)
    mine = [p for p in problems if p.startswith("inputs[0]: ")]
    assert len(mine) == 3, problems
    assert any("'paht'" in p for p in mine) and any("'setle'" in p for p in mine)
    assert any("needs option 'path'" in p for p in mine)


def test_heading_helpers() -> None:
    assert compass_from_enu_yaw(0.0) == pytest.approx(90.0)  # ENU east
    assert compass_from_enu_yaw(math.pi / 2) == pytest.approx(0.0)  # north
    assert compass_from_enu_yaw(math.pi) == pytest.approx(270.0)  # west
    half = math.sqrt(0.5)
    assert yaw_of_quaternion(0, 0, half, half) == pytest.approx(math.pi / 2)
    assert yaw_of_quaternion(0, 0, 2 * half, 2 * half) == pytest.approx(math.pi / 2)  # unnormalised
    assert yaw_of_quaternion(0, 0, 0, 0) is None


def test_as_pixels_normalises_layouts_and_types() -> None:
    rgba = np.zeros((4, 5, 4), np.uint8)
    assert as_pixels(rgba).shape == (4, 5, 3)
    planar = np.zeros((3, 6, 7), np.uint16)
    assert as_pixels(planar).shape == (6, 7, 3)
    f = as_pixels(np.array([[0.0, 0.5], [1.0, np.nan]]))
    assert f.dtype == np.uint16 and f.tolist() == [[0, 32768], [65535, 0]]
    assert as_pixels(np.array([[1, 300]], np.int32)).dtype == np.uint16
    assert as_pixels(np.array([[True, False]])).tolist() == [[255, 0]]
    with pytest.raises(ValueError):
        as_pixels(np.zeros((2, 3, 5, 6)))


# --------------------------------------------------------------------------- directory
def _png(path: Path, array: np.ndarray, mtime: float | None = OLD) -> None:
    from PIL import Image as PILImage

    PILImage.fromarray(array).save(path)
    if mtime is not None:
        os.utime(path, (mtime, mtime))


def _directory(tmp_path: Path, **options: object) -> DirectoryInput:
    opts = {"path": "transmit", "interval": 0.0, **options}
    return DirectoryInput(opts, InputContext(origin_lat=41.0, origin_lon=-71.0, base_dir=str(tmp_path)))


def test_directory_takes_new_images_with_pixels_time_and_sidecar(tmp_path: Path) -> None:
    import tifffile

    d = tmp_path / "transmit"
    d.mkdir()
    _png(d / "before.png", np.zeros((4, 4), np.uint8))
    adapter = _directory(tmp_path)  # relative to base_dir
    adapter.open()
    assert adapter.poll(100.0) == []  # existing = false: skipped

    gray = np.arange(48, dtype=np.uint8).reshape(6, 8)
    _png(d / "a.png", gray, mtime=OLD)
    rgb16 = (np.arange(2 * 3 * 3, dtype=np.uint16).reshape(2, 3, 3) * 1000)
    tifffile.imwrite(d / "b.TIFF", rgb16, photometric="rgb")
    os.utime(d / "b.TIFF", (OLD + 5, OLD + 5))
    (d / "b.TIFF.json").write_text(json.dumps({"time": 1.7e9, "x": 12.5, "y": -3.0}))
    (d / "notes.txt").write_text("not an image")
    items = adapter.poll(101.0)
    assert [Path(i.path).name for i in items] == ["a.png", "b.TIFF"]  # oldest first
    a, b = items
    assert isinstance(a, Image) and a.time == pytest.approx(OLD) and a.x is None and a.y is None
    np.testing.assert_array_equal(a.pixels, gray)
    assert b.time == 1.7e9 and (b.x, b.y) == (12.5, -3.0)
    assert b.pixels.dtype == np.uint16 and b.pixels.shape == (2, 3, 3)
    np.testing.assert_array_equal(b.pixels, rgb16)
    assert adapter.poll(102.0) == []  # each file once

    # a stem sidecar with lat/lon goes through the origin
    _png(d / "c.jpg", np.full((8, 8, 3), 128, np.uint8))
    (d / "c.json").write_text(json.dumps({"lat": 41.001, "lon": -71.0}))
    (c,) = adapter.poll(103.0)
    assert c.pixels.shape == (8, 8, 3) and c.x == pytest.approx(0.0, abs=1e-6)
    assert c.y == pytest.approx(111.32, abs=0.01)
    assert c.time == pytest.approx(OLD)

    # rewriting a file makes it new again
    _png(d / "a.png", gray[::-1].copy(), mtime=OLD + 60)
    (a2,) = adapter.poll(104.0)
    np.testing.assert_array_equal(a2.pixels, gray[::-1])
    adapter.close()


def test_directory_waits_until_a_file_has_settled(tmp_path: Path) -> None:
    d = tmp_path / "transmit"
    d.mkdir()
    adapter = _directory(tmp_path, settle=30.0)  # 30 s: the wall clock never settles it here
    adapter.open()
    img = np.full((16, 16), 7, np.uint8)
    _png(d / "new.png", img, mtime=None)  # just written
    assert adapter.poll(0.0) == []
    assert adapter.next_event(0.0) == pytest.approx(30.0)
    assert adapter.poll(29.0) == []
    # it grows: the clock restarts
    with (d / "new.png").open("ab") as fh:
        fh.write(b"\0" * 10)
    assert adapter.poll(29.5) == []
    assert adapter.poll(59.0) == []
    (item,) = adapter.poll(59.5)
    np.testing.assert_array_equal(item.pixels, img)  # trailing bytes after IEND are harmless
    assert adapter.next_event(60.0) is None


def test_directory_existing_true_takes_what_is_there(tmp_path: Path) -> None:
    d = tmp_path / "transmit"
    d.mkdir()
    _png(d / "old.png", np.zeros((3, 3), np.uint8))
    adapter = _directory(tmp_path, existing=True)
    adapter.open()
    assert [Path(i.path).name for i in adapter.poll(1.0)] == ["old.png"]
    # close and open again: the same object remembers what it took
    adapter.close()
    adapter.open()
    assert adapter.poll(2.0) == []


def test_directory_skips_unreadable_files_and_logs_once(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    d = tmp_path / "transmit"
    d.mkdir()
    adapter = _directory(tmp_path)
    adapter.open()
    (d / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    (d / "broken.tif").write_bytes(b"II*\0 nonsense")
    (d / ".partial.png").write_bytes(b"hidden: never looked at")
    for p in d.iterdir():
        os.utime(p, (OLD, OLD))
    _png(d / "good.png", np.ones((2, 2), np.uint8))
    with caplog.at_level(logging.WARNING):
        items = adapter.poll(1.0)
        assert [Path(i.path).name for i in items] == ["good.png"]
        assert adapter.poll(2.0) == []
    warnings = [r.getMessage() for r in caplog.records if "cannot read" in r.getMessage()]
    assert len(warnings) == 2 and any("broken.png" in w for w in warnings)


def test_directory_that_appears_later_is_watched(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    adapter = _directory(tmp_path, existing=False)
    with caplog.at_level(logging.WARNING):
        adapter.open()
        assert adapter.poll(1.0) == [] and adapter.poll(2.0) == []
    assert sum("will keep looking" in r.getMessage() for r in caplog.records) == 1
    (tmp_path / "transmit").mkdir()
    _png(tmp_path / "transmit" / "first.png", np.zeros((2, 2), np.uint8))
    assert len(adapter.poll(3.0)) == 1  # created after open: new


def test_directory_scan_interval(tmp_path: Path) -> None:
    d = tmp_path / "transmit"
    d.mkdir()
    adapter = _directory(tmp_path, interval=5.0)
    adapter.open()
    assert adapter.poll(0.0) == []
    _png(d / "x.png", np.zeros((2, 2), np.uint8))
    assert adapter.poll(4.0) == []  # not scanned yet
    assert len(adapter.poll(5.0)) == 1


# --------------------------------------------------------------------------- points
def test_points_from_a_directory_of_npy_and_csv(tmp_path: Path) -> None:
    d = tmp_path / "soundings"
    d.mkdir()
    adapter = PointsInput({"path": str(d), "interval": 0}, InputContext())
    adapter.open()
    xyz = np.array([[1.0, 2.0, -30.0], [np.nan, 0.0, -31.0], [3.0, 4.0, -32.5]])
    np.save(d / "ping1.npy", xyz)
    (d / "ping2.csv").write_text("x,y,z\n10,20,-40\n11,21,-41.5\n")
    (d / "ping3.csv").write_text("5 6 -7\n8 9 -10\n")  # no header, spaces
    (d / "bad.csv").write_text("this,is\nnot,numbers\n")
    (d / "ping2.csv.json").write_text('{"time": 1700000000.5}')
    for p in d.iterdir():
        os.utime(p, (OLD, OLD))
    os.utime(d / "ping3.csv", (OLD + 1, OLD + 1))
    items = adapter.poll(1.0)
    assert all(isinstance(i, Points) for i in items)
    by_first = {tuple(i.xyz[0]): i for i in items}
    assert len(items) == 3
    np.testing.assert_array_equal(by_first[(1.0, 2.0, -30.0)].xyz, xyz[[0, 2]])  # NaN row dropped
    p2 = by_first[(10.0, 20.0, -40.0)]
    assert p2.time == 1700000000.5 and p2.xyz.tolist() == [[10, 20, -40], [11, 21, -41.5]]
    p3 = by_first[(5.0, 6.0, -7.0)]
    assert p3.time == pytest.approx(OLD + 1) and p3.xyz.dtype == np.float64
    assert adapter.poll(2.0) == []


def test_points_single_file_is_taken_even_if_there_before(tmp_path: Path) -> None:
    f = tmp_path / "survey.npy"
    np.save(f, np.array([[0.0, 0.0, -5.0]], np.float32))
    os.utime(f, (OLD, OLD))
    adapter = PointsInput({"path": "survey.npy"}, InputContext(base_dir=str(tmp_path)))
    adapter.open()
    (item,) = adapter.poll(0.0)
    assert item.xyz.tolist() == [[0.0, 0.0, -5.0]] and item.time == pytest.approx(OLD)
    assert adapter.poll(10.0) == []
    np.save(f, np.array([[1.0, 1.0, -6.0]]))  # rewritten: new again
    os.utime(f, (OLD + 9, OLD + 9))
    (again,) = adapter.poll(20.0)
    assert again.xyz.tolist() == [[1.0, 1.0, -6.0]]


def test_points_bad_array_is_skipped(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    d = tmp_path / "s"
    d.mkdir()
    np.save(d / "flat.npy", np.zeros(5))
    (d / "junk.npy").write_bytes(b"not numpy")
    for p in d.iterdir():
        os.utime(p, (OLD, OLD))
    adapter = PointsInput({"path": str(d), "existing": True, "interval": 0}, InputContext())
    adapter.open()
    with caplog.at_level(logging.WARNING):
        assert adapter.poll(0.0) == []
    assert sum("cannot read" in r.getMessage() for r in caplog.records) == 2


# --------------------------------------------------------------------------- docs
DOC = ROOT / "docs" / "inputs.md"


def test_docs_give_every_option_and_valid_examples() -> None:
    import re

    text = DOC.read_text()
    sections = {m.group(1): m.start() for m in re.finditer(r"^## (\w+)$", text, re.M)}
    blocks = re.findall(r"```toml\n(.*?)```", text, re.S)
    examples = [t for b in blocks for t in tomllib.loads(b).get("inputs", [])]
    for name, value in entry_points().items():
        cls = load(value)
        start = sections[name]
        end = min([s for s in sections.values() if s > start], default=len(text))
        section = text[start:end]
        for option in cls.options:
            assert f"| `{option}` |" in section, f"docs/inputs.md: {name} does not document {option!r}"
        mine = [e for e in examples if e["type"] == name]
        assert mine, f"docs/inputs.md: no example of {name}"
        for example in mine:
            assert check_options(cls, example) == []
    # and the example of "Writing your own input" is a working input
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    namespace: dict[str, object] = {}
    exec(compile(code, "docs/inputs.md", "exec"), namespace)
    ctd = namespace["CtdInput"]
    assert check_options(ctd, {"port": 70000}) == ["port: 70000 is outside 1..65535"]
    assert check_options(ctd, {"port": True}) == ["port: not an integer, got true"]
    import socket

    from coex_transports.testing import free_port

    port = free_port()
    adapter = ctd({"port": port}, InputContext())
    adapter.open()
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            tx.sendto(b"4.5,33.1,120.0", ("127.0.0.1", port))
            tx.sendto(b"nonsense", ("127.0.0.1", port))
            items: list[object] = []
            deadline = time.monotonic() + 2.0
            while len(items) < 2 and time.monotonic() < deadline:
                items += adapter.poll(9.0)
        samples, nav = items
        assert samples.values.tolist() == [4.5] and nav.depth == 120.0
    finally:
        adapter.close()


def test_adapters_load_without_their_optional_libraries() -> None:
    """Each module imports its library when it opens: a vehicle without lcm loads the others."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "for m in ('lcm', 'pymavlink', 'serial', 'rosbags', 'tifffile', 'PIL'): sys.modules[m] = None\n"
        "from coex_core.errors import PluginLoadError\n"
        "from coex import InputContext\n"
        "from coex_plugins.inputs import directory, points, rosbag, lcm, mavlink, nmea\n"
        "try:\n"
        "    lcm.LcmInput({'nav_channel': 'NAV'}, InputContext()).open()\n"
        "except PluginLoadError as exc:\n"
        "    print(exc)\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=env)
    assert out.returncode == 0, out.stderr
    assert "pip install 'coexploration[lcm]'" in out.stdout


def test_log_once_logs_each_problem_once_and_stays_bounded(caplog: pytest.LogCaptureFixture) -> None:
    from coex_plugins.options import LogOnce

    once = LogOnce(logging.getLogger("test.inputs"))
    once.LIMIT = 3
    with caplog.at_level(logging.WARNING):
        for key in ("a", "a", "b", "c", "d", "a"):
            once(key, "problem %s", key)
    assert [r.getMessage() for r in caplog.records] == ["problem a", "problem b", "problem c", "problem d",
                                                       "problem a"]
    assert len(once.counts) == 3


# ------------------------------------------------------------------ what every input counts
#: the least options each built-in input is built with
MINIMAL = {"directory": {"path": "."}, "points": {"path": "."}, "rosbag": {"path": "x.bag", "nav_topic": "/nav"},
           "lcm": {"nav_channel": "NAV"}, "mavlink": {"connection": "udpin:127.0.0.1:0"},
           "nmea": {"udp": "127.0.0.1:0"}, "moos": {}}


@pytest.mark.parametrize("name", sorted(MINIMAL))
def test_every_input_counts_what_it_skips_under_the_documented_key(name: str, tmp_path: Path) -> None:
    """The contract of ``Input``: ``counts["skipped"]`` exists from the start (the adapters' own
    keys are added beside it), and ``skip()`` / ``skipped`` count and read it."""
    module, _, attr = entry_points()[name].partition(":")
    cls = getattr(importlib.import_module(module), attr.split()[0])
    adapter = cls(MINIMAL[name], InputContext(base_dir=str(tmp_path)))
    assert isinstance(adapter, Input) and adapter.counts["skipped"] == 0 == adapter.skipped
    adapter.skip()
    adapter.skip(2)
    assert adapter.skipped == 3 == adapter.counts["skipped"]


def test_a_directory_counts_the_images_it_cannot_read(tmp_path: Path) -> None:
    (tmp_path / "a.png").write_bytes(b"not a png")
    (tmp_path / "b.tif").write_bytes(b"II*\x00 broken")
    _png(tmp_path / "c.png", np.zeros((16, 16), np.uint8))
    for p in tmp_path.iterdir():
        os.utime(p, (OLD, OLD))
    adapter = DirectoryInput({"path": str(tmp_path), "existing": True, "interval": 0.0}, InputContext())
    adapter.open()
    items = adapter.poll(100.0)
    assert len(items) == 1 and adapter.counts == {"skipped": 2}


def test_a_third_party_input_gets_the_counter_from_the_base_class() -> None:
    class Mine(Input):
        name = "mine"
        feeds = ("status",)

        def poll(self, now: float) -> list:  # type: ignore[type-arg]
            self.skip()  # a line it could not parse
            return []

    adapter = Mine({}, InputContext())
    adapter.poll(1.0)
    assert adapter.counts == {"skipped": 1} and adapter.skipped == 1


def test_whether_the_daemon_stamps_an_inputs_images_is_declared_on_input(tmp_path: Path) -> None:
    """``Input.stamp_images`` (the vehicle daemon gives images without a position the newest
    vehicle position): by default the input's ``nav`` option (the directory input's), False for
    an input without one; an input overrides it (the MOOS and ROS inputs: ``nav_images``)."""
    assert _directory(tmp_path).stamp_images is False
    assert _directory(tmp_path, nav=True).stamp_images is True

    class Camera(Input):
        name = "camera"
        feeds = ("imagery",)

        def poll(self, now: float) -> list[Image]:
            return []

    ctx = InputContext(origin_lat=41.0, origin_lon=-71.0, base_dir=str(tmp_path))
    assert Camera({}, ctx).stamp_images is False
    moos = load(entry_points()["moos"])
    assert moos.stamp_images is not Input.stamp_images  # its own (option nav_images)
