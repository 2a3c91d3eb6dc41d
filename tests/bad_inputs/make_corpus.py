"""Generate the bad-input corpus: ``python tests/bad_inputs/make_corpus.py <folder>`` (the tests call
:func:`make` into a temporary folder). Every file is tiny and derived from synthetic data; the DRIVE frame
imitates the zero timestamps of ../shared/data/real/drive/ without copying it.

The expected outcome of each file is stated in ONE table: ``CASES`` in tests/test_reliability_bad_inputs.py.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd


def _pose_table(n: int = 50, rate: float = 20.0, t0_ns: int = 1_000_000_000) -> pd.DataFrame:
    t = t0_ns + (np.arange(n) * 1e9 / rate).astype(np.int64)
    yaw = np.linspace(0.0, 0.5, n)
    return pd.DataFrame(
        {
            "stamp_ns": t, "bag_time_ns": t,
            "x": np.linspace(0.0, 2.0, n), "y": np.zeros(n), "z": np.zeros(n),
            "qx": np.zeros(n), "qy": np.zeros(n), "qz": np.sin(yaw / 2), "qw": np.cos(yaw / 2),
        }
    )  # fmt: skip


def _tum_rows(n: int = 40, t0: float = 100.0, rate: float = 10.0, unit_ns: bool = False) -> list[str]:
    rows = []
    for i in range(n):
        t = t0 + i / rate
        stamp = f"{int(round(t * 1e9))}" if unit_ns else f"{t:.6f}"
        rows.append(f"{stamp} 0 0 {0.05 * i:.6f} 0 0 0 1")  # camera z-forward: driving forwards
    return rows


def _amrl(n: int, t0: float = 0.0, rate: float = 20.0) -> tuple[list[str], list[str]]:
    cmd = [f"0.5,0,0,0,0,0.2,{t0 + i / rate:.4f}" for i in range(n)]
    loc = [f"{t0 + i / rate:.4f},{0.025 * i:.4f},0,{0.01 * i:.4f}" for i in range(n)]
    return cmd, loc


def _drive_raw(n_steps: int = 3, per_step: int = 20) -> pd.DataFrame:
    n = n_steps * per_step
    t = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 50_000_000
    yaw = np.linspace(0.0, 0.3, n)
    return pd.DataFrame(
        {
            "ros_time": t.astype(float), "cmd_vel_x": np.full(n, 0.5), "cmd_vel_omega": np.full(n, 0.1),
            "meas_left_vel": np.full(n, 4.0), "meas_right_vel": np.full(n, 5.0),
            "calib_step": np.repeat(np.arange(n_steps), per_step).astype(float),
            "icp_pos_x": np.linspace(0, 3, n), "icp_pos_y": np.zeros(n), "icp_pos_z": np.zeros(n),
            "icp_quat_x": np.zeros(n), "icp_quat_y": np.zeros(n),
            "icp_quat_z": np.sin(yaw / 2), "icp_quat_w": np.cos(yaw / 2),
        }
    )  # fmt: skip


HUSKY = (0.165, 0.55)  # the Husky's spec sheet (wheel radius, track width)
STEPS = [(0.5, 0.0), (0.6, 0.05), (-0.4, 0.0), (0.3, 0.4), (0.7, -0.05), (0.5, 0.0)]


def _drive_windows(cmd_kin=(0.3, 1.08), gain: float = 1.0, icp: str = "moves", wheels: bool = True):
    """A small window-form frame (DRIVE's torch_ready blocks) of a Husky driving ``STEPS`` (v, w), three
    2 s windows of 40 samples at 20 Hz each. Commands: the steps converted to wheel rates with ``cmd_kin``
    (DRIVE's configured [r, B]); encoders: ``gain`` x the Husky's own wheel rates of the steps (settled at
    once); ICP: the pose relative to each window start (``icp``: ``moves``, ``still`` (millimetre noise:
    lifted off the ground) or ``constant`` (ICP did not run))."""
    rng = np.random.default_rng(1)
    rows = []
    for i in range(3 * len(STEPS)):
        v, w = STEPS[i // 3]
        t = np.arange(40) / 20.0
        yaw = w * t
        x = np.where(abs(w) > 1e-9, v / (w if w else 1) * np.sin(yaw), v * t)
        y = np.where(abs(w) > 1e-9, v / (w if w else 1) * (1 - np.cos(yaw)), 0.0)
        if icp == "still":
            x, y, yaw = (rng.normal(0, 1e-3, 40) for _ in range(3))
        elif icp == "constant":
            x, y, yaw = np.zeros(40), np.zeros(40), np.zeros(40)
        row = {"calib_step": float(i // 3)}
        for k in range(40):
            row[f"cmd_left_{k}"] = (v - w * cmd_kin[1] / 2) / cmd_kin[0]
            row[f"cmd_right_{k}"] = (v + w * cmd_kin[1] / 2) / cmd_kin[0]
            row[f"left_wheel_vel_{k}"] = gain * (v - w * HUSKY[1] / 2) / HUSKY[0] if wheels else 0.0
            row[f"right_wheel_vel_{k}"] = gain * (v + w * HUSKY[1] / 2) / HUSKY[0] if wheels else 0.0
            row[f"icp_x_{k}"], row[f"icp_y_{k}"], row[f"icp_yaw_{k}"] = x[k], y[k], yaw[k]
        rows.append(row)
    return pd.DataFrame(rows)


class _RunsCode:
    """Pickled as a call of ``os.system``: what an unpickler must never look up."""

    def __reduce__(self):
        import os

        return (os.system, ("true",))


def _drive(out: Path) -> None:
    """DRIVE files of every new form and failure (the window cases from :func:`_drive_windows`)."""
    import pickle

    _drive_windows(cmd_kin=HUSKY, gain=0.956).to_parquet(out / "drive_deflated_windows.parquet")
    _drive_windows(icp="still").to_parquet(out / "drive_lifted_windows.parquet")
    _drive_windows(icp="constant").to_parquet(out / "drive_constant_icp_windows.parquet")
    _drive_windows(wheels=False).to_parquet(out / "drive_zero_wheels_windows.parquet")
    _drive_windows().to_pickle(out / "drive_torch_ready_dataframe.pkl")
    raw = _drive_raw()
    text = raw.astype(str).assign(ros_time=raw["ros_time"].astype(np.int64).astype(str), calib_state="calib")
    head = pd.DataFrame({c: ["0.0"] for c in text.columns})  # DRIVE's logger: text, a zero first row
    pd.concat([head, text], ignore_index=True).to_pickle(out / "drive_raw_dataframe.pkl")
    raw.drop(columns=["cmd_vel_x", "cmd_vel_omega"]).to_parquet(out / "drive_no_commands_raw.parquet")
    lifted = _drive_raw(n_steps=6)
    lifted[["icp_pos_x", "icp_pos_y"]] = np.random.default_rng(2).normal(0, 1e-3, (len(lifted), 2))
    lifted.to_parquet(out / "drive_lifted_raw.parquet")
    (out / "drive_unsafe.pkl").write_bytes(pickle.dumps({"frame": raw, "x": _RunsCode()}))
    (out / "drive_not_a_frame.pkl").write_bytes(pickle.dumps(raw["cmd_vel_x"].to_numpy()))


def _bags(out: Path) -> None:
    from skidbench.pipeline.extract.synthetic import JACKAL_TOPICS, write_bag

    good = write_bag(out / "bag_good.bag", "ros1", 0.5)
    data = good.read_bytes()
    (out / "bag_truncated.bag").write_bytes(data[: len(data) // 2])
    rng = np.random.default_rng(0)
    corrupt = bytearray(data)
    corrupt[64:4096] = rng.integers(0, 256, 4096 - 64, dtype=np.uint8).tobytes()
    (out / "bag_corrupt.bag").write_bytes(bytes(corrupt))
    (out / "bag_not_a_bag.bag").write_text("this is not a bag\n")
    wrong = {**JACKAL_TOPICS, "/joint_states": ("sensor_msgs/msg/Imu", 20.0)}
    write_bag(out / "bag_wrong_type.bag", "ros1", 0.5, wrong)
    missing = {k: v for k, v in JACKAL_TOPICS.items() if k != "/cmd_vel"}
    write_bag(out / "bag_missing_topic.bag", "ros1", 0.5, missing)
    blind = {k: v for k, v in JACKAL_TOPICS.items() if "Image" not in v[0] and "Odometry" not in v[0]}
    write_bag(out / "bag_no_ground_truth_source.bag", "ros1", 0.5, blind)  # no camera, no pose topic
    good.unlink()


def make(out: Path) -> dict[str, Path]:
    """Write every corpus file under ``out``; returns name -> path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    _bags(out)

    # pose tables (groundtruth.method=pose_topic)
    p = _pose_table()
    p.iloc[::-1].reset_index(drop=True).to_parquet(out / "pose_reversed.parquet")
    d = p.copy()
    d.loc[10, ["stamp_ns", "bag_time_ns"]] = d.loc[9, "stamp_ns"]
    d.to_parquet(out / "pose_duplicated.parquet")
    nan = p.copy()
    nan.loc[20:22, "x"] = np.nan
    nan.to_parquet(out / "pose_nan.parquet")
    inf = p.copy()
    inf.loc[30, "qw"] = np.inf
    inf.to_parquet(out / "pose_inf.parquet")
    alln = p.copy()
    alln["x"] = np.nan
    alln.to_parquet(out / "pose_all_nan.parquet")
    gap = p.copy()
    gap.loc[25:, ["stamp_ns", "bag_time_ns"]] += 3_000_000_000
    gap.to_parquet(out / "pose_time_gap.parquet")
    p.iloc[:0].to_parquet(out / "pose_empty.parquet")
    p.iloc[:1].to_parquet(out / "pose_one_row.parquet")
    p.drop(columns=["qx", "qy", "qz", "qw"]).to_parquet(out / "pose_no_orientation.parquet")

    # ORB-SLAM files
    (out / "orb_tum_ok.txt").write_text("\n".join(_tum_rows()) + "\n")
    (out / "orb_euroc_ns.txt").write_text("\n".join(_tum_rows(unit_ns=True)) + "\n")
    (out / "orb_wrong_columns.txt").write_text("\n".join(r + " 0 0" for r in _tum_rows()) + "\n")
    (out / "orb_empty.txt").write_text("# ORB-SLAM lost tracking at once\n")
    jump = _tum_rows()
    jump[20:] = [f"{100.0 + i / 10:.6f} 0 0 {50 + 0.05 * i:.6f} 0 0 0 1" for i in range(20, 40)]
    (out / "orb_tracking_reset.txt").write_text("\n".join(jump) + "\n")
    kitti = ["1 0 0 0 0 1 0 0 0 0 1 %.3f" % (0.05 * i) for i in range(10)]
    text_row = _tum_rows()
    text_row[6] = text_row[6].replace(" 0 0 0 1", " 0 0 zero 1")  # an 8-field row with a non-number
    (out / "orb_non_numeric.txt").write_text("\n".join(text_row) + "\n")
    (out / "kitti_no_times.txt").write_text("\n".join("1 0 0 0 0 1 0 0 0 0 1 0" for _ in range(5)) + "\n")
    (out / "kitti_poses.txt").write_text("\n".join(kitti) + "\n")
    (out / "kitti_poses.times.txt").write_text("\n".join(str(int(1e9 * (5 + i / 10))) for i in range(10)))
    (out / "kitti_short.txt").write_text("\n".join(kitti) + "\n")
    (out / "kitti_short.times.txt").write_text("\n".join(f"{5 + i / 10:.2f}" for i in range(7)))
    # a written ground-truth TUM file with a short row
    bad_tum = _tum_rows(5)
    bad_tum[2] = "100.2 0 0 0.1 0 0"
    (out / "gt_bad_row.tum").write_text("\n".join(bad_tum) + "\n")

    # AMRL text files (cmd: v_x,v_y,v_z,w_x,w_y,w_z,t; loc: t,x,y,yaw)
    def amrl(name: str, cmd: list[str], loc: list[str]) -> None:
        (out / f"amrl_{name}_cmd.txt").write_text("\n".join(cmd) + ("\n" if cmd else ""))
        (out / f"amrl_{name}_loc.txt").write_text("\n".join(loc) + ("\n" if loc else ""))

    cmd, loc = _amrl(100)
    amrl("mismatched_lengths", cmd, loc[:50])  # loc ends 2.5 s before cmd
    amrl("no_overlap", cmd[:40], [f"{10 + i / 20:.4f},0,0,0" for i in range(40)])
    amrl("wrong_columns", cmd[:10] + ["0.5,0,0,0,0.2,1.0"] + cmd[11:], loc)
    amrl("reversed", list(reversed(cmd)), loc)
    amrl("duplicated", cmd[:10] + [cmd[9]] + cmd[10:], loc)
    amrl("empty", [], loc)
    amrl("nan_time", cmd[:5] + ["0.5,0,0,0,0,0.2,nan"] + cmd[6:], loc)

    # DRIVE raw frames (real Husky data has rows with ros_time == 0; here a small synthetic frame)
    df = _drive_raw()
    z = df.copy()
    z.loc[[0, 1, 2, 41], "ros_time"] = 0.0
    z.to_parquet(out / "drive_zero_timestamps_raw.parquet")
    allz = df.copy()
    allz["ros_time"] = 0.0
    allz.to_parquet(out / "drive_all_zero_raw.parquet")
    back = df.copy()
    back.loc[30, "ros_time"] = back.loc[10, "ros_time"]
    back.to_parquet(out / "drive_reversed_raw.parquet")
    df.to_parquet(out / "drive_ok_raw.parquet")
    data = (out / "drive_ok_raw.parquet").read_bytes()
    (out / "drive_truncated_raw.parquet").write_bytes(data[: len(data) // 2])
    (out / "drive_ok_raw.parquet").unlink()
    _drive(out)
    return {p.name: p for p in sorted(out.iterdir())}


if __name__ == "__main__":
    for name in make(Path(sys.argv[1] if len(sys.argv) > 1 else "bad_inputs_corpus")):
        print(name)
