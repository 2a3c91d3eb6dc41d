"""Every refusal names the setting that fixes it, and following it works: each test runs `skidbench` as a
user would, takes the advice from the one-line error, runs again with it, and reaches either success or
the next true reason (issue 48: a setting another stage owns, ``.dir`` where ``.pattern`` was meant, a
robot setting that needs ``+``, a dataset without commands, wheel odometry as ground truth)."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import numpy as np
import pytest

from skidbench.pipeline.cli import main as cli
from skidbench.pipeline.extract.synthetic import T0_NS, write_bag
from skidbench.pipeline.groundtruth.orbslam import write_orbslam

JACKAL = {
    "/cmd_vel": ("geometry_msgs/msg/Twist", 45.0),
    "/joint_states": ("sensor_msgs/msg/JointState", 20.0),
    "/jackal_velocity_controller/odom": ("nav_msgs/msg/Odometry", 20.0),
    "/imu/data": ("sensor_msgs/msg/Imu", 75.0),
}


def skidbench(capsys, *argv: str) -> tuple[int, str, str]:
    """``skidbench <argv>`` in this process: (exit status, stdout, the last stderr line)."""
    try:
        cli.main(list(argv))
        code = 0
    except SystemExit as exc:
        code = int(exc.code or 0)
    out, err = capsys.readouterr()
    lines = [line for line in err.splitlines() if line.strip()]
    return code, out, lines[-1] if lines else ""


def dataset(tmp_path: Path, bag: Path) -> list[str]:
    return [f"out_root={tmp_path / 'out'}", "source=bag", f"source.root={bag}", "source.terrain=lab",
            "source.category=train", "dataset=advice", "robot=husky", "extract.progress=false"]  # fmt: skip


@pytest.fixture
def extracted(tmp_path, capsys) -> list[str]:
    bag = write_bag(tmp_path / "seq.bag", "ros1", 3.0, JACKAL)
    args = dataset(tmp_path, bag)
    assert skidbench(capsys, "extract", *args)[0] == 0
    return args


def advice(line: str, pattern: str) -> str:
    m = re.search(pattern, line)
    assert m, line
    return m.group(1)


def test_orbslam_settings_a_user_gets_wrong_each_name_their_fix(tmp_path, capsys, extracted):
    """``robot.camera.xyz`` on a robot without a camera (+ needed), ``.dir`` right but ``.pattern`` wrong,
    the camera's rotation missing, then the file's clock: each fix as the message says, then success."""
    orb = tmp_path / "orb"
    orb.mkdir()
    t = T0_NS + np.arange(45) * (10**9 // 15) + 1000 * 10**9  # another clock: 1000 s later than the bag's
    T = np.tile(np.eye(4), (45, 1, 1))
    T[:, 2, 3] = np.linspace(0.0, 1.0, 45)  # the camera's z (optical axis): the robot drives forward
    write_orbslam(orb / "CameraTrajectory.txt", t, T, "tum")
    args = [*extracted, "groundtruth.method=orbslam", f"groundtruth.orbslam.dir={orb}"]

    code, _, err = skidbench(capsys, "groundtruth", *args, "robot.camera.xyz=[0.3,0.0,0.5]")
    assert code == 2 and "robot=husky has no setting robot.camera.xyz" in err
    args.append(advice(err, r"add it with '\+': (\S+)"))  # +robot.camera.xyz=[0.3,0.0,0.5]

    code, _, err = skidbench(capsys, "groundtruth", *args)
    assert code == 2 and "no ORB-SLAM file for sequence seq" in err and "CameraTrajectory.txt" in err
    args += shlex.split(advice(err, r"set (groundtruth\.orbslam\.pattern='[^']+')"))

    code, _, err = skidbench(capsys, "groundtruth", *args)
    assert code == 2 and "robot.camera.rpy absent" in err
    assert advice(err, r"add it: (\+robot\.camera\.rpy)=") == "+robot.camera.rpy"
    args.append("+robot.camera.rpy=[-1.5708,0.0,-1.5708]")  # optical z forward along the base x

    code, _, err = skidbench(capsys, "groundtruth", *args)  # the next true reason: the file's clock
    assert code == 2 and "never overlap the recording of seq" in err
    assert "set groundtruth.orbslam.time_offset" in err
    code, _, err = skidbench(capsys, "groundtruth", *args, "groundtruth.orbslam.time_offset=-1000")
    assert code == 0, err
    assert (tmp_path / "out" / "advice" / "groundtruth" / "seq.tum").is_file()


def test_an_orbslam_folder_that_does_not_exist_names_dir(tmp_path, capsys, extracted):
    args = [*extracted, "groundtruth.method=orbslam", f"groundtruth.orbslam.dir={tmp_path / 'nope'}"]
    code, _, err = skidbench(capsys, "groundtruth", *args, "+robot.camera.xyz=[0,0,0]")
    assert code == 2 and err.endswith(f"{tmp_path / 'nope'}: no such folder; set groundtruth.orbslam.dir="
                                      "<the folder of the ORB-SLAM files>")  # fmt: skip


def test_wheel_odometry_is_refused_as_ground_truth_until_allowed(tmp_path, capsys, extracted):
    args = [*extracted, "groundtruth.method=pose_topic", "groundtruth.pose_topic.key=odom"]
    code, _, err = skidbench(capsys, "groundtruth", *args)
    assert code == 2 and "/jackal_velocity_controller/odom is wheel odometry, not ground truth" in err
    assert not (tmp_path / "out" / "advice" / "groundtruth" / "seq.tum").exists()
    code, _, err = skidbench(capsys, "groundtruth", *args, advice(err, r"set (\S+=true) to use it anyway"))
    assert code == 0, err
    assert (tmp_path / "out" / "advice" / "groundtruth" / "seq.tum").is_file()


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_a_bag_without_commands_is_refused_at_extract_whatever_inspect_said(tmp_path, capsys, fmt):
    """inspect never proposes ``cmd_vel=null``; its overrides pasted, extract refuses the bag (not split);
    ``cmd_vel=null`` by hand is refused too, and its advice followed reaches the true reason: no command
    topic in the bag. Nothing is left behind."""
    topics = {k: v for k, v in JACKAL.items() if k != "/cmd_vel"}
    bag = write_bag(tmp_path / ("bag.bag" if fmt == "ros1" else "bag"), fmt, 1.0, topics)
    code, out, _ = skidbench(capsys, "inspect", str(bag))
    assert code == 0 and "cmd_vel=null" not in out and "no cmd_vel topic" in out
    pasted = shlex.split(out.split("overrides to paste (or source.topics=auto):")[1].replace("\\\n", " "))
    pasted = [a for a in pasted if "=" in a]
    args = dataset(tmp_path, bag)

    code, _, err = skidbench(capsys, "extract", *args, *pasted)
    assert code == 2 and "topic /cmd_vel not found" in err and "set source.topics.cmd_vel.topic" in err
    assert "required=false" not in err  # commands are never optional

    code, _, err = skidbench(capsys, "extract", *args, "source.topics.cmd_vel=null")
    assert code == 2 and "source.topics.cmd_vel is not set: a dataset without commands" in err
    assert "set source.topics.cmd_vel.topic=" in err
    code, _, err = skidbench(capsys, "extract", *args, "source.topics.cmd_vel.topic=/drive_cmd")
    assert code == 2 and "topic /drive_cmd not found (topics: " in err
    extracted = tmp_path / "out" / "advice" / "extracted"
    assert not extracted.exists() or not any(extracted.rglob("*.parquet"))


WHEEL = ["/odom", "/jackal_velocity_controller/odom", "/a200/platform/odom", "/wheel_odom", "/odometry/wheel"]
NOT_WHEEL = ["/icp_odom", "/dlio/odom_node/odom", "/Odometry", "/lio_sam/mapping/odometry",
             "/kiss/odometry", "/rtabmap/odom", "/vins_estimator/odometry", "/ground_truth/odom",
             "/mocap/odom", "/gt_pose"]  # fmt: skip


@pytest.mark.parametrize("topic", WHEEL + NOT_WHEEL)
def test_wheel_odometry_is_told_by_the_drive_controllers_names_not_by_odom_alone(topic):
    from skidbench.pipeline.groundtruth.app import wheel_odometry

    assert bool(wheel_odometry("odom", topic, None)) == (topic in WHEEL)
    assert bool(wheel_odometry("tf", None, topic.strip("/").rsplit("/", 1)[-1])) == topic.endswith("/odom")
