"""A first-order body-velocity model (issue 49; DRIVE's powertrain idea, Baril et al., applied to the body):
the body velocity relaxes from the robot's state at the window start toward what a kinematic model
predicts, with a time constant per axis.

    v_a(k+1) = e_a v_a(k) + (1 - e_a) u_a(k+1),   e_a = exp(-dt / tau_a),   v_a(0) = v0_a

for the axes a = vx, vy, wz, with u the base kinematic model's prediction of the window's commands and
v0 the body velocity at t0 the ``state`` protocol estimates from the ground truth (models/rollout.py). At
tau -> 0 it is the base model; at a large tau the robot keeps its initial velocity. Fitted on Train only:
the base model first (its own fit), then each tau_a by a bounded scalar search (``scipy.optimize.
minimize_scalar`` on log tau) of the squared velocity error over Train windows of ``fit_horizon_s``
(starts ``fit_stride_s`` apart), each window started from its own estimated state. The three axes are
independent, so three 1-D searches. ``rollout`` is batched: one base prediction of every window's commands
(each window its own sequence) and ``scipy.signal.lfilter`` along the steps.

Under the other protocols (no state) ``predict`` relaxes from the base model's first value of each
sequence: a first-order lag of the base model.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd
from scipy.optimize import minimize_scalar
from scipy.signal import lfilter

from skidbench.models import rollout as st
from skidbench.models.base import KinematicModel, ModelError
from skidbench.models.columns import mse, sequence_starts, targets

AXES = ("vx", "vy", "wz")


def relax(u: np.ndarray, v0: np.ndarray, t: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """(W, n+1, 3) the first-order response to the targets ``u`` (W, n+1, 3) from ``v0`` (W, 3) at times
    ``t`` (W, n+1) (uniform steps) with time constants ``tau`` (3,) s (module docstring)."""
    u = np.asarray(u, float)
    out = np.empty_like(u)
    out[:, 0] = v0
    if u.shape[1] < 2:
        return out
    dt = float(np.median(np.diff(t, axis=1)))
    for a in range(3):
        out[:, 1:, a] = relax_axis(u[:, 1:, a], v0[:, a], dt, float(tau[a]))
    return out


def relax_axis(u: np.ndarray, v0: np.ndarray, dt: float, tau: float) -> np.ndarray:
    """(W, n) one axis' response at steps 1..n to its targets ``u`` (W, n) from ``v0`` (W,)."""
    e = float(np.exp(-dt / max(tau, 1e-9)))
    return lfilter([1.0 - e], [1.0, -e], u, axis=1, zi=(e * v0)[:, None])[0]


def window_table(commands: st.Commands) -> pd.DataFrame:
    """The windows' commands as one table of the protocol's input columns, each window its own sequence
    (what a kinematic model's ``predict`` takes), W*(n+1) rows, window by window."""
    W, n1 = commands.t.shape
    out = pd.DataFrame({"t": commands.t.ravel(), "sequence": np.repeat(np.arange(W), n1).astype(str)})
    for c in st.STATE_INPUTS:
        out[c] = commands.inputs[c].ravel()
    return out


def training_windows(table: pd.DataFrame, horizon_s: float, stride_s: float, history_s: float):
    """Yields ``(history, commands, true velocities (W, n+1, 3))`` of a Train table
    (inputs, poses and targets), per sequence, windows ``stride_s`` apart with a full history."""
    starts_of = np.flatnonzero(sequence_starts(table))
    ends = np.r_[starts_of[1:], len(table)]
    for a, b in zip(starts_of, ends, strict=True):
        df = table.iloc[a:b]
        t = df["t"].to_numpy(float)
        if len(t) < 3:
            continue
        dt = float(np.median(np.diff(t)))
        n, m = int(round(horizon_s / dt)), st.history_steps(dt, history_s)
        starts = st.window_starts(df["valid"].to_numpy(bool), m, n, max(int(round(stride_s / dt)), 1))
        if not len(starts):
            continue
        history, commands = st.cut_windows(st.Sequence.of(df, history_s), starts, m, n)
        true = targets(df)[starts[:, None] + np.arange(n + 1)[None, :]]
        yield history, commands, true


