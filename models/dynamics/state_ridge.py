"""A learned dynamics model conditioned on the robot's history (issue 49; the setting of Trivedi et al. 2024,
who learn from the history of past motion): ridge regression of the body velocity's deviation from a
kinematic base model over a window, from the state at its start and its recent past.

For a window starting at t0 (``state`` protocol, models/rollout.py), per axis a (vx, vy, wz) and step k
(tau_k = t_k - t0):

    v_a(k) = u_a(k) + sum_j phi_j(tau_k) (theta_aj . z) + eta_a . x(k)

* u: the base kinematic model's prediction of the window's commands (option ``base``, default ``edd``);
* z (10): what the window knows of its past: 1, the state's deviation from the base at t0 (v0 - u(0)),
  the state v0, and the mean slip over the history (the mean body velocity over the last ``history_s``
  from the ground-truth displacement, minus the mean commanded (cmd_v, 0, cmd_w));
* phi: how that knowledge fades along the window: 1 and exp(-tau / T) for T in ``decays_s``;
* x(k) (6): the step's own regressors: u(k) and the commanded accelerations and centripetal term
  (d cmd_v/dt, d cmd_w/dt, cmd_v cmd_w), the slip a kinematic model leaves.

Linear in its parameters, so the fit is one regularised least-squares solve per axis (numpy, closed form,
standardised features, ``ridge`` x the number of rows): no optimiser, no kernel matrix. Fitted on Train
only: windows of ``fit_horizon_s`` every ``fit_stride_s`` with a full history, every ``fit_step``-th step,
a random ``subsample`` of them drawn with ``seed`` (the seed spread of ``evaluate seeds=N``). The rollout
is batched over windows (one base prediction, one matrix product per axis). Without a state (the other
protocols) it predicts what its base predicts.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from skidbench.models import rollout as st
from skidbench.models.base import ModelError
from skidbench.models.columns import mse
from skidbench.models.dynamics.relaxation import OnKinematicBase, training_windows, window_table

N_Z = 10
N_X = 6


def window_features(history: st.History, commands: st.Commands, u: np.ndarray, decays: tuple) -> np.ndarray:
    """(W, n+1, F) the design rows of every window and step: phi(tau) (x) z, then x(k) (module docstring)."""
    W, n1 = commands.t.shape
    h = np.maximum(-history.t[:, 0], 1e-9)  # s of history
    past_vel = (
        -np.stack([history.pose[:, 0, 0], history.pose[:, 0, 1], history.pose[:, 0, 2]], -1) / h[:, None]
    )
    past_cmd = np.stack([history.inputs["cmd_v"].mean(1), np.zeros(W), history.inputs["cmd_w"].mean(1)], -1)
    v0 = history.velocity
    z = np.concatenate([np.ones((W, 1)), v0 - u[:, 0], v0, past_vel - past_cmd], axis=1)  # (W, 10)
    tau = commands.t
    phi = np.stack([np.ones_like(tau), *(np.exp(-tau / T) for T in decays)], axis=-1)  # (W, n+1, J)
    zz = (phi[..., :, None] * z[:, None, None, :]).reshape(W, n1, -1)
    cv, cw = commands.inputs["cmd_v"], commands.inputs["cmd_w"]
    dt = np.maximum(np.diff(tau, axis=1).mean(), 1e-9)
    x = np.concatenate([u, np.gradient(cv, dt, axis=1)[..., None], np.gradient(cw, dt, axis=1)[..., None],
                        (cv * cw)[..., None]], axis=-1)  # fmt: skip
    return np.concatenate([zz, x], axis=-1)


class StateRidge(OnKinematicBase):
    name = "state_ridge"
    version = "1.0"
    required_columns = ("cmd_wl", "cmd_wr", "cmd_dwl", "cmd_dwr")
    DEFAULTS: dict[str, Any] = {
        "base": "edd",  # the kinematic model whose deviation is learned (any installed model)
        "base_options": {},
        "decays_s": [0.25, 1.0, 4.0],  # s: the fading of the history's information along a window
        "ridge": 1e-4,  # x rows: the penalty on the standardised coefficients
        "fit_horizon_s": 6.0,  # s: the Train windows fitted on
        "fit_stride_s": 0.5,  # s between their starts
        "fit_step": 3,  # every fit_step-th step of a window is a training row
        "history_s": st.HISTORY_S,  # s behind a window's initial velocity (as state.history_s)
        "subsample": 0.8,  # the fraction of Train windows drawn (with seed) for the fit
        "seed": 0,
    }

    def _base_windows(self, commands: st.Commands) -> np.ndarray:
        W, n1 = commands.t.shape
        return np.asarray(self.base().predict(window_table(commands)), float).reshape(W, n1, 3)

    def fit(self, table: pd.DataFrame) -> StateRidge:
        from skidbench.models.registry.specs import get_model_class

        self.check_columns(table, fitting=True)
        o = self.options
        base = get_model_class(str(o["base"]))(self.robot, **dict(o["base_options"] or {})).fit(table)
        self._base, self.params = base, {"base_model": base.to_json()}
        rng = np.random.default_rng(int(o["seed"]))
        decays, step = tuple(float(d) for d in o["decays_s"]), max(int(o["fit_step"]), 1)
        X, Y = [], []
        for history, commands, true in training_windows(
            table, float(o["fit_horizon_s"]), float(o["fit_stride_s"]), float(o["history_s"])
        ):
            keep = rng.random(len(history)) < float(o["subsample"])
            if not keep.any():
                continue
            history, commands = _take(history, keep), _take_commands(commands, keep)
            u = self._base_windows(commands)
            F = window_features(history, commands, u, decays)[:, 1::step]
            X.append(F.reshape(-1, F.shape[-1]))
            Y.append((true[keep] - u)[:, 1::step].reshape(-1, 3))
        if not X:
            raise ModelError(
                f"model {self.name}: no Train window of {o['fit_horizon_s']} s with a full history"
            )
        Xa, Ya = np.concatenate(X), np.concatenate(Y)
        mean, scale = Xa.mean(0), Xa.std(0)
        scale[scale < 1e-12] = 1.0
        mean[0] = 0.0  # the constant column (phi = 1, z = 1) stays the intercept
        scale[0] = 1.0
        Xs = (Xa - mean) / scale
        A = Xs.T @ Xs + float(o["ridge"]) * len(Xs) * np.eye(Xs.shape[1])
        coef = np.linalg.solve(A, Xs.T @ Ya)  # (F, 3)
        self.arrays = {"coef": coef, "mean": mean, "scale": scale}
        self.fit_loss_ = mse(Xs @ coef, Ya)
        return self

    def rollout(self, history: st.History, commands: st.Commands) -> np.ndarray:
        if "coef" not in self.arrays:
            raise ModelError(f"model {self.name}: not fitted (no coefficients)")
        u = self._base_windows(commands)
        F = window_features(history, commands, u, tuple(float(d) for d in self.options["decays_s"]))
        out = u + ((F - self.arrays["mean"]) / self.arrays["scale"]) @ self.arrays["coef"]
        out[:, 0] = history.velocity
        return out

    def predict(self, table: pd.DataFrame) -> np.ndarray:
        return np.asarray(self.base().predict(table), float)


def _take(h: st.History, keep: np.ndarray) -> st.History:
    return st.History(h.t[keep], h.pose[keep], h.velocity[keep], {k: v[keep] for k, v in h.inputs.items()},
                      None if h.encoders is None else h.encoders[keep])  # fmt: skip


def _take_commands(c: st.Commands, keep: np.ndarray) -> st.Commands:
    return st.Commands(c.t[keep], {k: v[keep] for k, v in c.inputs.items()})
