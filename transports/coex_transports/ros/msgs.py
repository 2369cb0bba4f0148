"""CoEx data as standard ROS messages: pure functions that fill message objects by their fields.

Each builder takes ``cls``, a function from a type name (``nav_msgs/Odometry``) to its class
(:meth:`RosNode.message_class <coex_transports.ros.node.RosNode.message_class>` for rospy), so the
same code fills ROS 1 (genpy) and ROS 2 (rclpy) messages; stamps are set by field
(:func:`set_stamp`: ``secs``/``nsecs`` or ``sec``/``nanosec``). The local grid is ENU: x east,
y north of ``node.origin``, z up (so a depth is ``z = -depth``), headings become yaws
counter-clockwise from east (ROS REP 103).

* :func:`odometry`: a received ``VehicleStatus`` -> ``nav_msgs/Odometry``;
* :func:`level_cloud`, :func:`level_grid`: a received map level (the bathymetry receiver's
  ``map-level`` product: an array, row 0 south, NaN = nothing) -> ``sensor_msgs/PointCloud2``
  (one point per cell held, z = elevation) and ``nav_msgs/OccupancyGrid`` (-1 unknown, else the
  elevation on a fixed scale: 0 = ``lo`` .. 100 = ``hi`` metres, the same for every message, or
  without one the level's own deepest .. shallowest);
* :func:`image`: pixels -> ``sensor_msgs/Image`` (mono8, mono16, rgb8, rgb16);
  :func:`compressed_image`: the same as a PNG ``sensor_msgs/CompressedImage`` (the
  ``image_transport`` ``compressed`` form);
* :func:`transform`: a ``VehicleStatus`` -> ``tf2_msgs/TFMessage`` (the vehicle's pose in the
  local frame);
* :func:`series`: a time series (times, values, error bounds) -> ``std_msgs/Float64MultiArray``;
* :func:`path`: waypoints -> ``nav_msgs/Path`` (what the ``ros`` autonomy output publishes);
* :func:`cloud`: any ``N x 3`` points -> ``PointCloud2`` (float32 x, y, z).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

__all__ = ["cloud", "compressed_image", "grid_values", "image", "level_cloud", "level_grid", "odometry", "path",
           "quaternion", "series", "set_stamp", "set_time", "transform"]

ClassOf = Callable[[str], Any]


def set_stamp(header: Any, t: float) -> None:
    """Set ``header.stamp`` to ``t`` seconds (genpy ``secs``/``nsecs``, ROS 2 ``sec``/``nanosec``)."""
    set_time(header.stamp, t)


def set_time(stamp: Any, t: float) -> None:
    """Set a time field to ``t`` seconds since the epoch."""
    t = max(0.0, float(t))
    sec = math.floor(t)
    nsec = min(round((t - sec) * 1e9), 999_999_999)
    if hasattr(stamp, "nsecs"):
        stamp.secs, stamp.nsecs = sec, nsec
    else:
        stamp.sec, stamp.nanosec = sec, nsec


def _header(msg: Any, t: float, frame: str) -> None:
    set_stamp(msg.header, t)
    msg.header.frame_id = frame


def quaternion(q: Any, yaw: float) -> None:
    """Set the quaternion ``q`` to a turn of ``yaw`` radians about z."""
    q.x, q.y, q.z, q.w = 0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0)


def _bytes(a: np.ndarray) -> bytes:
    return np.ascontiguousarray(a).tobytes()


def odometry(status: Any, cls: ClassOf, t: float, frame: str, child_frame: str = "coex_vehicle") -> Any:
    """A ``nav_msgs/Odometry`` of a ``VehicleStatus``: position (x, y, -depth), orientation from
    the heading, ``twist.linear.x`` = speed (forward, in ``child_frame``)."""
    msg = cls("nav_msgs/Odometry")()
    _header(msg, t, frame)
    msg.child_frame_id = child_frame
    p = msg.pose.pose.position
    p.x, p.y, p.z = float(status.x), float(status.y), -float(status.depth)
    quaternion(msg.pose.pose.orientation, math.radians(90.0 - float(status.heading)))
    msg.twist.twist.linear.x = float(status.speed)
    return msg


def position_fix(fix: Any, cls: ClassOf, frame: str) -> Any:
    """A ``geometry_msgs/PoseWithCovarianceStamped`` of a position fix (``time``, ``x``, ``y``,
    ``sigma``, ``depth`` or None): position (x, y, -depth), variance ``sigma``² on x and y, the
    depth's 0.01 m² when known (else 1e6), orientation unknown (identity, variance 1e6): what
    robot_localization's ``pose0`` input takes."""
    msg = cls("geometry_msgs/PoseWithCovarianceStamped")()
    _header(msg, float(fix.time), frame)
    p = msg.pose.pose.position
    p.x, p.y, p.z = float(fix.x), float(fix.y), 0.0 if fix.depth is None else -float(fix.depth)
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = 0.0, 0.0, 0.0, 1.0
    var = float(fix.sigma) ** 2
    cov = [0.0] * 36
    cov[0] = cov[7] = var
    cov[14] = 1e6 if fix.depth is None else 0.01
    cov[21] = cov[28] = cov[35] = 1e6
    msg.pose.covariance = cov
    return msg


