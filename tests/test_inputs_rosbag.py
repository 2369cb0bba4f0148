"""The ``rosbag`` input: ROS 1 and ROS 2 bags replayed with their timing into Points, Image and
Nav items."""

from __future__ import annotations

import io
import logging
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from coex import Image, InputContext, Nav, Points
from coex_core.errors import ConfigError
from coex_plugins.inputs.rosbag import RosbagInput

Build = Callable[[Any, Any], Any]  # (typestore, header) -> message


def write_bag(path: Path, records: list[tuple[str, str, float, Build]], ros1: bool = False,
              stamp_offset: dict[float, float] | None = None) -> Path:
    """Write ``(topic, msgtype, bag time, builder)`` records; a header stamp equals the bag time
    unless ``stamp_offset`` shifts it."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    header_t = store.types["std_msgs/msg/Header"]
    time_t = store.types["builtin_interfaces/msg/Time"]

    def header(t: float) -> Any:
        sec = int(t)
        stamp = time_t(sec=sec, nanosec=round((t - sec) * 1e9))
        return header_t(seq=0, stamp=stamp, frame_id="map") if ros1 else header_t(stamp=stamp, frame_id="map")

    if ros1:
        from rosbags.rosbag1 import Writer
    else:
        from rosbags.rosbag2 import Writer  # type: ignore[assignment]
    kwargs = {} if ros1 else {"version": 8}
    with Writer(path, **kwargs) as w:
        conns: dict[str, Any] = {}
        for topic, msgtype, t, build in records:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=store)
            msg = build(store, header(t + (stamp_offset or {}).get(t, 0.0)))
            raw = store.serialize_ros1(msg, msgtype) if ros1 else store.serialize_cdr(msg, msgtype)
            w.write(conns[topic], round(t * 1e9), raw)
    return path


PC2 = "sensor_msgs/msg/PointCloud2"
IMG = "sensor_msgs/msg/Image"
CIMG = "sensor_msgs/msg/CompressedImage"
ODOM = "nav_msgs/msg/Odometry"
POSE = "geometry_msgs/msg/PoseStamped"
FIX = "sensor_msgs/msg/NavSatFix"


def cloud(xyz: np.ndarray) -> Build:
    def build(store: Any, header: Any) -> Any:
        field = store.types["sensor_msgs/msg/PointField"]
        data = np.ascontiguousarray(xyz, dtype="<f4").view(np.uint8).ravel()
        return store.types[PC2](
            header=header, height=1, width=len(xyz),
            fields=[field(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")],
            is_bigendian=False, point_step=12, row_step=12 * len(xyz), data=data, is_dense=True)
    return build


def raw_image(encoding: str, rows: np.ndarray, step: int, bigendian: bool = False) -> Build:
    """rows: h x step bytes already laid out."""
    h = rows.shape[0]

    def build(store: Any, header: Any) -> Any:
        return store.types[IMG](header=header, height=h, width=WIDTH[encoding], encoding=encoding,
                                is_bigendian=int(bigendian), step=step,
                                data=np.ascontiguousarray(rows, np.uint8).ravel())
    return build


WIDTH: dict[str, int] = {}


def compressed(fmt: str, pixels: np.ndarray, pil_format: str) -> Build:
    from PIL import Image as PILImage

    buf = io.BytesIO()
    PILImage.fromarray(pixels).save(buf, format=pil_format)
    data = np.frombuffer(buf.getvalue(), np.uint8)

    def build(store: Any, header: Any) -> Any:
        return store.types[CIMG](header=header, format=fmt, data=data)
    return build


def quat(yaw: float) -> tuple[float, float, float, float]:
    return 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)


def odometry(x: float, y: float, z: float, yaw: float, vx: float, vy: float) -> Build:
    def build(store: Any, header: Any) -> Any:
        T = store.types
        qx, qy, qz, qw = quat(yaw)
        pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                                           orientation=T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw))
        vec = T["geometry_msgs/msg/Vector3"]
        twist = T["geometry_msgs/msg/Twist"](linear=vec(x=vx, y=vy, z=0.0), angular=vec(x=0.0, y=0.0, z=0.0))
        cov = np.zeros(36)
        return T[ODOM](header=header, child_frame_id="base_link",
                       pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov),
                       twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=cov))
    return build


def pose_stamped(x: float, y: float, z: float, yaw: float) -> Build:
    def build(store: Any, header: Any) -> Any:
        T = store.types
        qx, qy, qz, qw = quat(yaw)
        pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                                           orientation=T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw))
        return T[POSE](header=header, pose=pose)
    return build


def navsatfix(lat: float, lon: float, status: int = 0) -> Build:
    def build(store: Any, header: Any) -> Any:
        T = store.types
        return T[FIX](header=header, status=T["sensor_msgs/msg/NavSatStatus"](status=status, service=1),
                      latitude=lat, longitude=lon, altitude=-5.0, position_covariance=np.zeros(9),
                      position_covariance_type=0)
    return build


# --------------------------------------------------------------------------- ROS 2
MONO = np.arange(12, dtype=np.uint8).reshape(3, 4)
BGR = np.arange(2 * 2 * 3, dtype=np.uint8).reshape(2, 2, 3)
MONO16 = np.array([[1, 256, 65535]], np.uint16)
WIDTH.update({"mono8": 4, "bgr8": 2, "mono16": 3, "bayer_rggb8": 2, "rgb8": 2, "bgra8": 1})


def ros2_bag(tmp_path: Path) -> Path:
    padded = np.zeros((3, 6), np.uint8)  # step 6 for 4 pixels: rows padded
    padded[:, :4] = MONO
    records = [
        ("/sonar/points", PC2, 100.0, cloud(np.array([[1, 2, -30], [np.nan, 0, 0]], np.float32))),
        ("/odom", ODOM, 100.1, odometry(10.0, 20.0, -30.0, 0.0, 1.0, 1.0)),
        ("/camera/image", IMG, 100.2, raw_image("mono8", padded, 6)),
        ("/camera/image", IMG, 100.3, raw_image("bgr8", BGR.reshape(2, 6), 6)),
        ("/camera/image", IMG, 100.4, raw_image("bayer_rggb8", np.zeros((2, 2), np.uint8), 2)),
        ("/camera/image", IMG, 100.45, raw_image("mono16", MONO16.astype(">u2").view(np.uint8), 6, True)),
        ("/odom", ODOM, 100.5, odometry(11.0, 21.0, -31.0, math.pi / 2, 0.0, 2.0)),
        ("/sonar/points", PC2, 101.0, cloud(np.array([[3, 4, -32]], np.float32))),
        ("/other", POSE, 100.05, pose_stamped(0, 0, 0, 0)),
    ]
    return write_bag(tmp_path / "dive_ros2", records, stamp_offset={100.1: -0.05})


def test_ros2_bag_replays_with_its_timing(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    bag = ros2_bag(tmp_path)
    adapter = RosbagInput({"path": "dive_ros2", "points_topic": "/sonar/points", "image_topic": "/camera/image",
                           "nav_topic": "/odom"}, InputContext(base_dir=str(tmp_path)))
    adapter.open()
    assert bag.is_dir() and (bag / "metadata.yaml").is_file()
    assert adapter.next_event(1000.0) == pytest.approx(1000.0)  # anchored: first message now
    (p1,) = adapter.poll(1000.0)
    assert isinstance(p1, Points) and p1.time == pytest.approx(1000.0)
    assert p1.xyz.tolist() == [[1.0, 2.0, -30.0]]  # the NaN row dropped
    assert adapter.next_event(1000.0) == pytest.approx(1000.1)
    assert adapter.poll(1000.09) == []
    with caplog.at_level(logging.WARNING):
        items = adapter.poll(1000.46)
    odom, mono, bgr, mono16 = items  # the bayer image skipped
    assert any("bayer_rggb8" in r.getMessage() for r in caplog.records)
    assert isinstance(odom, Nav) and odom.time == pytest.approx(1000.05)  # its header stamp, shifted
    assert (odom.x, odom.y, odom.depth) == (10.0, 20.0, 30.0)
    assert odom.heading == pytest.approx(90.0) and odom.speed == pytest.approx(math.sqrt(2))
    assert isinstance(mono, Image) and mono.time == pytest.approx(1000.2)
    np.testing.assert_array_equal(mono.pixels, MONO)
    np.testing.assert_array_equal(bgr.pixels, BGR[..., ::-1])
    assert mono16.pixels.dtype == np.uint16 and mono16.pixels.tolist() == MONO16.tolist()
    (odom2,) = adapter.poll(1000.7)
    assert odom2.heading == pytest.approx(0.0) and odom2.speed == pytest.approx(2.0) and odom2.depth == 31.0
    assert adapter.next_event(1000.7) == pytest.approx(1001.0)
    (p2,) = adapter.poll(1005.0)
    assert p2.xyz.tolist() == [[3.0, 4.0, -32.0]]
    assert adapter.next_event(1005.0) is None and adapter.poll(1010.0) == []
    assert adapter.counts == {"points": 2, "image": 3, "nav": 2, "skipped": 1}
    adapter.close()


def test_speed_original_times_and_the_context_clock(tmp_path: Path) -> None:
    ros2_bag(tmp_path)

    adapter = RosbagInput({"path": str(tmp_path / "dive_ros2"), "points_topic": "/sonar/points",
                           "nav_topic": "/odom", "start": "original", "speed": 2.0},
                          InputContext(clock=lambda: 500.0))  # the daemon's clock: a function
    adapter.open()  # anchored at the clock's time, not the first poll
    assert adapter.next_event(900.0) == pytest.approx(500.0)
    items = adapter.poll(500.26)  # 100.5 is due at 500.25 at twice the speed
    assert [type(i).__name__ for i in items] == ["Points", "Nav", "Nav"]
    assert [i.time for i in items] == pytest.approx([100.0, 100.05, 100.5])  # as recorded
    assert adapter.next_event(500.26) == pytest.approx(500.5)
    adapter.close()


# --------------------------------------------------------------------------- ROS 1
def test_ros1_bag_compressed_images_and_navsatfix(tmp_path: Path) -> None:
    rgb = np.zeros((8, 8, 3), np.uint8)
    rgb[:4] = (200, 10, 10)
    gray = np.arange(64, dtype=np.uint8).reshape(8, 8)
    records = [
        ("/fix", FIX, 50.0, navsatfix(41.5, -70.7)),
        ("/cam/compressed", CIMG, 50.5, compressed("rgb8; jpeg compressed bgr8", rgb, "JPEG")),
        ("/fix", FIX, 51.0, navsatfix(0.0, 0.0, status=-1)),  # no fix: nothing
        ("/cam/compressed", CIMG, 51.5, compressed("png", gray, "PNG")),
        ("/cam/compressed", CIMG, 51.7, lambda store, header: store.types[CIMG](
            header=header, format="jpeg", data=np.frombuffer(b"not a jpeg", np.uint8))),
        ("/points", PC2, 52.0, cloud(np.array([[5, 6, -7]], np.float32))),
    ]
    bag = write_bag(tmp_path / "dive.bag", records, ros1=True)
    adapter = RosbagInput({"path": str(bag), "image_topic": "/cam/compressed", "nav_topic": "/fix",
                           "points_topic": "/points"}, InputContext())
    adapter.open()
    items = adapter.poll(10.0) + adapter.poll(12.0)
    fix, jpeg, png, pts = items
    assert isinstance(fix, Nav) and (fix.lat, fix.lon) == (41.5, -70.7) and fix.x is None
    assert fix.time == pytest.approx(10.0)
    assert jpeg.time == pytest.approx(10.5) and jpeg.pixels.shape == (8, 8, 3)
    assert abs(int(jpeg.pixels[0, 0, 0]) - 200) < 12 and jpeg.pixels[7, 7].max() < 12  # red on top
    np.testing.assert_array_equal(png.pixels, gray)
    assert isinstance(pts, Points) and pts.xyz.tolist() == [[5.0, 6.0, -7.0]] and pts.time == pytest.approx(12.0)
    assert adapter.counts["skipped"] == 1
    adapter.close()


def test_ned_poses(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "ned", [("/pose", POSE, 1.0, pose_stamped(5.0, -2.0, 12.0, math.pi / 2))])
    adapter = RosbagInput({"path": str(bag), "nav_topic": "/pose", "nav_frame": "ned"}, InputContext())
    adapter.open()
    (nav,) = adapter.poll(0.0)
    assert (nav.x, nav.y, nav.depth) == (-2.0, 5.0, 12.0)  # east, north, down
    assert nav.heading == pytest.approx(90.0) and nav.speed is None  # yaw from north, clockwise
    adapter.close()


def test_configuration_errors_name_the_option(tmp_path: Path) -> None:
    ros2_bag(tmp_path)
    ctx = InputContext(base_dir=str(tmp_path))
    with pytest.raises(ConfigError, match="at least one of the options 'points_topic'"):
        RosbagInput({"path": "dive_ros2"}, ctx)
    with pytest.raises(ConfigError, match="speed: 0 is not above 0"):
        RosbagInput({"path": "dive_ros2", "nav_topic": "/odom", "speed": 0}, ctx)
    with pytest.raises(ConfigError, match="start: one of 'now', 'original', got 'later'"):
        RosbagInput({"path": "dive_ros2", "nav_topic": "/odom", "start": "later"}, ctx)
    missing = RosbagInput({"path": "dive_ros2", "nav_topic": "/nav"}, ctx)
    with pytest.raises(ConfigError, match=r"'nav_topic': no topic '/nav' .*/odom \(nav_msgs/msg/Odometry\)"):
        missing.open()
    wrong = RosbagInput({"path": "dive_ros2", "points_topic": "/odom"}, ctx)
    with pytest.raises(ConfigError, match="'points_topic': topic '/odom' holds nav_msgs/msg/Odometry"):
        wrong.open()
    with pytest.raises(ConfigError, match=r"'path'.*does not exist"):
        RosbagInput({"path": "nope.bag", "nav_topic": "/odom"}, ctx).open()
    (tmp_path / "junk.bag").write_bytes(b"#ROSBAG V2.0\n garbage")
    with pytest.raises(ConfigError, match=r"cannot read .* as a bag"):
        RosbagInput({"path": "junk.bag", "nav_topic": "/odom"}, ctx).open()
