"""The wheels' response to their commands, identified from encoders: a dead time and a first-order lag
(:func:`apply`, :func:`identify`), and the general response built on them (:class:`WheelResponse`,
:func:`respond`, :func:`identify_response`: per sum/difference mode a gain, a saturation, a lag and a slew
limit, and the wheels' rate limit, its structure chosen on held-out blocks of the Train rows).

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
only to identify ``(delay_s, tau_s)`` on the Train split.

This module is the one home of the concept "the wheels do not follow their commands at once": the
``calibrate`` stage identifies the response per terrain from the Train encoders
(:func:`identify_response`), the ``response`` input protocol (:mod:`skidbench.pipeline.core.protocol`) drives
every model with it, and the discovery effect ``actuator_lag`` is its first-order lag of commands linear
between clock samples, :func:`lag_response` (restarted at each sequence start). The identification (the dead
time, the limits, the general response) builds on the zero-order-hold recursion :func:`lag_filter`; the
general response's recursion reduces to it exactly with unit gains and no limits.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd
from numba import njit
from scipy.optimize import least_squares, minimize_scalar
from scipy.signal import lfilter

CMD_COLUMNS = ("cmd_v", "cmd_w", "cmd_wl", "cmd_wr")


def lag_filter(table: pd.DataFrame, tau: float, groups: np.ndarray) -> pd.DataFrame:
    """Commands through a causal first-order lag with time constant ``tau`` (s), restarted at each
    group (sequence) start with the first command (a robot at rest starts where it is told).
    Returns a copy with ``cmd_*`` replaced and ``cmd_dwl``/``cmd_dwr`` = (u - y) / tau."""
    out = table.copy()
    t = table["t"].to_numpy(float)
    u = table[list(CMD_COLUMNS)].to_numpy(float)
    y = np.empty_like(u)
    starts = np.flatnonzero(np.r_[True, groups[1:] != groups[:-1]])
    ends = np.r_[starts[1:], len(t)]
    for a, b in zip(starts, ends, strict=True):
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
    the
    commanded rates at the clock (aligned with what the velocities see by discovery's ``align_commands``),
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
    starts = np.flatnonzero(np.r_[True, groups[1:] != groups[:-1]])
    ends = np.r_[starts[1:], len(t)]
    for a, b in zip(starts, ends, strict=True):
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


# --- the general wheel response ---------------------------------------------------------------------------
#
# DRIVE's Warthog shows what a dead time and a lag cannot: its encoders saturate at 13.67 rad/s while the
# commands reach 16.5, a skid turn gets 0.7-0.8 of its commanded wheel-rate difference (and ~0.5 beyond
# 9 rad/s: the motors cannot deliver the turn's torque), and a step is followed along a ramp (an
# acceleration limit) rather than an exponential. The general response works in the wheels' sum and
# difference modes, S = (wl + wr) / 2 and D = (wr - wl) / 2, which is where those limits differ:
#
#   1. dead time ``delay_s`` (continuous: the held command is interpolated between clock samples, so the
#      identification can move it smoothly; on the clock's grid it is the plain delay of :func:`delay`);
#   2. a static map per mode: m* = sign(m) min(gain |m|, sat) (``sat`` 0: none), then each wheel's target
#      clipped to +-(``wheel_max`` - ``wheel_drop`` |D*|) (``wheel_max`` 0: none; identified from the
#      encoders, so a lab need not hand-set it; ``wheel_drop``: a motor's speed falls with its torque);
#   3. per mode, a first-order lag whose rate is limited: dm/dt = clip((m* - m) / tau, -accel, accel)
#      (``accel`` 0: none), discretised as lag_filter's exact zero-order-hold recursion with the step
#      clipped to accel dt. Gain 1 and no limits give exactly :func:`apply` (the delay + lag model).
#
# Every stage is causal and reads only the commands: the encoders are needed only to identify it.

#: a slew limit or saturation below these is not tried (rad/s^2, rad/s)
ACCEL_MIN = 0.5
SAT_MIN = 0.5
#: the static gain's range
GAIN_RANGE = (0.2, 2.0)
#: candidate structures, simplest first, each the previous one plus: the free parameters of each ("lag" =
#: delay_s, tau_s shared by both modes; "slew" = one acceleration limit for both modes; "gain" = per-mode
#: gain and saturation and the wheel-rate saturation; "modes" = separate lag and slew limit for the
#: difference mode; "torque" = the wheel-rate limit falls with the turn: a motor's speed falls as its
#: torque rises, and a skid turn asks for torque)
_GAIN = ("gain_s", "gain_d", "sat_s", "sat_d", "wheel_max")
_MODES = ("delay_s", "tau_s", "tau_d_s", "accel_s", "accel_d", *_GAIN)
CANDIDATES = {
    "delay+lag": ("delay_s", "tau_s"),
    "delay+lag+slew": ("delay_s", "tau_s", "accel_s"),
    "delay+lag+slew+gain": ("delay_s", "tau_s", "accel_s", *_GAIN),
    "delay+lag+slew+gain+modes": _MODES,
    "delay+lag+slew+gain+modes+torque": (*_MODES, "wheel_drop"),
}  # fmt: skip
#: a richer structure is chosen only if its held-out Train RMSE is below the simpler one's by this fraction
SELECT_TOL = 0.02
#: contiguous blocks of the Train rows for the held-out structure choice
N_BLOCKS = 3


@dataclass(frozen=True)
class WheelResponse:
    """The general response's parameters (0 for a limit means no limit); see the section comment."""

    delay_s: float = 0.0
    tau_s: float = 0.0  # sum mode's lag, s
    tau_d_s: float = 0.0  # difference mode's lag, s
    accel_s: float = 0.0  # sum mode's rate limit, rad/s^2
    accel_d: float = 0.0  # difference mode's rate limit, rad/s^2
    gain_s: float = 1.0
    gain_d: float = 1.0
    sat_s: float = 0.0  # rad/s
    sat_d: float = 0.0  # rad/s
    wheel_max: float = 0.0  # rad/s
    wheel_drop: float = 0.0  # wheel_max lost per rad/s of (shaped) difference-mode rate

    def wheels(self, table: pd.DataFrame, groups: np.ndarray | None = None) -> np.ndarray:
        """(T, 4) the wheels' response (wl, wr, dwl, dwr) to ``table``'s commands: :func:`wheel_response`
        (what the ``response`` input protocol calls, so that ``pipeline/core/protocol.py`` needs no import of
        this module)."""
        return wheel_response(table, self, groups)

    def to_params(self) -> dict[str, float]:
        """The ``actuator_*`` entries of a model's ``params``."""
        return {f"actuator_{k}": float(v) for k, v in asdict(self).items()}

    @classmethod
    def from_params(cls, params: dict) -> WheelResponse:
        """From ``actuator_*`` params (older fits hold only ``actuator_delay_s``/``actuator_tau_s``: the
        difference mode then shares the sum mode's lag, and there are no limits)."""
        kw = {}
        for k in cls.__dataclass_fields__:
            v = params.get(f"actuator_{k}")
            if v is not None:
                kw[k] = float(v)
        if "tau_d_s" not in kw:
            kw["tau_d_s"] = kw.get("tau_s", 0.0)
        if "accel_d" not in kw:
            kw["accel_d"] = kw.get("accel_s", 0.0)
        return cls(**kw)

    @classmethod
    def from_dict(cls, data: dict) -> WheelResponse:
        """From a mapping holding (at least) the fields, e.g. a calibration document's ``wheel_response``."""
        return cls(**{k: float(data[k]) for k in cls.__dataclass_fields__ if data.get(k) is not None})

    @property
    def is_delay_lag(self) -> bool:
        """Unit gains, no limits and one lag: the delay + lag model of :func:`apply`."""
        return (
            self.gain_s == 1.0 and self.gain_d == 1.0 and self.tau_d_s == self.tau_s
            and not any((self.accel_s, self.accel_d, self.sat_s, self.sat_d, self.wheel_max, self.wheel_drop))
        )  # fmt: skip

    @property
    def is_identity(self) -> bool:
        return self.is_delay_lag and self.delay_s <= 0 and self.tau_s <= 0


