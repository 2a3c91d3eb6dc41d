"""The paper's h-second horizon error (SPEC.md "Evaluation"), for all windows at once in O(T).

A model's velocities depend only on the inputs, so one dead-reckoned trajectory D (from the identity)
serves every window: the prediction for the window [i, i+n] is ``gt[i] (+) (D[i]^-1 (+) D[i+n])``,
which equals integrating the same velocities from gt[i]: exact SE(2) steps of constant twist, the
twist of step [t_k, t_k+1] the mean of the velocities at its two ends (``geometry.step_velocities``, the
trapezoidal rule). The left-point rule (the velocity at t_k over the whole step) costs 0.4-0.8 % RMSRE
at 30 Hz even on the simulator's exact truth (the floor, benchmark/scoring/floor.py); the trapezoidal one
0.005-0.03 %.

A model that returns a predictive covariance of its velocities (``predict_cov``) also gets its pose
uncertainty scored: :func:`window_pose_covariance` propagates the velocity covariance along every window
(first-order SE(2) propagation, O(T) by prefix sums like the mean), and :func:`uncertainty_scores`
gives the coverage of the 95 % region of the end position and yaw and the position's negative
log-likelihood.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.signal import savgol_filter

from skidbench.benchmark.errors import EvaluationError
from skidbench.pipeline.core.geometry import (
    integrate_body_velocity,
    se2_compose,
    se2_relative,
    step_velocities,
)

#: the horizon (s) the minimum distance and rotation are stated at: the paper's 6 s
MINIMUMS_AT_S = 6.0


@dataclass(frozen=True)
class HorizonConfig:
    """The board's horizon and the minimums a window must travel (``min_distance_m``) or turn
    (``min_rotation_rad``) to count in the translational / rotational metric, stated at the paper's 6 s
    horizon (:data:`MINIMUMS_AT_S`) and scaled in proportion at another (:meth:`minimums`)."""

    horizon_s: float = 6.0
    min_distance_m: float = 0.5  # windows that travel less are left out of the translational metric
    min_rotation_rad: float = np.deg2rad(10.0)  # ... that turn less, out of the rotational metric

    def minimums(self, horizon_s: float) -> tuple[float, float]:
        """``(distance m, rotation rad)`` a window of ``horizon_s`` must travel / turn: the stated minimums
        times ``horizon_s / 6 s``, i.e. the same mean speed and turn rate (0.5 m in 6 s is 0.083 m/s; a
        0.5 s window must travel 0.042 m). A fixed distance would leave out every short window of a robot
        that drives slower than ``min_distance_m / horizon_s`` and keep only its fastest ones."""
        k = float(horizon_s) / MINIMUMS_AT_S
        return self.min_distance_m * k, self.min_rotation_rad * k


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
    hcfg: HorizonConfig | None = None,
    velocity_cov: np.ndarray | None = None,
    autocorr: np.ndarray | None = None,
) -> pd.DataFrame:
    """Errors of every window with a full horizon in one sequence.

    t: (T,) s, uniform clock. gt_pose: (T, 3) ground truth (x, y, unwrapped yaw). velocity: (T, 3) the
    model's (vx, vy, wz). valid: (T,) bool; windows touching an invalid sample are dropped.
    Returns one row per window: ``start`` (index), ``t0``, ``distance`` (m travelled, ground truth),
    ``rotation`` (rad turned: the sum of |d yaw| of the smoothed yaw, :func:`smoothed_yaw`),
    ``trans_err`` (m), ``rot_err`` (rad, signed: true - predicted),
    ``rel_trans``, ``rel_rot`` (NaN where the window is under the minimum distance / rotation), then the
    details: ``end`` (index), ``pred_x``, ``pred_y``, ``pred_yaw`` (predicted pose at the window's end).
    With ``velocity_cov`` (T, 3, 3), the model's predictive covariance of (vx, vy, wz), and optionally
    its error ``autocorr`` (L, 3), the columns of :data:`UNCERTAINTY_COLUMNS` follow. ``hcfg``: the
    windows' minimum distance and rotation at ``horizon_s`` (:meth:`HorizonConfig.minimums`; default
    :class:`HorizonConfig`'s).
    """
    hcfg = hcfg or HorizonConfig(horizon_s=horizon_s)
    t = np.asarray(t, dtype=float)
    gt_pose = np.asarray(gt_pose, dtype=float)
    velocity = np.asarray(velocity, dtype=float)
    T = len(t)
    n = horizon_steps(t, horizon_s)
    if n < 1 or T <= n:
        return pd.DataFrame({c: np.array([], dtype=float) for c in WINDOW_COLUMNS})
    dt = np.diff(t)
    dead = integrate_body_velocity(np.zeros(3), step_velocities(velocity), dt)  # (T, 3)
    starts = np.arange(T - n)
    ends = starts + n
    rel = se2_relative(dead[starts], dead[ends])
    pred = se2_compose(gt_pose[starts], rel)
    pos_err = np.hypot(gt_pose[ends, 0] - pred[:, 0], gt_pose[ends, 1] - pred[:, 1])
    rot_err = gt_pose[ends, 2] - pred[:, 2]
    step_len = np.hypot(np.diff(gt_pose[:, 0]), np.diff(gt_pose[:, 1]))
    step_rot = np.abs(np.diff(smoothed_yaw(gt_pose[:, 2], valid)))
    cum_len = np.concatenate([[0.0], np.cumsum(step_len)])
    cum_rot = np.concatenate([[0.0], np.cumsum(step_rot)])
    distance = cum_len[ends] - cum_len[starts]
    rotation = cum_rot[ends] - cum_rot[starts]
    keep = np.ones(len(starts), dtype=bool)
    if valid is not None:
        bad = np.concatenate([[0], np.cumsum(~np.asarray(valid, dtype=bool))])
        keep = (bad[ends + 1] - bad[starts]) == 0
    min_distance, min_rotation = hcfg.minimums(horizon_s)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel_trans = np.where(distance >= min_distance, pos_err / distance, np.nan)
        rel_rot = np.where(rotation >= min_rotation, np.abs(rot_err) / rotation, np.nan)
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
    if velocity_cov is not None:
        cov = window_pose_covariance(dead, dt, velocity_cov, starts, ends, autocorr)
        err_xy = gt_pose[ends, :2] - pred[:, :2]
        scores = uncertainty_scores(err_xy, rot_err, cov, gt_pose[starts, 2] - dead[starts, 2])
        for k in UNCERTAINTY_COLUMNS:
            out[k] = scores[k]
    return out[keep].reset_index(drop=True)


#: the smoothing of the yaw behind the rotational denominator: the split's differentiator's defaults
#: (conf/split.yaml ``split.differentiator``, pipeline/splits/build.py), so the rotation a window counts
#: is the one its yaw rate integrates to, not the frame-to-frame jitter of the ground truth's heading
YAW_WINDOW, YAW_ORDER = 9, 3


def smoothed_yaw(yaw: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """(T,) the unwrapped yaw through the Savitzky-Golay filter (:data:`YAW_WINDOW` samples, order
    :data:`YAW_ORDER`) on each run of valid samples separately (a run shorter than the window as it is).
    0.1 deg of independent jitter per 30 Hz frame adds over 10 deg (the inclusion threshold) to the sum
    of |d yaw| over 6 s of a straight drive (19 deg); through the filter, 5 deg
    (tests/test_evaluate_horizon.py)."""
    yaw = np.asarray(yaw, dtype=float)
    out = yaw.copy()
    ok = np.ones(len(yaw), bool) if valid is None else np.asarray(valid, dtype=bool)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(np.int8), [0]])))
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        if b - a >= YAW_WINDOW:
            out[a:b] = savgol_filter(yaw[a:b], YAW_WINDOW, YAW_ORDER, mode="interp")
    return out


#: chi-square quantiles of the 95 % region: 2 dof (position), 1 dof (yaw)
CHI2_95_2DOF = float(-2.0 * np.log(0.05))  # = 5.991, closed form for 2 dof
CHI2_95_1DOF = 3.841458820694124  # 1.959964^2
#: per-window uncertainty columns added by :func:`window_errors` when a velocity covariance is given
UNCERTAINTY_COLUMNS = ("cov_xx", "cov_xy", "cov_yy", "var_yaw", "pos_d2", "yaw_z2", "nll_pos")


def correlation_inflation(autocorr: np.ndarray | None, n: int) -> np.ndarray:
    """(3,) variance factor of a sum of ``n`` correlated steps relative to ``n`` independent ones:
    f = 1 + 2 sum_{k=1}^{n-1} (1 - k/n) rho_k (exact for a stationary error with autocorrelation rho;
    rho beyond the given lags is taken as 0). ``autocorr``: (L, 3), lag 0 first; None: white (f = 1)."""
    if autocorr is None:
        return np.ones(3)
    rho = np.asarray(autocorr, dtype=float).reshape(len(autocorr), -1)[:n]
    k = np.arange(len(rho))[:, None]
    f = 1.0 + 2.0 * np.sum(((1.0 - k / n) * rho)[1:], axis=0)
    return np.clip(f, 1.0 / n, None) * np.ones(3)


def window_pose_covariance(
    dead: np.ndarray,
    dt: np.ndarray,
    vel_cov: np.ndarray,
    starts: np.ndarray,
    ends: np.ndarray,
    autocorr: np.ndarray | None = None,
) -> np.ndarray:
    """Covariance (W, 3, 3) of the end pose (x, y, yaw) of each window relative to its start, in the
    frame of the dead-reckoned trajectory ``dead`` (T, 3).

    First-order propagation: a body-velocity error du_k over step k (length dt_k, pose p_k, heading
    th_k) moves the end pose by G_k du_k with G_k = dt_k [[R(th_k), J (p_e - p_k)], [0 0 1]]
    (J = rotation by +90 deg). G_k = B_k + c_e d_k^T is affine in the end position, so the sum over a
    window of G_k Q_k G_k^T is three prefix-sum differences: O(T) for all windows. Q_k is the mean of
    ``vel_cov`` (T, 3, 3) at the step's two ends (its twist is their mean, ``geometry.step_velocities``),
    scaled by :func:`correlation_inflation` (white errors when ``autocorr`` is None).
    """
    T = len(dead)
    n = int(np.median(ends - starts)) if len(starts) else 1
    f = np.sqrt(correlation_inflation(autocorr, max(n, 1)))
    vel_cov = np.asarray(vel_cov, dtype=float)[:T]
    Q = 0.5 * (vel_cov[:-1] + vel_cov[1:]) * (f[:, None] * f[None, :])  # a step's twist: mean of its ends
    c, s = np.cos(dead[:-1, 2]), np.sin(dead[:-1, 2])
    B = np.zeros((T - 1, 3, 3))
    B[:, 0, 0], B[:, 0, 1], B[:, 0, 2] = c, -s, dead[:-1, 1]
    B[:, 1, 0], B[:, 1, 1], B[:, 1, 2] = s, c, -dead[:-1, 0]
    B[:, 2, 2] = 1.0
    B *= dt[:, None, None]
    BQ = B @ Q
    m1 = np.einsum("kij,klj->kil", BQ, B)  # B Q B^T
    m2 = BQ[:, :, 2] * dt[:, None]  # B Q d, d = dt e3
    m3 = Q[:, 2, 2] * dt**2  # d^T Q d

    def window_sum(a: np.ndarray) -> np.ndarray:
        cum = np.concatenate([np.zeros((1, *a.shape[1:])), np.cumsum(a, axis=0)])
        return cum[ends] - cum[starts]

    M1, M2, M3 = window_sum(m1), window_sum(m2), window_sum(m3)
    ce = np.zeros((len(ends), 3))
    ce[:, 0], ce[:, 1] = -dead[ends, 1], dead[ends, 0]  # J p_e
    cov = M1 + ce[:, :, None] * M2[:, None, :] + M2[:, :, None] * ce[:, None, :]
    cov += M3[:, None, None] * ce[:, :, None] * ce[:, None, :]
    return 0.5 * (cov + np.transpose(cov, (0, 2, 1)))


def uncertainty_scores(
    err_xy: np.ndarray, err_yaw: np.ndarray, cov: np.ndarray, rotate: np.ndarray
) -> dict[str, np.ndarray]:
    """Per-window calibration scores. err_xy (W, 2) m and err_yaw (W,) rad: true - predicted end pose
    in the world frame; cov (W, 3, 3) from :func:`window_pose_covariance` (dead-reckoned frame);
    rotate (W,) rad: the dead-reckoned frame's heading in the world frame at each window's start.
    Returns the columns of :data:`UNCERTAINTY_COLUMNS`: the world-frame position covariance, the yaw
    variance, the squared Mahalanobis distances (position: 2 dof, yaw: 1 dof) and the position's
    Gaussian negative log-likelihood (nats)."""
    c, s = np.cos(rotate), np.sin(rotate)
    R = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    P = R @ cov[:, :2, :2] @ np.transpose(R, (0, 2, 1)) + 1e-12 * np.eye(2)  # jitter: rank-0 models
    det = P[:, 0, 0] * P[:, 1, 1] - P[:, 0, 1] ** 2
    ex, ey = err_xy[:, 0], err_xy[:, 1]
    d2 = (P[:, 1, 1] * ex**2 - 2 * P[:, 0, 1] * ex * ey + P[:, 0, 0] * ey**2) / det
    var_yaw = cov[:, 2, 2] + 1e-12
    return {
        "cov_xx": P[:, 0, 0],
        "cov_xy": P[:, 0, 1],
        "cov_yy": P[:, 1, 1],
        "var_yaw": var_yaw,
        "pos_d2": d2,
        "yaw_z2": err_yaw**2 / var_yaw,
        "nll_pos": 0.5 * d2 + 0.5 * np.log((2 * np.pi) ** 2 * det),
    }


def naive_window_errors(
    t: np.ndarray, gt_pose: np.ndarray, velocity: np.ndarray, horizon_s: float
) -> np.ndarray:
    """Reference: integrate every window separately from its ground-truth start, O(T*h).
    Returns predicted end poses (W, 3). Used by tests and ``make bench`` only."""
    t = np.asarray(t, dtype=float)
    n = horizon_steps(t, horizon_s)
    out = []
    for i in range(len(t) - n):
        traj = integrate_body_velocity(
            gt_pose[i], step_velocities(velocity[i : i + n + 1]), np.diff(t[i : i + n + 1])
        )
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
    vel = step_velocities(np.asarray(velocity, dtype=float)[start : start + n + 1])
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
