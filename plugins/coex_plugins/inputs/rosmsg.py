"""ROS messages as input items: what the ``rosbag`` input (recorded bags, read with rosbags) and
the ``ros`` input (live topics, rospy) share, so that a message means the same thing whichever way
it arrives.

The functions take messages by their fields only, so they serve every source of them: rosbags'
classes (ROS 1 and ROS 2 bags: ``stamp.sec``/``nanosec``, arrays), genpy's (rospy:
``stamp.secs``/``nsecs``, ``bytes``) and rclpy's (ROS 2: ``sec``/``nanosec``, ``array``).

* :func:`canonical` names a type as ROS 2 does (``sensor_msgs/msg/Image``; ROS 1 says
  ``sensor_msgs/Image``); :data:`POINTS_TYPES`, :data:`IMAGE_TYPES`, :data:`NAV_TYPES` are what
  each role takes.
* :class:`FrameMap`: how the frames of the vehicle's messages (their ``header.frame_id``) map
  onto CoEx's local grid (x east, y north, z up, metres from ``node.origin``): the options
  ``frames`` and ``nav_frame`` (:func:`frame_problems` checks them).
* :func:`item_of`: one message of a role (``points``, ``image``, ``nav``) -> a Points, Image or
  Nav item (or None: nothing to take, such as a NavSatFix without a fix); ValueError when it
  cannot be converted (an unknown encoding, a frame not in the map).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from coex import Image, Item, Nav, Points

from ..options import Problems, compass_from_enu_yaw, finite, yaw_of_quaternion
from ._files import as_pixels, decode_image

__all__ = [
    "IMAGE_TYPES",
    "NAV_TYPES",
    "POINTS_TYPES",
    "ROLES",
    "Frame",
    "FrameMap",
    "canonical",
    "check_frames",
    "frame_problems",
    "image_pixels",
    "item_of",
    "nav_of",
    "points_of",
    "ros_image_pixels",
    "stamp_of",
    "u8",
]

POINTS_TYPES = ("sensor_msgs/msg/PointCloud2",)
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
NAV_TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped",
             "geometry_msgs/msg/PoseWithCovarianceStamped", "sensor_msgs/msg/NavSatFix")
#: role -> (option naming its topic, message types it takes)
ROLES = {"points": ("points_topic", POINTS_TYPES), "image": ("image_topic", IMAGE_TYPES),
         "nav": ("nav_topic", NAV_TYPES)}

#: sensor_msgs/Image encodings: channels, bytes per channel, channel order reversed (BGR)
_ENCODINGS = {
    "mono8": (1, 1, False), "8uc1": (1, 1, False), "mono16": (1, 2, False), "16uc1": (1, 2, False),
    "rgb8": (3, 1, False), "bgr8": (3, 1, True), "8uc3": (3, 1, True),
    "rgba8": (4, 1, False), "bgra8": (4, 1, True), "8uc4": (4, 1, True),
    "rgb16": (3, 2, False), "bgr16": (3, 2, True), "16uc3": (3, 2, True),
}


def canonical(msgtype: str) -> str:
    """``sensor_msgs/Image`` (ROS 1) -> ``sensor_msgs/msg/Image`` (ROS 2 and rosbags' name)."""
    parts = str(msgtype).split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else str(msgtype)


def u8(data: Any) -> np.ndarray:
    """A message's ``uint8[]`` field as a flat uint8 array (bytes from genpy, arrays or lists
    from rosbags and rclpy)."""
    if isinstance(data, bytes | bytearray | memoryview):
        return np.frombuffer(data, dtype=np.uint8)
    return np.asarray(data, dtype=np.uint8).ravel()


def stamp_of(msg: Any) -> float | None:
    """The message's ``header.stamp`` in seconds, or None without one (or when it is zero)."""
    stamp = getattr(getattr(msg, "header", None), "stamp", None)
    if stamp is None:
        return None
    if hasattr(stamp, "nanosec"):
        t = float(stamp.sec) + float(stamp.nanosec) * 1e-9
    elif hasattr(stamp, "nsecs"):
        t = float(stamp.secs) + float(stamp.nsecs) * 1e-9
    else:
        return None
    return t if t > 0 else None


def frame_id_of(msg: Any) -> str:
    return str(getattr(getattr(msg, "header", None), "frame_id", "") or "").lstrip("/")


# --------------------------------------------------------------------------- frames
@dataclass(frozen=True)
class Frame:
    """How one ROS frame maps onto the local grid: its axes (``enu``: x east, y north, z up,
    yaw counter-clockwise from east, ROS REP 103; ``ned``: x north, y east, z down, yaw
    clockwise from north), then a turn of ``yaw`` degrees counter-clockwise about the vertical,
    then where the frame's origin is in the local grid (``x``, ``y``, ``z`` metres)."""

    axes: str = "enu"
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    yaw: float = 0.0

    def points(self, xyz: np.ndarray) -> np.ndarray:
        """``N x 3`` points of this frame in the local grid (east, north, up)."""
        p = np.asarray(xyz, dtype=np.float64)
        if self.axes == "ned":
            p = np.column_stack([p[:, 1], p[:, 0], -p[:, 2]])
        if self.yaw:
            c, s = math.cos(math.radians(self.yaw)), math.sin(math.radians(self.yaw))
            p = np.column_stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1], p[:, 2]])
        if self.x or self.y or self.z:
            p = p + np.array([self.x, self.y, self.z])
        return p

    def heading(self, yaw: float) -> float:
        """The compass heading (degrees clockwise from north) of a yaw (radians) in this frame."""
        if self.axes == "ned":
            return (math.degrees(yaw) - self.yaw) % 360.0
        return compass_from_enu_yaw(yaw + math.radians(self.yaw))