@njit(cache=True)
def _slew_lag_loop(u: np.ndarray, alpha: np.ndarray, lim: np.ndarray) -> np.ndarray:
    """The recursion of :func:`_slew_lag`, compiled."""
    n, m = u.shape
    y = np.empty((n, m))
    for c in range(m):
        prev = u[0, c]
        y[0, c] = prev
        for k in range(1, n):
            step = alpha[k - 1, c] * (u[k, c] - prev)
            if step > lim[k - 1, c]:
                step = lim[k - 1, c]
            elif step < -lim[k - 1, c]:
                step = -lim[k - 1, c]
            prev = prev + step
            y[k, c] = prev
    return y


def _slew_lag(t: np.ndarray, u: np.ndarray, tau: np.ndarray, accel: np.ndarray) -> np.ndarray:
    """(n, m) for each column j of ``u`` (n, m): y_0 = u_0, y_k = y_k-1 + clip(alpha_k (u_k - y_k-1),
    -accel_j dt_k, accel_j dt_k), alpha_k = 1 - exp(-dt_k / tau_j): a first-order lag whose rate is
    limited (accel_j <= 0: none; tau_j <= 0: instant). The recursion itself is compiled (numba): the
    identification evaluates it some thousand times (a Python loop over the rows of a command that changes
    every row, as the simulated ones do, took 26 ms per call on 1,801 rows)."""
    u = np.ascontiguousarray(u, dtype=float)
    n, m = u.shape
    if n < 2:
        return u.copy()
    tau, accel = np.asarray(tau, float), np.asarray(accel, float)
    dt = np.diff(np.asarray(t, float))
    with np.errstate(divide="ignore"):
        alpha = np.where(tau > 0, 1.0 - np.exp(-dt[:, None] / np.where(tau > 0, tau, 1.0)), 1.0)  # (n-1, m)
    lim = np.where(accel > 0, accel * dt[:, None], np.inf)  # (n-1, m)
    return _slew_lag_loop(u, np.ascontiguousarray(alpha), np.ascontiguousarray(lim))


