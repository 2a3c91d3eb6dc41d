"""Held-out evaluation for discrepancy discovery (:mod:`skidbench.benchmark.discover`): the k-fold
predictions of a candidate model, its 6 s horizon errors, and the significance rule that decides whether
it earns its place.

The held-out prediction of each unit comes from the model fitted without it (k-fold over sequences,
never random rows). Velocity-based fitting, pose-based scoring: the 6 s windows integrate the velocity
noise of differentiated visual-odometry poses away, and are what the benchmark ranks models by.

Significance rule (every part must hold; the constants are ``discover.*`` settings):

* the held-out 6 s horizon gain ``G = sum_m log(RMSRE_m,before^2 / RMSRE_m,after^2)`` over the metrics
  m in (translational, rotational) (the Gaussian log-likelihood gain of the benchmark's own pose errors)
  pays for the effect's parameters: ``G - penalty_per_param * n_params >= min_gain`` (defaults 0.02
  and 0.02: an information-criterion-like charge, AIC's 2/n_eff for ~100 independent windows, so a
  one-parameter effect must cut one held-out RMSRE by at least 2 %, or both by 1 %);
* a paired one-sided sign-flip (permutation) test over the held-out units (whole sequences, or
  contiguous chunks) of the per-unit gains ``d_s`` (the same log ratio, per unit) rejects "no
  improvement" at ``alpha`` (default 0.05; exact for up to 16 units);
* the held-out velocity residuals agree: ``sum_c log(MSE_c,before / MSE_c,after)`` over (vx, vy, wz)
  is positive, and no channel the effect changes gets worse by more than ``channel_tolerance`` (0.01)
  (an effect that fixes poses while making a velocity worse is compensating for another, not real).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from skidbench.benchmark.horizon import rmsre, window_errors
from skidbench.models import terms as termlib
from skidbench.models.effect_fit import CHANNELS, Augmenter, DiscoverSettings, Pool
from skidbench.models.effects import CATALOGUE


@dataclass
class HeldOut:
    """The held-out (k-fold) predictions of one candidate model over the pool and their errors: velocity
    MSE per channel (pooled and per unit) and the 6 s horizon RMSRE (fractions) with its windows."""

    effects: list[str]
    pred: np.ndarray  # (T, 3) held-out prediction of every row
    mse: np.ndarray  # (3,) pooled held-out MSE per channel
    unit_mse: np.ndarray  # (U, 3)
    rmsre: dict[str, float]
    windows: pd.DataFrame
    fold_params: list[dict[str, list[float]]] = field(default_factory=list)


def folds_of(pool: Pool, k: int) -> list[np.ndarray]:
    """The held-out unit ids of each fold: unit u in fold u mod k, k clipped to [2, number of units]."""
    k = max(2, min(k, pool.n_units))
    ids = np.arange(pool.n_units)
    return [ids[ids % k == j] for j in range(k)]


def horizon_metrics(pool: Pool, pred: np.ndarray, horizon_s: float) -> tuple[dict[str, float], pd.DataFrame]:
    """The ``horizon_s`` RMSRE (translational, rotational; fractions) of the body velocities ``pred`` (T, 3)
    integrated over every sequence of the pool, and the per-window errors, each with the ``unit`` its
    first row belongs to (a window of a time-blocked sequence may run into the next block: every row's
    prediction is still held out from its own unit's fit)."""
    frames = []
    for g in range(len(pool.sequences)):
        idx = np.flatnonzero(pool.groups == g)
        w = window_errors(pool.t[idx], pool.pose[idx], pred[idx], horizon_s, valid=pool.valid[idx])
        w["unit"] = pool.units[idx][w["start"].to_numpy(int)] if len(w) else np.zeros(0, int)
        frames.append(w)
    win = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    if win.empty:
        return {"translational": float("nan"), "rotational": float("nan")}, win
    return {"translational": rmsre(win["rel_trans"]), "rotational": rmsre(win["rel_rot"])}, win


def cross_validate(
    aug: Augmenter, effects: list[str], warm: dict | None = None, terms: list[termlib.Term] | None = None
) -> HeldOut:
    """Held-out predictions by k-fold over units. The lag time constant of a model that already has
    ``actuator_lag`` stays at its fitted value while other candidates are scored (it is re-searched
    when the model is refitted after an effect is added)."""
    pool = aug.pool
    pred = np.zeros_like(pool.target)
    fold_params = []
    for held in folds_of(pool, aug.s.folds):
        train = np.setdiff1d(np.arange(pool.n_units), held)
        st = aug.fit(effects, train, warm, fixed_tau=True, terms=terms or [])
        rows = np.isin(pool.units, held)
        pred[rows] = st.pred[rows]
        fold_params.append(
            {
                **{e: [float(v) for v in p] for e, p in st.params.items()},
                **{k: [v["theta"]] for k, v in st.term_params.items()},
            }
        )
    err2 = (pred - pool.target) ** 2
    v = pool.valid
    mse = err2[v].mean(axis=0)
    unit_mse = np.array(
        [
            err2[v & (pool.units == u)].mean(axis=0) if np.any(v & (pool.units == u)) else [np.nan] * 3
            for u in range(pool.n_units)
        ]
    )
    rm, win = horizon_metrics(pool, pred, aug.s.horizon_s)
    return HeldOut(list(effects), pred, mse, unit_mse, rm, win, fold_params)


def sign_flip_pvalue(d: np.ndarray, seed: int = 0, n_random: int = 20000) -> float:
    """One-sided p-value of mean(d) > 0 under random sign flips (exact for up to 16 units)."""
    d = np.asarray(d, dtype=float)
    d = d[np.isfinite(d)]
    n = len(d)
    if n == 0:
        return 1.0
    obs = d.mean()
    if n <= 16:
        signs = np.array(list(itertools.product((-1.0, 1.0), repeat=n)))
    else:
        signs = np.random.default_rng(seed).choice((-1.0, 1.0), size=(n_random, n))
    null = (signs * d).mean(axis=1)
    return float(np.mean(null >= obs - 1e-15))


def unit_rmsre(ho: HeldOut, n_units: int) -> np.ndarray:
    """(U, 2) held-out translational and rotational RMSRE of every unit."""
    out = np.full((n_units, 2), np.nan)
    if ho.windows.empty:
        return out
    for u, w in ho.windows.groupby("unit"):
        out[int(u)] = [rmsre(w["rel_trans"]), rmsre(w["rel_rot"])]
    return out


def _log_ratio2(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        g = 2.0 * np.log(np.asarray(before, float) / np.asarray(after, float))
    return np.where(np.isfinite(g), g, np.nan)


def channels_of(eid: str) -> tuple[str, ...]:
    """The velocity channels a catalogue effect changes (all three for a whole-body effect)."""
    ch = CATALOGUE[eid].channel
    return CHANNELS if ch < 0 else (CHANNELS[ch],)


def compare(
    before: HeldOut,
    after: HeldOut,
    n_params: int,
    s: DiscoverSettings,
    touched_channels: tuple[int, ...] | None = None,
) -> dict[str, Any]:
    """The evidence for one candidate: held-out gains and the significance rule's verdict
    (``touched_channels``: the velocity channels the candidate changes; default: its effect's)."""
    keys = ("translational", "rotational")
    pose_gain = _log_ratio2([before.rmsre[k] for k in keys], [after.rmsre[k] for k in keys])
    G = float(np.nansum(pose_gain))
    n_units = len(before.unit_mse)
    d = np.nansum(_log_ratio2(unit_rmsre(before, n_units), unit_rmsre(after, n_units)), axis=1)
    p = sign_flip_pvalue(d, s.seed)
    eps = 1e-18
    vel_gain = np.log((before.mse + eps) / (after.mse + eps))
    Gv = float(np.sum(vel_gain))
    penalised = G - s.penalty_per_param * n_params
    if touched_channels is not None:
        touched = list(touched_channels)
    else:
        touched = [CHANNELS.index(c) for c in channels_of(after.effects[-1])] if after.effects else []
    worse = [CHANNELS[c] for c in touched if vel_gain[c] < -s.channel_tolerance]
    passes = bool(penalised >= s.min_gain and p <= s.alpha and Gv > 0.0 and not worse)
    return {
        "n_params": n_params,
        "heldout_gain": G,
        "heldout_gain_per_metric": dict(zip(keys, map(float, pose_gain), strict=True)),
        "penalised_gain": float(penalised),
        "velocity_gain": Gv,
        "velocity_gain_per_channel": dict(zip(CHANNELS, map(float, vel_gain), strict=True)),
        "heldout_mse_before": dict(zip(CHANNELS, map(float, before.mse), strict=True)),
        "heldout_mse_after": dict(zip(CHANNELS, map(float, after.mse), strict=True)),
        "velocity_channels_worse": worse,
        "paired_p_value": p,
        "n_heldout_units": int(np.sum(np.isfinite(d))),
        "units_improved": int(np.sum(d > 0)),
        "heldout_rmsre_before": before.rmsre,
        "heldout_rmsre_after": after.rmsre,
        "passes": passes,
    }


def explains_better(ho_a: HeldOut, ho_b: HeldOut, s: DiscoverSettings) -> tuple[bool, float]:
    """Whether model a's held-out velocity residual is smaller than model b's, unit by unit: the per-unit
    sum over channels of log(MSE_b / MSE_a), one-sided sign-flip test at ``alpha``."""
    eps = 1e-18
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.nansum(np.log((ho_b.unit_mse + eps) / (ho_a.unit_mse + eps)), axis=1)
    p = sign_flip_pvalue(d, s.seed)
    return bool(np.nanmean(d) > 0 and p <= s.alpha), p