def cloud(xyz: np.ndarray, cls: ClassOf, t: float, frame: str) -> Any:
    """A ``sensor_msgs/PointCloud2`` of ``N x 3`` points (float32 x, y, z; little-endian)."""
    pts = np.ascontiguousarray(np.asarray(xyz, dtype="<f4").reshape(-1, 3))
    msg = cls("sensor_msgs/PointCloud2")()
    _header(msg, t, frame)
    field = cls("sensor_msgs/PointField")
    fields = []
    for i, name in enumerate("xyz"):
        f = field()
        f.name, f.offset, f.datatype, f.count = name, 4 * i, 7, 1  # FLOAT32
        fields.append(f)
    msg.fields = fields
    msg.height, msg.width = 1, len(pts)
    msg.is_bigendian = False
    msg.point_step, msg.row_step = 12, 12 * len(pts)
    msg.is_dense = True
    msg.data = _bytes(pts)
    return msg


def _cells(grid: np.ndarray, meta: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    a = np.asarray(grid, dtype=np.float64)
    rows, cols = np.nonzero(np.isfinite(a))
    cell = float(meta["cell_size"])
    x = float(meta["x0"]) + (cols + 0.5) * cell
    y = float(meta["y0"]) + (rows + 0.5) * cell
    return x, y, a[rows, cols]


def level_cloud(grid: np.ndarray, meta: Any, cls: ClassOf, t: float, frame: str) -> Any:
    """A map level as a ``PointCloud2``: the centre of each cell held, at its elevation (z up)."""
    x, y, z = _cells(grid, meta)
    return cloud(np.column_stack([x, y, z]), cls, t, frame)


def grid_values(grid: np.ndarray, lo: float | None = None, hi: float | None = None) -> np.ndarray:
    """The OccupancyGrid values (int8) of elevations: -1 where nothing is held (NaN), else
    ``round(100 * (z - lo) / (hi - lo))`` clipped to 0..100, so 0 is ``lo`` (deep) and 100 ``hi``
    (shallow) on every message alike; without ``lo``/``hi`` the grid's own deepest and
    shallowest held."""
    a = np.asarray(grid, dtype=np.float64)
    held = np.isfinite(a)
    out = np.full(a.shape, -1, dtype=np.int8)
    if held.any():
        if lo is None or hi is None:
            lo, hi = float(a[held].min()), float(a[held].max())
        span = hi - lo if hi > lo else 1.0
        out[held] = np.clip(np.round((a[held] - lo) / span * 100.0), 0, 100).astype(np.int8)
    return out


def level_grid(grid: np.ndarray, meta: Any, cls: ClassOf, t: float, frame: str, *,
               lo: float | None = None, hi: float | None = None) -> Any:
    """A map level as a ``nav_msgs/OccupancyGrid``: cells of ``meta["cell_size"]`` from the
    south-west corner ``x0``, ``y0``; -1 where nothing is held, else the elevation on the scale
    ``lo`` (0) .. ``hi`` (100) metres (:func:`grid_values`; rviz's ``map`` scheme draws shallow
    ground dark)."""
    a = np.asarray(grid, dtype=np.float64)
    msg = cls("nav_msgs/OccupancyGrid")()
    _header(msg, t, frame)
    info = msg.info
    set_time(info.map_load_time, t)
    info.resolution = float(meta["cell_size"])
    info.height, info.width = int(a.shape[0]), int(a.shape[1])
    info.origin.position.x, info.origin.position.y = float(meta["x0"]), float(meta["y0"])
    info.origin.orientation.w = 1.0
    msg.data = grid_values(a, lo, hi).ravel().tolist()  # int8[]: a list for genpy and rclpy alike
    return msg


def image(pixels: np.ndarray, cls: ClassOf, t: float, frame: str) -> Any:
    """A ``sensor_msgs/Image`` of ``H x W`` (mono8, mono16) or ``H x W x 3`` (rgb8, rgb16) pixels."""
    a = np.asarray(pixels)
    if a.dtype not in (np.uint8, np.uint16) or a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] != 3):
        raise ValueError(f"pixels of shape {a.shape} and type {a.dtype}: H x W or H x W x 3, uint8 or uint16")
    size = a.dtype.itemsize
    msg = cls("sensor_msgs/Image")()
    _header(msg, t, frame)
    msg.height, msg.width = int(a.shape[0]), int(a.shape[1])
    msg.encoding = ("mono" if a.ndim == 2 else "rgb") + ("8" if size == 1 else "16")
    msg.is_bigendian = False
    msg.step = msg.width * (1 if a.ndim == 2 else 3) * size
    msg.data = _bytes(a.astype("<u2") if size == 2 else a)
    return msg