def _shape(m: np.ndarray, gain: float, sat: float) -> np.ndarray:
    out = gain * m
    return np.clip(out, -sat, sat) if sat > 0 else out


def wheel_response(table: pd.DataFrame, resp: WheelResponse, groups: np.ndarray | None = None) -> np.ndarray:
    """(T, 4) the wheels' rates and their derivatives (wl, wr, dwl, dwr) the response ``resp`` gives to
    ``table``'s ``cmd_wl``/``cmd_wr``, restarted at each sequence start from its first (shaped) command."""
    groups = groups_of(table) if groups is None else groups
    t = table["t"].to_numpy(float)
    # column by column: selecting a list of columns costs more than the response itself (the fits call
    # this a few thousand times on the same table)
    cmd_l, cmd_r = table["cmd_wl"].to_numpy(float), table["cmd_wr"].to_numpy(float)
    out = np.empty((len(t), 4))
    if len(t) == 0:
        return out
    step = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    # one more clock step than the dead time, as in :func:`apply` (the zero-order-hold lag's y_k responds
    # to u_k, the continuous lag's y(t_k) to the command held before t_k)
    lag_step = step if (resp.tau_s > 0 or resp.tau_d_s > 0 or resp.accel_s > 0 or resp.accel_d > 0) else 0.0
    d = max(resp.delay_s, 0.0) + lag_step
    starts = np.flatnonzero(np.r_[True, groups[1:] != groups[:-1]])
    ends = np.r_[starts[1:], len(t)]
    for a, b in zip(starts, ends, strict=True):
        ts = t[a:b]
        if d > 0:
            # before the sequence: its first command; on a uniform clock in sample units (a delay on the
            # clock's grid is then an exact shift, as in :func:`delay`)
            x, xp = ts - d, ts
            if b - a > 1 and np.allclose(np.diff(ts), step):
                k = d / step
                k = round(k) if abs(k - round(k)) < 1e-6 else k
                x, xp = np.arange(b - a) - k, np.arange(b - a)
            ul, ur = np.interp(x, xp, cmd_l[a:b]), np.interp(x, xp, cmd_r[a:b])
        else:
            ul, ur = cmd_l[a:b], cmd_r[a:b]
        S = _shape((ul + ur) / 2.0, resp.gain_s, resp.sat_s)
        D = _shape((ur - ul) / 2.0, resp.gain_d, resp.sat_d)
        if resp.wheel_max > 0:
            top = np.maximum(resp.wheel_max - resp.wheel_drop * np.abs(D), 0.0)
            wl, wr = np.clip(S - D, -top, top), np.clip(S + D, -top, top)
            S, D = (wl + wr) / 2.0, (wr - wl) / 2.0
        y = _slew_lag(ts, np.c_[S, D], [resp.tau_s, resp.tau_d_s], [resp.accel_s, resp.accel_d])
        ys, yd = y[:, 0], y[:, 1]
        rs = _rate(S, ys, resp.tau_s, resp.accel_s)
        rd = _rate(D, yd, resp.tau_d_s, resp.accel_d)
        out[a:b] = np.c_[ys - yd, ys + yd, rs - rd, rs + rd]
    return out


