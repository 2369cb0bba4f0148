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
  (one point per cell held, z = elevation) and ``nav_msgs/OccupancyGrid`` (-1 unknown, else
  0 = the level's deepest .. 100 = its shallowest);
* :func:`image`: pixels -> ``sensor_msgs/Image`` (mono8, mono16, rgb8, rgb16);
* :func:`path`: waypoints -> ``nav_msgs/Path`` (what the ``ros`` autonomy output publishes);
* :func:`cloud`: any ``N x 3`` points -> ``PointCloud2`` (float32 x, y, z).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

__all__ = ["cloud", "image", "level_cloud", "level_grid", "odometry", "path", "quaternion", "set_stamp", "set_time"]

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


def level_grid(grid: np.ndarray, meta: Any, cls: ClassOf, t: float, frame: str) -> Any:
    """A map level as a ``nav_msgs/OccupancyGrid``: cells of ``meta["cell_size"]`` from the
    south-west corner ``x0``, ``y0``; -1 where nothing is held, else the elevation scaled from the
    level's deepest (0) to its shallowest (100) (rviz's ``map`` scheme draws shallow ground dark)."""
    a = np.asarray(grid, dtype=np.float64)
    msg = cls("nav_msgs/OccupancyGrid")()
    _header(msg, t, frame)
    info = msg.info
    set_time(info.map_load_time, t)
    info.resolution = float(meta["cell_size"])
    info.height, info.width = int(a.shape[0]), int(a.shape[1])
    info.origin.position.x, info.origin.position.y = float(meta["x0"]), float(meta["y0"])
    info.origin.orientation.w = 1.0
    held = np.isfinite(a)
    out = np.full(a.shape, -1, dtype=np.int8)
    if held.any():
        lo, hi = float(a[held].min()), float(a[held].max())
        span = hi - lo if hi > lo else 1.0
        out[held] = np.clip(np.round((a[held] - lo) / span * 100.0), 0, 100).astype(np.int8)
    msg.data = out.ravel().tolist()  # int8[]: a list for genpy and rclpy alike
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
