"""The wheels' general response to their commands, identified from encoders (:class:`WheelResponse`,
:func:`respond`, :func:`identify_response`): per sum/difference mode a gain, a saturation, a lag and a slew
limit, and the wheels' rate limit, its structure chosen on held-out blocks of the Train rows. Its
simplest member is the dead time and first-order lag of :mod:`.actuator`, which it builds on.

The ``calibrate`` stage identifies the response per terrain from the Train encoders
(:func:`identify_response`) and the ``response`` input protocol (:mod:`skidbench.pipeline.core.protocol`)
drives every model with it. The general response's recursion reduces exactly to the actuator's
zero-order-hold :func:`~.actuator.lag_filter` with unit gains and no limits.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd
from numba import njit
from scipy.optimize import least_squares

from skidbench.pipeline.calibrate.actuator import (
    MAX_DELAY_S,
    TAU_RANGE,
    apply,
    groups_of,
    identify,
    runs,
)

# --- the general wheel response ---------------------------------------------------------------------------
#
# DRIVE's Warthog shows what a dead time and a lag cannot: its encoders saturate at 13.67 rad/s while the
# commands reach 16.5, a skid turn gets 0.7-0.8 of its commanded wheel-rate difference (and ~0.5 beyond
# 9 rad/s: the motors cannot deliver the turn's torque), and a step is followed along a ramp (an
# acceleration limit) rather than an exponential. The general response works in the wheels' sum and
# difference modes, S = (wl + wr) / 2 and D = (wr - wl) / 2, which is where those limits differ:
#
#   1. dead time ``delay_s`` (continuous: the held command is interpolated between clock samples, so the
#      identification can move it smoothly; on the clock's grid it is the plain delay of
#      :func:`.actuator.delay`);
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
    for a, b in runs(groups):
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
    ``actuator.MIN_ROWS`` rows of readings. Each candidate structure (``CANDIDATES``, simplest first) is
    fitted by
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
