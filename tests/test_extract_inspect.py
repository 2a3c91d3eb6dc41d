"""`skidbench inspect`: per-topic type, count, rate, start/end and gaps; the proposed source.topics; and
`source.topics=auto`, which extracts what the proposal names or refuses in one line."""

from __future__ import annotations

import shlex

import pandas as pd
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.typesys import Stores, get_typestore
from test_extract_bad_input import assert_nothing_left, assert_one_line, single
from test_extract_real import BAG, OVERRIDES
from test_extract_roundtrip import extract_cfg
from test_extract_single_file import _tables, bare_file

from skidbench.pipeline.cli import main as cli
from skidbench.pipeline.core.errors import ExtractError
from skidbench.pipeline.extract.app import run
from skidbench.pipeline.extract.inspect import inspect_bag, propose
from skidbench.pipeline.extract.synthetic import write_bag

TWIST, STAMPED = "geometry_msgs/msg/Twist", "geometry_msgs/msg/TwistStamped"
ODOM, IMU, JOINTS = "nav_msgs/msg/Odometry", "sensor_msgs/msg/Imu", "sensor_msgs/msg/JointState"
IMAGE, INFO = "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/CameraInfo"


def _chosen(topics: dict[str, str]) -> dict[str, str]:
    return {k: t for k, (t, _) in propose(topics).chosen.items()}


@pytest.mark.shared
def test_inspect_on_the_real_bag_counts_rates_and_proposes_its_topics(shared_real, capsys):
    bag = shared_real / BAG
    stats = {s.topic: s for s in inspect_bag(bag)}
    # counts from PROVENANCE.md; the VESC command and the odometry at 20 Hz, the IMU at 40 Hz
    assert {t: (s.msgtype, s.count) for t, s in stats.items()} == {
        "/joystick": ("sensor_msgs/msg/Joy", 2175),
        "/odom": (ODOM, 1518),
        "/vectornav/IMU": (IMU, 3038),
        "/vesc_drive": (STAMPED, 1519),
    }
    for topic, hz in (("/vesc_drive", 20.0), ("/odom", 20.0), ("/vectornav/IMU", 40.0)):
        s = stats[topic]
        assert s.rate_hz == pytest.approx((s.count - 1) / ((s.end_ns - s.start_ns) / 1e9))
        assert s.rate_hz == pytest.approx(hz, rel=0.01)
        assert 70 < (s.end_ns - s.start_ns) / 1e9 < 80
    cli.main(["inspect", str(bag)])
    out = capsys.readouterr().out
    assert "cmd_vel      /vesc_drive  [geometry_msgs/msg/TwistStamped]" in out
    pasted = shlex.split(out.split("overrides to paste (or source.topics=auto):", 1)[1].replace("\\\n", " "))
    for line in OVERRIDES[2:-1]:  # the README's hand-written overrides, found by inspect
        assert line in pasted


@pytest.mark.shared
def test_source_topics_auto_on_the_real_bag_extracts_what_hand_written_overrides_do(tmp_path, shared_real):
    bag = shared_real / BAG
    run(extract_cfg(tmp_path / "hand", bag, *OVERRIDES))
    info = run(
        extract_cfg(tmp_path / "auto", bag, "source.terrain=lab", "source.category=ld", "source.topics=auto")
    )
    assert {k: (v["topic"], v["type"]) for k, v in info[0]["topics"].items()} == {
        "cmd_vel": ("/vesc_drive", STAMPED),
        "odom": ("/odom", ODOM),
        "imu": ("/vectornav/IMU", IMU),
    }
    want, got = _tables(tmp_path / "hand", bag.stem), _tables(tmp_path / "auto", bag.stem)
    assert sorted(got) == sorted(want) == ["cmd_vel", "imu", "odom"]
    for key in want:
        pd.testing.assert_frame_equal(got[key], want[key], check_exact=True)


def test_gaps_and_rates_are_measured_on_the_bag_clock(tmp_path):
    """50 Hz for 1 s, a 0.5 s hole, 50 Hz for 1 s: one gap, the longest interval 0.52 s."""
    ts = get_typestore(Stores.ROS1_NOETIC)
    Twist, Vec = ts.types[TWIST], ts.types["geometry_msgs/msg/Vector3"]
    zero = Vec(x=0.0, y=0.0, z=0.0)
    stamps = [i * 20_000_000 for i in range(50)] + [1_500_000_000 + i * 20_000_000 for i in range(50)]
    bag = tmp_path / "gap.bag"
    with Writer1(bag) as writer:
        conn = writer.add_connection("/cmd_vel", TWIST, typestore=ts)
        for t in stamps:
            writer.write(conn, 10**18 + t, ts.serialize_ros1(Twist(linear=zero, angular=zero), TWIST))
    (s,) = inspect_bag(bag)
    assert (s.count, s.gaps) == (100, 1)
    assert s.max_gap_s == pytest.approx(0.52, abs=1e-9)
    assert s.rate_hz == pytest.approx(99 / 2.48, abs=1e-9)
    assert (s.start_ns, s.end_ns) == (10**18, 10**18 + stamps[-1])