_FRAME_KEYS = ("axes", "x", "y", "z", "yaw")


def _frame(spec: Any) -> Frame:
    if isinstance(spec, str):
        return Frame(axes=spec)
    given = dict(spec)
    unknown = set(given) - set(_FRAME_KEYS)
    if unknown:  # refused by frame_problems first
        raise TypeError(f"a frame has no {', '.join(sorted(unknown))}")
    x, y, z, yaw = (float(given.get(k, 0.0)) for k in ("x", "y", "z", "yaw"))
    return Frame(axes=str(given.get("axes", "enu")), x=x, y=y, z=z, yaw=yaw)


def frame_problems(name: str, options: Mapping[str, Any]) -> list[str]:
    """Problems of the options ``frames`` (frame id -> ``"enu"`` | ``"ned"`` | ``{axes, x, y, z,
    yaw}``) and ``nav_frame``."""
    p = Problems()
    check_frames(p, name, options)
    return p.items


def check_frames(p: Problems, name: str, options: Mapping[str, Any]) -> None:
    """:func:`frame_problems` into ``p``, each with the option it names."""
    nav = options.get("nav_frame", "enu")
    if nav not in ("enu", "ned"):
        p.said("nav_frame", f"input {name!r}: option 'nav_frame' must be one of 'enu', 'ned', not {nav!r}")
    frames = options.get("frames", {})
    if not isinstance(frames, Mapping):
        p.said("frames", f"input {name!r}: option 'frames' must be a table of frame id = "
                         "\"enu\" | \"ned\" | {axes, x, y, z, yaw}")
        return
    for fid, spec in frames.items():
        key = f"frames.{fid}"
        if isinstance(spec, str):
            spec = {"axes": spec}
        if not isinstance(spec, Mapping):
            p.said(key, f"input {name!r}: option {key!r} must be \"enu\", \"ned\" or a table "
                        "{axes, x, y, z, yaw}")
            continue
        for k, v in spec.items():
            if k not in _FRAME_KEYS:
                p.said(f"{key}.{k}", f"input {name!r}: option '{key}.{k}' is not one of {', '.join(_FRAME_KEYS)}")
            elif k == "axes" and v not in ("enu", "ned"):
                p.said(f"{key}.axes", f"input {name!r}: option '{key}.axes' must be 'enu' or 'ned', not {v!r}")
            elif k != "axes" and (isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v)):
                p.said(f"{key}.{k}", f"input {name!r}: option '{key}.{k}' must be a number, not {v!r}")


class FrameMap:
    """The frames of a configuration (options ``frames`` and ``nav_frame``; checked with
    :func:`frame_problems`). Without ``frames`` every message is taken as given: points as ENU
    local metres, poses in ``nav_frame``, whatever their ``frame_id`` (what the bag input always
    did). With ``frames``, a message's ``header.frame_id`` must be one of them (``"*"`` matches
    any other); a message of another frame is refused (ValueError, logged once per topic)."""

    def __init__(self, frames: Mapping[str, Any] | None = None, nav_frame: str = "enu") -> None:
        self.frames = {str(k).lstrip("/"): _frame(v) for k, v in (frames or {}).items()}
        self.nav_default = Frame(axes=nav_frame)

    def of(self, msg: Any, role: str) -> Frame:
        if not self.frames:
            return self.nav_default if role == "nav" else Frame()
        fid = frame_id_of(msg)
        frame = self.frames.get(fid, self.frames.get("*"))
        if frame is None:
            raise ValueError(f"frame {fid!r} is not mapped to the local grid (option 'frames' knows "
                             f"{', '.join(sorted(self.frames))})")
        return frame


