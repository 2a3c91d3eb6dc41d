"""extract: bags with known messages (ROS1, ROS2 sqlite3, ROS2 mcap) come back value for value."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from hydra import compose, initialize_config_module

from skidbench.pipeline.extract.app import run
from skidbench.pipeline.extract.synthetic import JACKAL_TOPICS, expected_messages, write_bag

DURATION_S = 1.0


def extract_cfg(out_root: Path, root: Path, *overrides: str):
    with initialize_config_module(config_module="skidbench.conf", version_base="1.3"):
        return compose(
            "extract",
            overrides=[
                f"out_root={out_root}",
                "source=bag",
                f"source.root={root}",
                "dataset=test",
                "extract.progress=false",
                *overrides,
            ],
        )


def make_bag(root: Path, fmt: str, cmd_type: str = "geometry_msgs/msg/Twist", name: str = "seq") -> Path:
    topics = {**JACKAL_TOPICS, "/cmd_vel": (cmd_type, 45.0)}
    folder = root / "tile" / "train"
    folder.mkdir(parents=True, exist_ok=True)
    return write_bag(folder / (f"{name}.bag" if fmt == "ros1" else name), fmt, DURATION_S, topics)


def _stamp(msg, bag_ns: int) -> int:
    ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
    return ns or bag_ns


def _expected_rows(msgtype: str, items) -> pd.DataFrame:
    rows = []
    for k, (t, m) in enumerate(items):
        if msgtype.endswith("/Twist"):
            row = {"stamp_ns": t, "linear_x": m.linear.x, "angular_z": m.angular.z, "linear_z": m.linear.z}
        elif msgtype.endswith("TwistStamped"):
            tw = m.twist
            row = {"stamp_ns": _stamp(m, t), "linear_x": tw.linear.x, "angular_z": tw.angular.z}
        elif msgtype.endswith("JointState"):
            row = {"stamp_ns": _stamp(m, t), "name": list(m.name), "velocity": list(m.velocity)}
        elif msgtype.endswith("Odometry"):
            p, v = m.pose.pose, m.twist.twist
            row = {
                "stamp_ns": _stamp(m, t),
                "frame_id": m.header.frame_id,
                "child_frame_id": m.child_frame_id,
                "x": p.position.x,
                "qz": p.orientation.z,
                "vx": v.linear.x,
                "wz": v.angular.z,
            }
        elif msgtype.endswith("Imu"):
            row = {"stamp_ns": _stamp(m, t), "qz": m.orientation.z, "wz": m.angular_velocity.z}
            row["ax"] = m.linear_acceleration.x
        elif msgtype.endswith("CompressedImage"):
            row = {"stamp_ns": _stamp(m, t), "format": m.format, "index": k, "nbytes": len(m.data)}
        elif msgtype.endswith("CameraInfo"):
            d = getattr(m, "d", None) if hasattr(m, "d") else m.D
            row = {"stamp_ns": _stamp(m, t), "width": m.width, "distortion_model": m.distortion_model}
            row["d"] = list(d)
        else:
            raise AssertionError(msgtype)
        rows.append({"bag_time_ns": t, **row})
    return pd.DataFrame(rows)


KEYS = {
    "/cmd_vel": "cmd_vel",
    "/joint_states": "joint_states",
    "/jackal_velocity_controller/odom": "odom",
    "/imu/data": "imu",
    "/stereo/left/image_raw/compressed": "left_image",
    "/stereo/left/camera_info": "left_info",
    "/skidbench/true_pose": "true_pose",
}


@pytest.mark.parametrize(
    "fmt, cmd_type",
    [
        ("ros1", "geometry_msgs/msg/Twist"),
        ("ros1", "geometry_msgs/msg/TwistStamped"),
        ("sqlite3", "geometry_msgs/msg/Twist"),
        ("mcap", "geometry_msgs/msg/TwistStamped"),
    ],
)
def test_every_value_of_every_topic_survives_extraction(tmp_path, fmt, cmd_type):
    make_bag(tmp_path / "bags", fmt, cmd_type)
    cfg = extract_cfg(tmp_path / "out", tmp_path / "bags", f"source.topics.cmd_vel.type={cmd_type}")
    run(cfg)
    seq = tmp_path / "out" / "test" / "extracted" / "seq"
    topics = {**JACKAL_TOPICS, "/cmd_vel": (cmd_type, 45.0)}
    expected = expected_messages(fmt, DURATION_S, topics)
    for topic, key in KEYS.items():
        table = pd.read_parquet(seq / f"{key}.parquet")
        want = _expected_rows(topics[topic][0], expected[topic])
        assert len(table) == len(want) > 0
        got = table[want.columns]
        for col in want.columns:
            a, b = got[col].tolist(), want[col].tolist()
            if isinstance(b[0], list):
                a = [list(x) for x in a]
            assert a == b, (key, col)  # exact: no float is touched on the way
    info = json.loads((seq / "_extract.json").read_text())
    assert info["topics"]["cmd_vel"]["type"] == cmd_type
    assert info["topics"]["imu"]["count"] == len(expected["/imu/data"])
    assert info["terrain"] == "tile" and info["category"] == "train"
    assert sorted(info["absent"]) == ["right_image", "right_info", "tf", "tf_static"]
    assert not list(seq.glob(".tmp-*"))


def test_tables_have_exactly_the_contract_columns(tmp_path):
    make_bag(tmp_path / "bags", "ros1")
    run(extract_cfg(tmp_path / "out", tmp_path / "bags"))
    seq = tmp_path / "out" / "test" / "extracted" / "seq"
    time = ["stamp_ns", "bag_time_ns"]
    twist = ["linear_x", "linear_y", "linear_z", "angular_x", "angular_y", "angular_z"]
    odom = ["frame_id", "child_frame_id", "x", "y", "z", "qx", "qy", "qz", "qw"]
    odom += ["vx", "vy", "vz", "wx", "wy", "wz"]
    want = {
        "cmd_vel": time + twist,
        "joint_states": time + ["name", "position", "velocity", "effort"],
        "odom": time + odom,
        "true_pose": time + odom,
        "imu": time + ["qx", "qy", "qz", "qw", "wx", "wy", "wz", "ax", "ay", "az"],
        "left_image": time + ["frame_id", "format", "index", "nbytes"],
        "left_info": time + ["frame_id", "width", "height", "distortion_model", "d", "k", "r", "p"],
    }
    for key, cols in want.items():
        schema = pq.read_schema(seq / f"{key}.parquet")
        assert schema.names == cols, key
        assert str(schema.field("stamp_ns").type) == "int64"


def test_rows_are_streamed_in_batches_not_one_table(tmp_path):
    make_bag(tmp_path / "bags", "ros1")
    run(extract_cfg(tmp_path / "out", tmp_path / "bags", "extract.batch_rows=16"))
    imu = pq.ParquetFile(tmp_path / "out" / "test" / "extracted" / "seq" / "imu.parquet")
    assert imu.metadata.num_rows == 75
    assert imu.metadata.num_row_groups == 5  # 75 rows in batches of 16


def test_images_inline_and_files_carry_the_exact_bytes(tmp_path):
    make_bag(tmp_path / "bags", "mcap")
    expected = [
        m.data.tobytes()
        for _, m in expected_messages("mcap", DURATION_S)["/stereo/left/image_raw/compressed"]
    ]
    run(extract_cfg(tmp_path / "out", tmp_path / "bags", "extract.images=inline"))
    seq = tmp_path / "out" / "test" / "extracted" / "seq"
    assert pd.read_parquet(seq / "left_image.parquet")["data"].tolist() == expected
    run(extract_cfg(tmp_path / "out", tmp_path / "bags", "extract.images=files"))
    files = sorted((seq / "images" / "left_image").glob("*.jpg"))
    assert [f.read_bytes() for f in files] == expected
    assert "data" not in pq.read_schema(seq / "left_image.parquet").names
    run(extract_cfg(tmp_path / "out", tmp_path / "bags"))  # back to references: the files go
    assert not (seq / "images" / "left_image").exists()


def test_a_rerun_with_unchanged_bag_and_config_skips_the_work(tmp_path):
    make_bag(tmp_path / "bags", "ros1")
    first = run(extract_cfg(tmp_path / "out", tmp_path / "bags"))
    again = run(extract_cfg(tmp_path / "out", tmp_path / "bags"))
    assert not first[0].get("skipped") and again[0]["skipped"]
    changed = run(extract_cfg(tmp_path / "out", tmp_path / "bags", "~source.topics.true_pose"))
    assert not changed[0].get("skipped")
    assert not (tmp_path / "out" / "test" / "extracted" / "seq" / "true_pose.parquet").exists()


def test_a_bag_tree_becomes_a_manifest_with_terrain_and_category(tmp_path):
    from skidbench.pipeline.core.manifest import Manifest

    make_bag(tmp_path / "bags", "ros1", name="a")
    make_bag(tmp_path / "bags", "sqlite3", name="b")
    run(extract_cfg(tmp_path / "out", tmp_path / "bags"))
    manifest = Manifest.read(tmp_path / "out" / "test" / "raw" / "manifest.json")
    assert [(s.name, s.terrain, s.category) for s in manifest.sequences] == [
        ("a", "tile", "train"),
        ("b", "tile", "train"),
    ]
    assert manifest.resolve(manifest.sequences[0]) == (tmp_path / "bags" / "tile" / "train" / "a.bag")


def test_a_manifest_of_simulated_bags_is_extracted_sequence_by_sequence(tmp_path):
    from skidbench.pipeline.core.manifest import Manifest, Sequence

    raw = tmp_path / "out" / "sim-tiny" / "raw"
    (raw / "bags").mkdir(parents=True)
    write_bag(raw / "bags" / "tile_train_00.bag", "ros1", 0.5)
    write_bag(raw / "bags" / "grass_cv_00", "sqlite3", 0.5)
    Manifest(
        [
            Sequence("tile_train_00", "tile", "train", "bags/tile_train_00.bag"),
            Sequence("grass_cv_00", "grass", "cv", "bags/grass_cv_00"),
        ]
    ).write(raw / "manifest.json")
    with initialize_config_module(config_module="skidbench.conf", version_base="1.3"):
        cfg = compose(
            "extract", overrides=[f"out_root={tmp_path / 'out'}", "scale=tiny", "extract.progress=false"]
        )
    records = run(cfg)
    assert [r["sequence"] for r in records] == ["tile_train_00", "grass_cv_00"]
    ext = tmp_path / "out" / "sim-tiny" / "extracted"
    assert np.all(np.diff(pd.read_parquet(ext / "grass_cv_00" / "cmd_vel.parquet")["bag_time_ns"]) > 0)
