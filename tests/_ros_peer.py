"""A vehicle's (or a ship's) ROS nodes for the ROS tests, as one rospy program: recorded-style
sensor messages, a planner that answers CoEx's survey paths, and a listener of topics. One JSON
line per event on stdout. Run with the venv's Python (rospy through `make ros`):

    python tests/_ros_peer.py --name vehicle_stack --publish --planner fly
    python tests/_ros_peer.py --name rviz_like --listen /coex/map/level_0 /coex/image

``ROS_MASTER_URI`` names the master. ``--publish`` publishes every ``--every`` seconds: a multibeam
swath (PointCloud2 in ``--points-frame``), a camera frame (``--image raw|compressed``), the
vehicle's Odometry (``--nav-frame`` enu: 30 m east, 10 m north, 25 m deep, heading 90), a
NavSatFix, a sensor_msgs/Temperature (the series) and an altimeter's sensor_msgs/Range on
/altimeter (5 m; every third one no bottom, inf). ``--planner fly|refuse|silent`` answers
each nav_msgs/Path on /coex/survey/path (``--survey-ns``): ``fly`` reports ``ID started 0``, each waypoint, then
``ID completed``; ``refuse`` reports ``ID refused no thrusters``; ``silent`` says nothing. An
empty path (CoEx's ended form) is flown by none of them (``{"event": "ended"}``), and stops a
survey ``fly`` is flying.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import sys
import threading
import time

import numpy as np

_OUT = threading.Lock()


def out(**event: object) -> None:
    """One JSON line on stdout, whole: rospy calls the callbacks of several topics from threads of
    their own, and print() writes a line and its newline separately, so two lines written at
    once interleave into one that is not JSON (the reader dropped both)."""
    line = json.dumps(event) + "\n"
    with _OUT:
        sys.stdout.write(line)
        sys.stdout.flush()


def stamp(header: object, t: float) -> None:
    import rospy

    header.stamp = rospy.Time.from_sec(t)  # type: ignore[attr-defined]


def swath(k: int) -> np.ndarray:
    """400 soundings of a gently sloping seafloor, one swath per call, 2 m further north each."""
    rng = np.random.default_rng(k)
    x = rng.uniform(-20, 20, 400)
    y = np.full(400, -20.0 + 2.0 * (k % 20)) + rng.uniform(-1, 1, 400)
    z = -30.0 + 0.05 * x + rng.normal(0, 0.05, 400)
    return np.column_stack([x, y, z])


def frame_image(k: int) -> np.ndarray:
    y, x = np.mgrid[0:96, 0:128]
    return (120 + 60 * np.sin(x / 9.0 + k) * np.cos(y / 7.0)).clip(0, 255).astype(np.uint8)


def publish(args: argparse.Namespace, stop: threading.Event) -> None:
    import rospy
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import (
        CompressedImage,
        Image,
        NavSatFix,
        PointCloud2,
        PointField,
        Range,
        Temperature,
    )

    pubs = {
        "points": rospy.Publisher(args.points_topic, PointCloud2, queue_size=10),
        "image": rospy.Publisher(args.image_topic, CompressedImage if args.image == "compressed" else Image,
                                 queue_size=5),
        "odom": rospy.Publisher(args.nav_topic, Odometry, queue_size=10),
        "fix": rospy.Publisher("/gps/fix", NavSatFix, queue_size=10),
        "ctd": rospy.Publisher("/ctd/temperature", Temperature, queue_size=10),
        "alt": rospy.Publisher("/altimeter", Range, queue_size=10),
    }
    deadline = time.monotonic() + 10.0  # CoEx connects (it subscribed before this started)
    while time.monotonic() < deadline and not any(p.get_num_connections() for p in pubs.values()):
        time.sleep(0.1)
    time.sleep(0.5)
    k = 0
    while not stop.is_set() and not rospy.is_shutdown():
        now = time.time()
        if k < args.swaths:
            xyz = swath(k)
            if args.points_frame == "ned":
                xyz = np.column_stack([xyz[:, 1], xyz[:, 0], -xyz[:, 2]])
            pc = PointCloud2()
            stamp(pc.header, now)
            pc.header.frame_id = args.points_frame_id
            pc.fields = [PointField(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")]
            pc.height, pc.width, pc.is_bigendian, pc.point_step = 1, len(xyz), False, 12
            pc.row_step, pc.is_dense = 12 * len(xyz), True
            pc.data = np.ascontiguousarray(xyz, dtype="<f4").tobytes()
            pubs["points"].publish(pc)
        od = Odometry()
        stamp(od.header, now)
        od.header.frame_id = args.nav_frame_id
        if args.nav_frame == "ned":
            od.pose.pose.position.x, od.pose.pose.position.y, od.pose.pose.position.z = 10.0, 30.0, 25.0
            od.pose.pose.orientation.z, od.pose.pose.orientation.w = math.sin(math.pi / 4), math.cos(math.pi / 4)
        else:
            od.pose.pose.position.x, od.pose.pose.position.y, od.pose.pose.position.z = 30.0, 10.0, -25.0
            od.pose.pose.orientation.w = 1.0  # yaw 0 = east = heading 90
        od.twist.twist.linear.x = 1.0
        pubs["odom"].publish(od)
        if k % args.image_every == 0 and k // args.image_every < args.images:
            pixels = frame_image(k)
            if args.image == "compressed":
                from PIL import Image as PilImage

                buf = io.BytesIO()
                PilImage.fromarray(pixels).save(buf, format="PNG")
                im = CompressedImage(format="png", data=buf.getvalue())
            else:
                im = Image(height=96, width=128, encoding="mono8", is_bigendian=0, step=128, data=pixels.tobytes())
            stamp(im.header, now)
            im.header.frame_id = "camera"
            pubs["image"].publish(im)
            out(event="image", k=k)
        fix = NavSatFix(latitude=41.5245, longitude=-70.6712)
        stamp(fix.header, now)
        pubs["fix"].publish(fix)
        temp = Temperature(temperature=4.0 + 0.01 * k, variance=0.0)
        stamp(temp.header, now)
        pubs["ctd"].publish(temp)
        # an altimeter 5 m above the seafloor; every third ping finds no bottom (beyond max_range)
        alt = Range(radiation_type=Range.ULTRASOUND, field_of_view=0.1, min_range=0.3, max_range=50.0,
                    range=5.0 if k % 3 else math.inf)
        stamp(alt.header, now)
        alt.header.frame_id = "altimeter"
        pubs["alt"].publish(alt)
        k += 1
        stop.wait(args.every)


def planner(args: argparse.Namespace, stop: threading.Event) -> None:
    import rospy
    from nav_msgs.msg import Path
    from std_msgs.msg import String

    ns = args.survey_ns.rstrip("/")
    answer = rospy.Publisher(f"{ns}/progress", String, queue_size=100)
    plans: dict[str, object] = {}

    def on_plan(msg: String) -> None:
        plans["latest"] = json.loads(msg.data)

    flying: dict[str, object] = {}

    def fly(path: Path) -> None:
        # the path's plan: the one of the same stamp (the two topics' messages may come in
        # either order: a newer path may come before its plan)
        stamp = path.header.stamp.to_sec()

        def mine() -> bool:
            latest = plans.get("latest")
            return isinstance(latest, dict) and abs(float(latest.get("stamp") or 0.0) - stamp) < 1e-3

        deadline = time.monotonic() + 5.0
        while not mine() and time.monotonic() < deadline:
            time.sleep(0.05)
        plan = dict(plans.get("latest") or {})  # type: ignore[call-overload]
        sid = plan.get("survey_id")
        pts = [[p.pose.position.x, p.pose.position.y, p.pose.position.z] for p in path.poses]
        if not pts:  # the ended form: fly nothing, stop flying it
            flying.pop("sid", None)
            out(event="ended", frame=path.header.frame_id, plan=plan)
            return
        out(event="path", frame=path.header.frame_id, poses=pts, plan=plan,
            stamps=[p.header.stamp.to_sec() for p in path.poses])
        if args.planner == "refuse":
            answer.publish(String(f"{sid} refused no thrusters"))
            return
        if args.planner == "silent":
            return
        flying["sid"] = sid
        for k in range(len(pts)):
            if flying.get("sid") != sid:
                out(event="stopped", survey_id=sid, at=k)
                return
            answer.publish(String(f"{sid} started {k}"))
            out(event="started", survey_id=sid, index=k)
            time.sleep(args.leg)
        answer.publish(String(f"{sid} completed"))
        out(event="flown", survey_id=sid)

    rospy.Subscriber(f"{ns}/plan", String, on_plan, queue_size=10)
    rospy.Subscriber(f"{ns}/path", Path, lambda p: threading.Thread(target=fly, args=(p,), daemon=True).start(),
                     queue_size=10)


def listen(topics: list[str]) -> None:
    import rospy

    def summary(topic: str) -> object:
        def got(msg: rospy.AnyMsg) -> None:
            kind = msg._connection_header["type"]
            import roslib.message

            m = roslib.message.get_message_class(kind)().deserialize(msg._buff)
            info: dict[str, object] = {"event": "message", "topic": topic, "type": kind,
                                       "frame": getattr(getattr(m, "header", None), "frame_id", None)}
            if kind == "sensor_msgs/PointCloud2":
                xyz = np.frombuffer(m.data, dtype="<f4").reshape(-1, 3)
                info.update(points=len(xyz), z=[float(xyz[:, 2].min()), float(xyz[:, 2].max())] if len(xyz) else None)
            elif kind == "nav_msgs/OccupancyGrid":
                info.update(width=m.info.width, height=m.info.height, resolution=m.info.resolution,
                            known=sum(1 for v in m.data if v >= 0), values=sorted(v for v in m.data if v >= 0))
            elif kind == "sensor_msgs/Image":
                info.update(width=m.width, height=m.height, encoding=m.encoding,
                            stamp=m.header.stamp.to_sec())
            elif kind == "sensor_msgs/CompressedImage":
                from PIL import Image as PilImage

                pic = np.asarray(PilImage.open(io.BytesIO(bytes(m.data))))
                info.update(format=m.format, shape=list(pic.shape), sum=int(pic.astype(np.int64).sum()),
                            stamp=m.header.stamp.to_sec())
            elif kind == "std_msgs/String":
                info.update(data=json.loads(m.data))
            elif kind == "std_msgs/Float64MultiArray":
                info.update(dims=[[d.label, d.size, d.stride] for d in m.layout.dim], data=list(m.data))
            elif kind == "tf2_msgs/TFMessage":
                info.update(transforms=[[t.header.frame_id, t.child_frame_id, t.transform.translation.x,
                                         t.transform.translation.y, t.transform.translation.z] for t in m.transforms])
            elif kind == "nav_msgs/Odometry":
                p = m.pose.pose.position
                info.update(x=p.x, y=p.y, z=p.z)
            elif kind == "nav_msgs/Path":
                info.update(poses=len(m.poses))
            out(**info)
        return got

    for topic in topics:
        rospy.Subscriber(topic, rospy.AnyMsg, summary(topic), queue_size=10)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--name", default="ros_peer")
    p.add_argument("--publish", action="store_true")
    p.add_argument("--every", type=float, default=0.5)
    p.add_argument("--swaths", type=int, default=20)
    p.add_argument("--images", type=int, default=1)
    p.add_argument("--image-every", type=int, default=4)
    p.add_argument("--image", choices=("raw", "compressed"), default="compressed")
    p.add_argument("--points-topic", default="/multibeam/points")
    p.add_argument("--image-topic", default="/camera/image/compressed")
    p.add_argument("--nav-topic", default="/odometry/filtered")
    p.add_argument("--points-frame", choices=("enu", "ned"), default="enu")
    p.add_argument("--points-frame-id", default="map")
    p.add_argument("--nav-frame", choices=("enu", "ned"), default="enu")
    p.add_argument("--nav-frame-id", default="map")
    p.add_argument("--planner", choices=("fly", "refuse", "silent"))
    p.add_argument("--leg", type=float, default=0.3)
    p.add_argument("--survey-ns", default="/coex/survey", help="the planner's topics: NS/path, NS/plan, NS/progress")
    p.add_argument("--listen", nargs="*", default=[])
    p.add_argument("--seconds", type=float, default=600.0)
    args = p.parse_args()

    import rospy

    rospy.init_node(args.name, disable_signals=True)
    out(event="up", name=args.name)
    stop = threading.Event()
    if args.planner:
        planner(args, stop)
    if args.listen:
        listen(args.listen)
    if args.publish:
        threading.Thread(target=publish, args=(args, stop), daemon=True).start()
    try:
        stop.wait(args.seconds)
    except KeyboardInterrupt:
        pass
    stop.set()
    rospy.signal_shutdown("done")
    return 0


if __name__ == "__main__":
    sys.exit(main())