# --------------------------------------------------------------------------- conversions
def ros_image_pixels(msg: Any) -> np.ndarray:
    """The pixels of a ``sensor_msgs/Image`` (rows padded to ``step`` are cut); ValueError for an
    encoding it does not know or data shorter than height x step."""
    enc = str(msg.encoding).lower()
    if enc not in _ENCODINGS:
        raise ValueError(f"image encoding {msg.encoding!r} not supported "
                         f"(known: {', '.join(sorted(_ENCODINGS))})")
    channels, size, reverse = _ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row = w * channels * size
    data = u8(msg.data)
    if h <= 0 or w <= 0 or step < row or data.size < h * step:
        raise ValueError(f"image {w} x {h} {enc} with step {step} and {data.size} bytes of data")
    rows = np.ascontiguousarray(data[: h * step].reshape(h, step)[:, :row])
    dtype = np.dtype(np.uint8) if size == 1 else np.dtype(">u2" if msg.is_bigendian else "<u2")
    a = rows.view(dtype).reshape((h, w, channels) if channels > 1 else (h, w))
    if reverse:
        a = a[..., ::-1]
    if channels == 4:
        a = a[..., 1:] if reverse else a[..., :3]  # after reversing BGRA is ARGB
    return as_pixels(a.astype(np.uint16) if size == 2 else a)


def image_pixels(msgtype: str, msg: Any) -> np.ndarray:
    """The pixels of a ``sensor_msgs/Image`` or ``CompressedImage`` (JPEG, PNG ...)."""
    if canonical(msgtype).endswith("CompressedImage"):
        return decode_image(u8(msg.data).tobytes())
    return ros_image_pixels(msg)


def points_of(msg: Any, frames: FrameMap | None = None) -> np.ndarray:
    """The soundings of a ``sensor_msgs/PointCloud2`` in the local grid (rows with a NaN dropped)."""
    from coex_plugins.bathymetry.points import pointcloud2_xyz

    xyz = pointcloud2_xyz(msg)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    frame = (frames or FrameMap()).of(msg, "points")
    return frame.points(xyz) if len(xyz) else xyz


def nav_of(msgtype: str, msg: Any, t: float, frames: FrameMap | None = None) -> Nav | None:
    """A ``Nav`` of an Odometry, PoseStamped, PoseWithCovarianceStamped (x, y, depth = -z up,
    heading from the yaw, speed = |twist.linear.x, y| of an Odometry) or NavSatFix (lat, lon;
    None without a fix)."""
    msgtype = canonical(msgtype)
    if msgtype == "sensor_msgs/msg/NavSatFix":
        lat, lon = finite(msg.latitude), finite(msg.longitude)
        if int(msg.status.status) < 0 or lat is None or lon is None:
            return None  # no fix
        return Nav(t, lat=lat, lon=lon)
    speed = None
    if msgtype == "nav_msgs/msg/Odometry":
        pose = msg.pose.pose
        lin = msg.twist.twist.linear
        speed = finite(math.hypot(lin.x, lin.y))
    elif msgtype == "geometry_msgs/msg/PoseWithCovarianceStamped":
        pose = msg.pose.pose
    else:
        pose = msg.pose
    frame = (frames or FrameMap()).of(msg, "nav")
    p, q = pose.position, pose.orientation
    yaw = yaw_of_quaternion(q.x, q.y, q.z, q.w)
    xyz = [finite(p.x), finite(p.y), finite(p.z)]
    local = frame.points(np.array([[v if v is not None else math.nan for v in xyz]]))[0]
    x, y, up = (finite(v) for v in local)
    return Nav(t, x=x, y=y, depth=None if up is None else -up,
               heading=None if yaw is None else frame.heading(yaw), speed=speed)


def item_of(role: str, msgtype: str, msg: Any, t: float, frames: FrameMap | None = None) -> Item | None:
    """The item of one message of a role (module docstring)."""
    if role == "points":
        xyz = points_of(msg, frames)
        return Points(t, xyz) if len(xyz) else None
    if role == "image":
        return Image(t, pixels=image_pixels(msgtype, msg))
    return nav_of(msgtype, msg, t, frames)
