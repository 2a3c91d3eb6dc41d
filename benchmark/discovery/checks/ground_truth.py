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


def _offsets(fits: list[tuple[np.ndarray, np.ndarray]], y: list[np.ndarray]) -> np.ndarray:
    """(rows,) the heading offset -arctan(b + c t) at every row of each fitted sequence, for its measured
    vy ``y``: ``fits`` holds, per sequence, the pseudo-inverse of its regressors (vx, vx t, 1) and the times
    of all its rows."""
    return np.concatenate([-np.arctan(b + c * t) for (pinv, t), yy in zip(fits, y, strict=True)
                           for b, c in [(pinv @ yy)[:2]]])  # fmt: skip


def _sumsq(b: np.ndarray, c: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The sum over the times ``t`` of the squared offset b + c t (small angles), for arrays of (b, c)."""
    return len(t) * (b * b + 2 * b * c * t.mean() + c * c * np.mean(t * t))


def _noise_test(fits, ys, flips, ok: list[np.ndarray], draws: int, rng) -> float:
    """The share of ``draws`` in which noise alone gives offsets as large as the measured ones: each
    sequence's vy less its mean (no offset) has its sign flipped at random in its blocks (``flips``: each
    moving row's block), and the sum of squared offsets over its valid rows (``ok``) is taken relative to
    its mean over the draws (a sequence whose few or uniform moving rows leave offset and drift poorly
    determined weighs less); the statistic is the sum over the sequences, the measured one likewise."""
    stat, null = 0.0, np.zeros(draws)
    for (pinv, t), y, k, v in zip(fits, ys, flips, ok, strict=True):
        b, c = pinv[:2] @ ((y - y.mean())[:, None] * rng.choice((-1.0, 1.0), (k.max() + 1, draws))[k])
        s = _sumsq(b, c, t[v])
        scale = max(float(s.mean()), 1e-300)
        null += s / scale
        stat += float(_sumsq(*(pinv[:2] @ y), t[v])) / scale
    return float((1 + np.sum(null >= stat)) / (1 + draws))


def heading_finding(
    pool: Pool, min_deg: float = 1.0, max_turn: float = 0.2, p_max: float = 0.001, block_s: float = 2.0,
    draws: int = 4999, seed: int = 0,
) -> tuple[Pool, dict | None]:  # fmt: skip
    """The ground truth's own consistency: does its heading point where it travels? A ground-truth heading
    off by d turns the measured body velocity by -d, vy = -tan(d) vx; a robot does not crab sideways in
    proportion to its speed on a straight line. Per sequence, on its moving low-turn rows (|wz| <=
    ``max_turn`` |vx| + 0.05, |vx| >= 0.2 m/s), least squares of the measured vy on (vx, vx t, 1): the
    heading offset and its drift, and a constant lateral velocity (a side slope, ``lateral_drift``).
    A finding is both large and more than noise: the RMS offset over the pool's rows is at least
    ``min_deg``, and noise alone gives offsets as large at most ``p_max`` of the time (:func:`_noise_test`:
    the measured vy less its sequence mean, its sign flipped at random in blocks of ``block_s`` of each
    sequence's rows, ``draws`` times, each sequence weighed by its own noise: velocities differentiated from
    poses are correlated over a fraction of a second, and a short or gentle sequence whose moving rows
    barely vary gives offset and drift estimates of several degrees that cancel each other: on clean
    generated data the RMS reached 2.3 deg). Then the targets and the pose headings are corrected by it
    before the search, and the finding is returned with the corrected pool (its size and drift, never a
    robot effect); otherwise the pool as it is and None."""
    tgt = pool.target
    moving = (
        pool.valid & (np.abs(tgt[:, 0]) >= 0.2) & (np.abs(tgt[:, 2]) <= max_turn * np.abs(tgt[:, 0]) + 0.05)
    )
    fits, ys, flips, per_seq, where = [], [], [], [], []
    for g in range(len(pool.sequences)):
        rows = pool.groups == g
        m = rows & moving
        if m.sum() < 60:
            continue
        tt = pool.t - pool.t[rows][0]
        X = np.column_stack([tgt[m, 0], tgt[m, 0] * tt[m], np.ones(m.sum())])
        fits.append((np.linalg.pinv(X), tt[rows]))
        ys.append(tgt[m, 1])
        flips.append(np.unique(np.floor(tt[m] / block_s), return_inverse=True)[1])
        where.append(np.flatnonzero(rows))
        b, c = fits[-1][0][:2] @ ys[-1]
        per_seq.append((pool.sequences[g], float(np.degrees(-np.arctan(b))), float(np.degrees(-c) * 60.0)))
    if not per_seq:
        return pool, None
    n_valid = max(int(pool.valid.sum()), 1)
    at = np.concatenate(where)
    ok = pool.valid[at]  # the RMS is over the pool's valid rows; rows without a fit count as no offset
    obs = _offsets(fits, ys)
    rms = float(np.degrees(np.sqrt(np.sum(obs[ok] ** 2) / n_valid)))
    if rms < min_deg:
        return pool, None
    oks = [pool.valid[w] for w in where]
    p_noise = _noise_test(fits, ys, flips, oks, draws, np.random.default_rng(seed))
    if p_noise > p_max:
        return pool, None
    d = np.zeros(len(tgt))
    d[at] = obs
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
        "p_noise": p_noise,
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


def _law(x: np.ndarray, tt: np.ndarray) -> np.ndarray:
    """The regressors of a speed law with a drift: f(x) = a1 x + a2 x |x| + a3 sgn(x) (a law of speed that
    need not be proportional: a dead zone or a limit of the drive is not a drift, and drives that start
    from rest put their slow rows first) and the drift b x tt."""
    return np.column_stack([x, x * np.abs(x), np.sign(x), x * tt])


def _trend(y: np.ndarray, x: np.ndarray, tt: np.ndarray) -> float:
    """The relative change of y against x per unit of tt: b of y = f(x) + b x tt by least squares
    (:func:`_law`), over the scale of y on x (least squares through the origin)."""
    b = np.linalg.lstsq(_law(x, tt), y, rcond=None)[0][-1]
    scale = float(x @ y / (x @ x))
    return float(b / scale) if abs(scale) > 1e-9 else 0.0


def _drift_noise(y: np.ndarray, x: np.ndarray, tt: np.ndarray, t_s: np.ndarray, block_s: float, draws: int,
                 rng) -> np.ndarray:  # fmt: skip
    """(draws,) the drift :func:`_trend` gives when noise alone is there: the residual of the law without
    a drift, its sign flipped at random in blocks of ``block_s`` seconds (``t_s``), refitted."""
    X = _law(x, tt)
    r0 = y - X[:, :3] @ np.linalg.lstsq(X[:, :3], y, rcond=None)[0]
    k = np.unique(np.floor(t_s / block_s), return_inverse=True)[1]
    b = np.linalg.pinv(X)[-1] @ (r0[:, None] * rng.choice((-1.0, 1.0), (k.max() + 1, draws))[k])
    scale = float(x @ y / (x @ x))
    return b / scale if abs(scale) > 1e-9 else np.zeros(draws)


def drift_estimate(pool: Pool, block_s: float = 6.0, draws: int = 4999, seed: int = 0) -> dict | None:
    """The distance scale's and the yaw rate's drift against the commands (:func:`scale_drift_finding`
    says what they are): their RMS change over the pool's rows about each sequence's mean (``rms_pct``,
    ``yaw_rate_rms_pct``), the share of draws in which noise alone gives distance-scale drifts as large
    (``p_noise``: :func:`_drift_noise` per sequence, each weighed by its own noise, as the heading check
    does), each row's correction ``ratio`` and each sequence's drifts; None when no sequence has 60 moving
    and 60 turning rows."""
    tgt, tab = pool.target, pool.table
    cv, cw = tab["cmd_v"].to_numpy(float), tab["cmd_w"].to_numpy(float)
    ratio = np.ones(len(tgt))
    dev_v, dev_w, used = np.zeros(len(tgt)), np.zeros(len(tgt)), np.zeros(len(tgt), bool)
    per_seq, stat, null, rng = [], 0.0, np.zeros(draws), np.random.default_rng(seed)
    for g in range(len(pool.sequences)):
        rows = pool.groups == g
        mv = rows & pool.valid & (np.abs(cv) >= 0.2)
        mw = rows & pool.valid & (np.abs(cw) >= 0.3)
        if mv.sum() < 60 or mw.sum() < 60:
            continue
        t_s = pool.t - pool.t[rows][0]
        tt = t_s / 60.0
        dv, dw = _trend(tgt[mv, 0], cv[mv], tt[mv]), _trend(tgt[mw, 2], cw[mw], tt[mw])
        centred = tt - tt[mv].mean()
        dev_v[mv], dev_w[mv], used[mv] = dv * centred[mv], dw * centred[mv], True
        ratio[rows] = 1.0 + dv * tt[rows]
        per_seq.append({"sequence": pool.sequences[g], "drift_pct_per_min": 100 * dv,
                        "yaw_rate_drift_pct_per_min": 100 * dw})  # fmt: skip
        noise = _drift_noise(tgt[mv, 0], cv[mv], tt[mv], t_s[mv], block_s, draws, rng) ** 2
        weight = 1.0 / max(float(noise.mean()), 1e-300)
        stat, null = stat + dv * dv * weight, null + noise * weight
    if not per_seq:
        return None
    rms_v, rms_w = (100 * float(np.sqrt(np.mean(x[used] ** 2))) for x in (dev_v, dev_w))
    return {
        "rms_pct": rms_v,
        "yaw_rate_rms_pct": rms_w,
        "p_noise": float((1 + np.sum(null >= stat)) / (1 + draws)),
        "ratio": ratio,
        "mean_drift_pct_per_min": float(np.mean([q["drift_pct_per_min"] for q in per_seq])),
        "per_sequence": per_seq,
    }


def scale_drift_finding(
    pool: Pool, min_pct: float = 1.5, max_yaw_share: float = 0.5, p_max: float = 0.001, block_s: float = 6.0,
    draws: int = 4999, seed: int = 0,
) -> tuple[Pool, dict | None]:  # fmt: skip
    """The ground truth's distance scale against time: does it measure the same speed for the same command
    all along? A visual odometry's scale drifts; a robot's speed may change too (a battery running down,
    a payload), but that moves its turn rate with it, since both come from the wheels, while the ground
    truth's scale moves its distances only. Per sequence, on its moving rows (|cmd_v| >= 0.2 m/s), the
    measured vx is fitted as f(cmd_v) + b cmd_v t (t in minutes from the sequence's start; :func:`_law`)
    and, on its turning rows (|cmd_w| >= 0.3 rad/s), the measured wz likewise: the drifts relative to the
    scale of each (change per minute; :func:`drift_estimate`). A finding is large, a scale and more than
    noise: the RMS over the pool's rows of the distance scale's change about its sequence mean is at
    least ``min_pct`` %, the yaw rate's at most ``max_yaw_share`` of it, the corrected distances stay
    within half and twice the measured ones, and noise alone gives drifts as large at most ``p_max`` of
    the time (each sequence's residual without a drift, its sign flipped in blocks of ``block_s`` s,
    ``draws`` times). Without that test, a few seconds of a robot's response to its commands read as a
    drift: on the DRIVE Warthog's sand recording (6 s command steps, a lag of about a second, sequences
    of 6 to 78 s) the estimate was 105 % RMS (+498 %/min), which noise gives 23 % of the time. A finding
    divides each sequence's body velocities (vx, vy) by 1 + (b / a) t and re-integrates its positions
    from the corrected displacements (the ground truth taken right at the sequence's start, as an
    odometry is), before the search; otherwise the pool as it is and None. A drift of the turn rate as
    well (the robot's own) or of the turn rate alone (a payload) is left to the search."""
    est = drift_estimate(pool, block_s, draws, seed)
    if est is None:
        return pool, None
    rms_v, rms_w, ratio = est["rms_pct"], est["yaw_rate_rms_pct"], est["ratio"]
    if rms_v < min_pct or rms_w > max_yaw_share * rms_v or np.any((ratio <= 0.5) | (ratio >= 2.0)):
        return pool, None
    if est["p_noise"] > p_max:
        return pool, None
    target = pool.target.copy()
    target[:, :2] /= ratio[:, None]
    pose = pool.pose.copy()
    for g in range(len(pool.sequences)):
        rows = np.flatnonzero(pool.groups == g)
        if len(rows) < 2:
            continue
        mid = 0.5 * (ratio[rows][1:] + ratio[rows][:-1])
        steps = np.diff(pool.pose[rows, :2], axis=0) / mid[:, None]
        pose[rows[1:], :2] = pool.pose[rows[0], :2] + np.cumsum(steps, axis=0)
    table = pool.table.copy()
    table["vx"], table["vy"], table["x"], table["y"] = target[:, 0], target[:, 1], pose[:, 0], pose[:, 1]
    mean_rate = est["mean_drift_pct_per_min"]
    finding = {
        "kind": "ground_truth",
        "what": "distance scale drifts against the commanded speeds",
        **{k: v for k, v in est.items() if k != "ratio"},
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
