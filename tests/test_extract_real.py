"""extract on a real ROS1 bag (UT AUTOmata) with its own topic names and a TwistStamped command."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from test_extract_roundtrip import extract_cfg

from skidbench.pipeline.extract.app import run

BAG = "bags/ut_automata_ikd_2023-03-23-10-44-04.bag"
OVERRIDES = [
    "source.terrain=lab",
    "source.category=ld",
    "source.topics.cmd_vel.topic=/vesc_drive",
    "source.topics.cmd_vel.type=geometry_msgs/msg/TwistStamped",
    "source.topics.odom.topic=/odom",
    "source.topics.imu.topic=/vectornav/IMU",
    "source.topics.joint_states.required=false",
]


@pytest.mark.shared
def test_the_real_bag_extracts_with_its_own_topic_names(tmp_path, shared_real):
    bag = shared_real / BAG
    run(extract_cfg(tmp_path / "out", bag, *OVERRIDES))
    seq = tmp_path / "out" / "test" / "extracted" / bag.stem
    info = json.loads((seq / "_extract.json").read_text())
    # counts from PROVENANCE.md
    assert {k: v["count"] for k, v in info["topics"].items()} == {"cmd_vel": 1519, "odom": 1518, "imu": 3038}
    assert info["topics"]["cmd_vel"]["type"] == "geometry_msgs/msg/TwistStamped"
    cmd = pd.read_parquet(seq / "cmd_vel.parquet")
    imu = pd.read_parquet(seq / "imu.parquet")
    for table in (cmd, imu):
        assert np.all(np.diff(table["bag_time_ns"]) >= 0)  # bag order
        # header stamps of a live robot are within a second of the recording time
        assert np.all(np.abs(table["stamp_ns"] - table["bag_time_ns"]) < 1_000_000_000)
    duration_s = (cmd["bag_time_ns"].iloc[-1] - cmd["bag_time_ns"].iloc[0]) / 1e9
    assert 70 < duration_s < 80  # "76 s"
    assert cmd["linear_x"].abs().max() > 0.1  # the car drove
    assert np.allclose(np.linalg.norm(imu[["qx", "qy", "qz", "qw"]], axis=1), 1.0, atol=1e-3)


@pytest.mark.shared
def test_the_real_bag_with_default_topics_names_what_to_set(tmp_path, shared_real):
    from skidbench.pipeline.core.errors import ExtractError

    with pytest.raises(ExtractError, match=r"/cmd_vel not found .*/vesc_drive.*source.topics.cmd_vel.topic"):
        run(extract_cfg(tmp_path / "out", shared_real / BAG, "source.terrain=lab", "source.category=ld"))
