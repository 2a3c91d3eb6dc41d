"""Synthetic Jackal-like bags with known messages, written with rosbags' writers.

For tests (round trips: every value is a closed-form function of the message index) and for the
extraction benchmark (long bags). Not physics: the simulator writes the real default dataset.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2

from skidbench.pipeline.extract.reader import ROS1, ROS2, default_typestore

FORMATS = ("ros1", "sqlite3", "mcap")
T0_NS = 1_700_000_000_000_000_000  # bag clock at the first message (ns)

# topic -> (message type, rate in Hz)
JACKAL_TOPICS: dict[str, tuple[str, float]] = {
    "/cmd_vel": ("geometry_msgs/msg/Twist", 45.0),
    "/joint_states": ("sensor_msgs/msg/JointState", 20.0),
    "/jackal_velocity_controller/odom": ("nav_msgs/msg/Odometry", 20.0),
    "/imu/data": ("sensor_msgs/msg/Imu", 75.0),
    "/stereo/left/image_raw/compressed": ("sensor_msgs/msg/CompressedImage", 15.0),
    "/stereo/left/camera_info": ("sensor_msgs/msg/CameraInfo", 15.0),
    "/skidbench/true_pose": ("nav_msgs/msg/Odometry", 50.0),
}
JOINTS = ["front_left_wheel", "rear_left_wheel", "front_right_wheel", "rear_right_wheel"]


def typestore_for(fmt: str):
    """The default typestore of a synthetic bag format (``ros1``, ``sqlite3``, ``mcap``)."""
    return default_typestore(ROS1 if fmt == "ros1" else ROS2)


class _Factory:
    """Builds messages of one typestore by keyword, filling ROS1/ROS2 differences (seq, D/d ...)."""

    def __init__(self, typestore):
        self.ts = typestore

    def __call__(self, msgtype: str, **kw: Any) -> Any:
        cls = self.ts.types[msgtype]
        names = {f.name for f in dataclasses.fields(cls) if not f.name.startswith("__")}
        args = {}
        for name in names:
            if name in kw:
                args[name] = kw[name]
            elif name.lower() in kw:  # CameraInfo: D K R P (ROS1) vs d k r p (ROS2)
                args[name] = kw[name.lower()]
        missing = names - set(args)
        for name in missing:  # fields we do not care about: zero values
            args[name] = self._zero(cls, name)
        return cls(**args)

    def _zero(self, cls, name):
        import numpy as np

        fdef = dict(self.ts.fielddefs[cls.__msgtype__][1])[name]
        kind = fdef[0]
        if kind == 1:  # base type
            return "" if fdef[1][0] == "string" else 0
        if kind == 2:  # nested message
            sub = fdef[1]
            return self(sub)
        if kind == 3:  # fixed array
            return np.zeros(fdef[1][1], dtype=np.float64)
        return np.zeros(0, dtype=np.float64) if fdef[1][0][0] == 1 else []

    def time(self, ns: int) -> Any:
        return self("builtin_interfaces/msg/Time", sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)

    def header(self, stamp_ns: int, frame_id: str, seq: int = 0) -> Any:
        return self("std_msgs/msg/Header", seq=seq, stamp=self.time(stamp_ns), frame_id=frame_id)

    def vec(self, x: float, y: float, z: float) -> Any:
        return self("geometry_msgs/msg/Vector3", x=x, y=y, z=z)

    def quat(self, yaw: float) -> Any:
        return self("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))


def message(f: _Factory, msgtype: str, i: int, bag_ns: int, image_bytes: int = 256) -> Any:
    """The ``i``-th message of a type: every field a closed-form function of ``i``. Header stamps are
    1 ms before the bag time, except every 10th, which is zero (extract falls back to the bag time)."""
    import numpy as np

    stamp = 0 if i % 10 == 0 else bag_ns - 1_000_000
    a = 0.001 * i
    if msgtype in ("geometry_msgs/msg/Twist", "geometry_msgs/msg/TwistStamped"):
        twist = f(
            msgtype="geometry_msgs/msg/Twist", linear=f.vec(a, -a, 0.5), angular=f.vec(0.25, -0.5, 2 * a)
        )
        if msgtype.endswith("Twist"):
            return twist
        return f(msgtype, header=f.header(stamp, "base_link", i), twist=twist)
    if msgtype == "sensor_msgs/msg/JointState":
        arr = np.array([a, 2 * a, 3 * a, 4 * a], dtype=np.float64)
        return f(
            msgtype,
            header=f.header(stamp, "", i),
            name=list(JOINTS),
            position=arr,
            velocity=arr + 1,
            effort=-arr,
        )
    if msgtype == "nav_msgs/msg/Odometry":
        pose = f("geometry_msgs/msg/Pose", position=f.vec(a, 2 * a, 0.0), orientation=f.quat(a))
        twist = f("geometry_msgs/msg/Twist", linear=f.vec(1.0 + a, 0.01, 0.0), angular=f.vec(0.0, 0.0, -a))
        return f(
            msgtype,
            header=f.header(stamp, "odom", i),
            child_frame_id="base_link",
            pose=f("geometry_msgs/msg/PoseWithCovariance", pose=pose),
            twist=f("geometry_msgs/msg/TwistWithCovariance", twist=twist),
        )
    if msgtype == "sensor_msgs/msg/Imu":
        return f(
            msgtype,
            header=f.header(stamp, "imu_link", i),
            orientation=f.quat(-a),
            angular_velocity=f.vec(0.1, 0.2, a),
            linear_acceleration=f.vec(a, 0.0, 9.81),
        )
    if msgtype == "sensor_msgs/msg/CompressedImage":
        data = np.frombuffer(bytes((i + k) % 256 for k in range(image_bytes)), dtype=np.uint8)
        return f(msgtype, header=f.header(stamp, "left_camera", i), format="jpeg", data=data)
    if msgtype == "sensor_msgs/msg/CameraInfo":
        k = np.array([400.0, 0, 320, 0, 400.0, 240, 0, 0, 1], dtype=np.float64)
        return f(
            msgtype,
            header=f.header(stamp, "left_camera", i),
            width=640,
            height=480,
            distortion_model="plumb_bob",
            d=np.array([0.01 * i, 0.0, 0.0, 0.0, 0.0]),
            k=k,
            r=np.eye(3).ravel(),
            p=np.array([400.0, 0, 320, 0, 0, 400.0, 240, 0, 0, 0, 1, 0]),
        )
    raise ValueError(f"no synthetic message for {msgtype}")


def schedule(topics: dict[str, tuple[str, float]], duration_s: float) -> Iterator[tuple[str, str, int, int]]:
    """``(topic, msgtype, index, bag_time_ns)`` in bag-time order, each topic at its own rate."""
    events = []
    for k, (topic, (msgtype, rate)) in enumerate(topics.items()):
        period = round(1e9 / rate)
        n = int(duration_s * rate)
        events.extend((T0_NS + i * period + k, topic, msgtype, i) for i in range(n))
    events.sort()
    for t, topic, msgtype, i in events:
        yield topic, msgtype, i, t


def write_bag(
    path: Path,
    fmt: str = "ros1",
    duration_s: float = 2.0,
    topics: dict[str, tuple[str, float]] | None = None,
    image_bytes: int = 256,
) -> Path:
    """Write a synthetic bag: ``fmt`` ``ros1`` (``path`` a .bag file) or ``sqlite3``/``mcap`` (ROS2, a
    folder). Returns the bag path. Messages come from :func:`message` on the :func:`schedule`."""
    topics = dict(JACKAL_TOPICS if topics is None else topics)
    path = Path(path)
    ts = typestore_for(fmt)
    f = _Factory(ts)
    if fmt == "ros1":
        writer, serialize = Writer1(path), ts.serialize_ros1
    else:
        plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
        writer, serialize = Writer2(path, version=9, storage_plugin=plugin), ts.serialize_cdr
    with writer:
        conns = {
            topic: writer.add_connection(topic, msgtype, typestore=ts)
            for topic, (msgtype, _) in topics.items()
        }
        for topic, msgtype, i, t in schedule(topics, duration_s):
            msg = message(f, msgtype, i, t, image_bytes)
            writer.write(conns[topic], t, serialize(msg, msgtype))
    return path


def expected_messages(fmt: str, duration_s: float, topics: dict[str, tuple[str, float]] | None = None):
    """The messages :func:`write_bag` writes, per topic: ``{topic: [(bag_time_ns, msg), ...]}``."""
    topics = dict(JACKAL_TOPICS if topics is None else topics)
    f = _Factory(typestore_for(fmt))
    out: dict[str, list] = {t: [] for t in topics}
    for topic, msgtype, i, t in schedule(topics, duration_s):
        out[topic].append((t, message(f, msgtype, i, t)))
    return out
