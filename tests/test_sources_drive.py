"""drive_df source on the real DRIVE files (skipped when ../shared is absent)."""

from __future__ import annotations

import logging
import re

import numpy as np
import pandas as pd
import pytest

from skidbench.pipeline.core.errors import GroundTruthError
from skidbench.pipeline.core.geometry import se2_compose
from skidbench.pipeline.sources.drive_df import raw_to_sequences
from skidbench.pipeline.sources.drive_windows import WindowSettings, windows_to_sequences


def test_windows_chain_into_train_cv_ld_sequences(shared_real):
    path = shared_real / "drive" / "husky_windows.parquet"
    df = pd.read_parquet(path)
    seqs = windows_to_sequences(df, path, WindowSettings(20.0, (0.6, 0.2, 0.2), "husky"))
    cats = [s.category for s in seqs]
    assert list(dict.fromkeys(cats)) == ["train", "cv", "ld"]  # contiguous blocks, in order
    # the file's 9 boundaries where a wheel jumps by more than it ever changes inside a window (5.4-6.8
    # rad/s against at most 2.1: the robot stood still in between), all inside a split, each start a
    # sequence: 7 Train, 2 CV, 3 LD
    assert [cats.count(c) for c in ("train", "cv", "ld")] == [7, 2, 3]
    assert [s.name for s in seqs if s.category == "cv"] == ["husky_cv_00", "husky_cv_01"]
    # one 2 s slot per window, back to back (no holes); held ICP repeats are thinned out of gt_pose
    assert sum(len(s.tables.enc_wheels) for s in seqs) == 40 * len(df)
    assert sum(len(s.tables.gt_pose) for s in seqs) < 40 * len(df)
    gt = seqs[0].tables.gt_pose
    # the second window starts where the first one ended (chaining in the start's body frame)
    first = df.sort_values("calib_step", kind="stable").iloc[:2]
    end0 = first[["icp_x_39", "icp_y_39", "icp_yaw_39"]].to_numpy()[0]
    rel1 = first[["icp_x_5", "icp_y_5", "icp_yaw_5"]].to_numpy()[1]
    row = gt[gt["stamp_ns"] == 45 * 50_000_000]
    if len(row):  # sample 5 of window 1 may be a held ICP repeat (then it is not in gt_pose)
        np.testing.assert_allclose(row[["x", "y", "yaw"]].to_numpy()[0], se2_compose(end0, rel1), atol=1e-12)
    assert np.all(np.diff(gt["stamp_ns"]) > 0)
    assert np.all(np.abs(np.diff(gt["yaw"])) < 1.0)  # per-window yaw wraps are unwrapped


def test_windows_pipeline_writes_splits_and_a_card(shared_real, tmp_path):
    from hydra import compose, initialize_config_module

    from skidbench.pipeline.cli.api import prepare_splits

    with initialize_config_module("skidbench.conf", version_base="1.3"):
        over = [
            f"out_root={tmp_path}",
            "source=drive_df",
            "robot=warthog",
            f"source.root={shared_real / 'drive'}",
        ]
        cfg = compose("split", [*over, "source.file=warthog_windows.parquet"])
    splits = prepare_splits(cfg)
    files = sorted(p.relative_to(splits).as_posix() for p in splits.glob("*/*/*.parquet"))
    # DRIVE's windows cut into back-to-back sequences per split: warthog_<split>_00, _01, ...
    assert {f.split("/")[1] for f in files} == {"cv", "ld", "train"}
    assert all(re.fullmatch(r"unspecified/(cv|ld|train)/warthog_\1_\d\d\.parquet", f) for f in files)
    assert "| train | unspecified |" in (splits / "card.md").read_text()
    mtime = (splits / "unspecified" / "train" / "warthog_train_00.parquet").stat().st_mtime_ns
    prepare_splits(cfg)  # up to date: nothing is rewritten
    assert (splits / "unspecified" / "train" / "warthog_train_00.parquet").stat().st_mtime_ns == mtime


@pytest.mark.parametrize("name", ["close_raw", "warthog_grass2_raw"])
def test_raw_text_storage_and_placeholder_row_are_read_without_warnings(shared_real, caplog, name):
    """DRIVE stores every raw column as text (warthog_grass2_raw: all 26) with a zero-initialised first
    row: read at the cause, with one info line and no warning (before: 15 "mixed types" warnings)."""
    path = shared_real / "drive" / f"{name}.parquet"
    with caplog.at_level(logging.INFO):
        raw_to_sequences(pd.read_parquet(path), path, (0.6, 0.2, 0.2), "x")
    assert "placeholder row" in caplog.text
    warned = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert not [m for m in warned if "type" in m or "timestamp" in m or "not numbers" in m], warned


def test_raw_form_without_icp_reports_missing_ground_truth(shared_real):
    path = shared_real / "drive" / "close_raw.parquet"
    seqs = raw_to_sequences(pd.read_parquet(path), path, (0.6, 0.2, 0.2), "close")
    assert [s.category for s in seqs] == ["train", "cv", "ld"]
    assert all(s.tables.gt_pose is None for s in seqs)  # ICP never ran in this file
    assert all(np.all(np.diff(s.tables.cmd_vel["stamp_ns"]) > 0) for s in seqs)
    assert "ICP did not run" in seqs[0].notes[0]


