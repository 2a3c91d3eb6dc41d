"""Message -> table row: the columns of CONTRIBUTING.md "Extracted tables", one converter per message type.

Pure functions on deserialised rosbags messages (no file access). Every table starts with ``stamp_ns``
(int64, the header stamp when the message has a positive one, else the bag time) and ``bag_time_ns``
(int64, the time the message was recorded). Lengths in m, angles in rad, velocities in m/s and rad/s,
accelerations in m/s^2, exactly as the messages carry them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import pyarrow as pa

from skidbench.pipeline.core.errors import ExtractError

F64 = pa.float64()
STR = pa.string()
LIST_F64 = pa.list_(F64)

TIME_FIELDS = [pa.field("stamp_ns", pa.int64()), pa.field("bag_time_ns", pa.int64())]


def normalize_msgtype(name: str) -> str:
    """``geometry_msgs/Twist`` (ROS1 spelling) -> ``geometry_msgs/msg/Twist`` (rosbags' spelling)."""
    parts = str(name).strip().split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return "/".join(parts)


def header_stamp_ns(msg: Any, bag_time_ns: int) -> int:
    """A message's ``header.stamp`` in ns (int), or ``bag_time_ns`` when the stamp is unset.

    The one conversion of header stamps (extract, VO, loop detection). rosbags gives ``sec``/``nanosec``
    for ROS1 and ROS2 alike; a ``nsec`` field (ROS1's spelling, from a typestore that keeps it) is read
    too. Zero rule: a stamp <= 0 (never set, or before the epoch: not a time on any recording clock) is
    replaced by the bag's receive time."""
    stamp = msg.header.stamp
    nanosec = stamp.nanosec if hasattr(stamp, "nanosec") else stamp.nsec
    ns = int(stamp.sec) * 1_000_000_000 + int(nanosec)
    return ns if ns > 0 else int(bag_time_ns)


def _vec(v: Any) -> tuple[float, float, float]:
    return (v.x, v.y, v.z)


def _quat(q: Any) -> tuple[float, float, float, float]:
    return (q.x, q.y, q.z, q.w)


def _floats(values: Any) -> list[float]:
    # rosbags gives numeric arrays as numpy arrays; pyarrow wants sequences of Python floats
    return values.tolist() if hasattr(values, "tolist") else [float(x) for x in values]


def _field(msg: Any, *names: str) -> Any:
    """The first attribute that exists: ROS1 CameraInfo spells D K R P, ROS2 spells d k r p."""
    for name in names:
        if hasattr(msg, name):
            return getattr(msg, name)
    raise AttributeError(names[0])


TWIST = ["linear_x", "linear_y", "linear_z", "angular_x", "angular_y", "angular_z"]
POSE = ["x", "y", "z", "qx", "qy", "qz", "qw"]


def _twist(msg: Any, t: int) -> tuple:
    return (t, t, *_vec(msg.linear), *_vec(msg.angular))


def _twist_stamped(msg: Any, t: int) -> tuple:
    return (header_stamp_ns(msg, t), t, *_vec(msg.twist.linear), *_vec(msg.twist.angular))


def _joint_state(msg: Any, t: int) -> tuple:
    return (
        header_stamp_ns(msg, t),
        t,
        list(msg.name),
        _floats(msg.position),
        _floats(msg.velocity),
        _floats(msg.effort),
    )


def _odometry(msg: Any, t: int) -> tuple:
    pose, twist = msg.pose.pose, msg.twist.twist
    return (
        header_stamp_ns(msg, t),
        t,
        msg.header.frame_id,
        msg.child_frame_id,
        *_vec(pose.position),
        *_quat(pose.orientation),
        *_vec(twist.linear),
        *_vec(twist.angular),
    )


def _pose_stamped(msg: Any, t: int) -> tuple:
    return (
        header_stamp_ns(msg, t),
        t,
        msg.header.frame_id,
        *_vec(msg.pose.position),
        *_quat(msg.pose.orientation),
    )


def _pose_cov_stamped(msg: Any, t: int) -> tuple:
    pose = msg.pose.pose
    return (header_stamp_ns(msg, t), t, msg.header.frame_id, *_vec(pose.position), *_quat(pose.orientation))


def _transform_stamped(msg: Any, t: int) -> tuple:
    tf = msg.transform
    return (header_stamp_ns(msg, t), t, msg.header.frame_id, *_vec(tf.translation), *_quat(tf.rotation))


def _imu(msg: Any, t: int) -> tuple:
    return (
        header_stamp_ns(msg, t),
        t,
        *_quat(msg.orientation),
        *_vec(msg.angular_velocity),
        *_vec(msg.linear_acceleration),
    )


def _camera_info(msg: Any, t: int) -> tuple:
    return (
        header_stamp_ns(msg, t),
        t,
        msg.header.frame_id,
        msg.width,
        msg.height,
        msg.distortion_model,
        _floats(_field(msg, "d", "D")),
        _floats(_field(msg, "k", "K")),
        _floats(_field(msg, "r", "R")),
        _floats(_field(msg, "p", "P")),
    )


def _schema(*fields: tuple[str, pa.DataType]) -> pa.Schema:
    return pa.schema([*TIME_FIELDS, *(pa.field(n, t) for n, t in fields)])


def _floats_named(names: list[str]) -> list[tuple[str, pa.DataType]]:
    return [(n, F64) for n in names]


@dataclass(frozen=True)
class Converter:
    """How one message type becomes rows: ``row(msg, bag_time_ns) -> tuple`` in ``schema`` order."""

    schema: pa.Schema
    row: Callable[[Any, int], tuple]


_TWIST_SCHEMA = _schema(*_floats_named(TWIST))
_POSE_SCHEMA = _schema(("frame_id", STR), *_floats_named(POSE))

CONVERTERS: dict[str, Converter] = {
    "geometry_msgs/msg/Twist": Converter(_TWIST_SCHEMA, _twist),
    "geometry_msgs/msg/TwistStamped": Converter(_TWIST_SCHEMA, _twist_stamped),
    "sensor_msgs/msg/JointState": Converter(
        _schema(
            ("name", pa.list_(STR)), ("position", LIST_F64), ("velocity", LIST_F64), ("effort", LIST_F64)
        ),
        _joint_state,
    ),
    "nav_msgs/msg/Odometry": Converter(
        _schema(
            ("frame_id", STR),
            ("child_frame_id", STR),
            *_floats_named([*POSE, "vx", "vy", "vz", "wx", "wy", "wz"]),
        ),
        _odometry,
    ),
    "geometry_msgs/msg/PoseStamped": Converter(_POSE_SCHEMA, _pose_stamped),
    "geometry_msgs/msg/PoseWithCovarianceStamped": Converter(_POSE_SCHEMA, _pose_cov_stamped),
    "geometry_msgs/msg/TransformStamped": Converter(_POSE_SCHEMA, _transform_stamped),
    "sensor_msgs/msg/Imu": Converter(
        _schema(*_floats_named(["qx", "qy", "qz", "qw", "wx", "wy", "wz", "ax", "ay", "az"])), _imu
    ),
    "sensor_msgs/msg/CameraInfo": Converter(
        _schema(
            ("frame_id", STR),
            ("width", pa.int64()),
            ("height", pa.int64()),
            ("distortion_model", STR),
            ("d", LIST_F64),
            ("k", LIST_F64),
            ("r", LIST_F64),
            ("p", LIST_F64),
        ),
        _camera_info,
    ),
}

COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
RAW_IMAGE = "sensor_msgs/msg/Image"
IMAGE_TYPES = (COMPRESSED_IMAGE, RAW_IMAGE)
_IMAGE_SCHEMA = _schema(("frame_id", STR), ("format", STR), ("index", pa.int64()), ("nbytes", pa.int64()))
# sensor_msgs/Image: the pixel layout (``step`` bytes per row, maybe padded; byte order of 16-bit data)
_RAW_IMAGE_SCHEMA = _schema(
    ("frame_id", STR),
    ("encoding", STR),
    ("width", pa.int64()),
    ("height", pa.int64()),
    ("step", pa.int64()),
    ("is_bigendian", pa.bool_()),
    ("index", pa.int64()),
    ("nbytes", pa.int64()),
)


def image_schema(mode: str, msgtype: str = COMPRESSED_IMAGE) -> pa.Schema:
    """CompressedImage or Image columns; ``inline`` adds the message's bytes as a ``data`` (binary)
    column (an Image's raw pixel rows, ``step`` bytes each)."""
    schema = _RAW_IMAGE_SCHEMA if msgtype == RAW_IMAGE else _IMAGE_SCHEMA
    if mode == "inline":
        return schema.append(pa.field("data", pa.binary()))
    return schema


def image_row(msg: Any, bag_time_ns: int, index: int, mode: str) -> tuple:
    """One CompressedImage or Image row; ``index`` is the message's ordinal on its topic."""
    data = msg.data
    head = (header_stamp_ns(msg, bag_time_ns), bag_time_ns, msg.header.frame_id)
    if hasattr(msg, "format"):
        row = (*head, msg.format, index, len(data))
    else:
        layout = (msg.encoding, msg.width, msg.height, msg.step, bool(msg.is_bigendian))
        row = (*head, *layout, index, len(data))
    return (*row, data.tobytes()) if mode == "inline" else row


def image_suffix(fmt: str) -> str:
    """File suffix for a CompressedImage ``format`` string (``"jpeg"``, ``"bgr8; png compressed"``)."""
    return ".png" if "png" in fmt.lower() else ".jpg"


def image_file(msg: Any) -> tuple[str, bytes]:
    """``(suffix, bytes)`` of the file ``extract.images=files`` writes for one image message: a
    CompressedImage's own bytes; an Image losslessly as PNG when its encoding is one
    :mod:`.images` decodes (colour as a viewable colour PNG, mono and Bayer as one channel, 16-bit
    as 16-bit), else its raw pixel rows (``.raw``; the table's encoding, width, height and step
    describe them)."""
    if hasattr(msg, "format"):
        return image_suffix(msg.format), msg.data.tobytes()
    from skidbench.pipeline.extract.images import png_bytes  # OpenCV only where images are written as files

    png = png_bytes(msg)
    return (".png", png) if png is not None else (".raw", msg.data.tobytes())


# tf2_msgs/TFMessage: one row per transform (an edge of the TF tree); ``static`` is True on the
# /tf_static topic (latched transforms that hold at every time), see :func:`tf_rows`.
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TF_SCHEMA = _schema(("parent", STR), ("child", STR), *_floats_named(POSE), ("static", pa.bool_()))


def is_static_tf_topic(topic: str) -> bool:
    """tf2's convention: static transforms are published on ``/tf_static`` (or ``<ns>/tf_static``)."""
    return topic.rstrip("/").rsplit("/", 1)[-1] == "tf_static"


def tf_rows(msg: Any, bag_time_ns: int, static: bool) -> list[tuple]:
    """One TFMessage -> a row per TransformStamped (stamp = its header stamp, or the bag time when
    zero, as static transforms often carry). Frame names are kept as published."""
    return [
        (
            header_stamp_ns(tf, bag_time_ns),
            bag_time_ns,
            tf.header.frame_id,
            tf.child_frame_id,
            *_vec(tf.transform.translation),
            *_quat(tf.transform.rotation),
            static,
        )
        for tf in msg.transforms
    ]


SUPPORTED = sorted([*CONVERTERS, *IMAGE_TYPES, TF_MESSAGE])


def schema_for(msgtype: str, images: str = "ref") -> pa.Schema:
    """The table schema of a (normalised) message type; ExtractError for a type we cannot tabulate."""
    if msgtype in IMAGE_TYPES:
        return image_schema(images, msgtype)
    if msgtype == TF_MESSAGE:
        return TF_SCHEMA
    try:
        return CONVERTERS[msgtype].schema
    except KeyError:
        raise ExtractError(
            f"message type {msgtype} is not supported (supported: {', '.join(SUPPORTED)})"
        ) from None


def rows_to_batch(rows: list[tuple], schema: pa.Schema) -> pa.RecordBatch:
    """Row tuples (in ``schema`` order) -> one Arrow record batch."""
    columns = list(zip(*rows, strict=True)) if rows else [()] * len(schema)
    arrays = [pa.array(col, type=f.type) for col, f in zip(columns, schema, strict=True)]
    return pa.RecordBatch.from_arrays(arrays, schema=schema)