class OnKinematicBase(KinematicModel):
    """A dynamics model built on a fitted kinematic model: ``params["base_model"]`` holds the base's fit
    (its JSON), loaded once by :meth:`base`."""

    def __init__(self, robot, params=None, **options):
        super().__init__(robot, params, **options)
        self._base: KinematicModel | None = None

    def base(self) -> KinematicModel:
        if self._base is None:
            from skidbench.models.registry.specs import get_model_class

            data = self.params.get("base_model")
            if not data:
                raise ModelError(f"model {self.name}: not fitted (no base model)")
            self._base = get_model_class(data["model"]).from_json(self.robot, data)
        return self._base


class FirstOrderRelaxation(OnKinematicBase):
    name = "relax"
    version = "1.0"
    required_columns = ("cmd_wl", "cmd_wr", "cmd_dwl", "cmd_dwr")
    DEFAULTS: dict[str, Any] = {
        "base": "edd",  # the kinematic model relaxed toward (any installed model)
        "base_options": {},
        "fit_horizon_s": 2.0,  # s: the Train windows the time constants are fitted on
        "fit_stride_s": 0.25,  # s between their starts
        "history_s": st.HISTORY_S,  # s behind a Train window's initial velocity (as the protocol's)
        "tau_bounds": [0.005, 10.0],  # s
    }

    def tau(self) -> np.ndarray:
        return np.array([float(self.params["tau"][a]) for a in AXES])

    def fit(self, table: pd.DataFrame) -> FirstOrderRelaxation:
        from skidbench.models.registry.specs import get_model_class

        self.check_columns(table, fitting=True)
        o = self.options
        base = get_model_class(str(o["base"]))(self.robot, **dict(o["base_options"] or {})).fit(table)
        self._base, self.params = base, {"base_model": base.to_json()}
        windows = list(
            training_windows(table, *(float(o[k]) for k in ("fit_horizon_s", "fit_stride_s", "history_s")))
        )
        if not windows:
            raise ModelError(
                f"model {self.name}: no Train window of {o['fit_horizon_s']} s with a full history"
            )
        u = [np.asarray(base.predict(window_table(c)), float).reshape(y.shape) for _h, c, y in windows]
        v0, true, t = [h.velocity for h, _c, _y in windows], [y for _h, _c, y in windows], windows[0][1].t
        U, V0, Y = np.concatenate(u), np.concatenate(v0), np.concatenate(true)
        self.params["tau"] = fit_time_constants(U, V0, Y, t[:1], tuple(o["tau_bounds"]))
        self.fit_loss_ = mse(relax(U, V0, np.repeat(t[:1], len(U), 0), self.tau()), Y)
        return self

    def rollout(self, history: st.History, commands: st.Commands) -> np.ndarray:
        W, n1 = commands.t.shape
        u = np.asarray(self.base().predict(window_table(commands)), float).reshape(W, n1, 3)
        return relax(u, np.asarray(history.velocity, float), commands.t, self.tau())

    def predict(self, table: pd.DataFrame) -> np.ndarray:
        u = np.asarray(self.base().predict(table), float)
        out = np.empty_like(u)
        starts = np.flatnonzero(sequence_starts(table))
        t = table["t"].to_numpy(float)
        for a, b in zip(starts, np.r_[starts[1:], len(table)], strict=True):
            out[a:b] = relax(u[None, a:b], u[a][None], t[None, a:b], self.tau())[0]
        return out


def fit_time_constants(
    u: np.ndarray, v0: np.ndarray, true: np.ndarray, t: np.ndarray, bounds: tuple[float, float]
) -> dict[str, float]:
    """Per axis, the tau (s) in ``bounds`` minimising the squared error of :func:`relax` against ``true``
    (W, n+1, 3) over windows with targets ``u`` and initial velocities ``v0``; ``t`` (1, n+1)."""
    lo, hi = np.log(bounds[0]), np.log(bounds[1])
    dt = float(np.median(np.diff(t)))
    out = {}
    for a, axis in enumerate(AXES):

        def loss(log_tau: float, a: int = a) -> float:
            v = relax_axis(u[:, 1:, a], v0[:, a], dt, float(np.exp(log_tau)))
            return float(np.mean((v - true[:, 1:, a]) ** 2))

        res = minimize_scalar(loss, bounds=(lo, hi), method="bounded", options={"xatol": 1e-4})
        out[axis] = float(np.exp(res.x))
    return out
