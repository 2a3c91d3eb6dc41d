"""The ground truth's own consistency (:mod:`skidbench.benchmark.discovery.discover`, before anything is
fitted): a residual the ground truth's inconsistency explains is a ground-truth finding with its size, the
pool corrected by it, and never a robot effect or a term (issue 47). Two checks, each against what the
robot's commands say, in turn: its heading against its direction of travel (:func:`heading_finding`) and
its distance scale against time (:func:`scale_drift_finding`).

An offset between the commands' and the poses' clocks is not among them: from commands and poses alone it
moves the poses as a dead time of the drive does (``actuator_lag``'s members say so), and against wheel
encoders as an acceleration slip does (vx - k dv is v a time k earlier, to first order), so it cannot be
told from robot physics without a clock reference the data do not have.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from skidbench.models.augmented.fit import Pool


def heading_finding(pool: Pool, min_deg: float = 1.0, max_turn: float = 0.2) -> tuple[Pool, dict | None]:
    """The ground truth's own consistency: does its heading point where it travels? A ground-truth heading
    off by d turns the measured body velocity by -d, vy = -tan(d) vx; a robot does not crab sideways in
    proportion to its speed on a straight line. Per sequence, on its moving low-turn rows (|wz| <=
    ``max_turn`` |vx| + 0.05, |vx| >= 0.2 m/s), least squares of the measured vy on (1, vx, vx t): a
    constant lateral velocity (a side slope, ``lateral_drift``) in the first, the heading offset and its
    drift in the others.
    When the RMS offset over the pool's rows is at least ``min_deg``, it is a ground-truth finding (its size
    and drift, never a robot effect): the targets and the pose headings are corrected by it before the
    search, and the finding is returned with the corrected pool; otherwise the pool as it is and None."""
    tgt = pool.target
    moving = (
        pool.valid & (np.abs(tgt[:, 0]) >= 0.2) & (np.abs(tgt[:, 2]) <= max_turn * np.abs(tgt[:, 0]) + 0.05)
    )
    d = np.zeros(len(tgt))
    per_seq = []
    for g in range(len(pool.sequences)):
        rows = pool.groups == g
        m = rows & moving
        if m.sum() < 60:
            continue
        t0 = pool.t[rows][0]
        tt = pool.t - t0
        X = np.column_stack([np.ones(m.sum()), tgt[m, 0], tgt[m, 0] * tt[m]])
        a, b, c = np.linalg.lstsq(X, tgt[m, 1], rcond=None)[0]
        d[rows] = -np.arctan(b + c * tt[rows])  # the heading's offset at each row of the sequence
        per_seq.append((pool.sequences[g], float(np.degrees(-np.arctan(b))), float(np.degrees(-c) * 60.0)))
    if not per_seq:
        return pool, None
    rms = float(np.degrees(np.sqrt(np.mean(d[pool.valid] ** 2))))
    if rms < min_deg:
        return pool, None
    c, s = np.cos(d), np.sin(d)  # the true body velocity is the measured one turned by +d
    target = pool.target.copy()
    target[:, 0], target[:, 1] = c * tgt[:, 0] - s * tgt[:, 1], s * tgt[:, 0] + c * tgt[:, 1]
    pose = pool.pose.copy()
    pose[:, 2] = pose[:, 2] - d
    table = pool.table.copy()
    table["vx"], table["vy"] = target[:, 0], target[:, 1]
    mean_start = float(np.mean([p[1] for p in per_seq]))
    mean_rate = float(np.mean([p[2] for p in per_seq]))
    finding = {
        "kind": "ground_truth",
        "what": "heading disagrees with the direction of travel",
        "rms_deg": rms,
        "mean_offset_deg": mean_start,
        "mean_drift_deg_per_min": mean_rate,
        "per_sequence": [{"sequence": n, "offset_deg": o, "drift_deg_per_min": r} for n, o, r in per_seq],
        "text": f"ground truth: its heading disagrees with its direction of travel by {rms:.1f} deg (RMS; "
        f"{mean_start:+.1f} deg at the start, drifting {mean_rate:+.2f} deg/min on average): check the "
        "ground truth (a heading bias or a misaligned frame); corrected before the search, not a robot "
        "effect",
    }
    out = dataclasses.replace(pool, table=table, target=target, pose=pose)
    return out, finding


def _trend(y: np.ndarray, x: np.ndarray, tt: np.ndarray) -> float:
    """The relative change of y against x per unit of tt: b of y = f(x) + b x tt by least squares, with
    f(x) = a1 x + a2 x |x| + a3 sgn(x) (a law of speed that need not be proportional: a dead zone or a limit
    of the drive is not a drift, and drives that start from rest put their slow rows first), over the
    scale of y on x (least squares through the origin)."""
    X = np.column_stack([x, x * np.abs(x), np.sign(x), x * tt])
    b = np.linalg.lstsq(X, y, rcond=None)[0][-1]
    scale = float(x @ y / (x @ x))
    return float(b / scale) if abs(scale) > 1e-9 else 0.0


def scale_drift_finding(
    pool: Pool, min_pct: float = 1.5, max_yaw_share: float = 0.5
) -> tuple[Pool, dict | None]:
    """The ground truth's distance scale against time: does it measure the same speed for the same command
    all along? A visual odometry's scale drifts; a robot's speed may change too (a battery running down,
    a payload), but that moves its turn rate with it, since both come from the wheels, while the ground
    truth's scale moves its distances only. Per sequence, on its moving rows (|cmd_v| >= 0.2 m/s), the
    measured vx is fitted as a cmd_v + b cmd_v t (t in minutes from the sequence's start) and, on its
    turning rows (|cmd_w| >= 0.3 rad/s), the measured wz as c cmd_w + e cmd_w t: the drifts b / a and e / c
    (relative change per minute). When the RMS over the pool's rows of the distance scale's change about
    its sequence mean is at least ``min_pct`` % and the yaw rate's is at most ``max_yaw_share`` of it, it is
    a ground-truth finding (its size, never a robot effect): each sequence's body velocities (vx, vy) are
    divided by 1 + (b / a) t and its positions re-integrated from the corrected displacements (the ground
    truth taken right at the sequence's start, as an odometry is), before the search; otherwise the pool as
    it is and None. A drift of the turn rate as well (the robot's own) or of the turn rate alone (a
    payload) is left to the search."""
    tgt, tab = pool.target, pool.table
    cv, cw = tab["cmd_v"].to_numpy(float), tab["cmd_w"].to_numpy(float)
    ratio = np.ones(len(tgt))
    dev_v, dev_w, used = np.zeros(len(tgt)), np.zeros(len(tgt)), np.zeros(len(tgt), bool)
    per_seq = []
    for g in range(len(pool.sequences)):
        rows = pool.groups == g
        mv = rows & pool.valid & (np.abs(cv) >= 0.2)
        mw = rows & pool.valid & (np.abs(cw) >= 0.3)
        if mv.sum() < 60 or mw.sum() < 60:
            continue
        tt = (pool.t - pool.t[rows][0]) / 60.0
        dv, dw = _trend(tgt[mv, 0], cv[mv], tt[mv]), _trend(tgt[mw, 2], cw[mw], tt[mw])
        centred = tt - tt[mv].mean()
        dev_v[mv], dev_w[mv], used[mv] = dv * centred[mv], dw * centred[mv], True
        ratio[rows] = 1.0 + dv * tt[rows]
        per_seq.append((pool.sequences[g], 100 * dv, 100 * dw))
    if not per_seq:
        return pool, None
    rms_v, rms_w = (100 * float(np.sqrt(np.mean(x[used] ** 2))) for x in (dev_v, dev_w))
    if rms_v < min_pct or rms_w > max_yaw_share * rms_v or np.any(ratio <= 0.5):
        return pool, None
    target = tgt.copy()
    target[:, :2] /= ratio[:, None]
    pose = pool.pose.copy()
    for g in range(len(pool.sequences)):
        rows = np.flatnonzero(pool.groups == g)
        if len(rows) < 2:
            continue
        mid = 0.5 * (ratio[rows][1:] + ratio[rows][:-1])
        steps = np.diff(pool.pose[rows, :2], axis=0) / mid[:, None]
        pose[rows[1:], :2] = pool.pose[rows[0], :2] + np.cumsum(steps, axis=0)
    table = tab.copy()
    table["vx"], table["vy"], table["x"], table["y"] = target[:, 0], target[:, 1], pose[:, 0], pose[:, 1]
    mean_rate = float(np.mean([p[1] for p in per_seq]))
    finding = {
        "kind": "ground_truth",
        "what": "distance scale drifts against the commanded speeds",
        "rms_pct": rms_v,
        "yaw_rate_rms_pct": rms_w,
        "mean_drift_pct_per_min": mean_rate,
        "per_sequence": [{"sequence": n, "drift_pct_per_min": a, "yaw_rate_drift_pct_per_min": b}
                         for n, a, b in per_seq],
        "text": f"ground truth: its distance scale drifts against the commanded speeds by {rms_v:.1f} % "
        f"(RMS; {mean_rate:+.2f} %/min on average) while its yaw rate does not ({rms_w:.1f} %): check the "
        "ground truth (an odometry's scale drift); corrected before the search, not a robot effect",
    }  # fmt: skip
    return dataclasses.replace(pool, table=table, target=target, pose=pose), finding


def ground_truth_findings(pool: Pool) -> tuple[Pool, list[dict]]:
    """The ground truth's own consistency checks in turn (its heading, then its distance scale), each
    correcting the pool it passes on: the pool the search runs on and the findings (a list, empty when
    the ground truth is consistent)."""
    found = []
    for check in (heading_finding, scale_drift_finding):
        pool, f = check(pool)
        if f:
            found.append(f)
    return pool, found
