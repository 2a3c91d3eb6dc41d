"""The paper's h-second horizon error (SPEC.md "Evaluation"), for all windows at once in O(T).

A model's velocities depend only on the inputs, so one dead-reckoned trajectory D (from the identity)
serves every window: the prediction for the window [i, i+n] is ``gt[i] (+) (D[i]^-1 (+) D[i+n])``,
which equals integrating the same velocities from gt[i] (exact SE(2) steps, left-point rule).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from skidbench.pipeline.errors import SkidbenchError
from skidbench.pipeline.geometry import integrate_body_velocity, se2_compose, se2_relative


class EvaluationError(SkidbenchError):
    pass


@dataclass(frozen=True)
class HorizonConfig:
    horizon_s: float = 6.0
    min_distance_m: float = 0.5  # windows that travel less are left out of the translational metric
    min_rotation_rad: float = np.deg2rad(10.0)  # ... that turn less, out of the rotational metric


#: the columns of :func:`window_errors`, in order
WINDOW_COLUMNS = (
    "start",
    "t0",
    "distance",
    "rotation",
    "trans_err",
    "rot_err",
    "rel_trans",
    "rel_rot",
    "end",
    "pred_x",
    "pred_y",
    "pred_yaw",
)


def horizon_steps(t: np.ndarray, horizon_s: float) -> int:
    """Number of steps in the horizon for a uniform clock ``t`` (s)."""
    if len(t) < 2:
        return 0
    dt = float(np.median(np.diff(t)))
    return int(round(horizon_s / dt))


def window_errors(
    t: np.ndarray,
    gt_pose: np.ndarray,
    velocity: np.ndarray,
    horizon_s: float,
    valid: np.ndarray | None = None,
    cfg: HorizonConfig | None = None,
) -> pd.DataFrame:
    """Errors of every window with a full horizon in one sequence.

    t: (T,) s, uniform clock. gt_pose: (T, 3) ground truth (x, y, unwrapped yaw). velocity: (T, 3) the
    model's (vx, vy, wz). valid: (T,) bool; windows touching an invalid sample are dropped.
    Returns one row per window: ``start`` (index), ``t0``, ``distance`` (m travelled, ground truth),
    ``rotation`` (rad turned, absolute), ``trans_err`` (m), ``rot_err`` (rad, signed: true - predicted),
    ``rel_trans``, ``rel_rot`` (NaN where the window is under the minimum distance / rotation), then the
    details: ``end`` (index), ``pred_x``, ``pred_y``, ``pred_yaw`` (predicted pose at the window's end).
    """
    cfg = cfg or HorizonConfig(horizon_s=horizon_s)
    t = np.asarray(t, dtype=float)
    gt_pose = np.asarray(gt_pose, dtype=float)
    velocity = np.asarray(velocity, dtype=float)
    T = len(t)
    n = horizon_steps(t, horizon_s)
    if n < 1 or T <= n:
        return pd.DataFrame({c: np.array([], dtype=float) for c in WINDOW_COLUMNS})
    dt = np.diff(t)
    dead = integrate_body_velocity(np.zeros(3), velocity[:-1], dt)  # (T, 3)
    starts = np.arange(T - n)
    ends = starts + n
    rel = se2_relative(dead[starts], dead[ends])
    pred = se2_compose(gt_pose[starts], rel)
    pos_err = np.hypot(gt_pose[ends, 0] - pred[:, 0], gt_pose[ends, 1] - pred[:, 1])
    rot_err = gt_pose[ends, 2] - pred[:, 2]
    step_len = np.hypot(np.diff(gt_pose[:, 0]), np.diff(gt_pose[:, 1]))
    step_rot = np.abs(np.diff(gt_pose[:, 2]))
    cum_len = np.concatenate([[0.0], np.cumsum(step_len)])
    cum_rot = np.concatenate([[0.0], np.cumsum(step_rot)])
    distance = cum_len[ends] - cum_len[starts]
    rotation = cum_rot[ends] - cum_rot[starts]
    keep = np.ones(len(starts), dtype=bool)
    if valid is not None:
        bad = np.concatenate([[0], np.cumsum(~np.asarray(valid, dtype=bool))])
        keep = (bad[ends + 1] - bad[starts]) == 0
    with np.errstate(divide="ignore", invalid="ignore"):
        rel_trans = np.where(distance >= cfg.min_distance_m, pos_err / distance, np.nan)
        rel_rot = np.where(rotation >= cfg.min_rotation_rad, np.abs(rot_err) / rotation, np.nan)
    out = pd.DataFrame(
        {
            "start": starts,
            "t0": t[starts],
            "distance": distance,
            "rotation": rotation,
            "trans_err": pos_err,
            "rot_err": rot_err,
            "rel_trans": rel_trans,
            "rel_rot": rel_rot,
            "end": ends,
            "pred_x": pred[:, 0],
            "pred_y": pred[:, 1],
            "pred_yaw": pred[:, 2],
        }
    )
    return out[keep].reset_index(drop=True)


def naive_window_errors(
    t: np.ndarray, gt_pose: np.ndarray, velocity: np.ndarray, horizon_s: float
) -> np.ndarray:
    """Reference: integrate every window separately from its ground-truth start, O(T*h).
    Returns predicted end poses (W, 3). Used by tests and ``make bench`` only."""
    t = np.asarray(t, dtype=float)
    n = horizon_steps(t, horizon_s)
    out = []
    for i in range(len(t) - n):
        traj = integrate_body_velocity(gt_pose[i], velocity[i : i + n], np.diff(t[i : i + n + 1]))
        out.append(traj[-1])
    return np.array(out).reshape(-1, 3)


def window_trajectory(
    t: np.ndarray, gt_pose: np.ndarray, velocity: np.ndarray, start: int, horizon_s: float
) -> np.ndarray:
    """The predicted trajectory (n+1, 3) of one window, integrated from the ground truth at ``start``
    (the same steps :func:`window_errors` composes; for plots such as the paper's Fig. 7)."""
    t = np.asarray(t, dtype=float)
    n = horizon_steps(t, horizon_s)
    if n < 1 or start + n >= len(t):
        raise EvaluationError(f"window at sample {start} has no full {horizon_s:g} s horizon")
    vel = np.asarray(velocity, dtype=float)[start : start + n]
    return integrate_body_velocity(
        np.asarray(gt_pose, dtype=float)[start], vel, np.diff(t[start : start + n + 1])
    )


def rmsre(rel: np.ndarray) -> float:
    """Root mean square of relative errors, ignoring NaN (windows left out of the metric)."""
    rel = np.asarray(rel, dtype=float)
    rel = rel[np.isfinite(rel)]
    if rel.size == 0:
        return float("nan")
    return float(np.sqrt(np.mean(rel**2)))


def count_windows(tables, horizon_s: float) -> tuple[int, int, int]:
    """``(windows, sequences, too_short)`` for split tables (each with ``t`` and ``valid``): the windows
    of ``horizon_s`` with a full horizon of valid samples (those :func:`window_errors` scores, before the
    minimum distance/rotation), the number of sequences, and how many of them are shorter than the
    horizon (no window at all)."""
    total = short = n_seq = 0
    for df in tables:
        n_seq += 1
        t = df["t"].to_numpy(float)
        n = horizon_steps(t, horizon_s)
        if n < 1 or len(t) <= n:
            short += 1
            continue
        bad = np.concatenate([[0], np.cumsum(~df["valid"].to_numpy(bool))])
        starts = np.arange(len(t) - n)
        total += int(((bad[starts + n + 1] - bad[starts]) == 0).sum())
    return total, n_seq, short
