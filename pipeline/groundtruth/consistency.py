"""The ground-truth consistency gate: does a sequence's ground truth move the way its wheels turn?

Beside the loop-closure check (which needs loop trials), this one needs nothing but the sequence itself,
so it applies to every source. Per sequence, on its split table (``schema.SPLIT_COLUMNS``), the ground
truth's body velocities (vx, wz, from the smoothing differentiator) are compared with the ideal
differential-drive ones of the wheels, ``v = r (wl + wr) / 2``, ``w = r (wr - wl) / B`` (the measured
encoder rates when the split has them, else the commanded ones), on the valid rows where either moves:

- ``sign_agreement``: the fraction of rows where both ``|v|`` and ``|vx|`` are over ``min_speed`` in which
  vx has the sign of v (a ground truth whose heading is off by pi, or a robot pushed backwards while its
  wheels drive forwards, is near 0; DRIVE's Warthog steps, with their transients after each reversal,
  0.7-0.9);
- ``heading_offset_deg``: the body-frame angle that rotates the wheels' forward motion onto the ground
  truth's, ``atan2(sum v vy, sum v vx)`` (0 for a consistent ground truth, +-180 for one flipped by pi, a
  constant in between for a yaw offset between the pose's frame and the body);
- ``corr_v``, ``corr_w``: Pearson correlations of vx with v and wz with w (NaN without variance);
- ``uncommanded_s``: seconds in which the commanded wheel rates have been zero for over ``settle_s`` s
  while a wheel turns faster than ``moving_wheel`` rad/s or the ground truth moves faster than
  ``min_speed`` m/s: driven by something other than the recorded commands (the first ``settle_s`` s after a
  stop command are the robot braking, which a model must predict).

A sequence is flagged when, over at least ``min_rows`` moving rows, the sign agreement is under
``min_sign_agreement``, ``|heading_offset_deg|`` over ``max_heading_offset_deg``, or ``corr_v`` under
``min_corr_v``;
or when ``uncommanded_s`` is over ``max_uncommanded_frac`` of its valid time (and at least 1 s). The
thresholds are ``split.consistency.*`` (:class:`~skidbench.pipeline.splits.settings.GateConfig`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from skidbench.pipeline.splits.settings import GateConfig


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    if len(a) < 3 or np.std(a) < 1e-9 or np.std(b) < 1e-9:
        return float("nan")
    return float(np.corrcoef(a, b)[0, 1])


def consistency(df: pd.DataFrame, wheel_radius: float, track_width: float, gate: GateConfig | None = None):
    """The gate's numbers for one split table (module docstring): a dict with ``wheels`` (``encoders`` or
    ``commands``), ``moving_rows``, ``sign_agreement``, ``heading_offset_deg``, ``corr_v``, ``corr_w``,
    ``uncommanded_s``, ``valid_s``, ``flagged`` (bool) and ``reasons`` (list of str)."""
    gate = gate or GateConfig()
    valid = df["valid"].to_numpy(bool)
    t = df["t"].to_numpy(float)
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    enc = df[["enc_wl", "enc_wr"]].to_numpy(float)
    has_enc = np.isfinite(enc).all(axis=1)
    use_enc = has_enc[valid].mean() > 0.5 if valid.any() else False
    wl = (
        np.where(has_enc, enc[:, 0], df["cmd_wl"].to_numpy(float))
        if use_enc
        else df["cmd_wl"].to_numpy(float)
    )
    wr = (
        np.where(has_enc, enc[:, 1], df["cmd_wr"].to_numpy(float))
        if use_enc
        else df["cmd_wr"].to_numpy(float)
    )
    v = wheel_radius * (wl + wr) / 2
    w = wheel_radius * (wr - wl) / track_width
    vx, vy, wz = (df[c].to_numpy(float) for c in ("vx", "vy", "wz"))
    moving = valid & ((np.abs(v) > gate.min_speed) | (np.abs(vx) > gate.min_speed))
    signed = valid & (np.abs(v) > gate.min_speed) & (np.abs(vx) > gate.min_speed)
    out: dict[str, Any] = {"wheels": "encoders" if use_enc else "commands", "moving_rows": int(moving.sum())}
    out["sign_agreement"] = (
        float(np.mean(np.sign(vx[signed]) == np.sign(v[signed]))) if signed.any() else None
    )
    if moving.any() and np.abs(v[moving]).sum() > 0:
        out["heading_offset_deg"] = float(
            np.degrees(np.arctan2(np.sum(v[moving] * vy[moving]), np.sum(v[moving] * vx[moving])))
        )
    else:
        out["heading_offset_deg"] = None
    out["corr_v"] = _corr(vx[moving], v[moving])
    out["corr_w"] = _corr(wz[moving], w[moving])
    cmd_zero = (np.abs(df["cmd_wl"].to_numpy(float)) < 1e-9) & (np.abs(df["cmd_wr"].to_numpy(float)) < 1e-9)
    turning = np.fmax(np.abs(np.nan_to_num(enc[:, 0])), np.abs(np.nan_to_num(enc[:, 1]))) > gate.moving_wheel
    # rows since the command last was non-zero (a run of zero commands longer than settle_s)
    last_cmd = np.maximum.accumulate(np.where(~cmd_zero, np.arange(len(t)), -(10**9)))
    settled = (np.arange(len(t)) - last_cmd) * dt > gate.settle_s
    uncommanded = valid & cmd_zero & settled & (turning | (np.hypot(vx, vy) > gate.min_speed))
    out["uncommanded_s"] = float(uncommanded.sum() * dt)
    out["valid_s"] = float(valid.sum() * dt)
    reasons = []
    if out["moving_rows"] >= gate.min_rows:
        sa, off, cv = out["sign_agreement"], out["heading_offset_deg"], out["corr_v"]
        if sa is not None and signed.sum() >= gate.min_rows and sa < gate.min_sign_agreement:
            reasons.append(f"vx has the sign of the wheels' speed in {100 * sa:.0f} % of moving rows")
        if off is not None and abs(off) > gate.max_heading_offset_deg:
            reasons.append(f"the ground truth moves at {off:.0f} deg from the wheels' forward direction")
        if np.isfinite(cv) and cv < gate.min_corr_v:
            reasons.append(f"vx and the wheels' speed are anti-correlated ({cv:.2f})")
    if out["uncommanded_s"] >= 1.0 and out["uncommanded_s"] > gate.max_uncommanded_frac * out["valid_s"]:
        reasons.append(
            f"{out['uncommanded_s']:.1f} s of {out['valid_s']:.1f} s move under zero commands "
            "(driven by something else)"
        )
    out["flagged"] = bool(reasons)
    out["reasons"] = reasons
    return out


def describe(name: str, rep: dict) -> str:
    """One line: the sequence, its numbers and why it is flagged."""

    def f(v, fmt):
        return "n/a" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, fmt)

    return (
        f"{name}: sign agreement {f(rep.get('sign_agreement'), '.2f')}, heading offset "
        f"{f(rep.get('heading_offset_deg'), '.0f')} deg, corr v {f(rep.get('corr_v'), '.2f')}, "
        f"corr w {f(rep.get('corr_w'), '.2f')}, uncommanded {f(rep.get('uncommanded_s'), '.1f')} s "
        f"({'; '.join(rep.get('reasons', [])) or 'consistent'})"
    )
