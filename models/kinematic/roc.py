"""ROC-based model (Wang et al.), eq. (3): the ICR coefficient chi depends on the radius of curvature,

    chi = 1 + b1 / (1 + b2 |R_ICR|^0.5),   b1, b2 > 0,

used in eq. (1). R_ICR is the commanded (ideal) radius of curvature v / w = (B/2)(wr + wl)/(wr - wl);
straight driving (R infinite) gives chi = 1 and a turn on the spot (R = 0) chi = 1 + b1. b1 = 0 is the ideal
model. Fitted by bounded nonlinear least squares on the yaw rate. A fit that ends at a bound is reported
(``fit_info_["at_bound"]``): b2 = 0 makes chi = 1 + b1 constant, which is ``edd`` (chi = 1 + b1); b1 = 0
is the ideal model. On data whose turning does not depend on the radius of curvature, roc is then edd to
every digit, and the board says so instead of showing two equal rows.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.optimize import least_squares

from skidbench.models.base import KinematicModel, ModelError
from skidbench.models.columns import bounds_reached, col, mse, targets, training_rows

#: what roc becomes with a parameter at its bound (0): the finding a fit there reports
AT_BOUND = {
    "b2": "roc degenerates to edd on this data: b2 at its bound",
    "b1": "roc degenerates to the ideal model on this data: b1 at its bound",
}


class RocBased(KinematicModel):
    name = "roc"
    version = "1.0"
    required_columns = ("cmd_wl", "cmd_wr")
    calibrated_constants = ("wheel_radius",)  # chi(R) absorbs the track width, as edd's chi
    calibration_usage = "calibrated radius; spec-sheet track: chi(R) absorbs the track width"

    def chi(self, wl: np.ndarray, wr: np.ndarray, b1: float, b2: float) -> np.ndarray:
        num = np.abs(self.robot.track_width / 2.0 * (wr + wl))
        den = np.abs(wr - wl)
        sqrt_r = np.sqrt(np.divide(num, den, out=np.full_like(num, np.inf), where=den > 0))
        return 1.0 + b1 / (1.0 + b2 * sqrt_r)  # eq. (3); b1 / inf = 0 when straight

    def _predict(self, wl, wr, b1, b2) -> np.ndarray:
        v, w = self.robot.twist_from_wheel_rates(wl, wr)
        return np.column_stack([v, np.zeros_like(v), w / self.chi(wl, wr, b1, b2)])  # eq. (1)

    def fit(self, table: pd.DataFrame) -> RocBased:
        self.check_columns(table, fitting=True)
        train = training_rows(table)
        wl, wr, wz = col(train, "cmd_wl"), col(train, "cmd_wr"), col(train, "wz")
        if not np.any(wl != wr):
            raise ModelError(f"model {self.name}: the training table never turns; b1, b2 are undetermined")
        x0 = [float(self.options.get("b1_init", 1.0)), float(self.options.get("b2_init", 1.0))]
        res = least_squares(
            lambda b: self._predict(wl, wr, b[0], b[1])[:, 2] - wz,
            x0,
            bounds=([0.0, 0.0], [np.inf, np.inf]),
            method="trf",
            xtol=1e-12,
            ftol=1e-12,
            gtol=1e-12,
        )
        self.params = {"b1": float(res.x[0]), "b2": float(res.x[1])}
        self.fit_loss_ = mse(self.predict(train), targets(train))
        # at a bound when it changes chi by under 1e-4 anywhere on the training rows (b2 multiplies sqrt|R|)
        sqrt_r = np.sqrt(
            np.abs(self.robot.track_width / 2.0 * (wr + wl))[wl != wr] / np.abs(wr - wl)[wl != wr]
        )
        tol = [1e-4, 1e-4 / max(float(sqrt_r.max()), 1.0)]
        at = bounds_reached(["b1", "b2"], res.x, [0.0, 0.0], [np.inf, np.inf], AT_BOUND, res.active_mask, tol)
        b1, b2 = (float(v) for v in res.x)
        positive = sqrt_r[sqrt_r > 0]
        if positive.size and b2 * float(positive.min()) > 1e4:  # the upper "bound": both run off together
            why = (
                f"roc's b1 and b2 grow without bound together on this data: chi = 1 + {b1 / b2:.3g} / sqrt|R|"
            )
            at.append({"param": "b2", "value": b2, "bound": None, "side": "upper", "finding": why})
        self.fit_info_ = {"at_bound": at} if at else {}
        return self

    def predict(self, table: pd.DataFrame) -> np.ndarray:
        self.check_columns(table)
        b1, b2 = float(self.params.get("b1", 0.0)), float(self.params.get("b2", 0.0))
        return self._predict(col(table, "cmd_wl"), col(table, "cmd_wr"), b1, b2)
