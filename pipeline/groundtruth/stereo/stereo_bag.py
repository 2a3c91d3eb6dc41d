"""A bag's stereo pairs for visual odometry: camera_info, image topics, and the left/right pairing.

Streams a bag's compressed or raw images with rosbags' AnyReader (never holding more than a few frames),
pairs left and right by header stamp (:func:`skidbench.pipeline.core.timesync.nearest` within
``max_pair_dt_ms``) and decodes each pair to 8-bit grey for :class:`.stereo_vo.StereoVO`.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from skidbench.pipeline.core.errors import GroundTruthError, one_line
from skidbench.pipeline.core.timesync import nearest
from skidbench.pipeline.extract.convert import header_stamp_ns
from skidbench.pipeline.extract.images import ImageDecodeError, gray8
from skidbench.pipeline.extract.reader import open_bag
from skidbench.pipeline.extract.settings import DEFAULT_STORES
from skidbench.pipeline.groundtruth.stereo.vo_settings import StereoCamera, VOConfig

__all__ = ["open_stereo_bag", "read_stereo_camera", "check_image_topics", "iter_stereo_frames"]


def open_stereo_bag(bag_path: Path, stores: Mapping[str, str] | None = None):
    """The bag open with rosbags' AnyReader (a context manager); ``stores``: ``extract.typestores``
    (default :data:`~skidbench.pipeline.extract.settings.DEFAULT_STORES`)."""
    return open_bag(bag_path, stores or DEFAULT_STORES)


def read_stereo_camera(reader, bag_path: Path, vo: VOConfig) -> StereoCamera:
    infos = {}
    conns = {c.topic: c for c in reader.connections if c.topic in (vo.left_info_topic, vo.right_info_topic)}
    for topic in (vo.left_info_topic, vo.right_info_topic):
        if topic not in conns:
            raise GroundTruthError(
                f"{bag_path}: camera_info topic {topic} not found; "
                "set source.topics.left_info.topic and source.topics.right_info.topic"
            )
    for conn, _, raw in reader.messages(connections=list(conns.values())):
        if conn.topic in infos:
            continue
        msg = reader.deserialize(raw, conn.msgtype)
        infos[conn.topic] = {
            "P": np.asarray(getattr(msg, "p", getattr(msg, "P", None)), float),
            "K": np.asarray(getattr(msg, "k", getattr(msg, "K", None)), float),
            "width": int(msg.width),
            "height": int(msg.height),
        }
        if len(infos) == 2:
            break
    if len(infos) < 2:
        raise GroundTruthError(f"{bag_path}: no camera_info message on {sorted(set(conns) - set(infos))}")
    try:
        return StereoCamera.from_camera_info(infos[vo.left_info_topic], infos[vo.right_info_topic])
    except (KeyError, ValueError) as exc:
        raise GroundTruthError(f"{bag_path}: unusable camera_info ({one_line(exc)})") from exc


IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
#: message types a ground-truth pose can come from (``groundtruth.method=pose_topic``)
POSE_TYPES = (
    "nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped",
    "geometry_msgs/msg/TransformStamped", "tf2_msgs/msg/TFMessage",
)  # fmt: skip


def _norm(msgtype: str) -> str:
    """``sensor_msgs/Image`` (ROS1) -> ``sensor_msgs/msg/Image``."""
    return msgtype if "/msg/" in msgtype else msgtype.replace("/", "/msg/", 1)


def check_image_topics(reader, bag_path: Path, vo: VOConfig) -> None:
    """GroundTruthError when VO's image topics are not in the bag: "no ground-truth source" with the
    settings that would give one when the bag holds no camera image at all, else the topic to set."""
    types = {c.topic: _norm(c.msgtype) for c in reader.connections}
    topics = set(types)
    if not any(t in IMAGE_TYPES for t in types.values()):
        poses = [f"{k} [{t}]" for k, t in sorted(types.items()) if t in POSE_TYPES]
        from_pose = f"; its pose topics: {', '.join(poses)}" if poses else "; it has no pose topic either"
        raise GroundTruthError(
            f"{bag_path}: this bag has no ground-truth source: no camera image for groundtruth.method=vo "
            f"(it has no Image/CompressedImage topic){from_pose}. Give one: groundtruth.method=pose_topic "
            "groundtruth.pose_topic.key=<the extracted table of an external pose: motion capture, a "
            "localizer, lidar ICP; key=tf with .parent/.child for /tf>, or groundtruth.method=orbslam "
            "groundtruth.orbslam.dir=<folder of ORB-SLAM trajectories>, or record a stereo pair "
            "(source.topics.left_image.topic, right_image, left_info, right_info and robot.camera)"
        )
    for key, topic in (("left_topic", vo.left_topic), ("right_topic", vo.right_topic)):
        if topic not in topics:
            raise GroundTruthError(
                f"{bag_path}: image topic {topic} not found (topics: {', '.join(sorted(topics))}); "
                f"set source.topics.{key.removesuffix('_topic')}_image.topic"
            )


def iter_stereo_frames(reader, bag_path: Path, vo: VOConfig) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """Stream decoded (stamp_ns, left, right) pairs in stamp order; left/right paired by header stamp.

    The topics may carry ``sensor_msgs/CompressedImage`` or raw ``sensor_msgs/Image`` (any encoding of
    :mod:`skidbench.pipeline.extract.images`: mono, RGB/BGR, Bayer, 16-bit), decoded to 8-bit grey."""
    check_image_topics(reader, bag_path, vo)
    conns = [c for c in reader.connections if c.topic in (vo.left_topic, vo.right_topic)]
    pending: dict[str, dict[int, Any]] = {vo.left_topic: {}, vo.right_topic: {}}
    other = {vo.left_topic: vo.right_topic, vo.right_topic: vo.left_topic}
    tol = int(vo.max_pair_dt_ms * 1e6)
    n_pair = 0
    n_seen = 0
    for conn, bag_ns, raw in reader.messages(connections=conns):
        n_seen += 1
        msg = reader.deserialize(raw, conn.msgtype)
        st = header_stamp_ns(msg, bag_ns)
        mine, theirs = pending[conn.topic], pending[other[conn.topic]]
        match = None
        if theirs:  # timesync's nearest rule on the pending partner stamps (a tie: the earlier stamp)
            ref = np.fromiter(sorted(theirs), np.int64, len(theirs))
            (i,), (ok,) = nearest(np.array([st], np.int64), ref, tol)
            if ok:
                match = int(ref[i])
        if match is None:
            mine[st] = msg
            # drop stale unpaired images (a lost partner) to keep memory bounded
            for s in [s for s in mine if s < st - 2_000_000_000]:
                del mine[s]
            continue
        msg_other = theirs.pop(match)
        for s in [s for s in theirs if s < match]:
            del theirs[s]
        l_msg, r_msg = (msg, msg_other) if conn.topic == vo.left_topic else (msg_other, msg)
        n_pair += 1
        if (n_pair - 1) % max(1, vo.stride):
            continue
        try:
            left, right = gray8(l_msg), gray8(r_msg)
        except ImageDecodeError as exc:
            raise GroundTruthError(
                f"{bag_path}: undecodable image at stamp {st} ns on {conn.topic} ({one_line(exc)})"
            ) from exc
        if left.shape != right.shape:
            raise GroundTruthError(
                f"{bag_path}: left and right images differ in size ({left.shape[1]}x{left.shape[0]} and "
                f"{right.shape[1]}x{right.shape[0]}) at stamp {st} ns"
            )
        yield min(st, match), left, right
    if n_pair == 0:
        raise GroundTruthError(
            f"{bag_path}: no stereo pairs on {vo.left_topic} and {vo.right_topic} ({n_seen} images; "
            f"left/right stamps must agree within groundtruth.vo.max_pair_dt_ms={vo.max_pair_dt_ms})"
        )
