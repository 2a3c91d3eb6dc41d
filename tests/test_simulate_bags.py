"""simulate end to end on a very small plan: bag contents, rates, ROS2, determinism, resume, manifest."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from skidbench.pipeline.core.manifest import Manifest
from skidbench.pipeline.simulate.app import run
from skidbench.pipeline.simulate.bag import TOPICS

# two short sequences: 3 s Train on tile, 2 s CV on grass (loop trials: test_simulate_plan.py)
SMALL_PLAN = {"train": {"tile": 3}, "cv": {"grass": 2}, "ld": {}}


def simulate(out: Path, *overrides: str) -> dict:
    with initialize_config_module(config_module="skidbench.conf", version_base="1.3"):
        cfg = compose("simulate", overrides=[f"out_root={out}", "scale=tiny", "jobs=1", *overrides])
    OmegaConf.update(cfg, "scale.simulate.durations", SMALL_PLAN, merge=False)
    OmegaConf.update(cfg, "scale.simulate.loops", {}, merge=False)
    return run(cfg)


@pytest.fixture(scope="module")
def ros1(tmp_path_factory) -> dict:
    return simulate(tmp_path_factory.mktemp("ros1"))


def read_counts(path: Path, store) -> tuple[dict[str, int], dict[str, str], dict[str, list]]:
    counts, types, first = {}, {}, {}
    with AnyReader([path], default_typestore=store) as reader:
        for conn, _t, raw in reader.messages():
            counts[conn.topic] = counts.get(conn.topic, 0) + 1
            types[conn.topic] = conn.msgtype
            if conn.topic not in first:
                first[conn.topic] = reader.deserialize(raw, conn.msgtype)
    return counts, types, first


def test_ros1_bag_has_the_jackal_topics_at_their_rates(ros1):
    layout = ros1["layout"]
    manifest = Manifest.read(layout.manifest)
    assert [s.name for s in manifest.sequences] == ["tile_train_00", "grass_cv_00"]
    seq = manifest.sequences[0]
    assert seq.terrain == "tile" and seq.category == "train" and seq.path == "bags/tile_train_00.bag"
    counts, types, first = read_counts(manifest.resolve(seq), get_typestore(Stores.ROS1_NOETIC))
    assert types == {topic: msgtype for topic, msgtype in TOPICS.values()}
    duration = 3.0
    for key, rate in {"cmd_vel": 45, "joint_states": 20, "odom": 20, "imu": 75, "true_pose": 50}.items():
        assert counts[TOPICS[key][0]] == int(duration * rate) + 1, key
    for key in ("left_image", "right_image", "left_info", "right_info"):
        assert counts[TOPICS[key][0]] == int(duration * 15) + 1, key
    js = first[TOPICS["joint_states"][0]]
    assert list(js.name) == ["front_left_wheel", "rear_left_wheel", "front_right_wheel", "rear_right_wheel"]
    img = first[TOPICS["left_image"][0]]
    assert bytes(img.data[:2]) == b"\xff\xd8"  # JPEG
    info = first[TOPICS["right_info"][0]]
    assert info.P[3] < 0  # right camera: -fx * baseline
    pose = first[TOPICS["true_pose"][0]]
    assert pose.header.frame_id == "world" and pose.child_frame_id == "base_link"


def test_same_seed_gives_same_bytes_in_parallel_and_a_rerun_skips(ros1, tmp_path):
    again = simulate(tmp_path, "jobs=2")
    bags = sorted(p.name for p in (ros1["layout"].raw / "bags").iterdir())
    assert bags == ["grass_cv_00.bag", "tile_train_00.bag"]
    for name in bags:
        a = (ros1["layout"].raw / "bags" / name).read_bytes()
        b = (again["layout"].raw / "bags" / name).read_bytes()
        assert a == b, name
    assert (ros1["layout"].raw / "card.md").read_text() == (again["layout"].raw / "card.md").read_text()
    resumed = simulate(tmp_path)
    assert resumed["skipped"] == 2
    # no temporary files are left next to the bags
    assert not [p for p in (tmp_path / "sim-tiny" / "raw" / "bags").iterdir() if p.name.startswith(".tmp")]


def test_another_seed_gives_another_trajectory(ros1, tmp_path):
    other = simulate(tmp_path, "seed=1", "images=false")
    store = get_typestore(Stores.ROS1_NOETIC)
    a = read_counts(ros1["layout"].raw / "bags" / "tile_train_00.bag", store)
    b = read_counts(other["layout"].raw / "bags" / "tile_train_00.bag", store)
    assert "/stereo/left/image_raw/compressed" not in b[0]
    pa = a[2]["/skidbench/true_pose"].pose.pose.position
    pb = b[2]["/skidbench/true_pose"].pose.pose.position
    assert (pa.x, pa.y) != (pb.x, pb.y)


@pytest.mark.parametrize("fmt", ["ros2", "mcap"])
def test_ros2_bags_are_readable(tmp_path, fmt):
    out = simulate(tmp_path, f"format={fmt}", "images=false")
    manifest = Manifest.read(out["layout"].manifest)
    assert manifest.format == fmt
    path = manifest.resolve(manifest.sequences[1])
    assert path.is_dir() and (path / "metadata.yaml").is_file()
    counts, types, first = read_counts(path, get_typestore(Stores.ROS2_HUMBLE))
    assert counts["/cmd_vel"] == 2 * 45 + 1
    assert types["/jackal_velocity_controller/odom"] == "nav_msgs/msg/Odometry"
    odom = first["/jackal_velocity_controller/odom"]
    assert np.isfinite(odom.pose.pose.position.x)


def test_bad_format_is_a_one_line_error(tmp_path):
    from skidbench.pipeline.core.errors import SimulateError

    with pytest.raises(SimulateError, match="format='ros3'"):
        simulate(tmp_path, "format=ros3")


def test_a_subset_has_the_same_bytes_as_in_the_whole_dataset(ros1, tmp_path):
    whole = ros1["layout"].raw / "bags" / "grass_cv_00.bag"
    part = simulate(tmp_path, "only=[grass_cv_00]")
    assert [s.name for s in Manifest.read(part["layout"].manifest).sequences] == ["grass_cv_00"]
    assert (part["layout"].raw / "bags" / "grass_cv_00.bag").read_bytes() == whole.read_bytes()
