"""DRIVE's dataframe versions, the robot checked against the data, and the raw form's segment
classification (command-driven / driven by something else / idle)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from test_sources_drive_synthetic import drive_like_frame

from skidbench.pipeline.core.errors import ConfigError, SourceError
from skidbench.pipeline.core.robot import load_robot
from skidbench.pipeline.sources.drive_df import raw_to_sequences
from skidbench.pipeline.sources.drive_files import SLIP_BLOCKS, WINDOW, detect_form
from skidbench.pipeline.sources.drive_rows import COMMAND, classify_rows
from skidbench.pipeline.sources.drive_windows import WindowSettings, window_segments, windows_to_sequences

STEPS = [(0.6, 0.0), (0.0, 0.8), (-0.4, 0.3), (0.9, -0.5), (0.3, 0.2)]


def as_slip_version(df: pd.DataFrame) -> pd.DataFrame:
    """The same windows in the 1218-column ``slip_dataset_all`` layout: extra 40-sample blocks (ICP and
    IDD velocities, interpolated ICP, disturbances) and scalars, interleaved before the original ones."""
    rng = np.random.default_rng(0)
    extra = {f"{b}_{k}": rng.normal(size=len(df)) for b in SLIP_BLOCKS for k in range(WINDOW)}
    extra.update({"icp_vx": rng.normal(size=len(df)), "init_icp_x": np.zeros(len(df))})
    slip = pd.concat([pd.DataFrame(extra), df], axis=1)
    return slip[sorted(slip.columns)]  # another column order too


def test_slip_version_reads_into_the_same_tables_as_the_578_column_version():
    df, _, _ = drive_like_frame(STEPS)
    slip = as_slip_version(df)
    assert detect_form(slip, "x")[1] == "slip_dataset_all"
    assert detect_form(df, "x")[0] == "windows"
    settings = WindowSettings(20.0, (0.6, 0.2, 0.2), "w", cmd_kinematics=(0.3, 1.08))
    a = windows_to_sequences(df, Path("a.parquet"), settings)
    b = windows_to_sequences(slip, Path("b.parquet"), settings)
    assert [s.name for s in a] == [s.name for s in b]
    for sa, sb in zip(a, b, strict=True):
        assert sa.tables.present().keys() == sb.tables.present().keys()
        for k in sa.tables.present():
            pd.testing.assert_frame_equal(sa.tables.present()[k], sb.tables.present()[k])


def test_window_samples_under_a_zero_command_while_moving_are_reported():
    df, _, _ = drive_like_frame([(0.6, 0.0), (0.5, 0.2), (0.4, -0.3)])
    assert {s["class"] for s in window_segments(df, Path("w.parquet"))} == {COMMAND}
    cmd = [c for c in df.columns if c.startswith("cmd_")]
    df.loc[3:5, cmd] = 0.0  # step 1: zero commands, the wheels still turn (something else drives it)
    segs = window_segments(df, Path("w.parquet"))
    other = [s for s in segs if s["class"] == "other"]
    assert len(other) == 1 and other[0]["rows"] == 3 * WINDOW


def test_a_window_file_without_calib_step_is_one_clear_line():
    df, _, _ = drive_like_frame(STEPS)
    with pytest.raises(SourceError, match=r"w\.parquet: window form without a calib_step column"):
        windows_to_sequences(df.drop(columns="calib_step"), Path("w.parquet"), WindowSettings(label="w"))


def test_not_a_drive_frame_is_one_line():
    with pytest.raises(SourceError, match="not a DRIVE dataframe"):
        detect_form(pd.DataFrame({"a": [1.0]}), "f.parquet")


def test_classify_rows_from_state_and_from_consistency():
    n = 100
    state = np.array(["idle"] * 30 + ["calib"] * 40 + [""] * 30)
    cmd = np.r_[np.zeros(30), np.full(40, 0.5), np.zeros(30)]
    wheels = np.r_[np.full(30, 2.0), np.full(40, 1.5), np.zeros(30)]  # idle phase: moved by something else
    cls, why = classify_rows(state, cmd, np.zeros(n), wheels, wheels)
    assert list(cls[[0, 40, 80]]) == ["other", COMMAND, "idle"]
    assert "calib_state 'idle'" in why[0] and "(empty)" in why[80]
    cls2, _ = classify_rows(None, cmd, np.zeros(n), wheels, wheels)  # no state column: the same classes
    np.testing.assert_array_equal(cls, cls2)


def test_raw_segments_keep_only_the_calib_rows_of_the_shared_grass_file(shared_real):
    path = shared_real / "drive" / "warthog_grass2_raw.parquet"
    df = pd.read_parquet(path)
    segs: list = []
    seqs = raw_to_sequences(df, path, (0.6, 0.2, 0.2), "w", segments=segs)
    calib = df["calib_state"].astype(str) == "calib"
    stamps = pd.to_numeric(df["ros_time"], errors="coerce").to_numpy(float).astype(np.int64)
    kept = np.concatenate([s.tables.cmd_vel["stamp_ns"].to_numpy() for s in seqs])
    # every calib row is kept (2583 rows = 129.1 s at 20 Hz), and no other row
    assert len(kept) == int(calib.sum()) == 2583
    assert set(kept) == set(stamps[calib.to_numpy()])
    # the non-calib phases where the robot moved under zero commands are left out and reported
    other = [s for s in segs if s["class"] == "other"]
    assert sum(s["seconds"] for s in other) > 150 and sum(s["metres"] for s in other) > 50
    uncommanded = (~calib) & (pd.to_numeric(df["meas_left_vel"], errors="coerce").abs() > 0.3)
    assert not set(stamps[uncommanded.to_numpy()]) & set(kept)
    # several 6 s steps per sequence (runs of calib rows), not one sequence per step
    assert [s.category for s in seqs] == ["train", "train", "cv", "cv", "ld"]
    assert max(len(s.tables.cmd_vel) for s in seqs) > 3 * 121


def test_a_recording_with_wheels_reading_zero_is_one_line(shared_real):
    path = shared_real / "drive" / "husky_plank_raw.parquet"
    with pytest.raises(SourceError, match="nothing can be scored: the wheels read zero throughout"):
        raw_to_sequences(pd.read_parquet(path), path, (0.6, 0.2, 0.2), "h")


def test_windows_are_checked_against_the_robot_from_the_data(shared_real):
    path = shared_real / "drive" / "husky_windows.parquet"
    df = pd.read_parquet(path)
    checks: dict = {}
    settings = WindowSettings(20.0, (0.6, 0.2, 0.2), "h", cmd_kinematics=(0.3, 1.08))
    windows_to_sequences(df, path, settings, robot=load_robot("husky"), checks=checks)
    assert 0.7 < checks["speed_gain"] < 1.1 and 0.8 < checks["implied_radius_ratio"] < 1.1
    # the geometry refuses it as a Warthog's (not the speed gain, which the command conversion also moves)
    refused = r"robot=warthog: the ground truth travels 0\.15\d m per wheel radian.* 0\.50x the spec sheet's"
    identified = WindowSettings(20.0, (0.6, 0.2, 0.2), "h", cmd_kinematics=(0.3, 1.08), identify=True)
    with pytest.raises(ConfigError, match=refused) as e:
        windows_to_sequences(df, path, identified, robot=load_robot("warthog"))
    # below the radius, heavy slip (ice, mud) is the other reading: said, with the key that scores it
    assert "or its wheels slip by 50% on straight stretches (ice, mud)" in str(e.value)
    assert str(e.value).endswith("or source.check_geometry=false to score it as this robot's")


def test_a_geometry_check_turned_off_scores_the_file_with_a_warning(shared_real, caplog):
    """source.check_geometry=false (a Warthog on ice looks like a smaller robot): the same file the
    geometry refuses is extracted as this robot's, the contradiction one warning, its numbers recorded;
    the raw form likewise (the Warthog's grass file as a Husky: 1.58x the Husky's wheel radius)."""
    import dataclasses
    import logging

    path = shared_real / "drive" / "husky_windows.parquet"
    settings = WindowSettings(20.0, (0.6, 0.2, 0.2), "h", cmd_kinematics=(0.3, 1.08), identify=True)
    off = dataclasses.replace(settings, check_geometry=False)
    checks: dict = {}
    with caplog.at_level(logging.WARNING):
        seqs = windows_to_sequences(pd.read_parquet(path), path, off, load_robot("warthog"), checks)
    assert seqs and checks["implied_radius_ratio"] == pytest.approx(0.50, abs=0.01)
    assert "0.50x the spec sheet's wheel radius 0.3 m" in caplog.text
    assert "scored as this robot's anyway (source.check_geometry=false)" in caplog.text
    raw = shared_real / "drive" / "warthog_grass2_raw.parquet"
    args = (pd.read_parquet(raw), raw, (0.6, 0.2, 0.2), "g", None, load_robot("husky"))
    with pytest.raises(ConfigError, match=r"1\.58x the spec sheet's wheel radius 0\.165 m"):
        raw_to_sequences(*args)
    assert raw_to_sequences(*args, check_geometry=False)


def test_a_shuffled_window_file_is_said_to_be_out_of_recording_order(shared_real, caplog):
    """DRIVE writes a step's windows in order (no boundary inside a calib_step breaks); a shuffled copy of
    the real Husky file breaks a quarter of them: one warning says the windows are not in recording
    order, the ordered file gets none."""
    import logging

    path = shared_real / "drive" / "husky_windows.parquet"
    df = pd.read_parquet(path)
    settings = WindowSettings(20.0, (0.6, 0.2, 0.2), "h", cmd_kinematics=(0.3, 1.08))
    with caplog.at_level(logging.WARNING):
        windows_to_sequences(df, path, settings)
        assert "not in recording order" not in caplog.text
        short = windows_to_sequences(df.sample(frac=1, random_state=0), path, settings)
    assert "husky_windows.parquet: 119 of 402 boundaries between windows of one calib_step" in caplog.text
    assert "not in recording order (shuffled?)" in caplog.text and len(short) > 200


def test_a_renamed_husky_file_run_as_a_warthog_is_refused_in_one_line(shared_real, tmp_path):
    from hydra import compose, initialize_config_module

    from skidbench.pipeline.extract.app import run as extract

    data = tmp_path / "data"
    data.mkdir()
    shutil.copy(shared_real / "drive" / "husky_windows.parquet", data / "warthog_day2.parquet")
    over = [f"out_root={tmp_path}", "source=drive_df", f"source.root={data}", "robot=warthog",
            "source.file=warthog_day2.parquet"]  # fmt: skip
    with initialize_config_module("skidbench.conf", version_base="1.3"):
        with pytest.raises(ConfigError, match="warthog_day2.parquet: robot=warthog: .*not this robot's") as e:
            extract(compose("extract", over))
    assert "\n" not in str(e.value)


IDENT_STEPS = [(0.5, 0.0), (0.6, 0.05), (-0.4, 0.0), (0.3, 0.4), (0.7, -0.05), (0.45, 0.0), (0.2, -0.5)]


def _arrays(df: pd.DataFrame) -> dict:
    from skidbench.pipeline.sources.drive_windows import window_arrays

    return window_arrays(df, Path("w.parquet"))


def test_command_kinematics_are_identified_from_the_gain_and_matched_to_a_spec_sheet():
    from skidbench.pipeline.sources.drive_checks import identify_cmd_kinematics

    husky = load_robot("husky")
    # the published Husky file's case: commands converted with the Warthog's [0.3, 1.08] (gain 0.3/0.165)
    df, _, _ = drive_like_frame(IDENT_STEPS)
    kin, report = identify_cmd_kinematics(Path("w.parquet"), husky, _arrays(df), None, "k")
    assert kin == (0.3, 1.08) and "warthog's spec sheet" in report["how"] and "gain 1.818" in report["how"]
    # a Husky whose commands were converted with its own [0.165, 0.55], its wheels at 0.956 of them
    df, _, _ = drive_like_frame(IDENT_STEPS, cmd_kin=(0.165, 0.55), wheel_gain=0.956)
    kin, report = identify_cmd_kinematics(
        Path("w.parquet"), husky, _arrays(df), (0.3, 1.08), "source.ck.husky"
    )
    assert kin == (0.165, 0.55) and "husky's spec sheet" in report["how"]
    assert report["disagrees"].startswith("source.ck.husky=[0.3, 1.08] disagrees with the file")
    # a conversion no spec sheet has: the identified radius itself, the track scaled alike
    df, _, _ = drive_like_frame(IDENT_STEPS, cmd_kin=(0.21, 0.7))
    kin, report = identify_cmd_kinematics(Path("w.parquet"), husky, _arrays(df), None, "k")
    assert kin[0] == pytest.approx(0.21, rel=1e-3) and kin[1] == pytest.approx(0.55 * kin[0] / 0.165)
    # too few steady straight windows: the configured fallback, said
    df, _, _ = drive_like_frame([(0.3, 0.4), (0.2, -0.5)])
    kin, report = identify_cmd_kinematics(Path("w.parquet"), husky, _arrays(df), (0.3, 1.08), "k")
    assert kin == (0.3, 1.08) and "only 0 steady straight windows" in report["how"]


def test_the_slip_version_gives_the_kinematics_exactly():
    from skidbench.pipeline.sources.drive_checks import kinematics_from_idd

    rng = np.random.default_rng(3)
    tl, tr = rng.normal(size=(5, WINDOW)), rng.normal(size=(5, WINDOW))
    blocks = {"transitory_vel_left": tl, "transitory_vel_right": tr, "idd_vel_x": 0.3 * (tl + tr) / 2,
              "idd_vel_yaw": 0.3 * (tr - tl) / 1.08}  # fmt: skip
    assert kinematics_from_idd(blocks) == pytest.approx((0.3, 1.08), rel=1e-12)
    blocks["idd_vel_x"] = blocks["idd_vel_x"] + rng.normal(0, 0.01, size=(5, WINDOW))  # not that relation
    assert kinematics_from_idd(blocks) is None


def test_a_husky_with_its_own_command_kinematics_is_scored_with_them(tmp_path, caplog):
    """A deflated-tyre-like Husky file (commands in the Husky's own [0.165, 0.55], measured/commanded
    gain 0.956, not the default's 1.82): extracted and split as a Husky, with the identified kinematics
    reported and the default named in a warning; its commanded body speed then matches the ground truth's
    (under the default [0.3, 1.08] it would be 1.82x)."""
    import json
    import logging

    from drive_data import drive_splits, split_table

    data = tmp_path / "data"
    data.mkdir()
    steps = IDENT_STEPS * 2
    drive_like_frame(steps, cmd_kin=(0.165, 0.55), wheel_gain=0.956)[0].to_parquet(
        data / "husky_windows.parquet"
    )
    with caplog.at_level(logging.WARNING):
        splits = drive_splits(data, tmp_path / "out", "husky", "split.allow_flagged=true")
    assert "source.cmd_kinematics.husky=[0.3, 1.08] disagrees with the file" in caplog.text
    info = json.loads(next((tmp_path / "out").glob("*/extracted/husky_train_00/_extract.json")).read_text())
    assert info["robot_checks"]["cmd_kinematics"]["value"] == [0.165, 0.55]
    assert info["robot_checks"]["cmd_kinematics"]["configured"] == [0.3, 1.08]
    from skidbench.pipeline.core.layout import Layout
    from skidbench.pipeline.splits.app import recording_section

    ds = next((tmp_path / "out").glob("*/extracted")).parent.name
    card = recording_section(Layout(tmp_path / "out", ds))  # and the dataset card says it
    row = next(ln for ln in card.splitlines() if ln.startswith("| husky_windows.parquet | windows"))
    assert "| [0.165, 0.55]: the husky's spec sheet (measured/commanded common-mode wheel-rate gain" in row
    assert row.endswith("; the configured fallback [0.3, 1.08] not used |")
    t = split_table(splits)
    moving = t["valid"].astype(bool) & (t["cmd_v"].abs() > 0.2) & (t["cmd_w"].abs() < 0.1)
    ratio = float(np.median(t.loc[moving, "vx"] / t.loc[moving, "cmd_v"]))
    assert 0.9 < ratio < 1.1, ratio


def _raw_frame(n_steps: int = 4, per_step: int = 40) -> pd.DataFrame:
    """A small raw DRIVE frame driving forward (ns clock of 2024, 20 Hz, every row ``calib``)."""
    n = n_steps * per_step
    t = 1_721_336_326_440_222_197 + np.arange(n, dtype=np.int64) * 50_000_000
    return pd.DataFrame(
        {
            "ros_time": t, "cmd_vel_x": np.full(n, 0.5), "cmd_vel_omega": np.zeros(n),
            "meas_left_vel": np.full(n, 1.6), "meas_right_vel": np.full(n, 1.6),
            "calib_step": np.repeat(np.arange(n_steps), per_step).astype(float), "calib_state": "calib",
            "icp_pos_x": 0.025 * np.arange(n), "icp_pos_y": np.zeros(n), "icp_pos_z": np.zeros(n),
            "icp_quat_x": np.zeros(n), "icp_quat_y": np.zeros(n), "icp_quat_z": np.zeros(n),
            "icp_quat_w": np.ones(n),
        }
    )  # fmt: skip


def test_a_raw_clock_in_seconds_ms_or_us_is_read_as_nanoseconds(caplog):
    """ros_time in s, ms, us (a converted file) or a datetime column of any resolution: the same tables as
    DRIVE's ns clock, with one warning naming the unit; a clock stepping by under 1 per row that is no
    date is refused in one line."""
    import logging

    df = _raw_frame()
    want = raw_to_sequences(df, Path("r.parquet"), (0.5, 0.25, 0.25), "r")
    ns = df["ros_time"].to_numpy()
    variants = {
        "s": ns / 1e9, "ms": ns / 1e6, "us": ns // 1000,
        "datetime us": pd.to_datetime(ns // 1000, unit="us").as_unit("us"),
    }  # fmt: skip
    for unit, t in variants.items():
        with caplog.at_level(logging.WARNING):
            caplog.clear()
            got = raw_to_sequences(df.assign(ros_time=t), Path("r.parquet"), (0.5, 0.25, 0.25), "r")
        assert [s.name for s in got] == [s.name for s in want]
        for a, b in zip(got, want, strict=True):
            for k, table in b.tables.present().items():
                x, clock = a.tables.present()[k], [c for c in table.columns if c.endswith("_ns")]
                assert np.abs(x[clock].to_numpy() - table[clock].to_numpy()).max() < 1e3, unit  # float s
                pd.testing.assert_frame_equal(x.drop(columns=clock), table.drop(columns=clock))
        if unit in ("s", "ms", "datetime us"):
            assert f"ros_time is in {unit[-2:].strip()} (median" in caplog.text and "of 2024" in caplog.text
    with pytest.raises(SourceError, match=r"r\.parquet: ros_time steps by 0\.05 per row \(median\): not"):
        raw_to_sequences(df.assign(ros_time=100 + 0.05 * np.arange(len(df))), Path("r.parquet"), (1,), "r")
