"""Point-cloud inputs: ``.npy``, ``.csv`` and ROS 1 / ROS 2 bags (``sensor_msgs/PointCloud2``).

Bags are read with ``rosbags`` (no ROS install). PointCloud2 payloads are decoded with one
``np.frombuffer`` per message through a structured dtype built from the message's field list.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from .quadtree import InputError

__all__ = ["iter_points", "load_points", "pointcloud2_xyz", "write_pointcloud_bag"]

FloatArray = npt.NDArray[np.float64]

#: PointField datatype codes (sensor_msgs/PointField) to numpy kinds.
_POINTFIELD = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"


def load_points(path: str | Path, topic: str | None = None) -> FloatArray:
    """Every point of a file as one ``N x 3`` array."""
    parts = [xyz for _, xyz in iter_points(path, topic)]
    if not parts:
        return np.zeros((0, 3))
    return np.concatenate(parts)


def iter_points(path: str | Path, topic: str | None = None) -> Iterator[tuple[float | None, FloatArray]]:
    """``(time or None, N x 3 points)`` chunks from a ``.npy``, ``.csv`` or bag (ROS 1 ``.bag`` file
    or ROS 2 bag directory / ``.db3`` / ``.mcap``)."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: no such file or directory")
    suffix = p.suffix.lower()
    if suffix == ".npy":
        try:
            arr = np.load(p, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise InputError(f"{p}: not a readable .npy file ({exc})") from exc
        yield None, _as_xyz(arr, p)
    elif suffix in (".csv", ".txt", ".xyz"):
        yield None, _read_csv(p)
    elif suffix in (".bag", ".db3", ".mcap") or p.is_dir():
        yield from _read_bag(p, topic)
    else:
        raise InputError(f"{p}: unknown point file type (use .npy, .csv or a ROS bag)")


def _as_xyz(arr: Any, p: Path) -> FloatArray:
    a = np.asarray(arr)
    if a.dtype.names:
        names = [n.lower() for n in a.dtype.names]
        try:
            cols = [a.dtype.names[names.index(c)] for c in ("x", "y", "z")]
        except ValueError:
            raise InputError(f"{p}: structured array without x, y, z fields") from None
        return np.column_stack([a[c].astype(np.float64) for c in cols])
    if a.ndim != 2 or a.shape[1] < 3 or not np.issubdtype(a.dtype, np.number):
        raise InputError(f"{p}: expected an N x 3 numeric array, got {a.dtype} {a.shape}")
    return a[:, :3].astype(np.float64)


def _read_csv(p: Path) -> FloatArray:
    with p.open("r", encoding="utf-8", errors="replace") as fh:
        first = fh.readline()
    delim = "," if "," in first else None
    header = any(ch.isalpha() for ch in first.replace("e", "").replace("E", "").replace("nan", ""))
    cols = (0, 1, 2)
    if header:
        names = [n.strip().lower() for n in (first.split(delim) if delim else first.split())]
        if all(c in names for c in ("x", "y", "z")):
            cols = (names.index("x"), names.index("y"), names.index("z"))
    try:
        data = np.loadtxt(p, delimiter=delim, skiprows=1 if header else 0, usecols=cols, ndmin=2)
    except (ValueError, IndexError) as exc:
        raise InputError(f"{p}: not a CSV of x, y, z columns ({exc})") from exc
    return data.astype(np.float64)


def pointcloud2_xyz(msg: Any) -> FloatArray:
    """The x, y, z of a ``sensor_msgs/PointCloud2`` message as an ``N x 3`` array."""
    fields = {f.name: f for f in msg.fields}
    if not all(c in fields for c in ("x", "y", "z")):
        raise InputError("PointCloud2 without x, y, z fields")
    order = ">" if msg.is_bigendian else "<"
    dtype = np.dtype({
        "names": ["x", "y", "z"],
        "formats": [order + _POINTFIELD[int(fields[c].datatype)] for c in ("x", "y", "z")],
        "offsets": [int(fields[c].offset) for c in ("x", "y", "z")],
        "itemsize": int(msg.point_step),
    })
    n = int(msg.width) * int(msg.height)
    raw = msg.data  # bytes (rospy), an array or a list (rosbags, rclpy)
    data = np.frombuffer(raw, np.uint8) if isinstance(raw, bytes | bytearray | memoryview) else np.asarray(raw, np.uint8).ravel()
    if msg.height > 1 and msg.row_step != msg.width * msg.point_step:
        rows = data.reshape(int(msg.height), int(msg.row_step))[:, : int(msg.width) * int(msg.point_step)]
        data = np.ascontiguousarray(rows).ravel()
    if data.size < n * int(msg.point_step):
        raise InputError("PointCloud2 data shorter than width x height x point_step")
    rec = np.frombuffer(data.tobytes(), dtype=dtype, count=n)
    return np.column_stack([rec["x"].astype(np.float64), rec["y"].astype(np.float64), rec["z"].astype(np.float64)])


def _read_bag(p: Path, topic: str | None) -> Iterator[tuple[float | None, FloatArray]]:
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError as exc:  # pragma: no cover - the bathymetry extra installs rosbags
        raise InputError("reading bags needs rosbags: pip install 'coexploration[bathymetry]'") from exc
    try:
        with AnyReader([p], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
            conns = [c for c in reader.connections if c.msgtype == POINTCLOUD2 and (topic is None or c.topic == topic)]
            if not conns:
                topics = sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections})
                raise InputError(f"{p}: no PointCloud2 topic {topic or ''} (topics: {', '.join(topics)})")
            for conn, timestamp, raw in reader.messages(connections=conns):
                msg = reader.deserialize(raw, conn.msgtype)
                yield timestamp / 1e9, pointcloud2_xyz(msg)
    except InputError:
        raise
    except Exception as exc:  # rosbags raises several reader errors for damaged bags
        raise InputError(f"{p}: cannot read bag ({type(exc).__name__}: {exc})") from exc


