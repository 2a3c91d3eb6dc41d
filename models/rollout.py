"""The ``state`` input protocol's data (issue 49): windows cut from a sequence at their start t0, each
holding the robot's past up to t0 (:class:`History`) and the window's commands (:class:`Commands`), and
nothing else.

What a model gets at a window starting at sample i (time t0), with ``m = round(history_s / dt)``:

* :class:`History`: the samples i-m .. i (times t0 - history_s .. t0): their times relative to t0 (<= 0),
  the ground-truth poses expressed in the body frame at t0 (the last one is 0), the protocol's inputs
  (the commanded ``cmd_*`` columns of :data:`~skidbench.pipeline.core.protocol.INPUT_COLUMNS`), the wheel
  encoders when the split has them (else None), and ``velocity``: the body velocity (vx, vy, wz) at t0
  estimated from the ground-truth poses of those samples only (:func:`causal_body_velocity`: the twists
  of the steps between them, fitted by a quadratic in time and evaluated at t0).
* :class:`Commands`: the samples i .. i+n of the window (times 0 .. horizon relative to t0) and the same
  input columns; never a pose, target or encoder reading.

Every array is a fresh copy (never a view of the sequence's arrays, which would reach the future through
``.base``). A window is cut only where the history and the window are all ``valid`` samples of one
sequence. Pure numpy: no stage, no model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: the input columns a window carries (the protocol's, without ``t``/``sequence``)
STATE_INPUTS = ("cmd_v", "cmd_w", "cmd_wl", "cmd_wr", "cmd_dwl", "cmd_dwr")
#: the default history (s) behind a window's initial velocity, and the estimator's polynomial order
HISTORY_S = 1.0
VELOCITY_ORDER = 2


@dataclass(frozen=True)
class History:
    """The past of W windows, H = m + 1 samples each (the last at t0). ``t`` (W, H) s relative to t0;
    ``pose`` (W, H, 3) ground-truth (x, y, yaw) in the body frame at t0 (m, m, rad); ``velocity`` (W, 3)
    the body velocity at t0 estimated from those poses (m/s, m/s, rad/s); ``inputs`` name -> (W, H) of
    :data:`STATE_INPUTS`; ``encoders`` (W, H, 2) measured wheel rates (rad/s) or None."""

    t: np.ndarray
    pose: np.ndarray
    velocity: np.ndarray
    inputs: dict[str, np.ndarray]
    encoders: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.t)


@dataclass(frozen=True)
class Commands:
    """The window of W windows, n + 1 samples each (the first at t0). ``t`` (W, n+1) s relative to t0;
    ``inputs`` name -> (W, n+1) of :data:`STATE_INPUTS`."""

    t: np.ndarray
    inputs: dict[str, np.ndarray]

    def __len__(self) -> int:
        return len(self.t)


def history_steps(dt: float, history_s: float) -> int:
    """Samples m behind t0 (at least the estimator's order + 1)."""
    return max(int(round(history_s / dt)), VELOCITY_ORDER + 1)


def endpoint_weights(m: int, dt: float, order: int = VELOCITY_ORDER) -> np.ndarray:
    """(m,) weights c with sum_j c_j y_j = the value at the end (tau = 0) of the least-squares polynomial
    of ``order`` through m samples y_j at the step midpoints tau_j = -(m - j - 1/2) dt: one-sided, reading
    nothing after the end."""
    tau = (np.arange(m) - m + 0.5) * dt
    return np.linalg.pinv(np.vander(tau, order + 1, increasing=True))[0]


def step_twists(pose: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """(T-1, 3) the constant body twist (vx, vy, wz) of each step between consecutive poses (T, 3): the
    SE(2) logarithm of the relative pose over the step's length (exact for the horizon's steps)."""
    d = np.diff(pose, axis=0)
    c, s = np.cos(pose[:-1, 2]), np.sin(pose[:-1, 2])
    x, y, th = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]
    small = np.abs(th) < 1e-9
    th_safe = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(th_safe) / th_safe)
    b = np.where(small, th / 2.0, (1.0 - np.cos(th_safe)) / th_safe)
    k = 1.0 / (a**2 + b**2)
    return np.column_stack([k * (a * x + b * y), k * (a * y - b * x), th]) / dt[:, None]