def test_clearpath_ros1_names_pick_what_the_wheel_controller_received():
    topics = {
        "/cmd_vel": TWIST,
        "/joy_teleop/cmd_vel": TWIST,
        "/twist_marker_server/cmd_vel": TWIST,
        "/jackal_velocity_controller/cmd_vel": TWIST,
        "/jackal_velocity_controller/odom": ODOM,
        "/odometry/filtered": ODOM,
        "/imu/data": IMU,
        "/imu/data_raw": IMU,
        "/joint_states": JOINTS,
        "/ground_truth/odom": ODOM,
    }
    assert _chosen(topics) == {
        "cmd_vel": "/jackal_velocity_controller/cmd_vel",
        "odom": "/jackal_velocity_controller/odom",
        "joint_states": "/joint_states",
        "imu": "/imu/data",
        "true_pose": "/ground_truth/odom",
    }
    # without the controller's topic, the mux output /cmd_vel ranks above the teleop inputs
    del topics["/jackal_velocity_controller/cmd_vel"]
    assert _chosen(topics)["cmd_vel"] == "/cmd_vel"


def test_clearpath_ros2_namespaced_names_and_a_stereo_pair():
    ns = "/a200_0000"
    topics = {
        f"{ns}/cmd_vel": STAMPED,
        f"{ns}/joy_teleop/cmd_vel": STAMPED,
        f"{ns}/platform/cmd_vel": STAMPED,
        f"{ns}/platform/odom": ODOM,
        f"{ns}/platform/odom/filtered": ODOM,
        f"{ns}/platform/joint_states": JOINTS,
        f"{ns}/sensors/imu_0/data": IMU,
        f"{ns}/sensors/camera_0/left/image_rect/compressed": IMAGE,
        f"{ns}/sensors/camera_0/right/image_rect/compressed": IMAGE,
        f"{ns}/sensors/camera_0/left/camera_info": INFO,
        f"{ns}/sensors/camera_0/right/camera_info": INFO,
        f"{ns}/sensors/camera_1/image/compressed": IMAGE,  # a mono camera: not a pair
    }
    cam = f"{ns}/sensors/camera_0"
    assert _chosen(topics) == {
        "cmd_vel": f"{ns}/platform/cmd_vel",
        "odom": f"{ns}/platform/odom",
        "joint_states": f"{ns}/platform/joint_states",
        "imu": f"{ns}/sensors/imu_0/data",
        "left_image": f"{cam}/left/image_rect/compressed",
        "right_image": f"{cam}/right/image_rect/compressed",
        "left_info": f"{cam}/left/camera_info",
        "right_info": f"{cam}/right/camera_info",
    }


def test_tf_and_a_raw_image_stereo_pair_are_proposed():
    raw = "sensor_msgs/msg/Image"
    topics = {
        "/cmd_vel": TWIST,
        "/tf": "tf2_msgs/msg/TFMessage",
        "/tf_static": "tf2_msgs/msg/TFMessage",
        "/zed/left/image_raw": raw,
        "/zed/right/image_raw": raw,
        "/zed/left/image_rect": raw,
        "/zed/right/image_rect": raw,
        "/zed/left/camera_info": INFO,
        "/zed/right/camera_info": INFO,
    }
    assert _chosen(topics) == {
        "cmd_vel": "/cmd_vel",
        "tf": "/tf",
        "tf_static": "/tf_static",
        "left_image": "/zed/left/image_rect",  # rectified before raw
        "right_image": "/zed/right/image_rect",
        "left_info": "/zed/left/camera_info",
        "right_info": "/zed/right/camera_info",
    }


def test_two_robots_commands_are_ambiguous_and_auto_refuses_in_one_line(tmp_path):
    topics = {"/robot1/cmd_vel": (TWIST, 45.0), "/robot2/cmd_vel": (TWIST, 45.0), "/imu/data": (IMU, 75.0)}
    assert propose({t: m for t, (m, _) in topics.items()}).ambiguous == {
        "cmd_vel": ["/robot1/cmd_vel", "/robot2/cmd_vel"]
    }
    bag = bare_file(write_bag(tmp_path / "two", "mcap", 0.3, topics), tmp_path / "two.mcap")
    with pytest.raises(ExtractError) as exc:
        run(single(tmp_path, bag, "source.topics=auto"))
    assert_one_line(
        exc, bag, "cannot choose cmd_vel among /robot1/cmd_vel, /robot2/cmd_vel", "skidbench inspect"
    )
    assert_nothing_left(tmp_path, "two")