def _rate(u: np.ndarray, y: np.ndarray, tau: float, accel: float) -> np.ndarray:
    """The lag's continuous-time rate at each sample: clip((u - y) / tau, -accel, accel)."""
    r = (u - y) / max(tau, 1e-6)
    return np.clip(r, -accel, accel) if accel > 0 else r


def respond(table: pd.DataFrame, resp: WheelResponse) -> pd.DataFrame:
    """``table`` with its wheel commands replaced by the response's output (``cmd_wl``, ``cmd_wr`` and
    their derivatives ``cmd_dwl``, ``cmd_dwr``; ``cmd_v``/``cmd_w`` follow the wheels through the table's
    own linear relation to them). The delay + lag special case is :func:`apply` itself."""
    if resp.is_identity:
        return table
    if resp.is_delay_lag:
        return apply(table, resp.delay_s, resp.tau_s)
    out = table.copy()
    w = wheel_response(table, resp)
    S0 = (table["cmd_wl"].to_numpy(float) + table["cmd_wr"].to_numpy(float)) / 2.0
    D0 = (table["cmd_wr"].to_numpy(float) - table["cmd_wl"].to_numpy(float)) / 2.0
    for c, m0, m1 in (("cmd_v", S0, (w[:, 0] + w[:, 1]) / 2.0), ("cmd_w", D0, (w[:, 1] - w[:, 0]) / 2.0)):
        if c in out.columns:
            den = float(m0 @ m0)
            k = float(m0 @ out[c].to_numpy(float)) / den if den > 0 else 0.0
            out[c] = k * m1
    for j, c in enumerate(("cmd_wl", "cmd_wr", "cmd_dwl", "cmd_dwr")):
        out[c] = w[:, j]
    return out


# the identification's coordinates: delay linear, lags in log, limits as their inverses (0 = none)
def _to_z(name: str, v: float) -> float:
    if name.startswith("tau"):
        return float(np.log(np.clip(v, *TAU_RANGE)))
    if name.startswith(("accel", "sat", "wheel_max")):
        return 0.0 if v <= 0 else 1.0 / v
    return float(v)  # delay_s, gains, wheel_drop


def _from_z(name: str, z: float) -> float:
    if name.startswith("tau"):
        return float(np.exp(z))
    if name.startswith(("accel", "sat", "wheel_max")):
        return 0.0 if z <= 1e-9 else 1.0 / z
    return float(z)


