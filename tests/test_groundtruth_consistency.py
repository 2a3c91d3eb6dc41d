"""The ground-truth consistency gate (pipeline/groundtruth/consistency.py) and split's refusal of it."""

from __future__ import annotations

import numpy as np
import pytest

from skidbench.pipeline.groundtruth.consistency import consistency
from skidbench.pipeline.splits.build import build_split_table

S = 1_000_000_000


def drive(jackal, flip=False, zero_cmd_from=None):
    """A 20 s drive of constant-twist steps with encoders equal to the commands (no slip); the ground
    truth is the exact arc, its heading turned by pi when ``flip`` (a pose frame facing backwards)."""
    t = np.arange(0, 20, 1 / 20)
    v = np.where(t < 10, 0.8, -0.5)
    w = np.where((t // 4) % 2 == 0, 0.4, -0.3)
    pose = np.zeros((len(t), 3))
    for k in range(1, len(t)):
        x, y, th = pose[k - 1]
        dt = t[k] - t[k - 1]
        pose[k] = [x + v[k - 1] * np.cos(th) * dt, y + v[k - 1] * np.sin(th) * dt, th + w[k - 1] * dt]
    if flip:
        pose[:, 2] += np.pi
    ns = (t * S).astype(np.int64) + 3 * S
    cmd = np.column_stack([v, w])
    enc = np.column_stack(jackal.wheel_rates_from_twist(v, w))
    if zero_cmd_from is not None:
        cmd[t >= zero_cmd_from] = 0.0  # something else drives it from here: the encoders still turn
    return build_split_table(jackal, ns, pose, [], ns, cmd, "twist", ns, enc)


def test_a_consistent_drive_passes_with_zero_heading_offset(jackal):
    rep = consistency(drive(jackal), jackal.wheel_radius, jackal.track_width)
    assert not rep["flagged"], rep["reasons"]
    assert rep["wheels"] == "encoders"
    assert rep["sign_agreement"] > 0.95
    assert abs(rep["heading_offset_deg"]) < 2.0
    assert rep["corr_v"] > 0.95 and rep["corr_w"] > 0.9
    assert rep["uncommanded_s"] == 0.0


def test_a_ground_truth_whose_heading_is_flipped_by_pi_is_flagged(jackal):
    rep = consistency(drive(jackal, flip=True), jackal.wheel_radius, jackal.track_width)
    assert rep["flagged"]
    assert rep["sign_agreement"] < 0.05
    assert abs(rep["heading_offset_deg"]) > 178.0  # +-180: the implied offset is pi
    assert rep["corr_v"] < -0.9
    assert any("sign" in r for r in rep["reasons"])


def test_motion_under_zero_commands_is_flagged_as_driven_by_something_else(jackal):
    rep = consistency(drive(jackal, zero_cmd_from=14.0), jackal.wheel_radius, jackal.track_width)
    assert rep["flagged"]
    # 14-20 s, less the 1.5 s after the stop in which the robot may still be braking (and 0.25 s timeout)
    assert rep["uncommanded_s"] == pytest.approx(6.0 - 1.5, abs=0.3)
    assert any("zero commands" in r for r in rep["reasons"])


def test_split_refuses_a_flipped_sequence_unless_allowed(jackal, tmp_path):
    """Through the split stage: a sequence whose ground truth is flipped is refused in one line with its
    numbers; ``split.allow_flagged=true`` writes it with the gate's numbers in its metadata."""
    from hydra import compose, initialize_config_module

    from skidbench.pipeline.core.errors import SplitError
    from skidbench.pipeline.core.io import read_parquet_metadata
    from skidbench.pipeline.core.layout import Layout
    from skidbench.pipeline.core.manifest import Manifest, Sequence
    from skidbench.pipeline.groundtruth.trajectory import Trajectory, write_tum
    from skidbench.pipeline.sources.common import TWIST_COLUMNS, stamped, write_sequence
    from skidbench.pipeline.splits.app import run as split_run
    from skidbench.pipeline.splits.app import split_sequence

    df = drive(jackal, flip=True)
    layout = Layout(tmp_path, "ds")
    seq = Sequence("flip_train_00", "lab", "train", "x")
    ns = df["stamp_ns"].to_numpy()
    v, w = df["cmd_v"].to_numpy(), df["cmd_w"].to_numpy()
    z = np.zeros_like(v)
    tables = {"cmd_vel": stamped(ns, **dict(zip(TWIST_COLUMNS, [v, z, z, z, z, w], strict=True))),
              "enc_wheels": stamped(ns, wl=df["enc_wl"], wr=df["enc_wr"])}  # fmt: skip
    write_sequence(layout.extracted / seq.name, tables, [], {"sequence": seq.name})
    layout.groundtruth.mkdir(parents=True)
    xyz = np.column_stack([df["x"], df["y"], np.zeros(len(df))])
    yaw = df["yaw"].to_numpy()
    quat = np.column_stack([z, z, np.sin(yaw / 2), np.cos(yaw / 2)])
    write_tum(Trajectory(ns, xyz, quat), layout.groundtruth / f"{seq.name}.tum")
    (layout.groundtruth / "loop_closure.json").write_text('{"flagged": false}')
    Manifest([seq], robot="jackal").write(layout.manifest)
    with initialize_config_module("skidbench.conf", version_base="1.3"):
        cfg = compose("split", [f"out_root={tmp_path}", "dataset=ds"])
        allowed = compose("split", [f"out_root={tmp_path}", "dataset=ds", "split.allow_flagged=true"])
    from omegaconf import OmegaConf

    path, gate = split_sequence(OmegaConf.to_object(cfg.split), layout, jackal, seq)
    assert path is None and gate["flagged"]
    with pytest.raises(SplitError, match=r"1 of 1 sequence.*flip_train_00: sign agreement 0\.0.*allow"):
        split_run(cfg)
    assert not layout.split_file("lab", "train", seq.name).exists()  # nothing written for it
    (path,) = split_run(allowed)
    assert read_parquet_metadata(path)["consistency"]["flagged"]