def test_auto_without_any_command_topic_names_the_topics_there(tmp_path):
    bag = write_bag(tmp_path / "imu.bag", "ros1", 0.3, {"/imu/data": (IMU, 75.0)})
    with pytest.raises(ExtractError) as exc:
        run(single(tmp_path, bag, "source.topics=auto"))
    assert_one_line(exc, bag, "found no cmd_vel topic (topics: /imu/data [sensor_msgs/msg/Imu])")
    assert_nothing_left(tmp_path, "imu")


def test_auto_on_a_mixed_folder_chooses_per_bag_and_leaves_out_what_a_bag_lacks(tmp_path):
    root = tmp_path / "data" / "grass" / "cv"
    root.mkdir(parents=True)
    write_bag(root / "full.bag", "ros1", 0.5)
    lean = {"/cmd_vel": (STAMPED, 45.0), "/odom": (ODOM, 20.0)}
    bare_file(write_bag(tmp_path / "lean", "sqlite3", 0.5, lean), root / "lean.db3")
    records = {
        r["sequence"]: r for r in run(extract_cfg(tmp_path / "out", tmp_path / "data", "source.topics=auto"))
    }
    assert sorted(records["lean"]["topics"]) == ["cmd_vel", "odom"]
    assert records["lean"]["topics"]["cmd_vel"]["type"] == STAMPED
    full = records["full"]["topics"]
    assert (
        full["cmd_vel"]["topic"] == "/cmd_vel" and full["odom"]["topic"] == "/jackal_velocity_controller/odom"
    )
    assert full["true_pose"]["topic"] == "/skidbench/true_pose"
    assert {"imu", "joint_states"} <= set(full)
    assert "left_image" not in full  # a left camera without a right one is no stereo pair


def test_inspect_of_a_truncated_file_is_one_line_and_exit_2(tmp_path, capsys):
    bag = bare_file(write_bag(tmp_path / "t", "mcap", 1.0), tmp_path / "t.mcap")
    bag.write_bytes(bag.read_bytes()[:-100])
    with pytest.raises(SystemExit) as exit_:
        cli.main(["inspect", str(bag)])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(f"skidbench inspect: error: {bag}: truncated or corrupt bag")


def test_inspect_of_a_folder_reports_every_bag(tmp_path, capsys):
    write_bag(tmp_path / "a.bag", "ros1", 0.3)
    (tmp_path / "sub").mkdir()
    bare_file(write_bag(tmp_path / "b", "mcap", 0.3), tmp_path / "sub" / "b.mcap")
    cli.main(["inspect", str(tmp_path)])
    out = capsys.readouterr().out
    assert f"{tmp_path / 'a.bag'}: ROS1 bag, 7 topics" in out
    assert f"{tmp_path / 'sub' / 'b.mcap'}: ROS2 bag (mcap), 7 topics" in out
    assert out.count("cmd_vel      /cmd_vel  [geometry_msgs/msg/Twist]") == 2


def test_vo_reads_the_stereo_topics_that_auto_chose_for_the_bag(tmp_path):
    """With source.topics=auto, VO takes the stereo pair extract chose (its _extract.json), not the
    Jackal defaults; with explicit topics it takes those."""
    import json

    from omegaconf import OmegaConf

    from skidbench.pipeline.groundtruth.stereo.vo import source_image_topics

    chosen = {
        "left_image": "/cam/left/image_raw",
        "right_image": "/cam/right/image_raw",
        "left_info": "/cam/left/camera_info",
        "right_info": "/cam/right/camera_info",
        "cmd_vel": "/cmd_vel",
    }
    topics = {k: {"topic": t, "type": "x", "count": 1} for k, t in chosen.items()}
    (tmp_path / "_extract.json").write_text(json.dumps({"topics": topics}))
    assert source_image_topics("auto", tmp_path) == {
        "left_topic": "/cam/left/image_raw",
        "right_topic": "/cam/right/image_raw",
        "left_info_topic": "/cam/left/camera_info",
        "right_info_topic": "/cam/right/camera_info",
    }
    explicit = OmegaConf.create({"left_image": {"topic": "/a"}})  # source.topics as the config holds it
    assert source_image_topics(explicit, tmp_path) == {"left_topic": "/a"}