def compressed_image(pixels: np.ndarray, cls: ClassOf, t: float, frame: str) -> Any:
    """A ``sensor_msgs/CompressedImage`` holding ``pixels`` as a PNG (lossless: the image is
    already what the link brought), ``format`` as ``image_transport``'s ``compressed`` plugin
    writes it (``mono8; png compressed mono8``, ``rgb8; png compressed bgr8``, ...), so that
    rqt_image_view, rviz and ``republish`` decode it. 16-bit colour goes as 8 bits (PNG readers
    differ on 48-bit colour)."""
    import io

    from PIL import Image as PilImage

    a = np.asarray(pixels)
    if a.dtype not in (np.uint8, np.uint16) or a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] != 3):
        raise ValueError(f"pixels of shape {a.shape} and type {a.dtype}: H x W or H x W x 3, uint8 or uint16")
    if a.ndim == 3 and a.dtype == np.uint16:
        a = (a >> 8).astype(np.uint8)
    buf = io.BytesIO()
    if a.ndim == 2 and a.dtype == np.uint16:
        PilImage.fromarray(np.ascontiguousarray(a.astype("<u2")), mode="I;16").save(buf, format="PNG")
        encoding, target = "mono16", "mono16"
    else:
        PilImage.fromarray(np.ascontiguousarray(a)).save(buf, format="PNG")
        encoding, target = ("mono8", "mono8") if a.ndim == 2 else ("rgb8", "bgr8")
    msg = cls("sensor_msgs/CompressedImage")()
    _header(msg, t, frame)
    msg.format = f"{encoding}; png compressed {target}"
    msg.data = buf.getvalue()
    return msg


def transform(status: Any, cls: ClassOf, t: float, frame: str, child_frame: str = "coex_vehicle") -> Any:
    """A ``tf2_msgs/TFMessage`` of one ``geometry_msgs/TransformStamped``: ``child_frame`` (the
    vehicle) in ``frame`` at the status's position (x, y, -depth) and heading (a yaw)."""
    tf = cls("geometry_msgs/TransformStamped")()
    _header(tf, t, frame)
    tf.child_frame_id = child_frame
    tr = tf.transform.translation
    tr.x, tr.y, tr.z = float(status.x), float(status.y), -float(status.depth)
    quaternion(tf.transform.rotation, math.radians(90.0 - float(status.heading)))
    msg = cls("tf2_msgs/TFMessage")()
    msg.transforms = [tf]
    return msg


def series(times: np.ndarray, values: np.ndarray, bounds: np.ndarray, cls: ClassOf) -> Any:
    """A time series as a ``std_msgs/Float64MultiArray`` of 3 rows by N samples, row-major:
    times (POSIX seconds), values, error bounds (the largest error of each value; ``inf``: not
    known yet). ``layout.dim``: ``[{label "time,value,bound", size 3, stride 3N}, {label
    "sample", size N, stride N}]``."""
    t = np.asarray(times, dtype=np.float64).ravel()
    v = np.asarray(values, dtype=np.float64).ravel()
    b = np.asarray(bounds, dtype=np.float64).ravel()
    if not t.shape == v.shape == b.shape:
        raise ValueError(f"times, values and bounds of {t.size}, {v.size} and {b.size} samples")
    n = int(t.size)
    dim = cls("std_msgs/MultiArrayDimension")
    rows, cols = dim(), dim()
    rows.label, rows.size, rows.stride = "time,value,bound", 3, 3 * n
    cols.label, cols.size, cols.stride = "sample", n, n
    msg = cls("std_msgs/Float64MultiArray")()
    msg.layout.dim = [rows, cols]
    msg.layout.data_offset = 0
    msg.data = np.concatenate([t, v, b]).tolist()
    return msg


def path(waypoints: Sequence[tuple[float, float]], cls: ClassOf, t: float, frame: str, *,
         z: float = 0.0, speed: float | None = None) -> Any:
    """A ``nav_msgs/Path`` through ``waypoints`` (x east, y north) at height ``z`` (up): each pose
    faces the next leg (the last faces the last leg) and is stamped with when it is reached at
    ``speed`` from ``t`` (all ``t`` without a speed)."""
    msg = cls("nav_msgs/Path")()
    _header(msg, t, frame)
    pose_t = cls("geometry_msgs/PoseStamped")
    pts = [(float(x), float(y)) for x, y in waypoints]
    poses = []
    when = float(t)
    yaw = 0.0
    for k, (x, y) in enumerate(pts):
        if k > 0 and speed:
            when += math.hypot(x - pts[k - 1][0], y - pts[k - 1][1]) / speed
        if k + 1 < len(pts):
            yaw = math.atan2(pts[k + 1][1] - y, pts[k + 1][0] - x)
        pose = pose_t()
        _header(pose, when, frame)
        pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = x, y, float(z)
        quaternion(pose.pose.orientation, yaw)
        poses.append(pose)
    msg.poses = poses
    return msg
