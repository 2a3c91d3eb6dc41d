"""The split table: uniform clock, command hold and timeout, gaps, the smoothing differentiator."""

from __future__ import annotations

import json

import numpy as np
import pytest

from skidbench.pipeline.core.errors import SplitError
from skidbench.pipeline.core.layout import Layout
from skidbench.pipeline.splits.app import check_flag
from skidbench.pipeline.splits.build import body_velocities, build_split_table, hold

S = 1_000_000_000


def arc(t, v=1.2, w=0.7):
    yaw = w * t
    return np.column_stack([v / w * np.sin(yaw), v / w * (1 - np.cos(yaw)), yaw])


def test_savitzky_golay_differentiator_recovers_a_constant_twist_arc():
    dt = 1 / 30
    t = np.arange(300) * dt
    vel = body_velocities(arc(t), np.ones(len(t), bool), dt, window=9, order=3)
    np.testing.assert_allclose(vel, [[1.2, 0.0, 0.7]] * len(t), atol=1e-4)


def test_differentiator_never_uses_samples_across_an_invalid_run():
    dt = 1 / 30
    t = np.arange(120) * dt
    pose = arc(t)
    pose[60:] += [5.0, -3.0, 0.0]  # a jump (tracking reset) hidden behind invalid samples
    valid = np.ones(len(t), bool)
    valid[55:60] = False
    vel = body_velocities(pose, valid, dt)
    np.testing.assert_allclose(vel[valid], [[1.2, 0.0, 0.7]] * int(valid.sum()), atol=1e-4)
    assert np.all(vel[~valid] == 0)


def test_command_hold_times_out_to_zero():
    stamps = np.array([0, 100_000_000]) * 1
    grid = np.array([0, 50_000_000, 300_000_000, 400_000_000])
    held = hold(stamps, np.array([[1.0], [2.0]]), grid, 250_000_000)
    np.testing.assert_array_equal(held[:, 0], [1.0, 1.0, 2.0, 0.0])


def test_split_table_marks_gaps_invalid_and_converts_commands(jackal):
    t = np.arange(0, 10, 1 / 15)
    gt_ns = (t * S).astype(np.int64) + 5 * S
    cmd_ns = (np.arange(0, 10, 1 / 45) * S).astype(np.int64) + 5 * S
    cmd = np.tile([1.2, 0.7], (len(cmd_ns), 1))
    gap = (int(gt_ns[40]), int(gt_ns[41]))
    df = build_split_table(jackal, gt_ns, arc(t), [gap], cmd_ns, cmd, "twist")
    assert df["stamp_ns"].iloc[0] == 5 * S and np.allclose(np.diff(df["t"]), 1 / 30)
    inside = (df["stamp_ns"] > gap[0]) & (df["stamp_ns"] < gap[1])
    assert inside.any() and not df.loc[inside, "valid"].any()
    assert df["valid"].sum() == len(df) - inside.sum()
    wl, wr = jackal.wheel_rates_from_twist(1.2, 0.7)
    np.testing.assert_allclose(df[["cmd_wl", "cmd_wr"]].iloc[5].to_numpy(), [wl, wr])
    ok = df["valid"] & (df["t"] > 0.5) & (df["t"] < 9.0)
    np.testing.assert_allclose(
        df.loc[ok, ["vx", "vy", "wz"]].to_numpy(), [[1.2, 0, 0.7]] * int(ok.sum()), atol=5e-3
    )
    assert df["enc_wl"].isna().all()


def test_split_refuses_a_flagged_ground_truth_unless_allowed(tmp_path):
    layout = Layout(tmp_path, "ds")
    with pytest.raises(SplitError, match="run `skidbench groundtruth` first"):
        check_flag(layout, False)
    layout.groundtruth.mkdir(parents=True)
    report = {"flagged": True, "translational_mean": 0.02, "rotational_mean": 0.001, "bounds": {}}
    (layout.groundtruth / "loop_closure.json").write_text(json.dumps(report))
    with pytest.raises(SplitError, match="flagged.*split.allow_flagged=true"):
        check_flag(layout, False)
    check_flag(layout, True)


