"""Ridge regression of slip: ideal differential drive plus a linear-in-features residual.

Features (per row): the ideal body velocities v = r (wl + wr) / 2 and w = r (wr - wl) / B, the skid terms
v |w| and w |w| (slip grows with turning), v w (centripetal side slip), the commanded accelerations
dv = r (dwl + dwr) / 2 and dw = r (dwr - dwl) / B, and w |v|. Each of (vx, vy, wz) minus the ideal
prediction is a ridge regression on the standardised features (closed form, no intercept).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from skidbench.models.base import KinematicModel, ModelError

FEATURES = ("v", "w", "v|w|", "w|w|", "vw", "dv", "dw", "w|v|")


class RidgeSlip(KinematicModel):
    name = "ridge"
    version = "0.1.0"
    required_columns = ("cmd_wl", "cmd_wr", "cmd_dwl", "cmd_dwr")

    def features(self, table: pd.DataFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(X (T, 8), ideal v (T,), ideal w (T,))."""
        wl, wr, dwl, dwr = (table[c].to_numpy(float) for c in self.required_columns)
        v, w = self.robot.twist_from_wheel_rates(wl, wr)
        dv, dw = self.robot.twist_from_wheel_rates(dwl, dwr)
        X = np.column_stack([v, w, v * np.abs(w), w * np.abs(w), v * w, dv, dw, w * np.abs(v)])
        return X, v, w

    def fit(self, table: pd.DataFrame) -> RidgeSlip:
        self.check_columns(table, fitting=True)
        train = table[table["valid"].to_numpy(bool)]
        X, v, w = self.features(train)
        y = train[["vx", "vy", "wz"]].to_numpy(float) - np.column_stack([v, np.zeros_like(v), w])
        scale = X.std(axis=0)
        scale[scale == 0] = 1.0
        Z = X / scale
        alpha = float(self.options.get("alpha", 1e-3))
        if alpha < 0:
            raise ModelError(f"model {self.name}: option alpha must be >= 0, got {alpha}")
        coef = np.linalg.solve(Z.T @ Z + alpha * len(Z) * np.eye(Z.shape[1]), Z.T @ y)  # (8, 3)
        self.params = {"features": list(FEATURES), "coef": (coef / scale[:, None]).T.tolist()}
        self.fit_loss_ = float(
            np.mean((self.predict(train) - train[["vx", "vy", "wz"]].to_numpy(float)) ** 2)
        )
        return self

    def predict(self, table: pd.DataFrame) -> np.ndarray:
        self.check_columns(table)
        X, v, w = self.features(table)
        base = np.column_stack([v, np.zeros_like(v), w])
        if "coef" not in self.params:
            return base
        return base + X @ np.asarray(self.params["coef"], dtype=float).T
