"""Synthetic split-like tables for tests, benchmarks and examples (no dataset needed).

``command_table`` draws smooth random commanded body velocities (sums of sinusoids), converts them to wheel
rates with the ideal inverse kinematics and differentiates analytically; ``label_with`` fills the
ground-truth columns (vx, vy, wz and the integrated pose) from a model's prediction, so that fitting that
model on the table must recover its parameters.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from skidbench.pipeline.core.geometry import integrate_body_velocity, step_velocities
from skidbench.pipeline.core.schema import SPLIT_COLUMNS, write_split


def command_table(
    robot, n: int = 2000, seed: int = 0, rate_hz: float = 30.0, v_max: float = 1.5, w_max: float = 2.0
) -> pd.DataFrame:
    """A split table (all ``SPLIT_COLUMNS``) of ``n`` rows of smooth commands; ground truth = commands."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate_hz
    v = np.zeros(n)
    dv = np.zeros(n)
    w = np.zeros(n)
    dw = np.zeros(n)
    for k in range(4):
        fv, fw = rng.uniform(0.01, 0.1, 2) * (k + 1)
        av, aw = rng.uniform(0.2, 1.0, 2) / (k + 1)
        pv, pw = rng.uniform(0, 2 * np.pi, 2)
        v += av * np.sin(2 * np.pi * fv * t + pv)
        dv += av * 2 * np.pi * fv * np.cos(2 * np.pi * fv * t + pv)
        w += aw * np.sin(2 * np.pi * fw * t + pw)
        dw += aw * 2 * np.pi * fw * np.cos(2 * np.pi * fw * t + pw)
    sv = v_max / max(np.max(np.abs(v)), 1e-9)
    sw = w_max / max(np.max(np.abs(w)), 1e-9)
    v, dv, w, dw = v * sv, dv * sv, w * sw, dw * sw
    wl, wr = robot.wheel_rates_from_twist(v, w)
    dwl, dwr = robot.wheel_rates_from_twist(dv, dw)
    df = pd.DataFrame(
        {
            "t": t,
            "stamp_ns": (t * 1e9).astype(np.int64),
            "cmd_v": v,
            "cmd_w": w,
            "cmd_wl": wl,
            "cmd_wr": wr,
            "cmd_dwl": dwl,
            "cmd_dwr": dwr,
            "enc_wl": np.full(n, np.nan),
            "enc_wr": np.full(n, np.nan),
            "x": 0.0,
            "y": 0.0,
            "yaw": 0.0,
            "vx": v,
            "vy": 0.0,
            "wz": w,
            "valid": True,
        }
    )
    return label_with(df[list(SPLIT_COLUMNS)], np.column_stack([v, np.zeros(n), w]))


def label_with(table: pd.DataFrame, velocities: np.ndarray) -> pd.DataFrame:
    """Copy of ``table`` with ground truth set to ``velocities`` (T, 3) = (vx m/s, vy m/s, wz rad/s) and the
    pose (x m, y m, unwrapped yaw rad) dead-reckoned from them, starting at the origin.

    The step ``[t_i, t_i+1]`` moves with the mean of rows ``i`` and ``i+1``'s velocities, an exact SE(2) step
    (:func:`~skidbench.pipeline.core.geometry.step_velocities`, the rule of the horizon evaluation), so a
    model
    that predicts ``velocities`` exactly has zero window error on the table."""
    df = table.copy()
    vel = np.asarray(velocities, dtype=float)
    df["vx"], df["vy"], df["wz"] = vel[:, 0], vel[:, 1], vel[:, 2]
    pose = integrate_body_velocity(np.zeros(3), step_velocities(vel), np.diff(df["t"].to_numpy(dtype=float)))
    df["x"], df["y"], df["yaw"] = pose[:, 0], pose[:, 1], pose[:, 2]
    return df


def write_train_splits(
    root, robot, terrains=("tile", "grass"), n: int = 600, chi: float = 1.5, dataset="sim-mini"
):
    """Write ``<root>/<dataset>/splits/<terrain>/train/<terrain>_train_0{0,1}.parquet`` (two sequences per
    terrain, labelled by an extended differential drive with ``chi``) and the manifest that lists them
    (``<root>/<dataset>/raw/manifest.json``: stages read their sequences from it). Returns ``root``."""
    from skidbench.models.kinematic.linear import ExtendedDifferentialDrive
    from skidbench.pipeline.core.manifest import Manifest, Sequence

    root = Path(root)
    seqs = []
    for k, terrain in enumerate(terrains):
        for i in range(2):
            tab = command_table(robot, n, seed=10 * k + i)
            tab = label_with(tab, ExtendedDifferentialDrive(robot, {"chi": chi}).predict(tab))
            seq = f"{terrain}_train_{i:02d}"
            meta = {
                "sequence": seq,
                "terrain": terrain,
                "split": "train",
                "robot": robot.name,
                "sources": {},
                "rate_hz": 30.0,
            }
            write_split(tab, root / dataset / "splits" / terrain / "train" / f"{seq}.parquet", meta)
            seqs.append(Sequence(seq, terrain, "train", f"{seq}.bag"))
    raw = root / dataset / "raw"
    Manifest(seqs, robot=robot.name, base=raw).write(raw / "manifest.json")
    return root