def write_pointcloud_bag(
    path: str | Path, clouds: list[tuple[float, FloatArray]], topic: str = "/points", ros1: bool = False
) -> Path:
    """Write ``(time, N x 3)`` clouds as float32 PointCloud2 messages to a ROS 2 bag directory (or
    a ROS 1 ``.bag`` with ``ros1``). Used by the tests and to make sample data."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    pc2 = store.types["sensor_msgs/msg/PointCloud2"]
    field = store.types["sensor_msgs/msg/PointField"]
    header_t = store.types["std_msgs/msg/Header"]
    time_t = store.types["builtin_interfaces/msg/Time"]
    fields = [field(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")]
    out = Path(path)

    def message(t: float, xyz: FloatArray) -> Any:
        data = np.ascontiguousarray(xyz, dtype="<f4").view(np.uint8).ravel()
        sec = int(t)
        stamp = time_t(sec=sec, nanosec=round((t - sec) * 1e9))
        hdr = header_t(seq=0, stamp=stamp, frame_id="map") if ros1 else header_t(stamp=stamp, frame_id="map")
        return pc2(header=hdr, height=1, width=len(xyz), fields=fields, is_bigendian=False,
                   point_step=12, row_step=12 * len(xyz), data=data, is_dense=True)

    if ros1:
        from rosbags.rosbag1 import Writer as Writer1

        with Writer1(out) as w1:
            conn = w1.add_connection(topic, POINTCLOUD2, typestore=store)
            for t, xyz in clouds:
                w1.write(conn, int(t * 1e9), store.serialize_ros1(message(t, xyz), POINTCLOUD2))
    else:
        from rosbags.rosbag2 import Writer as Writer2

        with Writer2(out, version=8) as w2:
            conn = w2.add_connection(topic, POINTCLOUD2, typestore=store)
            for t, xyz in clouds:
                w2.write(conn, int(t * 1e9), store.serialize_cdr(message(t, xyz), POINTCLOUD2))
    return out