def _z_bounds(name: str) -> tuple[float, float]:
    if name == "delay_s":
        return 0.0, MAX_DELAY_S
    if name.startswith("tau"):
        return float(np.log(TAU_RANGE[0])), float(np.log(TAU_RANGE[1]))
    if name.startswith("accel"):
        return 0.0, 1.0 / ACCEL_MIN
    if name.startswith(("sat", "wheel_max")):
        return 0.0, 1.0 / SAT_MIN
    if name == "wheel_drop":
        return 0.0, 1.0
    return GAIN_RANGE


def _with(base: WheelResponse, names: tuple[str, ...], z: np.ndarray) -> WheelResponse:
    kw = asdict(base)
    for n, v in zip(names, z, strict=True):
        kw[n] = _from_z(n, float(v))
    if "tau_d_s" not in names:
        kw["tau_d_s"] = kw["tau_s"]
    if "accel_d" not in names:
        kw["accel_d"] = kw["accel_s"]
    return WheelResponse(**kw)


@dataclass(frozen=True)
class ResponseFit:
    response: WheelResponse  # the selected structure refitted on all Train rows
    structure: str  # its name in CANDIDATES
    candidates: dict  # name -> {"train_rmse", "heldout_rmse" (None: not held out), "params", "param_se"}
    rmse_command: float  # rad/s: encoders against the raw commands
    rmse_response: float  # rad/s: encoders against the selected response
    n_rows: int

    @property
    def param_se(self) -> dict:
        """The selected structure's parameters' block-jackknife standard errors (same units as them)."""
        return dict(self.candidates[self.structure].get("param_se") or {})

    def to_dict(self) -> dict:
        return {
            "structure": self.structure,
            **asdict(self.response),
            "param_se": self.param_se,
            "heldout_rmse": self.candidates[self.structure].get("heldout_rmse"),
            "rmse_command": self.rmse_command,
            "rmse_response": self.rmse_response,
            "n_rows": self.n_rows,
            "candidates": self.candidates,
            "selection": f"{N_BLOCKS} contiguous Train blocks held out in turn; the simplest structure "
            f"within {SELECT_TOL:.0%} of the best held-out RMSE",
            "uncertainty": f"param_se: block jackknife over the {N_BLOCKS} leave-one-block-out refits",
        }


def _fit_structure(
    table: pd.DataFrame, groups: np.ndarray, enc: np.ndarray, rows: np.ndarray, names: tuple[str, ...],
    start: WheelResponse, max_nfev: int,
) -> WheelResponse:  # fmt: skip
    """The structure ``names`` (the other parameters at their neutral values) fitted by least squares to
    the encoders on ``rows``, from ``start``'s values of ``names``."""

    def resid(z):
        w = wheel_response(table, _with(WheelResponse(), names, z), groups)
        return (w[rows, :2] - enc[rows]).ravel()

    bounds = np.array([_z_bounds(n) for n in names]).T
    z0 = np.clip([_to_z(n, getattr(start, n)) for n in names], bounds[0], bounds[1])
    res = least_squares(
        resid, z0, bounds=bounds, method="trf", x_scale="jac", diff_step=1e-3, max_nfev=max_nfev
    )
    return _with(WheelResponse(), names, res.x)


