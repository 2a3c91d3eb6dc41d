"""ORB-SLAM output ingestion: formats, units, camera->base conversion, association, gaps, bad input."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from skidbench.pipeline.core.errors import GroundTruthError
from skidbench.pipeline.core.geometry import quaternion_from_yaw, se3_from_xyz_rpy, se3_matrix
from skidbench.pipeline.groundtruth.orbslam import base_to_camera, detect_unit, read_orbslam, write_orbslam

T_B_C = se3_from_xyz_rpy(np.array([0.20, 0.06, 0.30]), np.array([-np.pi / 2, 0.0, -np.pi / 2]))
T0 = 1_700_000_000_123_456_789


def base_trajectory(n=150, rate=15.0):
    """A planar arc (base frame) at the camera rate with a tracking loss between 4 s and 5.5 s."""
    stamps = T0 + np.round(np.arange(n) / rate * 1e9).astype(np.int64)
    t = (stamps - T0) * 1e-9
    yaw = 0.3 * t
    x, y = np.sin(yaw) / 0.3, (1 - np.cos(yaw)) / 0.3
    keep = (t < 4.0) | (t > 5.5)
    T = se3_matrix(np.column_stack([x, y, 0 * x]), quaternion_from_yaw(yaw))
    return stamps, T, keep


@pytest.mark.parametrize("fmt", ["tum", "euroc", "kitti"])
def test_orbslam_round_trip_recovers_base_trajectory_and_gap(tmp_path, fmt):
    stamps, T_b, keep = base_trajectory()
    T_c = base_to_camera(T_b, T_B_C)
    path, times = tmp_path / f"traj.{fmt}", tmp_path / "times.txt"
    write_orbslam(path, stamps[keep], T_c[keep], fmt, times=times)
    # images at the camera rate, header stamps offset from the bag time by 3 ms
    bag = stamps + 3_000_000
    traj, report = read_orbslam(
        path,
        T_B_C,
        fmt="auto",
        times=times if fmt == "kitti" else None,
        ref_stamp_ns=stamps,
        ref_bag_time_ns=bag,
    )
    np.testing.assert_array_equal(traj.stamp_ns, bag[keep])
    np.testing.assert_allclose(traj.matrices(), T_b[keep], atol=1e-9)
    assert len(traj.gaps) == 1
    a, b = traj.gaps[0]
    assert (a - T0) * 1e-9 < 4.0 < 5.5 < (b - T0) * 1e-9
    assert report["gaps"] == [[a, b]]


def test_unit_is_detected_and_logged(tmp_path, caplog):
    stamps, T_b, _ = base_trajectory(30)
    path = tmp_path / "f.txt"
    write_orbslam(path, stamps, base_to_camera(T_b, T_B_C), "euroc")
    with caplog.at_level(logging.INFO):
        traj, report = read_orbslam(path, T_B_C)
    assert "assumed ns" in caplog.text
    assert "ns" in report["format"]
    np.testing.assert_array_equal(traj.stamp_ns, stamps)
    assert detect_unit(np.arange(10) * 0.033) == "s"
    assert detect_unit(np.arange(10) * 33_000_000) == "ns"


def test_configured_unit_that_contradicts_the_data_is_an_error(tmp_path):
    stamps, T_b, _ = base_trajectory(30)
    path = tmp_path / "f.txt"
    write_orbslam(path, stamps, base_to_camera(T_b, T_B_C), "euroc")
    with pytest.raises(GroundTruthError, match=r"f\.txt: timestamps in the wrong unit.*unit=ns"):
        read_orbslam(path, T_B_C, unit="s")


def test_wrong_column_count_names_file_and_line(tmp_path):
    path = tmp_path / "bad.txt"
    path.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n")
    with pytest.raises(GroundTruthError, match=r"bad\.txt:3: wrong column count 7"):
        read_orbslam(path, T_B_C)
    path.write_text("1.0 0 0 0 0 0\n")
    with pytest.raises(GroundTruthError, match=r"bad\.txt:1: wrong column count 6"):
        read_orbslam(path, T_B_C)


def test_nan_poses_are_dropped_and_become_a_gap(tmp_path, caplog):
    lines = [f"{i * 0.1:.1f} {i * 0.1} 0 0 0 0 0 1" for i in range(10)]
    lines[4] = "0.4 nan nan nan 0 0 0 1"
    path = tmp_path / "nan.txt"
    path.write_text("\n".join(lines) + "\n")
    with caplog.at_level(logging.WARNING):
        traj, _ = read_orbslam(path, np.eye(4))
    assert len(traj) == 9 and "NaN" in caplog.text
    assert traj.gaps == [(300_000_000, 500_000_000)]


def test_non_monotonic_time_and_empty_file_are_one_line_errors(tmp_path):
    path = tmp_path / "back.txt"
    path.write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1\n1.5 0 0 0 0 0 0 1\n")
    with pytest.raises(GroundTruthError, match=r"back\.txt: non-monotonic time.*row 2"):
        read_orbslam(path, np.eye(4))
    empty = tmp_path / "empty.txt"
    empty.write_text("# nothing tracked\n")
    with pytest.raises(GroundTruthError, match=r"empty\.txt: empty sequence"):
        read_orbslam(empty, np.eye(4))


def test_tracking_reset_jump_is_a_gap(tmp_path):
    lines = [f"{i * 0.1:.1f} {i * 0.05 if i < 5 else (i - 5) * 0.05 - 20} 0 0 0 0 0 1" for i in range(10)]
    path = tmp_path / "reset.txt"
    path.write_text("\n".join(lines) + "\n")
    traj, _ = read_orbslam(path, np.eye(4), max_speed=5.0)
    assert traj.gaps == [(400_000_000, 500_000_000)]
