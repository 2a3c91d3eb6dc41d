"""DRIVE's slip model (Baril et al., norlab-ulaval/DRIVE): Bayesian linear regression of the body slip on
the ideal differential-drive velocities of the wheel rates, with its Student-t predictive variance.

What DRIVE does (``model_training/models/learning/blr_slip.py``, ``model_trainers/blr_slip_trainer.py``,
``data_utils/slip_dataset_parser.py``), carried over here:
- its powertrain (a bounded first-order wheel response identified per side) turns commands into wheel
  rates; here that is the ``response`` input protocol, shared by every model; under the other protocols
  the model reads the protocol's wheel rates the same way;
- the ideal differential-drive body velocities of those wheel rates, v = r (wl + wr) / 2,
  w = r (wr - wl) / B (DRIVE's "idd" velocities; lateral 0);
- the body slip ("disturbance") idd - measured, regressed per component on its own features, without
  intercept: x on [v]; y on [v w] (centripetal); yaw on [v w, v, w] (centripetal, asymmetry, yaw rate);
- a normal-inverse-gamma prior per component: weights 0, a_0 = b_0 = 0, weight covariance
  (tau_0 / sigma_0) I with tau_0 = 1e21, sigma_0 = 1e9 (so nearly flat), posterior in closed form;
- the predictive of a new row: Student-t with 2 a_n degrees of freedom, mean x^T w_n, variance
  2 a_n / (2 a_n - 2) * b_n / a_n * (1 + x^T Sigma_n x) (DRIVE takes the diagonal per step).

The predicted body velocity is idd - slip, its covariance diagonal (the three regressions are
independent). DRIVE fits on the steady-state part of its windows; ``options.train_rows: steady`` does the
same here (rows whose wheel accelerations are under ``steady_accel_max``), the default ``all`` uses every
valid Train row (our Train sequences are continuous driving, not step windows). The error autocorrelation
of the fit (for the horizon's uncertainty) is measured on the Train residuals.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from skidbench.models.base import KinematicModel, ModelError
from skidbench.models.columns import col, error_autocorrelation, mse, sequence_starts, targets, training_rows

#: DRIVE's feature sets (names of the columns of :func:`slip_features`)
FEATURES = {"x": ("v",), "y": ("v_w",), "yaw": ("v_w", "v", "w")}
COMPONENTS = ("x", "y", "yaw")


def slip_features(v: np.ndarray, w: np.ndarray) -> dict[str, np.ndarray]:
    """DRIVE's regressors per slip component: (T, k) arrays from the idd velocities v (m/s), w (rad/s)."""
    cols = {"v": v, "w": w, "v_w": v * w}
    return {c: np.column_stack([cols[f] for f in FEATURES[c]]) for c in COMPONENTS}


