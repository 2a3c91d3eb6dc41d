"""The wheels' response to their commands: a dead time and a first-order lag, identified from encoders.

A real robot's wheels do not turn at the commanded rate the instant it is commanded: the command reaches
the motor controller late (dead time ``delay_s``) and the speed loop follows it through a lag (time
constant ``tau_s``): ``tau dw/dt = w_cmd(t - delay) - w``. On DRIVE's Husky an encoder reaches half of a
command step 0.7 s after it and 90 % after 1.2 s (Train split). The split's commanded accelerations are
the derivatives of a held command: a step becomes a one-sample pulse of up to 270 rad/s^2, which no
friction can deliver and which forces a friction model given them to explain a pulse in M a the robot
never had. Driving the force balance with the actuator's output instead (the rates the wheels can
actually have, and their finite accelerations ``(w_cmd(t - delay) - w) / tau``) keeps the model a
function of the commands only, so it still predicts on data without encoders; the encoders are needed
only to identify ``(delay_s, tau_s)`` on the Train split.

The lag itself is :func:`skidbench.benchmark.effects.lag_filter` (the one home of the first-order command
lag, restarted at each sequence start); this module adds the dead time and the identification.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd
from scipy.optimize import minimize_scalar

#: dead times tried by :func:`identify` (s): 0 .. 0.6 s on the split clock
MAX_DELAY_S = 0.6
#: the lag's time-constant range (s)
TAU_RANGE = (0.01, 3.0)
#: rows with finite encoder readings needed to identify the actuator
MIN_ROWS = 300


@dataclass(frozen=True)
class ActuatorFit:
    delay_s: float  # dead time, s
    tau_s: float  # first-order time constant, s
    rmse_command: float  # rad/s: encoders against the raw commands
    rmse_actuator: float  # rad/s: encoders against the actuator's output
    n_rows: int  # rows (wheel samples / 2) the identification used

    def to_dict(self) -> dict:
        return asdict(self)


def groups_of(table: pd.DataFrame) -> np.ndarray:
    """(T,) sequence labels (one group when the table has no ``sequence`` column)."""
    if "sequence" in table.columns:
        return table["sequence"].astype(str).to_numpy()
    return np.zeros(len(table), dtype=int)


def delay(table: pd.DataFrame, delay_s: float, groups: np.ndarray | None = None) -> pd.DataFrame:
    """A copy of ``table`` whose commands (``cmd_v``, ``cmd_w``, ``cmd_wl``, ``cmd_wr``) are those of
    ``delay_s`` earlier, per sequence; the first ``delay_s`` of a sequence holds its first command."""
    from skidbench.benchmark.effects import CMD_COLUMNS

    out = table.copy()
    if delay_s <= 0 or len(table) < 2:
        return out
    groups = groups_of(table) if groups is None else groups
    t = table["t"].to_numpy(float)
    u = table[list(CMD_COLUMNS)].to_numpy(float)
    y = u.copy()
    starts = np.flatnonzero(np.r_[True, groups[1:] != groups[:-1]])
    ends = np.r_[starts[1:], len(t)]
    for a, b in zip(starts, ends, strict=True):
        src = np.searchsorted(t[a:b], t[a:b] - delay_s + 1e-9, side="right") - 1  # last sample <= t - d
        y[a:b] = u[a:b][np.clip(src, 0, None)]
    for j, c in enumerate(CMD_COLUMNS):
        out[c] = y[:, j]
    return out


def apply(table: pd.DataFrame, delay_s: float, tau_s: float) -> pd.DataFrame:
    """``table`` with its wheel commands replaced by the actuator's output: delayed by ``delay_s``, then
    through the lag ``tau_s``; ``cmd_dwl``/``cmd_dwr`` become the output's derivatives. ``tau_s <= 0``
    and ``delay_s <= 0`` leave the commands as they are."""
    from skidbench.benchmark.effects import lag_filter

    groups = groups_of(table)
    if tau_s <= 0:
        return delay(table, delay_s, groups)
    # lag_filter's exact zero-order-hold recursion y_k = y_k-1 + alpha (u_k - y_k-1) lets y_k respond to
    # u_k, the command that holds from t_k on; the continuous lag's y(t_k) responds to the command held
    # over [t_k-1, t_k), u_k-1: one more clock step of delay makes the output the continuous response
    t = table["t"].to_numpy(float)
    step = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    return lag_filter(delay(table, delay_s + step, groups), tau_s, groups)


def _encoder_error(table: pd.DataFrame, delay_s: float, tau_s: float, rows: np.ndarray) -> float:
    out = apply(table, delay_s, tau_s)
    pred = out[["cmd_wl", "cmd_wr"]].to_numpy(float)[rows]
    enc = table[["enc_wl", "enc_wr"]].to_numpy(float)[rows]
    return float(np.sqrt(np.mean((pred - enc) ** 2)))


def identify(table: pd.DataFrame) -> ActuatorFit | None:
    """(delay_s, tau_s) minimising the RMS difference between the actuator's output and the encoders
    (``enc_wl``, ``enc_wr``) over the rows where both encoders read; None when fewer than ``MIN_ROWS``
    rows have readings (no encoders: the actuator cannot be identified). Dead times on the table's own
    clock from 0 to ``MAX_DELAY_S``; for each, the time constant by a bounded scalar search (the error is
    unimodal in tau for a fixed dead time on a step-like command)."""
    if not {"enc_wl", "enc_wr", "t"} <= set(table.columns):
        return None
    enc = table[["enc_wl", "enc_wr"]].to_numpy(float)
    rows = np.flatnonzero(np.all(np.isfinite(enc), axis=1))
    if rows.size < MIN_ROWS:
        return None
    t = table["t"].to_numpy(float)
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    if not np.isfinite(dt) or dt <= 0:
        return None
    best = None
    for k in range(int(round(MAX_DELAY_S / dt)) + 1):
        d = k * dt
        res = minimize_scalar(
            lambda lt, d=d: _encoder_error(table, d, float(np.exp(lt)), rows),
            bounds=np.log(TAU_RANGE),
            method="bounded",
            options={"xatol": 1e-3},
        )
        if best is None or res.fun < best[0]:
            best = (float(res.fun), d, float(np.exp(res.x)))
    e0 = _encoder_error(table, 0.0, 0.0, rows)
    return ActuatorFit(best[1], best[2], e0, best[0], int(rows.size))
