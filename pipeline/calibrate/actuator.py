"""The actuator's dead time and first-order lag: the simplest answer to "the wheels do not follow their
commands at once", and the base the general wheel response (:mod:`.wheel_response`) builds on.

A real robot's wheels do not turn at the commanded rate the instant it is commanded: the command reaches
the motor controller late (dead time ``delay_s``) and the speed loop follows it through a lag (time
constant ``tau_s``): ``tau dw/dt = w_cmd(t - delay) - w``. On DRIVE's Husky an encoder reaches half of a
command step 0.7 s after it and 90 % after 1.2 s (Train split). The split's commanded accelerations are
the derivatives of a held command: a step becomes a pulse two samples long (central differences, each
sample half the step over one sample period) of up to 270 rad/s^2, which no
friction can deliver and which forces a friction model given them to explain a pulse in M a the robot
never had. Driving the force balance with the actuator's output instead (the rates the wheels can
actually have, and their finite accelerations ``(w_cmd(t - delay) - w) / tau``) keeps the model a
function of the commands only, so it still predicts on data without encoders; the encoders are needed
only to identify ``(delay_s, tau_s)`` on the Train split (:func:`identify`; :func:`apply` runs it).

The zero-order-hold recursion :func:`lag_filter` is what the identification and the general response
build on; the discovery effect ``actuator_lag`` is :func:`lag_response`, the first-order lag of commands
linear between clock samples (restarted at each sequence start).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd
from scipy.optimize import minimize_scalar
from scipy.signal import lfilter

CMD_COLUMNS = ("cmd_v", "cmd_w", "cmd_wl", "cmd_wr")


def runs(groups: np.ndarray) -> list[tuple[int, int]]:
    """``(start, end)`` of each run of equal ``groups`` values (one per row: a sequence's rows), in order."""
    starts = np.flatnonzero(np.r_[True, groups[1:] != groups[:-1]])
    return list(zip(starts.tolist(), np.r_[starts[1:], len(groups)].tolist(), strict=True))


def lag_filter(table: pd.DataFrame, tau: float, groups: np.ndarray) -> pd.DataFrame:
    """Commands through a causal first-order lag with time constant ``tau`` (s), restarted at each
    group (sequence) start with the first command (a robot at rest starts where it is told).
    Returns a copy with ``cmd_*`` replaced and ``cmd_dwl``/``cmd_dwr`` = (u - y) / tau."""
    out = table.copy()
    t = table["t"].to_numpy(float)
    u = table[list(CMD_COLUMNS)].to_numpy(float)
    y = np.empty_like(u)
    for a, b in runs(groups):
        y[a] = u[a]
        if b - a < 2:
            continue
        dt = np.diff(t[a:b])
        alpha = 1.0 - np.exp(-dt / max(tau, 1e-6))  # exact zero-order-hold discretisation
        seg_u = u[a + 1 : b]
        prev = u[a].copy()
        # a first-order recursion y_k = y_{k-1} + alpha_k (u_k - y_{k-1}); alpha varies only with dt
        if np.allclose(alpha, alpha[0]):
            al = float(alpha[0])
            zi = ((1.0 - al) * prev)[None, :]
            y[a + 1 : b] = lfilter([al], [1.0, -(1.0 - al)], seg_u, axis=0, zi=zi)[0]
        else:  # non-uniform clock: plain loop (rare)
            for k in range(len(seg_u)):
                prev = prev + alpha[k] * (seg_u[k] - prev)
                y[a + 1 + k] = prev
    for j, c in enumerate(CMD_COLUMNS):
        out[c] = y[:, j]
    out["cmd_dwl"] = (u[:, 2] - y[:, 2]) / max(tau, 1e-6)
    out["cmd_dwr"] = (u[:, 3] - y[:, 3]) / max(tau, 1e-6)
    return out


def lag_response(table: pd.DataFrame, tau: float, groups: np.ndarray) -> pd.DataFrame:
    """The continuous first-order lag ``tau dy/dt = u - y`` of commands that vary linearly between clock
    samples, sampled at the clock (restarted at each group start at rest on its first command): the exact
    first-order-hold discretisation ``y_k = e y_k-1 + (1 - e) u_k-1 + c (u_k - u_k-1)``, ``e =
    exp(-dt/tau)``, ``c = 1 - tau (1 - e) / dt``. Returns a copy with ``cmd_*`` replaced and
    ``cmd_dwl``/``cmd_dwr`` = (u - y) / tau, the response's derivative at the sample.

    The discovery effect ``actuator_lag`` (models/augmented/effects.py). The split's commands are samples of
    the commanded rates at the clock (aligned with what the velocities see by discovery's ``align_commands``),
    and the horizon integrates the predicted velocities as linear between samples (the trapezoidal rule):
    the lag of that same piecewise-linear signal is the consistent one. :func:`lag_filter`'s recursion
    lets ``y_k`` respond to ``u_k`` over the whole step before it (half a step early), its delayed form in
    :func:`apply` half a step late; on a lag of 80 ms at 30 Hz either leaves a residual that an extra
    acceleration slip on top of the lag fits (a false second name in discovery)."""
    out = table.copy()
    t = table["t"].to_numpy(float)
    u = table[list(CMD_COLUMNS)].to_numpy(float)
    y = np.empty_like(u)
    tau = max(float(tau), 1e-6)
    for a, b in runs(groups):
        y[a] = u[a]
        if b - a < 2:
            continue
        dt = np.diff(t[a:b])
        if np.allclose(dt, dt[0]):  # y_k = e y_k-1 + c u_k + (1 - e - c) u_k-1, from rest on u_a
            e = float(np.exp(-dt[0] / tau))
            c = 1.0 - tau * (1.0 - e) / dt[0]
            zi = ((1.0 - c) * u[a])[None, :]  # the filter's state at rest on u_a (y_a = u_a)
            y[a:b] = lfilter([c, 1.0 - e - c], [1.0, -e], u[a:b], axis=0, zi=zi)[0]
            continue
        for k in range(1, b - a):  # non-uniform clock (rare)
            e = float(np.exp(-dt[k - 1] / tau))
            c = 1.0 - tau * (1.0 - e) / dt[k - 1]
            y[a + k] = e * y[a + k - 1] + (1.0 - e) * u[a + k - 1] + c * (u[a + k] - u[a + k - 1])
    for j, col in enumerate(CMD_COLUMNS):
        out[col] = y[:, j]
    out["cmd_dwl"] = (u[:, 2] - y[:, 2]) / tau
    out["cmd_dwr"] = (u[:, 3] - y[:, 3]) / tau
    return out


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
    out = table.copy()
    if delay_s <= 0 or len(table) < 2:
        return out
    groups = groups_of(table) if groups is None else groups
    t = table["t"].to_numpy(float)
    u = table[list(CMD_COLUMNS)].to_numpy(float)
    y = u.copy()
    for a, b in runs(groups):
        src = np.searchsorted(t[a:b], t[a:b] - delay_s + 1e-9, side="right") - 1  # last sample <= t - d
        y[a:b] = u[a:b][np.clip(src, 0, None)]
    for j, c in enumerate(CMD_COLUMNS):
        out[c] = y[:, j]
    return out


def apply(table: pd.DataFrame, delay_s: float, tau_s: float) -> pd.DataFrame:
    """``table`` with its wheel commands replaced by the actuator's output: delayed by ``delay_s``, then
    through the lag ``tau_s``; ``cmd_dwl``/``cmd_dwr`` become the output's derivatives. ``tau_s <= 0``
    and ``delay_s <= 0`` leave the commands as they are."""
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