def blr_posterior(
    X: np.ndarray, y: np.ndarray, a0: float, b0: float, param_variance: float, variance: float
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Normal-inverse-gamma posterior of y = X w + e (DRIVE's SlipBayesianLinearRegression.train_params).
    Prior: w ~ N(0, sigma^2 Lambda_0^-1), Lambda_0 = (variance / param_variance) I, sigma^2 ~ IG(a0, b0).
    Returns (w_n (k,), Sigma_n = Lambda_n^-1 (k, k), a_n, b_n)."""
    k = X.shape[1]
    lam0 = np.eye(k) * (variance / param_variance)
    lam_n = lam0 + X.T @ X
    sigma_n = np.linalg.inv(lam_n)
    w_n = sigma_n @ (X.T @ y)  # prior mean 0
    a_n = a0 + len(y) / 2.0
    b_n = b0 + 0.5 * float(y @ y - w_n @ lam_n @ w_n)
    return w_n, sigma_n, a_n, b_n


def blr_predict(X: np.ndarray, w_n: np.ndarray, sigma_n: np.ndarray, a_n: float, b_n: float):
    """Student-t predictive mean (T,) and variance (T,) of rows X (T, k)."""
    mean = X @ w_n
    scale = b_n / a_n * (1.0 + np.einsum("ti,ij,tj->t", X, sigma_n, X))
    nu = 2.0 * a_n
    return mean, scale * nu / (nu - 2.0)


class DriveBLR(KinematicModel):
    name = "drive_blr"
    version = "1.0"
    required_columns = ("cmd_wl", "cmd_wr", "cmd_dwl", "cmd_dwr")
    #: like DRIVE, the idd velocities use the robot's kinematics; the regression weights absorb the rest
    calibrated_constants = ("wheel_radius",)
    DEFAULTS: dict[str, Any] = {
        "a_param_init": 0.0,  # a_0
        "b_param_init": 0.0,  # b_0
        "param_variance_init": 1e21,  # tau_0
        "variance_init": 1e9,  # sigma_0
        "train_rows": "all",  # all | steady (DRIVE: the steady-state part of its windows)
        "steady_accel_max": 1.0,  # rad/s^2, wheel acceleration under which a row is steady
        "autocorr_lags_s": 10.0,  # s of error autocorrelation kept for the horizon's uncertainty
    }

    def __init__(self, robot, params=None, **options):
        super().__init__(robot, params, **options)  # DEFAULTS: checked and applied there
        if self.options["train_rows"] not in ("all", "steady"):
            raise ModelError(f"model {self.name}: options.train_rows must be all or steady")

    def _idd(self, table: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
        return self.robot.twist_from_wheel_rates(col(table, "cmd_wl"), col(table, "cmd_wr"))

    def fit(self, table: pd.DataFrame) -> DriveBLR:
        self.check_columns(table, fitting=True)
        o = self.options
        use = table["valid"].to_numpy(bool)
        if o["train_rows"] == "steady":
            acc = np.maximum(np.abs(col(table, "cmd_dwl")), np.abs(col(table, "cmd_dwr")))
            use = use & (acc <= float(o["steady_accel_max"]))
        if use.sum() < 10:
            n = int(use.sum())
            raise ModelError(f"model {self.name}: {n} training rows (train_rows={o['train_rows']})")
        train = table.loc[use]
        v, w = self._idd(train)
        slip = np.column_stack([v - col(train, "vx"), -col(train, "vy"), w - col(train, "wz")])
        feats = slip_features(v, w)
        self.params = {}
        for i, c in enumerate(COMPONENTS):
            w_n, sigma_n, a_n, b_n = blr_posterior(
                feats[c], slip[:, i], o["a_param_init"], o["b_param_init"], o["param_variance_init"],
                o["variance_init"],
            )  # fmt: skip
            self.params[c] = {
                "weights": dict(zip(FEATURES[c], map(float, w_n), strict=True)),
                "covariance": sigma_n.tolist(),
                "a_n": float(a_n),
                "b_n": float(b_n),
            }
        rows = training_rows(table)
        res = targets(rows) - self.predict(rows)
        self.fit_loss_ = mse(self.predict(rows), targets(rows))
        dt = float(np.median(np.diff(col(table, "t")))) if len(table) > 1 else 1.0
        lags = max(1, int(round(float(o["autocorr_lags_s"]) / max(dt, 1e-6))))
        self.arrays = {
            "error_autocorrelation": error_autocorrelation(
                res, sequence_starts(rows) | (np.diff(rows.index.to_numpy(), prepend=-2) != 1), lags
            )
        }
        return self

    @property
    def error_autocorrelation_(self) -> np.ndarray | None:
        return self.arrays.get("error_autocorrelation")

    def _slip(self, table: pd.DataFrame):
        if not self.params:
            raise ModelError(f"model {self.name}: not fitted")
        v, w = self._idd(table)
        feats = slip_features(v, w)
        out = []
        for c in COMPONENTS:
            p = self.params[c]
            w_n = np.array([p["weights"][f] for f in FEATURES[c]])
            out.append(blr_predict(feats[c], w_n, np.asarray(p["covariance"]), p["a_n"], p["b_n"]))
        return v, w, out

    def predict(self, table: pd.DataFrame) -> np.ndarray:
        self.check_columns(table)
        v, w, ((sx, _), (sy, _), (sw, _)) = self._slip(table)
        return np.column_stack([v - sx, -sy, w - sw])  # body velocity = idd - slip

    def predict_cov(self, table: pd.DataFrame) -> np.ndarray:
        """(T, 3, 3) diagonal predictive covariance of (vx, vy, wz) (m^2/s^2, rad^2/s^2)."""
        self.check_columns(table)
        _, _, parts = self._slip(table)
        cov = np.zeros((len(table), 3, 3))
        for i, (_, var) in enumerate(parts):
            cov[:, i, i] = var
        return cov
