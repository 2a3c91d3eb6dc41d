"""The dataset card: the paper's Table I columns for a split dataset, next to the paper's own rows.

Per terrain and split (all its sequences together), over valid samples only:
- duration (s): valid samples x 1/rate; traversed distance (m): sum of |dp| between consecutive valid
  samples; absolute rotation (deg x 10^3): sum of |dyaw|;
- linear velocity (m/s): mean and std of sqrt(vx^2 + vy^2); angular velocity (deg/s): of |wz|;
- wheel slip velocity (m/s), our definition (the paper does not give one): per side, the wheel's
  surface speed minus the ground speed of that side's contact line, |r w_side - (vx -/+ wz B/2)|,
  averaged over the two sides; w_side is the encoder rate when the split has one, else the commanded
  rate (the "commanded-from-wheels" velocity).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from skidbench.pipeline.core.robot import Robot
from skidbench.pipeline.core.schema import list_split_files, read_split
from skidbench.pipeline.splits.table1 import PAPER_TABLE_I

COLUMNS = ["duration_s", "distance_m", "abs_rotation_kdeg", "lin_mean", "lin_std", "ang_mean", "ang_std",
           "slip_mean", "slip_std"]  # fmt: skip


def slip_velocity(df: pd.DataFrame, robot: Robot) -> np.ndarray:
    """Wheel slip velocity (m/s) per sample (module docstring)."""
    has_enc = df["enc_wl"].notna() & df["enc_wr"].notna()
    wl = np.where(has_enc, df["enc_wl"].fillna(0.0), df["cmd_wl"])
    wr = np.where(has_enc, df["enc_wr"].fillna(0.0), df["cmd_wr"])
    half_b = robot.track_width / 2.0
    vl = df["vx"].to_numpy() - df["wz"].to_numpy() * half_b
    vr = df["vx"].to_numpy() + df["wz"].to_numpy() * half_b
    r = robot.wheel_radius
    return 0.5 * (np.abs(r * wl - vl) + np.abs(r * wr - vr))


def table_stats(frames: list[pd.DataFrame], robot: Robot, rate_hz: float) -> dict[str, float]:
    """Table I's columns over several sequences' split tables."""
    dist = rot = 0.0
    lin, ang, slip = [], [], []
    n_valid = 0
    for df in frames:
        v = df["valid"].to_numpy(bool)
        both = v[1:] & v[:-1]
        dist += float(np.hypot(np.diff(df["x"]), np.diff(df["y"]))[both].sum())
        rot += float(np.abs(np.diff(df["yaw"]))[both].sum())
        n_valid += int(v.sum())
        lin.append(np.hypot(df["vx"], df["vy"])[v])
        ang.append(np.degrees(np.abs(df["wz"]))[v])
        slip.append(slip_velocity(df, robot)[v])
    lin, ang, slip = (np.concatenate(a) if a else np.array([]) for a in (lin, ang, slip))

    def ms(a):
        return (float(a.mean()), float(a.std())) if len(a) else (float("nan"), float("nan"))

    return dict(
        zip(
            COLUMNS,
            [n_valid / rate_hz, dist, np.degrees(rot) / 1e3, *ms(lin), *ms(ang), *ms(slip)],
            strict=True,
        )
    )


def dataset_card(splits_root: Path, robot: Robot, paper: bool = True, files: list[Path] | None = None) -> str:
    """Markdown: our Table I per terrain and split, and the paper's rows. ``files``: the split files (the
    current manifest's, :meth:`Layout.split_files`); default every split file under ``splits_root``."""
    groups: dict[tuple[str, str], list[pd.DataFrame]] = {}
    rate = 30.0
    for path in list_split_files(splits_root) if files is None else files:
        df, meta = read_split(path)
        rate = float(meta.get("rate_hz", rate))
        groups.setdefault(
            (meta.get("split", path.parent.name), meta.get("terrain", path.parent.parent.name)), []
        ).append(df)
    head = (
        "| Category | Terrain | Name | Duration (s) | Distance (m) | Abs. rotation (deg x1e3) "
        "| Lin. vel. mean (m/s) | Lin. vel. std | Ang. vel. mean (deg/s) | Ang. vel. std "
        "| Slip vel. mean (m/s) | Slip vel. std |"
    )
    sep = "|" + "---|" * 12
    order = {"train": 0, "cv": 1, "ld": 2}
    rows = []
    for (split, terrain), frames in sorted(groups.items(), key=lambda kv: (order.get(kv[0][0], 9), kv[0][1])):
        s = table_stats(frames, robot, rate)
        rows.append(
            f"| {split} | {terrain} | {len(frames)} seq | {s['duration_s']:.0f} | {s['distance_m']:.1f} | "
            f"{s['abs_rotation_kdeg']:.2f} | {s['lin_mean']:.2f} | {s['lin_std']:.2f} | "
            f"{s['ang_mean']:.1f} | "
            f"{s['ang_std']:.1f} | {s['slip_mean']:.3f} | {s['slip_std']:.3f} |"
        )
    note = (
        f"Robot: {robot.name}. Valid samples only; slip velocity = mean over sides of "
        "|r w_side - v_side| (pipeline/splits/card.py)."
    )
    text = [f"# Dataset card: {splits_root.parent.name}", "", note, "", head, sep, *rows]
    if not rows:
        text.append("| (no split files) |" + " |" * 11)
    if paper:
        text += ["", "## The paper's Table I (Rabiee & Biswas 2019, Jackal)", "", head, sep]
        for r in PAPER_TABLE_I:
            text.append("| " + " | ".join(str(v) for v in r) + " |")
    return "\n".join(text) + "\n"
