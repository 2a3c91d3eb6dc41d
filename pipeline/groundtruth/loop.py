"""Loop-closure errors of a ground truth (as the paper measured its localization) and its accuracy
against the simulator's true pose.

Loop trial (start at a marked point, drive, return to it), trajectory projected to SE(2):

- relative translational error = |p_end - p_start| / distance travelled (sum of the step lengths);
- relative rotational error = |wrap(yaw_end - yaw_start)| / absolute rotation (sum of |yaw steps|,
  yaw unwrapped).

Over the trials: mean and (population) standard deviation of both; the summary is flagged when a mean
exceeds its configured bound (default: the paper's 0.4 % and 0.2 %).

Accuracy against truth (``evaluate_against_truth``): the estimate is associated with the truth by
stamp (truth interpolated linearly, yaw on the unwrapped angle), both are expressed relative to their
first associated pose (start-pose alignment), then

- ATE: position error |p_est - p_true| per pose (mean, std, RMSE, max) and yaw error;
- RPE over ``rpe_window_s`` (6 s): for every pose i and the pose j at t_i + 6 s, the error of the
  relative motion (translation norm, |yaw| error): mean and std.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from skidbench.pipeline.core.errors import GroundTruthError
from skidbench.pipeline.core.geometry import se2_relative, wrap_angle
from skidbench.pipeline.core.timesync import interp_se2
from skidbench.pipeline.groundtruth.trajectory import Trajectory

PAPER_TRANS_BOUND = 0.004  # 0.4 %
PAPER_ROT_BOUND = 0.002  # 0.2 %


@dataclass
class LoopError:
    name: str
    distance_m: float
    abs_rotation_rad: float
    end_offset_m: float
    end_yaw_rad: float
    trans_err: float  # fraction (0.004 = 0.4 %)
    rot_err: float  # fraction


def loop_error(traj: Trajectory | np.ndarray, name: str = "") -> LoopError:
    """Relative translational and rotational loop-closure error of one trial (SE(2) poses (N, 3) or a
    Trajectory)."""
    se2 = traj.se2 if isinstance(traj, Trajectory) else np.asarray(traj, dtype=float)
    if se2.ndim != 2 or se2.shape[1] != 3 or len(se2) < 2:
        raise GroundTruthError(f"{name or 'loop trial'}: needs at least 2 planar poses")
    yaw = np.unwrap(se2[:, 2])
    dist = float(np.sum(np.hypot(np.diff(se2[:, 0]), np.diff(se2[:, 1]))))
    rot = float(np.sum(np.abs(np.diff(yaw))))
    off = float(np.hypot(se2[-1, 0] - se2[0, 0], se2[-1, 1] - se2[0, 1]))
    dyaw = float(abs(wrap_angle(se2[-1, 2] - se2[0, 2])))
    te = off / dist if dist > 0 else float("nan")
    re = dyaw / rot if rot > 0 else float("nan")
    return LoopError(name, dist, rot, off, dyaw, te, re)


def summarize_loops(
    errors: Iterable[LoopError],
    max_trans_err: float = PAPER_TRANS_BOUND,
    max_rot_err: float = PAPER_ROT_BOUND,
) -> dict[str, Any]:
    """Mean/std over trials (fractions and percent) and the bound check: ``flagged`` is True when a
    mean is over its bound (the ground truth is then not to be used silently)."""
    errors = list(errors)
    te = np.array([e.trans_err for e in errors], dtype=float)
    re = np.array([e.rot_err for e in errors], dtype=float)
    te, re = te[np.isfinite(te)], re[np.isfinite(re)]

    def stat(a):
        return (float(a.mean()), float(a.std())) if a.size else (float("nan"), float("nan"))

    tm, ts = stat(te)
    rm, rs = stat(re)
    reasons = []
    if not (tm <= max_trans_err):
        reasons.append(f"translational error mean {100 * tm:.3f}% > bound {100 * max_trans_err:.3f}%")
    if not (rm <= max_rot_err):
        reasons.append(f"rotational error mean {100 * rm:.3f}% > bound {100 * max_rot_err:.3f}%")
    return {
        "n_trials": len(errors),
        "trans_err_mean": tm,
        "trans_err_std": ts,
        "rot_err_mean": rm,
        "rot_err_std": rs,
        "trans_err_mean_pct": 100 * tm,
        "trans_err_std_pct": 100 * ts,
        "rot_err_mean_pct": 100 * rm,
        "rot_err_std_pct": 100 * rs,
        "bounds": {"max_trans_err": max_trans_err, "max_rot_err": max_rot_err},
        "flagged": bool(reasons),
        "reasons": reasons,
        "trials": [asdict(e) for e in errors],
    }


# -------------------------------------------------------------------------------------------------
# accuracy against the simulator's truth


def evaluate_against_truth(est: Trajectory, truth: Trajectory, rpe_window_s: float = 6.0) -> dict[str, Any]:
    """ATE (start-pose aligned) and ``rpe_window_s`` relative pose error of ``est`` against ``truth``."""
    t_true = truth.stamp_ns
    inside = (est.stamp_ns >= t_true[0]) & (est.stamp_ns <= t_true[-1])
    if inside.sum() < 2:
        raise GroundTruthError("estimate and truth do not overlap in time")
    t = est.stamp_ns[inside]
    e = est.se2[inside]
    g = interp_se2(t_true.astype(float), truth.se2, t.astype(float))
    # start-pose alignment: both relative to their first pose
    e_rel = se2_relative(e[0], e)
    g_rel = se2_relative(g[0], g)
    pos_err = np.hypot(e_rel[:, 0] - g_rel[:, 0], e_rel[:, 1] - g_rel[:, 1])
    yaw_err = np.abs(wrap_angle(e_rel[:, 2] - g_rel[:, 2]))
    out: dict[str, Any] = {
        "n_poses": int(len(t)),
        "ate_mean_m": float(pos_err.mean()),
        "ate_std_m": float(pos_err.std()),
        "ate_rms_m": float(np.sqrt(np.mean(pos_err**2))),
        "ate_max_m": float(pos_err.max()),
        "ate_yaw_mean_rad": float(yaw_err.mean()),
        "ate_yaw_max_rad": float(yaw_err.max()),
        "ate_yaw_rms_rad": float(np.sqrt(np.mean(yaw_err**2))),
    }
    ts = t.astype(float) * 1e-9
    j = np.searchsorted(ts, ts + rpe_window_s)
    ok = j < len(ts)
    i, j = np.nonzero(ok)[0], j[ok]
    # keep pairs whose partner really is ~window later (no long gap)
    ok2 = np.abs(ts[j] - ts[i] - rpe_window_s) < 0.5
    i, j = i[ok2], j[ok2]
    if i.size:
        de = se2_relative(e[i], e[j])
        dg = se2_relative(g[i], g[j])
        # error of the relative motion, expressed in the true start frame of the window
        dt = np.hypot(de[:, 0] - dg[:, 0], de[:, 1] - dg[:, 1])
        dr = np.abs(wrap_angle(de[:, 2] - dg[:, 2]))
        # relative to the distance the truth drove in the window (windows under 0.1 m left out)
        steps = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(g[:, :2], axis=0).T))])
        dist = steps[j] - steps[i]
        moving = dist > 0.1
        out.update(
            {
                "rpe_window_s": rpe_window_s,
                "rpe_n": int(i.size),
                "rpe_trans_mean_m": float(dt.mean()),
                "rpe_trans_std_m": float(dt.std()),
                "rpe_trans_rms_m": float(np.sqrt(np.mean(dt**2))),
                "rpe_trans_rel_rms": float(np.sqrt(np.mean((dt[moving] / dist[moving]) ** 2)))
                if moving.any()
                else None,
                "rpe_rot_mean_rad": float(dr.mean()),
                "rpe_rot_std_rad": float(dr.std()),
                "rpe_yaw_rms_rad": float(np.sqrt(np.mean(dr**2))),
            }
        )  # fmt: skip
    else:
        out.update({"rpe_window_s": rpe_window_s, "rpe_n": 0})
    return out
