"""Ground truth from /tf + /tf_static: a bag with a TF tree is extracted (one row per transform) and the
pose of a frame in another is composed back through the tree, against closed forms."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hydra import compose, initialize_config_module
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import get_types_from_msg

from skidbench.pipeline.core.errors import GroundTruthError
from skidbench.pipeline.core.geometry import (
    matrix_to_quaternion,
    quaternion_slerp,
    quaternion_to_matrix,
    se3_inverse,
    se3_matrix,
)
from skidbench.pipeline.extract.app import run as extract
from skidbench.pipeline.extract.synthetic import T0_NS, _Factory, typestore_for
from skidbench.pipeline.groundtruth.app import run as groundtruth
from skidbench.pipeline.groundtruth.tf import compose_tf, interpolate_edge
from skidbench.pipeline.groundtruth.trajectory import read_tum

TF = "tf2_msgs/msg/TFMessage"
TWIST = "geometry_msgs/msg/Twist"
MS = 1_000_000
DURATION_MS = 8000


def _quat_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return np.array(
        [sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy,
         cr * cp * cy + sr * sp * sy]
    )  # fmt: skip


# The tree: world -> map (moving, 10 Hz: linear in translation, constant-rate yaw, so that linear
# interpolation and slerp are exact), map -> odom and base_link -> camera_link (static, on /tf_static),
# odom -> base_link (moving, 50 Hz, any 3D motion). Times in ms from the bag start.
def world_map(t_ms: float) -> tuple[np.ndarray, np.ndarray]:
    s = t_ms * 1e-3
    return np.array([0.3 * s, -0.1 * s, 0.02 * s]), _quat_rpy(0.0, 0.0, 0.4 * s - 0.2)


def odom_base(t_ms: float) -> tuple[np.ndarray, np.ndarray]:
    s = t_ms * 1e-3
    xyz = np.array([2.0 * math.sin(0.5 * s), 1.5 * math.cos(0.3 * s), 0.05 * math.sin(2 * s)])
    return xyz, _quat_rpy(0.05 * math.sin(s), 0.03 * math.cos(1.3 * s), 0.9 * s)


STATIC = {
    ("map", "odom"): (np.array([1.0, -2.0, 0.0]), _quat_rpy(0.0, 0.0, 0.7)),
    ("base_link", "camera_link"): (np.array([0.2, 0.06, 0.3]), _quat_rpy(-1.78, 0.01, -1.57)),
}
BASE_MS = [t for t in range(0, DURATION_MS, 20) if not 3000 < t < 4000]  # a 1 s gap at 3-4 s
MAP_GAP = (5960, 6760)  # world -> map: no samples in between (0.8 s)
MAP_MS = [t for t in range(60, DURATION_MS - 300, 100) if not MAP_GAP[0] < t < MAP_GAP[1]]


def write_tf_bag(path: Path, fmt: str) -> Path:
    """The tree above: /tf messages (the two moving edges, in one message when their times coincide),
    /tf_static at the start and re-published (equal) mid-way. ROS1 names carry a leading slash."""
    ts = typestore_for(fmt)
    if TF not in ts.fielddefs:  # rosbags' Noetic store lacks tf2_msgs; the bag carries the definition
        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF))
    f = _Factory(ts)
    slash = "/" if fmt == "ros1" else ""

    def transform(stamp_ns: int, parent: str, child: str, xyz, q):
        return f(
            "geometry_msgs/msg/TransformStamped",
            header=f.header(stamp_ns, slash + parent),
            child_frame_id=child,
            transform=f(
                "geometry_msgs/msg/Transform",
                translation=f.vec(*map(float, xyz)),
                rotation=f("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]),
            ),
        )

    events: dict[int, list] = {}
    for t in BASE_MS:
        events.setdefault(t, []).append(("odom", "base_link", *odom_base(t)))
    for t in MAP_MS:
        events.setdefault(t, []).append(("world", "map", *world_map(t)))
    if fmt == "ros1":
        writer, serialize = Writer1(path), ts.serialize_ros1
    else:
        writer = Writer2(path, version=9, storage_plugin=StoragePlugin.MCAP)
        serialize = ts.serialize_cdr
    with writer:
        tf = writer.add_connection("/tf", TF, typestore=ts)
        tf_static = writer.add_connection("/tf_static", TF, typestore=ts)
        cmd = writer.add_connection("/cmd_vel", TWIST, typestore=ts)  # a dataset needs its commands
        for k in range(10):
            twist = f(TWIST, linear=f.vec(0.5, 0.0, 0.0), angular=f.vec(0.0, 0.0, 0.1))
            writer.write(cmd, T0_NS + k * 100 * MS + 1, serialize(twist, TWIST))
        statics = [transform(0, p, c, *v) for (p, c), v in STATIC.items()]  # zero stamp, as often
        writer.write(tf_static, T0_NS - 1, serialize(f(TF, transforms=statics), TF))
        for t in sorted(events):
            if t == 5000:
                writer.write(tf_static, T0_NS + t * MS - 1, serialize(f(TF, transforms=statics), TF))
            msg = f(TF, transforms=[transform(T0_NS + t * MS, *e) for e in events[t]])
            writer.write(tf, T0_NS + t * MS, serialize(msg, TF))
    return path


def _T(xyz, q) -> np.ndarray:
    return se3_matrix(np.asarray(xyz), np.asarray(q))


def expected(parent: str, child: str, t_ms: float) -> np.ndarray:
    T = {
        ("world", "map"): _T(*world_map(t_ms)),
        ("map", "odom"): _T(*STATIC[("map", "odom")]),
        ("odom", "base_link"): _T(*odom_base(t_ms)),
        ("base_link", "camera_link"): _T(*STATIC[("base_link", "camera_link")]),
    }
    chain = ["world", "map", "odom", "base_link", "camera_link"]
    i, j = chain.index(parent), chain.index(child)
    out = np.eye(4)
    for a, b in zip(chain[min(i, j) : max(i, j)], chain[min(i, j) + 1 : max(i, j) + 1], strict=True):
        out = out @ T[(a, b)]
    return out if i < j else se3_inverse(out)


def cfg(stage: str, out_root: Path, bag: Path, *overrides: str):
    with initialize_config_module(config_module="skidbench.conf", version_base="1.3"):
        return compose(
            stage,
            overrides=[
                f"out_root={out_root}",
                "source=bag",
                f"source.root={bag}",
                "source.terrain=lab",
                "source.category=train",
                "dataset=tf",
                "source.topics.joint_states.required=false",
                "source.topics.odom.required=false",
                "source.topics.imu.required=false",
                *overrides,
            ],
        )


@pytest.fixture(scope="module", params=["ros1", "mcap"])
def extracted(request, tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp(f"tf_{request.param}")
    bag = write_tf_bag(root / ("seq.bag" if request.param == "ros1" else "seq"), request.param)
    extract(cfg("extract", root / "out", bag, "extract.progress=false"))
    return root / "out", bag


def test_tf_tables_hold_one_row_per_transform_with_the_static_flag(extracted):
    out, _ = extracted
    tf = pd.read_parquet(out / "tf" / "extracted" / "seq" / "tf.parquet")
    static = pd.read_parquet(out / "tf" / "extracted" / "seq" / "tf_static.parquet")
    assert len(tf) == len(BASE_MS) + len(MAP_MS) and not tf["static"].any()
    assert len(static) == 4 and static["static"].all()  # two edges, published twice
    assert list(tf.columns) == [
        "stamp_ns", "bag_time_ns", "parent", "child", "x", "y", "z", "qx", "qy", "qz", "qw", "static"
    ]  # fmt: skip
    rows = tf[tf["child"] == "base_link"]
    assert np.array_equal(rows["stamp_ns"], T0_NS + np.array(BASE_MS) * MS)
    xyz = np.array([odom_base(t)[0] for t in BASE_MS])
    assert np.array_equal(rows[["x", "y", "z"]].to_numpy(), xyz)
    # a zero header stamp falls back to the bag time
    assert (static["stamp_ns"] == static["bag_time_ns"]).all()


@pytest.mark.parametrize(
    "parent, child", [("world", "camera_link"), ("camera_link", "odom"), ("map", "base_link")]
)
def test_groundtruth_composes_the_chain_through_the_tree_to_1e_9(extracted, parent, child):
    """extract -> groundtruth pose_topic on the tf table: every pose equals the closed-form chain; the
    moving world -> map edge is interpolated at odom -> base_link's stamps and never extrapolated; both
    holes are gaps."""
    out, bag = extracted
    over = ["groundtruth.method=pose_topic", "groundtruth.pose_topic.key=tf", "groundtruth.jobs=1"]
    over += [f"groundtruth.pose_topic.parent={parent}", f"groundtruth.pose_topic.child={child}"]
    groundtruth(cfg("groundtruth", out, bag, *over))
    traj = read_tum(out / "tf" / "groundtruth" / "seq.tum")
    t_ms = (traj.stamp_ns - T0_NS) / MS
    through_map = "world" in (parent, child)
    want_ms = [
        t
        for t in BASE_MS
        if not through_map or (MAP_MS[0] <= t <= MAP_MS[-1] and not MAP_GAP[0] < t < MAP_GAP[1])
    ]
    assert np.array_equal(t_ms, want_ms)
    want = np.array([expected(parent, child, t) for t in want_ms])
    got = traj.matrices()
    assert np.abs(got[:, :3, 3] - want[:, :3, 3]).max() < 1e-9
    assert np.abs(got[:, :3, :3] - want[:, :3, :3]).max() < 2e-9  # TUM's 9 decimals of q
    gaps = [((a - T0_NS) / MS, (b - T0_NS) / MS) for a, b in traj.gaps]
    assert (3000, 4000) in gaps  # odom -> base_link's own hole
    assert (MAP_GAP in gaps) == through_map  # world -> map's hole: the stamps inside it dropped
    assert len(gaps) == 1 + through_map


def test_compose_is_exact_before_any_file_rounding(extracted):
    out, _ = extracted
    folder = out / "tf" / "extracted" / "seq"
    df = pd.concat([pd.read_parquet(folder / "tf.parquet"), pd.read_parquet(folder / "tf_static.parquet")])
    traj = compose_tf(df, "world", "camera_link", "tf", max_gap_s=0.5)
    want = np.array([expected("world", "camera_link", (t - T0_NS) / MS) for t in traj.stamp_ns])
    assert np.abs(traj.matrices() - want).max() < 1e-12


def test_an_unknown_frame_is_one_line_listing_the_frames(extracted):
    out, bag = extracted
    over = ["groundtruth.method=pose_topic", "groundtruth.pose_topic.key=tf", "groundtruth.jobs=1"]
    over += ["groundtruth.allow_wheel_odometry=true"]  # parent=odom: the frames are under test here
    tum = out / "tf" / "groundtruth" / "seq.tum"
    before = tum.read_bytes() if tum.exists() else None
    with pytest.raises(GroundTruthError) as info:
        groundtruth(cfg("groundtruth", out, bag, *over, "groundtruth.pose_topic.parent=odom",
                        "groundtruth.pose_topic.child=base_lnk"))  # fmt: skip
    msg = str(info.value)
    assert "\n" not in msg and "'base_lnk'" in msg and "groundtruth.pose_topic.child" in msg
    assert "frames: base_link, camera_link, map, odom, world" in msg
    assert (tum.read_bytes() if tum.exists() else None) == before  # nothing written or changed
    with pytest.raises(GroundTruthError) as info:  # frames not set: the same listing, the keys to set
        groundtruth(cfg("groundtruth", out, bag, *over))
    msg = str(info.value)
    assert "\n" not in msg and "frames: base_link, camera_link, map, odom, world" in msg
    assert "groundtruth.pose_topic.parent and groundtruth.pose_topic.child" in msg


def test_frames_in_separate_trees_or_unset_are_one_line_errors():
    rows = [(0, "a", "b", False), (10, "a", "b", False), (0, "c", "d", True)]
    df = pd.DataFrame(
        [(t, t, p, c, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, s) for t, p, c, s in rows],
        columns=["stamp_ns", "bag_time_ns", "parent", "child", *"x y z qx qy qz qw".split(), "static"],
    )
    with pytest.raises(GroundTruthError, match="separate trees") as info:
        compose_tf(df, "a", "d", "t.parquet", 0.5)
    assert "\n" not in str(info.value)
    with pytest.raises(GroundTruthError, match="is static"):
        compose_tf(df, "c", "d", "t.parquet", 0.5)


def test_edge_interpolation_is_slerp_and_lerp_without_extrapolation():
    rng = np.random.default_rng(3)
    q = rng.normal(size=(2, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    stamps = np.array([1_000, 2_000, 5_000], dtype=np.int64)
    xyz = np.array([[0.0, 0, 0], [1.0, 2, 3], [4.0, 5, 6]])
    quat = np.array([q[0], q[1], q[1]])
    t = np.array([999, 1_000, 1_250, 2_000, 3_000, 5_000, 5_001], dtype=np.int64)
    T, valid = interpolate_edge(stamps, xyz, quat, t, max_gap_ns=1_500)
    assert valid.tolist() == [False, True, True, True, False, True, False]
    assert np.allclose(T[2, :3, 3], [0.25, 0.5, 0.75], atol=1e-15)
    # slerp at 1/4: a quarter of the relative rotation's angle, about its axis
    mid = quaternion_slerp(q[:1], q[1:], np.array([0.25]))[0]
    assert np.allclose(T[2, :3, :3], quaternion_to_matrix(mid), atol=1e-14)
    rel = quaternion_to_matrix(q[0]).T @ quaternion_to_matrix(q[1])
    part = quaternion_to_matrix(q[0]).T @ T[2, :3, :3]
    angle = np.arccos((np.trace(rel) - 1) / 2)
    assert np.arccos(np.clip((np.trace(part) - 1) / 2, -1, 1)) == pytest.approx(angle / 4, abs=1e-9)
    assert np.allclose(matrix_to_quaternion(T[3, :3, :3]), matrix_to_quaternion(quaternion_to_matrix(q[1])))


def test_slerp_matches_scipy_and_keeps_tiny_rotations_exact():
    from scipy.spatial.transform import Rotation, Slerp

    rng = np.random.default_rng(5)
    q = Rotation.random(2, random_state=7).as_quat()
    frac = rng.uniform(0, 1, 9)
    ref = Slerp([0.0, 1.0], Rotation.from_quat(q))(frac).as_matrix()
    got = quaternion_to_matrix(quaternion_slerp(np.tile(q[0], (9, 1)), np.tile(q[1], (9, 1)), frac))
    assert np.abs(got - ref).max() < 1e-14
    # 1e-9 rad about z between two samples: the midpoint is 0.5e-9 rad (arccos would return 0 or 2e-8)
    tiny = np.array([[0.0, 0.0, 0.0, 1.0]]), np.array([[0.0, 0.0, np.sin(0.5e-9), np.cos(0.5e-9)]])
    mid = quaternion_slerp(*tiny, np.array([0.5]))[0]
    assert 2 * np.arctan2(mid[2], mid[3]) == pytest.approx(0.5e-9, rel=1e-9)


def test_tf_from_the_odometry_frame_is_refused_as_ground_truth_until_allowed(extracted):
    """odom -> base_link is the drive controller's wheel odometry (REP 105): not ground truth unless
    groundtruth.allow_wheel_odometry=true, which the one-line refusal names."""
    out, bag = extracted
    over = ["groundtruth.method=pose_topic", "groundtruth.pose_topic.key=tf", "groundtruth.jobs=1",
            "groundtruth.pose_topic.parent=odom", "groundtruth.pose_topic.child=base_link"]  # fmt: skip
    tum = out / "tf" / "groundtruth" / "seq.tum"
    before = tum.read_bytes() if tum.exists() else None
    with pytest.raises(GroundTruthError) as info:
        groundtruth(cfg("groundtruth", out, bag, *over))
    msg = str(info.value)
    assert "\n" not in msg and "the TF chain from frame 'odom'" in msg and "is wheel odometry" in msg
    assert msg.endswith("or set groundtruth.allow_wheel_odometry=true to use it anyway")
    assert (tum.read_bytes() if tum.exists() else None) == before
    groundtruth(cfg("groundtruth", out, bag, *over, "groundtruth.allow_wheel_odometry=true"))
    assert len(read_tum(tum)) == len(BASE_MS)