def test_raw_form_without_ground_truth_fails_groundtruth_in_one_line(shared_real, tmp_path):
    from hydra import compose, initialize_config_module

    from skidbench.pipeline.extract.app import run as extract
    from skidbench.pipeline.groundtruth.app import run as groundtruth

    over = [f"out_root={tmp_path}", "source=drive_df", f"source.root={shared_real / 'drive'}",
            "source.file=workshop_raw.parquet", "source.label=workshop"]  # fmt: skip
    with initialize_config_module("skidbench.conf", version_base="1.3"):
        extract(compose("extract", over))
        with pytest.raises(GroundTruthError) as err:
            groundtruth(compose("groundtruth", over))
    line = str(err.value)  # the source file, the true reason with its numbers, and what would give one
    assert line.startswith(f"{shared_real / 'drive' / 'workshop_raw.parquet'}: nothing to score workshop_")
    assert "no ground truth: the ICP pose never changes in this file (ICP did not run) (4637 rows)" in line
    assert "groundtruth.method=orbslam" in line and "\n" not in line


def test_raw_form_with_icp_poses_yields_a_gt_pose_table(shared_real):
    path = shared_real / "drive" / "close_raw.parquet"
    df = pd.read_parquet(path)
    n = len(df)
    df["icp_pos_x"] = np.linspace(0, 5, n)
    df["icp_quat_z"], df["icp_quat_w"] = np.sin(0.1), np.cos(0.1)
    seqs = raw_to_sequences(df, path, (0.6, 0.2, 0.2), "close")
    gt = seqs[0].tables.gt_pose
    np.testing.assert_allclose(gt["yaw"], 0.2)
    assert gt["x"].is_monotonic_increasing


def test_husky_wheel_commands_clipped_to_max_wheel_rate_match_the_saturated_encoders(shared_real, tmp_path):
    """DRIVE's Husky is commanded beyond what its wheels turn; its encoders saturate at the config's
    ``max_wheel_rate`` (1.0 m/s / r). After the split's clip, the steady-state encoder rate of a
    saturated wheel is within 5 % of its clipped command (unclipped it was about 0.65-0.8 of it)."""
    from drive_data import drive_splits

    splits = drive_splits(shared_real / "drive", tmp_path, "husky")
    t = pd.concat([pd.read_parquet(f) for f in sorted((splits / "unspecified" / "train").glob("*.parquet"))])
    cmd, enc = t[["cmd_wl", "cmd_wr"]].to_numpy(), t[["enc_wl", "enc_wr"]].to_numpy()
    assert np.abs(cmd).max() == pytest.approx(6.06)
    steady = np.ones(len(t), bool)  # the command has not changed for 1.5 s
    for k in range(1, 45):
        steady[k:] &= np.all(cmd[k:] == cmd[:-k], axis=1)
    steady[:45] = False
    sat = steady[:, None] & np.isclose(np.abs(cmd), 6.06)
    assert sat.sum() > 1000
    ratio = np.median(np.abs(enc[sat]) / 6.06)
    assert 0.95 < ratio < 1.02


@pytest.mark.slow
@pytest.mark.parametrize("robot,over", [("husky", ()), ("warthog", ("source.file=warthog_windows.parquet",))])
def test_drive_splits_run_under_all_three_input_protocols(shared_real, tmp_path, robot, over):
    """The DRIVE fixtures under every input protocol: the wheel response identified from Train encoders
    (the calibration's implementation) brings the driving wheel rates closer to the encoders on the held-out
    CV split than the raw commands, ``measured`` is the encoders themselves, and one model fitted and scored
    under each protocol sees only the protocol's inputs and predicts finite velocities."""
    from drive_data import drive_splits, split_table

    from skidbench.models.kinematic.linear import FullLinear
    from skidbench.pipeline.calibrate.wheel_response import identify_response
    from skidbench.pipeline.core.layout import PROTOCOLS
    from skidbench.pipeline.core.protocol import INPUT_COLUMNS, fit_table, model_inputs
    from skidbench.pipeline.core.robot import load_robot

    splits = drive_splits(shared_real / "drive", tmp_path, robot, *over)
    spec = load_robot(robot)
    train, cv = split_table(splits, rows=6000), split_table(splits, "cv")
    response = identify_response(train).response
    enc = cv[["enc_wl", "enc_wr"]].to_numpy(float)
    rmse = {}
    for p in PROTOCOLS:
        inputs = model_inputs(cv, p, spec, response)
        assert tuple(inputs.columns) == INPUT_COLUMNS
        ok = np.all(np.isfinite(enc), axis=1)
        rmse[p] = float(np.sqrt(np.mean((inputs[["cmd_wl", "cmd_wr"]].to_numpy()[ok] - enc[ok]) ** 2)))
        model = FullLinear(spec).fit(fit_table(train, p, spec, response))
        assert np.isfinite(model.predict(inputs)).all()
    assert rmse["measured"] < 0.1 < rmse["response"] < 0.8 * rmse["commanded"], rmse
