"""How aggressive a window's commands are (issue 49, after Han et al. 2024, "Dynamics Models in the
Aggressive Off-Road Driving Regime", who condition model error on it), and the terciles that stratify a
dataset's windows by it.

The measure, from the window's own commands only (never the ground truth, so every model and protocol
sees the same strata): the root mean square over the window's samples of the commanded acceleration of a
wheel contact point,

    a_k = sqrt( dv_k^2 + (v_k w_k)^2 + (B/2 dw_k)^2 )    [m/s^2]

with v, w the commanded body velocities (``cmd_v``, ``cmd_w``), dv, dw their time derivatives (central
differences on the sequence's clock), v w the centripetal acceleration of a turn and B the track width
(the angular acceleration as the tangential acceleration of the wheels). A sharp stop, a fast turn and a
snap from one turn direction to the other all count; steady straight driving scores 0.

The strata are the dataset's terciles of the measure at each horizon (over the windows of every terrain
and test split): ``low`` (a <= q1/3), ``mid``, ``high`` (a > q2/3).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
import pandas as pd

STRATA = ("low", "mid", "high")
ALL = "all"


def sample_acceleration(table: pd.DataFrame, half_track: float) -> np.ndarray:
    """(T,) a_k of one sequence's rows (module docstring), m/s^2."""
    t = table["t"].to_numpy(float)
    v, w = table["cmd_v"].to_numpy(float), table["cmd_w"].to_numpy(float)
    if len(t) < 2:
        return np.zeros(len(t))
    dv, dw = np.gradient(v, t), np.gradient(w, t)
    return np.sqrt(dv**2 + (v * w) ** 2 + (half_track * dw) ** 2)


def window_aggressiveness(acc: np.ndarray, starts: np.ndarray, n: int) -> np.ndarray:
    """(W,) the RMS of ``acc`` (T,) over samples start..start+n of each window (O(T) prefix sums)."""
    cum = np.concatenate([[0.0], np.cumsum(np.asarray(acc, float) ** 2)])
    starts = np.asarray(starts, int)
    return np.sqrt((cum[starts + n + 1] - cum[starts]) / (n + 1))


def tercile_edges(values: Iterable[np.ndarray]) -> tuple[float, float]:
    """(q1/3, q2/3) of the pooled finite ``values``; (nan, nan) when there is none."""
    v = np.concatenate([np.asarray(x, float).ravel() for x in values] or [np.zeros(0)])
    v = v[np.isfinite(v)]
    if not v.size:
        return float("nan"), float("nan")
    q1, q2 = np.quantile(v, [1 / 3, 2 / 3])
    return float(q1), float(q2)


def strata(values: np.ndarray, edges: Sequence[float]) -> np.ndarray:
    """(W,) the stratum of each value for ``edges`` (q1, q2): ``low`` <= q1 < ``mid`` <= q2 < ``high``."""
    idx = np.searchsorted(np.asarray(edges, float), np.asarray(values, float), side="left")
    return np.asarray(STRATA, dtype=object)[np.clip(idx, 0, 2)]


def stratify(windows: pd.DataFrame, edges: dict[float, tuple[float, float]]) -> pd.DataFrame:
    """``windows`` (with ``horizon_s`` and ``aggressiveness``) with a ``stratum`` column from the edges of
    each horizon (``edges[horizon_s]``)."""
    out = windows.copy()
    out["stratum"] = ""
    for h, e in edges.items():
        rows = out["horizon_s"].to_numpy(float) == float(h)
        out.loc[rows, "stratum"] = strata(out.loc[rows, "aggressiveness"].to_numpy(float), e)
    return out
