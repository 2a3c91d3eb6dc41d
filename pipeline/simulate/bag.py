"""Write the simulated Jackal's topics to a ROS1 bag, or a ROS2 bag (sqlite3 or mcap), with rosbags.

Topics, types and rates are CONTRIBUTING.md's Jackal table. Messages are built from rosbags' typestores
(ROS1 Noetic / ROS2 Humble definitions) and serialised with ``serialize_ros1`` / ``serialize_cdr``.
Connections are added on a topic's first message, in a fixed order, so equal inputs give equal bytes.
"""

from __future__ import annotations

import functools
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from skidbench.pipeline.core.errors import SimulateError
from skidbench.pipeline.extract.reader import ROS1, ROS2, default_typestore
from skidbench.pipeline.simulate.settings import FORMATS

TOPICS = {
    "cmd_vel": ("/cmd_vel", "geometry_msgs/msg/Twist"),
    "joint_states": ("/joint_states", "sensor_msgs/msg/JointState"),
    "odom": ("/jackal_velocity_controller/odom", "nav_msgs/msg/Odometry"),
    "imu": ("/imu/data", "sensor_msgs/msg/Imu"),
    "left_image": ("/stereo/left/image_raw/compressed", "sensor_msgs/msg/CompressedImage"),
    "right_image": ("/stereo/right/image_raw/compressed", "sensor_msgs/msg/CompressedImage"),
    "left_info": ("/stereo/left/camera_info", "sensor_msgs/msg/CameraInfo"),
    "right_info": ("/stereo/right/camera_info", "sensor_msgs/msg/CameraInfo"),
    "true_pose": ("/skidbench/true_pose", "nav_msgs/msg/Odometry"),
}

CAMERA_FRAMES = {"left": "stereo_left_optical_frame", "right": "stereo_right_optical_frame"}


def bag_path(bags_dir: Path, name: str, fmt: str) -> Path:
    """``<seq>.bag`` for ROS1; a folder ``<seq>/`` for ROS2 (sqlite3 or mcap)."""
    return bags_dir / (f"{name}.bag" if fmt == "ros1" else name)


def _cov(diag: tuple[float, ...]) -> np.ndarray:
    n = len(diag)
    c = np.zeros(n * n)
    c[:: n + 1] = diag
    return c


POSE_COV = _cov((1e-3, 1e-3, 1e6, 1e6, 1e6, 1e-3))  # planar robot: z, roll, pitch unknown
TWIST_COV = _cov((1e-3, 1e-3, 1e6, 1e6, 1e6, 1e-3))
TRUTH_COV = np.zeros(36)
IMU_ORIENTATION_COV = _cov((1e-3, 1e-3, 1e-2))


@functools.cache
def _typestore(fmt: str):
    """The typestore of ``fmt`` (``ROS1``/``ROS2``), built once per process: every bag of a worker shares it
    (building one and its serialisers takes ~30 CPU-ms)."""
    return default_typestore(fmt)