def test_wheel_commands_are_clipped_to_the_robots_max_wheel_rate(jackal):
    """With ``max_wheel_rate`` the wheel commands are clipped to it, cmd_v/cmd_w follow the clipped
    wheels (ideal kinematics), the accelerations are those of the clipped commands; without, unchanged."""
    import dataclasses

    limited = dataclasses.replace(jackal, extra={**jackal.extra, "max_wheel_rate": 10.0})
    t = np.arange(0, 4, 1 / 15)
    gt_ns = (t * S).astype(np.int64)
    cmd_ns = (np.arange(0, 4, 1 / 45) * S).astype(np.int64)
    # 0.5 m/s straight, then a turn whose outer (right) wheel would be 13.1 rad/s
    cmd = np.where((cmd_ns < 2 * S)[:, None], [0.5, 0.0], [1.0, 1.5])
    free = build_split_table(jackal, gt_ns, arc(t), [], cmd_ns, cmd, "twist")
    df = build_split_table(limited, gt_ns, arc(t), [], cmd_ns, cmd, "twist")
    wl, wr = jackal.wheel_rates_from_twist(1.0, 1.5)
    assert wr > 10.0 > wl  # only the outer wheel is over the limit
    late = df["t"] > 2.2
    np.testing.assert_allclose(df.loc[late, "cmd_wr"], 10.0)
    np.testing.assert_allclose(df.loc[late, "cmd_wl"], wl)
    v, w = jackal.twist_from_wheel_rates(wl, 10.0)
    np.testing.assert_allclose(df.loc[late, ["cmd_v", "cmd_w"]].to_numpy(), [[v, w]] * int(late.sum()))
    np.testing.assert_allclose(df["cmd_dwr"], np.gradient(df["cmd_wr"], 1 / 30))
    assert df.attrs["clipped_rows"] == int((np.abs(free["cmd_wr"]) > 10.0).sum()) > 0
    early = df["t"] < 1.8
    np.testing.assert_array_equal(df.loc[early, "cmd_wr"], free.loc[early, "cmd_wr"])
    assert free.attrs["clipped_rows"] == 0 and np.isclose(free["cmd_wr"].max(), wr)


@pytest.mark.parametrize("bad", [0, -3.0, "fast", float("nan")])
def test_a_bad_max_wheel_rate_fails_when_the_robot_is_loaded(bad):
    from skidbench.pipeline.core.errors import ConfigError
    from skidbench.pipeline.core.robot import Robot

    base = {"name": "r", "mass": 10.0, "wheel_radius": 0.1, "track_width": 0.4, "wheelbase": 0.3}
    assert Robot.from_config(base).max_wheel_rate is None
    assert Robot.from_config({**base, "max_wheel_rate": 6}).max_wheel_rate == 6.0
    with pytest.raises(ConfigError, match="max_wheel_rate"):
        Robot.from_config({**base, "max_wheel_rate": bad})


def test_command_association_offset_is_the_excess_age_of_the_sampled_hold():
    from skidbench.pipeline.splits.build import command_association

    cmd = np.round(np.arange(0, 20 * 45) * S / 45).astype(np.int64)  # 45 Hz for 20 s
    for phase in (0.0, 0.004, 0.010):  # where the 30 Hz grid starts within the first command period
        grid = np.round((phase + np.arange(0, 19 * 30) / 30) * S).astype(np.int64)
        a = command_association(cmd, grid)
        # two phases per command period: ages phase and phase + T/2 (mod T); a steady hold is T/2 old
        ages = np.mod(np.array([phase, phase + 1 / 90]), 1 / 45)
        assert a["mean_age_s"] == pytest.approx(ages.mean(), abs=2e-6)
        assert a["time_average_age_s"] == pytest.approx(1 / 90, abs=1e-5)  # (partial periods at the ends)
        assert a["offset_s"] == pytest.approx(ages.mean() - 1 / 90, abs=1e-5)
    # incommensurate rates sample every age: no offset
    grid = np.round(np.arange(0, 19 * 31.7) / 31.7 * S).astype(np.int64)
    assert abs(command_association(cmd, grid)["offset_s"]) < 2e-4
    # the split records it; the table's values do not depend on it
    t = np.arange(0, 20, 1 / 50)
    df = build_split_table(load_robot_jackal(), np.round(t * S).astype(np.int64), arc(t), [], cmd,
                           np.tile([[1.2, 0.7]], (len(cmd), 1)), "twist")  # fmt: skip
    assert df.attrs["cmd_association"]["offset_s"] == pytest.approx(-1 / 180, abs=1e-5)


def load_robot_jackal():
    from skidbench.pipeline.core.robot import load_robot

    return load_robot("jackal")
