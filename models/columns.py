"""Column helpers for model authors (public: plugins import them): reading a table's columns as float
arrays, the rows a fit may use, the targets, the loss, and the sequence boundaries of a concatenated
table.

A table given to ``predict`` holds several sequences one after the other (``sequence`` column; ``t``
restarts at 0 in each), so anything that differentiates, filters or integrates over time must restart
at each boundary: :func:`sequence_starts` gives them.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

TARGETS = ("vx", "vy", "wz")


def col(table: pd.DataFrame, name: str) -> np.ndarray:
    """Column ``name`` as a float64 array (T,) (missing values as NaN)."""
    return table[name].to_numpy(dtype=float, na_value=np.nan)


def training_rows(table: pd.DataFrame) -> pd.DataFrame:
    """The rows a fit may use: ``valid`` True."""
    return table.loc[table["valid"].to_numpy(bool)]


def targets(table: pd.DataFrame) -> np.ndarray:
    """(T, 3) ground-truth body velocities (vx, vy, wz)."""
    return np.column_stack([col(table, c) for c in TARGETS])


def mse(pred: np.ndarray, true: np.ndarray) -> float:
    """Mean squared velocity error over rows and the three components (m^2/s^2 and rad^2/s^2 mixed)."""
    return float(np.mean((np.asarray(pred) - np.asarray(true)) ** 2))


def sequence_starts(table: pd.DataFrame) -> np.ndarray:
    """(T,) bool: True on the first row of each sequence (the ``sequence`` column changes, or ``t``
    goes back); a table without either is one sequence."""
    n = len(table)
    start = np.zeros(n, dtype=bool)
    if n == 0:
        return start
    start[0] = True
    if "sequence" in table:
        s = table["sequence"].to_numpy()
        start[1:] |= s[1:] != s[:-1]
    if "t" in table:
        t = col(table, "t")
        start[1:] |= np.diff(t) <= 0
    return start


def error_autocorrelation(
    residuals: np.ndarray, starts: np.ndarray, max_lag: int, weight: np.ndarray | None = None
) -> np.ndarray:
    """Autocorrelation (L, C) of a model's velocity errors, lags 0..max_lag-1 steps, within sequences.

    residuals: (T, C) true - predicted (not de-meaned: a bias is an error the horizon integrates too);
    starts: (T,) bool, first row of each sequence (:func:`sequence_starts`); weight: (T,) bool rows to
    use (others count as missing). rho_k = E[r_t r_{t+k}] / E[r_t^2] over pairs inside one sequence.
    This is what ``KinematicModel.error_autocorrelation_`` holds, for the horizon's uncertainty."""
    r = np.asarray(residuals, dtype=float)
    r = r.reshape(len(r), -1)
    m = np.ones(len(r)) if weight is None else np.asarray(weight, dtype=float)
    r = np.where(np.isfinite(r), r, 0.0) * m[:, None]
    bounds = np.flatnonzero(starts).tolist() + [len(r)]
    num = np.zeros((max_lag, r.shape[1]))
    cnt = np.zeros(max_lag)
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        n = b - a
        if n < 2:
            continue
        size = 1 << int(np.ceil(np.log2(2 * n)))
        L = min(max_lag, n)
        fr = np.fft.rfft(r[a:b], size, axis=0)
        num[:L] += np.fft.irfft(fr * np.conj(fr), size, axis=0)[:L]
        fm = np.fft.rfft(m[a:b], size)
        cnt[:L] += np.fft.irfft(fm * np.conj(fm), size)[:L]
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = num / np.maximum(cnt, 1.0)[:, None]
        rho = cov / cov[0]
    rho[~np.isfinite(rho)] = 0.0
    rho[cnt < 10] = 0.0  # too few pairs to say
    rho[0] = 1.0
    return rho


def bounds_reached(
    names: list[str],
    x: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    meanings: dict[str, str] | None = None,
    active_mask: np.ndarray | None = None,
    atol: float | list[float] = 1e-9,
) -> list[dict]:
    """The fitted parameters that ended at a bound of their box, for ``fit_info_["at_bound"]`` (the fit
    JSON; ``compare`` and the MLflow run report it: a fit at a bound is a finding, not a number to hide):
    ``[{"param", "value", "bound", "side", "finding"}]`` (``bound`` null for one that runs off to
    infinity, which a model reports itself). A parameter is at its bound when the optimizer
    says so (``active_mask``, as ``scipy.optimize.least_squares`` returns it) or it is within ``atol`` of
    it (one value, or one per parameter: how close makes no difference to the model's output on the
    data). ``meanings``: parameter -> what the model becomes there (``"roc degenerates to edd on this data:
    b2 at its bound"``); else a plain sentence."""
    out = []
    x, lower, upper = (np.asarray(a, dtype=float) for a in (x, lower, upper))
    tol = np.broadcast_to(np.asarray(atol, dtype=float), x.shape)
    for i, name in enumerate(names):
        for side, bound, sign in (("lower", lower[i], -1), ("upper", upper[i], 1)):
            if not np.isfinite(bound):
                continue
            active = active_mask is not None and int(active_mask[i]) == sign
            if active or abs(x[i] - bound) <= tol[i]:
                finding = (meanings or {}).get(name) or f"{name} at its {side} bound {bound:g}"
                out.append({"param": name, "value": float(x[i]), "bound": float(bound), "side": side,
                            "finding": finding})  # fmt: skip
    return out
