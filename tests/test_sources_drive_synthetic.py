"""drive_df window form on synthetic DRIVE-like frames with known motion (no ../shared needed)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from skidbench.pipeline.geometry import se2_compose
from skidbench.pipeline.sources.drive_df import WINDOW, command_gain, fresh_samples, windows_to_sequences

R_CMD, B_CMD = 0.3, 1.08  # the conversion "DRIVE" used for the commands


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def drive_like_frame(steps, rate=20.0, hold_icp=True):
    """Windows of constant-twist steps [(v, w)] * 3 windows each, as DRIVE writes them: poses relative
    to each window start in its body frame, yaw the difference of wrapped world yaws, ICP held 2 samples."""
    dt = 1.0 / rate
    nwin = len(steps) * 3
    # window i covers poses i*(K-1) .. i*(K-1)+K-1: it starts on the previous window's last pose, which
    # is what chaining assumes (DRIVE itself leaves one 50 ms interval out between windows)
    n = nwin * (WINDOW - 1) + 1
    win_of = np.minimum(np.arange(n) // (WINDOW - 1), nwin - 1)
    v = np.array([steps[i // 3][0] for i in win_of])
    w = np.array([steps[i // 3][1] for i in win_of])
    pose = np.zeros((n, 3))
    pose[0] = [1.0, -2.0, 3.0]  # a world start near the yaw wrap
    for k in range(1, n):  # exact constant-twist arcs
        pose[k] = se2_compose(pose[k - 1], _exp(v[k] * dt, w[k] * dt))
    world = pose.copy()
    if hold_icp:  # ICP at 10 Hz: every odd sample repeats the previous one
        world[1::2] = world[0::2]
    rows = []
    for i in range(nwin):
        sl = slice(i * (WINDOW - 1), i * (WINDOW - 1) + WINDOW)
        start = world[sl.start]
        c, s = np.cos(start[2]), np.sin(start[2])
        d = world[sl, :2] - start[:2]
        rel_x, rel_y = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
        rel_yaw = _wrap(world[sl, 2]) - _wrap(start[2])  # not wrapped: may jump by 2 pi
        row = {"calib_step": float(i // 3)}
        vv, ww = steps[i // 3]
        for k in range(WINDOW):
            row[f"cmd_left_{k}"] = (vv - ww * B_CMD / 2) / R_CMD
            row[f"cmd_right_{k}"] = (vv + ww * B_CMD / 2) / R_CMD
            row[f"left_wheel_vel_{k}"] = (vv - ww * 0.55 / 2) / 0.165
            row[f"right_wheel_vel_{k}"] = (vv + ww * 0.55 / 2) / 0.165
            row[f"icp_x_{k}"], row[f"icp_y_{k}"], row[f"icp_yaw_{k}"] = rel_x[k], rel_y[k], rel_yaw[k]
        rows.append(row)
    return pd.DataFrame(rows), pose, world


def _exp(dx, dth):
    if abs(dth) < 1e-12:
        return np.array([dx, 0.0, 0.0])
    rad = dx / dth
    return np.array([rad * np.sin(dth), rad * (1 - np.cos(dth)), dth])


def test_windows_chain_back_exactly_with_yaw_wraps_and_no_holes(tmp_path):
    # 4-window and 2-window "steps" (a window labelled with the step at its first sample) must not leave
    # holes: every window gets the next 2 s slot
    steps = [(0.5, 0.4), (0.3, -1.2), (-0.4, 0.9), (0.6, 0.0), (0.2, 1.5)]
    df, pose, world = drive_like_frame(steps, hold_icp=False)
    df.loc[3, "calib_step"] = 0.0  # step 0 "has 4 windows", step 1 "has 2"
    seqs = windows_to_sequences(df, tmp_path / "husky_windows.parquet", 20.0, (1.0, 0.0, 0.0), "husky")
    gt = seqs[0]["tables"]["gt_pose"]
    stamps = gt["stamp_ns"].to_numpy()
    assert np.all(np.diff(stamps) == 50_000_000)  # contiguous: no hole
    # expected: the world poses expressed in the first pose's frame; chaining drops the one 50 ms between
    # windows, so compare against the same construction done by hand
    first = world[0]
    c, s = np.cos(first[2]), np.sin(first[2])
    d = world[:, :2] - first[:2]
    exp = np.column_stack(
        [c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], np.unwrap(world[:, 2]) - first[2]]
    )
    got = gt[["x", "y", "yaw"]].to_numpy()
    # window w+1 starts at window w's last pose: sample k of window w is world[k + w*(WINDOW-1)]
    n_win = len(got) // WINDOW  # the train block's windows (the first ones)
    idx = np.concatenate([np.arange(WINDOW) + w * (WINDOW - 1) for w in range(n_win)])
    assert n_win >= 6
    np.testing.assert_allclose(got, exp[idx], atol=1e-9)


def test_held_icp_samples_are_dropped_but_standstill_is_no_gap():
    rel = np.zeros((2, WINDOW, 3))
    rel[0, :, 0] = np.repeat(np.arange(WINDOW // 2), 2) * 0.1  # moving, each value held twice
    keep = fresh_samples(rel, keep_every=4)
    assert keep[:WINDOW].sum() == WINDOW // 2  # only the updates
    second = np.flatnonzero(keep[WINDOW:])
    assert second[0] == 0 and np.max(np.diff(second)) == 4  # standing still: every 4th sample kept


def test_command_convention_is_converted_back_to_body_twist(tmp_path):
    steps = [(0.1, 0.2), (-0.15, -0.1), (0.12, -0.2), (0.05, 0.25), (-0.1, 0.15), (0.9, 1.5), (-0.9, -1.8)]
    df, _, _ = drive_like_frame(steps)
    cl = df[[f"cmd_left_{k}" for k in range(WINDOW)]].to_numpy()
    cr = df[[f"cmd_right_{k}" for k in range(WINDOW)]].to_numpy()
    ml = df[[f"left_wheel_vel_{k}" for k in range(WINDOW)]].to_numpy()
    mr = df[[f"right_wheel_vel_{k}" for k in range(WINDOW)]].to_numpy()
    gs, gd, n = command_gain(cl, cr, ml, mr)
    assert n >= 5 and abs(gs - R_CMD / 0.165) < 1e-6  # the mismatch is measured
    seqs = windows_to_sequences(
        df,
        tmp_path / "husky_windows.parquet",
        20.0,
        (1.0, 0.0, 0.0),
        "husky",
        cmd_kinematics=(R_CMD, B_CMD),
        cmd_limits=(1.0, 1.6),
    )
    assert all("cmd_wheels" not in q["tables"] for q in seqs)
    cmd = pd.concat([q["tables"]["cmd_vel"] for q in seqs])  # contiguous blocks, in order
    v = np.repeat([s[0] for s in steps], 3 * WINDOW)
    w = np.clip(np.repeat([s[1] for s in steps], 3 * WINDOW), -1.6, 1.6)
    np.testing.assert_allclose(cmd["linear_x"], v, atol=1e-12)
    np.testing.assert_allclose(cmd["angular_z"], w, atol=1e-12)