class BagSink:
    """A bag open for writing at a temporary ``path`` (the caller renames it when complete)."""

    def __init__(self, path: Path, fmt: str):
        if fmt not in FORMATS:
            raise SimulateError(f"format={fmt!r}: not one of {', '.join(FORMATS)}")
        self.path, self.fmt = Path(path), fmt
        if self.path.is_dir():
            shutil.rmtree(self.path)
        elif self.path.exists():
            self.path.unlink()  # rosbags refuses to overwrite; atomic_path made an empty placeholder
        if fmt == "ros1":
            from rosbags.rosbag1 import Writer

            self.store = _typestore(ROS1)
            self.writer = Writer(self.path)
            self._serialize = self.store.serialize_ros1
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            self.store = _typestore(ROS2)
            plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
            self.writer = Writer(self.path, version=9, storage_plugin=plugin)
            self._serialize = self.store.serialize_cdr
        self.ros1 = fmt == "ros1"
        self.types = self.store.types
        self.connections: dict[str, Any] = {}
        self.seq: dict[str, int] = {}
        self.count = 0
        self._covs: dict[float, np.ndarray] = {}  # variance -> its 3 x 3 covariance (an IMU's are constant)
        self._infos: dict[str, tuple] = {}  # side -> (info, its message fields but the header)

    def __enter__(self) -> BagSink:
        self.writer.open()
        return self

    def __exit__(self, *exc) -> None:
        self.writer.close()

    # -- plumbing ------------------------------------------------------------------------------------
    def _write(self, key: str, t_ns: int, msg: Any) -> None:
        topic, msgtype = TOPICS[key]
        conn = self.connections.get(key)
        if conn is None:
            conn = self.connections[key] = self.writer.add_connection(topic, msgtype, typestore=self.store)
        self.writer.write(conn, int(t_ns), self._serialize(msg, msgtype))
        self.count += 1

    def _header(self, key: str, t_ns: int, frame_id: str):
        T = self.types
        stamp = T["builtin_interfaces/msg/Time"](
            sec=int(t_ns // 1_000_000_000), nanosec=int(t_ns % 1_000_000_000)
        )
        if self.ros1:
            n = self.seq.get(key, 0)
            self.seq[key] = n + 1
            return T["std_msgs/msg/Header"](seq=n, stamp=stamp, frame_id=frame_id)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def _vec(self, x: float, y: float, z: float):
        return self.types["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=float(z))

    def _quat_yaw(self, yaw: float):
        return self.types["geometry_msgs/msg/Quaternion"](
            x=0.0, y=0.0, z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0)
        )

    # -- topics --------------------------------------------------------------------------------------
    def cmd_vel(self, t_ns: int, v: float, w: float) -> None:
        """/cmd_vel: geometry_msgs/Twist (no header; bag time is the stamp)."""
        T = self.types
        msg = T["geometry_msgs/msg/Twist"](linear=self._vec(v, 0.0, 0.0), angular=self._vec(0.0, 0.0, w))
        self._write("cmd_vel", t_ns, msg)

    def joint_states(self, t_ns: int, names, position, velocity, effort) -> None:
        msg = self.types["sensor_msgs/msg/JointState"](
            header=self._header("joint_states", t_ns, ""),
            name=list(names),
            position=np.asarray(position, dtype=np.float64),
            velocity=np.asarray(velocity, dtype=np.float64),
            effort=np.asarray(effort, dtype=np.float64),
        )
        self._write("joint_states", t_ns, msg)

    def odometry(self, key: str, t_ns: int, frame: str, child: str, pose, twist, pose_cov, twist_cov) -> None:
        """nav_msgs/Odometry: ``pose`` (x, y, yaw) in ``frame``; ``twist`` (vx, vy, wz) in ``child``."""
        T = self.types
        x, y, yaw = pose
        vx, vy, wz = twist
        p = T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
            orientation=self._quat_yaw(yaw),
        )
        tw = T["geometry_msgs/msg/Twist"](linear=self._vec(vx, vy, 0.0), angular=self._vec(0.0, 0.0, wz))
        msg = T["nav_msgs/msg/Odometry"](
            header=self._header(key, t_ns, frame),
            child_frame_id=child,
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=p, covariance=pose_cov),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=tw, covariance=twist_cov),
        )
        self._write(key, t_ns, msg)

    def imu(self, t_ns: int, yaw: float, gyro, accel, gyro_var: float, accel_var: float) -> None:
        """sensor_msgs/Imu in frame ``imu_link``: orientation (filtered yaw), rates rad/s, accel m/s^2."""
        msg = self.types["sensor_msgs/msg/Imu"](
            header=self._header("imu", t_ns, "imu_link"),
            orientation=self._quat_yaw(yaw),
            orientation_covariance=IMU_ORIENTATION_COV,
            angular_velocity=self._vec(*gyro),
            angular_velocity_covariance=self._cov3(gyro_var),
            linear_acceleration=self._vec(*accel),
            linear_acceleration_covariance=self._cov3(accel_var),
        )
        self._write("imu", t_ns, msg)

    def _cov3(self, var: float) -> np.ndarray:
        cov = self._covs.get(var)
        if cov is None:
            cov = self._covs[var] = _cov((var,) * 3)
        return cov

    def image(self, side: str, t_ns: int, jpeg: bytes) -> None:
        msg = self.types["sensor_msgs/msg/CompressedImage"](
            header=self._header(f"{side}_image", t_ns, CAMERA_FRAMES[side]),
            format="mono8; jpeg compressed mono8",
            data=np.frombuffer(jpeg, dtype=np.uint8),
        )
        self._write(f"{side}_image", t_ns, msg)

    def camera_info(self, side: str, t_ns: int, info: dict) -> None:
        cached = self._infos.get(side)
        if cached is None or cached[0] is not info:  # the same info every frame: its fields once
            cached = self._infos[side] = (info, self._camera_info_fields(info))
        msg = self.types["sensor_msgs/msg/CameraInfo"](
            header=self._header(f"{side}_info", t_ns, CAMERA_FRAMES[side]), **cached[1]
        )
        self._write(f"{side}_info", t_ns, msg)

    def _camera_info_fields(self, info: dict) -> dict[str, Any]:
        """A sensor_msgs/CameraInfo's fields but its header, from a camera info dict."""
        T = self.types
        arrays = {
            "D": np.asarray(info["D"], dtype=np.float64).ravel(),
            "K": np.asarray(info["K"], dtype=np.float64).ravel(),
            "R": np.asarray(info["R"], dtype=np.float64).ravel(),
            "P": np.asarray(info["P"], dtype=np.float64).ravel(),
        }
        if not self.ros1:  # ROS2 spells the matrices in lower case
            arrays = {k.lower(): v for k, v in arrays.items()}
        roi = T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        return {
            "height": int(info["height"]),
            "width": int(info["width"]),
            "distortion_model": str(info.get("distortion_model", "plumb_bob")),
            "binning_x": 0,
            "binning_y": 0,
            "roi": roi,
            **arrays,
        }