def causal_body_velocity(t: np.ndarray, pose: np.ndarray, history_s: float = HISTORY_S) -> np.ndarray:
    """(T, 3) body velocity (vx, vy, wz) at each sample from the poses of the ``history_s`` before it and
    the sample itself (one sequence on a uniform clock ``t``): the twists of the last m steps
    (:func:`step_twists`) fitted by a least-squares polynomial of order ``VELOCITY_ORDER`` in time,
    evaluated at the sample (:func:`endpoint_weights`). NaN for the first m samples (no full history)."""
    t, pose = np.asarray(t, float), np.asarray(pose, float)
    out = np.full((len(t), 3), np.nan)
    if len(t) < 2:
        return out
    dt = float(np.median(np.diff(t)))
    m = history_steps(dt, history_s)
    if len(t) <= m:
        return out
    twist = step_twists(pose, np.diff(t))
    c = endpoint_weights(m, dt)[::-1]  # np.convolve flips its kernel
    out[m:] = np.stack([np.convolve(twist[:, j], c, mode="valid") for j in range(3)], axis=-1)
    return out


def window_starts(valid: np.ndarray, m: int, n: int, stride: int = 1) -> np.ndarray:
    """Start samples i (every ``stride``-th) with a history of m samples and a window of n, all valid."""
    valid = np.asarray(valid, bool)
    T = len(valid)
    if T <= m + n:
        return np.zeros(0, dtype=int)
    bad = np.concatenate([[0], np.cumsum(~valid)])
    starts = np.arange(m, T - n, max(int(stride), 1))
    return starts[(bad[starts + n + 1] - bad[starts - m]) == 0]


@dataclass(frozen=True)
class Sequence:
    """One sequence's arrays the windows are cut from (uniform clock): ``t`` (T,), ``pose`` (T, 3),
    ``inputs`` name -> (T,), ``encoders`` (T, 2) or None, ``velocity`` (T, 3) from
    :func:`causal_body_velocity`."""

    t: np.ndarray
    pose: np.ndarray
    inputs: dict[str, np.ndarray]
    encoders: np.ndarray | None
    velocity: np.ndarray

    @classmethod
    def of(cls, table, history_s: float = HISTORY_S) -> Sequence:
        """From a split table (columns ``t``, ``x y yaw`` and :data:`STATE_INPUTS`; ``enc_wl``/``enc_wr``
        when every row has both)."""
        t = table["t"].to_numpy(float)
        pose = table[["x", "y", "yaw"]].to_numpy(float)
        inputs = {c: table[c].to_numpy(float) for c in STATE_INPUTS}
        enc = None
        if {"enc_wl", "enc_wr"} <= set(table.columns):
            e = table[["enc_wl", "enc_wr"]].to_numpy(float, na_value=np.nan)
            enc = e if np.isfinite(e).all() else None
        return cls(t, pose, inputs, enc, causal_body_velocity(t, pose, history_s))


def cut_windows(seq: Sequence, starts: np.ndarray, m: int, n: int) -> tuple[History, Commands]:
    """The :class:`History` (m samples back) and :class:`Commands` (n samples on) of the windows starting
    at ``starts`` (from :func:`window_starts`): fresh arrays, nothing after each window's t0 in the
    history."""
    starts = np.asarray(starts, int)
    back = starts[:, None] + np.arange(-m, 1)[None, :]  # (W, m+1)
    ahead = starts[:, None] + np.arange(n + 1)[None, :]  # (W, n+1)
    t0 = seq.t[starts]
    p0 = seq.pose[starts]
    rel = seq.pose[back] - p0[:, None, :]
    cos, sin = np.cos(p0[:, 2])[:, None], np.sin(p0[:, 2])[:, None]
    pose = np.stack([cos * rel[..., 0] + sin * rel[..., 1], -sin * rel[..., 0] + cos * rel[..., 1],
                     rel[..., 2]], axis=-1)  # fmt: skip
    history = History(
        t=seq.t[back] - t0[:, None],
        pose=pose,
        velocity=seq.velocity[starts].copy(),
        inputs={c: v[back] for c, v in seq.inputs.items()},
        encoders=None if seq.encoders is None else seq.encoders[back],
    )
    commands = Commands(t=seq.t[ahead] - t0[:, None], inputs={c: v[ahead] for c, v in seq.inputs.items()})
    return history, commands