def identify_response(
    table: pd.DataFrame, candidates: tuple[str, ...] | None = None, max_nfev: int = 30, fold_nfev: int = 8
) -> ResponseFit | None:
    """The wheel response of ``table``'s encoders (``enc_wl``, ``enc_wr``; Train), or None without
    ``MIN_ROWS`` rows of readings. Each candidate structure (``CANDIDATES``, simplest first) is fitted by
    least squares on the encoder rows, from the previous candidate's fit (the first from the delay + lag
    grid search of :func:`identify`) and, for its new parameters, from where the encoders put them (the
    largest wheel, sum and difference rates they read; a slew limit at half the largest acceleration the
    delay + lag model asks for). The structure is chosen on Train only: each of ``N_BLOCKS`` contiguous
    blocks of the encoder rows is held out in turn (refitted from the candidate's fit on the others), and
    the simplest structure whose pooled held-out RMSE is within ``SELECT_TOL`` of the best wins (a robot
    whose wheels follow their commands through a lag keeps the delay + lag model). A structure whose
    Train RMSE is not ``SELECT_TOL`` below the best simpler one's is not held out (``heldout_rmse``
    None: it cannot win)."""
    base = identify(table)
    if base is None:
        return None
    names_all = tuple(candidates or CANDIDATES)
    unknown = [n for n in names_all if n not in CANDIDATES]
    if unknown:
        raise ValueError(f"unknown actuator structures {unknown} (known: {list(CANDIDATES)})")
    groups = groups_of(table)
    enc = table[["enc_wl", "enc_wr"]].to_numpy(float)
    rows = np.flatnonzero(np.all(np.isfinite(enc), axis=1))
    lag = WheelResponse(delay_s=base.delay_s, tau_s=base.tau_s, tau_d_s=base.tau_s)
    w0 = wheel_response(table, lag, groups)
    S_e, D_e = (enc[rows, 0] + enc[rows, 1]) / 2.0, (enc[rows, 1] - enc[rows, 0]) / 2.0
    a0 = max(0.5 * float(np.percentile(np.abs(w0[rows, 2:]), 99)), 2 * ACCEL_MIN)
    guess = dict(
        asdict(lag), accel_s=a0, accel_d=a0, sat_s=float(np.abs(S_e).max()), sat_d=float(np.abs(D_e).max()),
        wheel_max=float(np.abs(enc[rows]).max()), wheel_drop=0.2,
    )  # fmt: skip
    blocks = np.array_split(rows, N_BLOCKS)
    cands: dict = {}
    fitted: dict = {}
    for name in names_all:
        names = CANDIDATES[name]
        full = _fit_structure(table, groups, enc, rows, names, WheelResponse(**guess), max_nfev)
        guess.update({n: getattr(full, n) for n in names})
        if "tau_d_s" not in names:
            guess["tau_d_s"] = full.tau_s
        if "accel_d" not in names and "accel_s" in names:
            guess["accel_d"] = full.accel_s
        fitted[name] = full
        e = wheel_response(table, full, groups)[rows, :2] - enc[rows]
        train_rmse = float(np.sqrt(np.mean(e**2)))
        cands[name] = {"train_rmse": train_rmse, "params": {n: float(getattr(full, n)) for n in names}}
        # a structure that does not beat the best simpler one by SELECT_TOL on the rows it was fitted to is
        # taken not to beat it on held-out rows either: it is not held out (saves its refits)
        simpler = [c["train_rmse"] for c in cands.values() if c.get("heldout_rmse") is not None]
        if simpler and train_rmse > (1.0 - SELECT_TOL) * min(simpler):
            cands[name]["heldout_rmse"] = None
            continue
        sq, count, folds = 0.0, 0, []
        for i, held in enumerate(blocks):
            fit_rows = np.concatenate([b for j, b in enumerate(blocks) if j != i])
            r = _fit_structure(table, groups, enc, fit_rows, names, full, fold_nfev)
            folds.append([float(getattr(r, n)) for n in names])
            e = wheel_response(table, r, groups)[held, :2] - enc[held]
            sq, count = sq + float(np.sum(e**2)), count + e.size
        cands[name]["heldout_rmse"] = float(np.sqrt(sq / count))
        # the parameters' uncertainty: the block jackknife of the leave-one-block-out refits (contiguous
        # blocks: neighbouring rows are correlated, and a per-row Jacobian error would be far too small)
        f = np.asarray(folds)
        k = len(f)
        se = np.sqrt((k - 1) / k * np.sum((f - f.mean(axis=0)) ** 2, axis=0))
        cands[name]["param_se"] = {n: float(v) for n, v in zip(names, se, strict=True)}
    scored = [n for n in names_all if cands[n]["heldout_rmse"] is not None]
    best = min(cands[n]["heldout_rmse"] for n in scored)
    chosen = next(n for n in scored if cands[n]["heldout_rmse"] <= (1.0 + SELECT_TOL) * best)
    return ResponseFit(
        fitted[chosen], chosen, cands, base.rmse_command, cands[chosen]["train_rmse"], int(rows.size)
    )
