"""Linear-regression models: extended differential drive (eq. 1) and the full linear model (eq. 2)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from skidbench.models.base import KinematicModel, ModelError
from skidbench.models.columns import col, mse, targets, training_rows


class ExtendedDifferentialDrive(KinematicModel):
    """Eq. (1): vx = r (wl + wr) / 2, vy = 0, wz = r (wr - wl) / (B chi). chi = 1 is the ideal model.

    chi is fitted by least squares on the yaw rate, which is linear in 1/chi."""

    name = "edd"
    version = "1.0"
    required_columns = ("cmd_wl", "cmd_wr")
    #: chi absorbs the track width (chi = B_eff / B_spec): the spec sheet's track keeps chi's meaning
    calibrated_constants = ("wheel_radius",)
    calibration_usage = (
        "calibrated radius; spec-sheet track: chi absorbs the track width (chi = B_eff / B_spec)"
    )

    def fit(self, table: pd.DataFrame) -> ExtendedDifferentialDrive:
        self.check_columns(table, fitting=True)
        train = training_rows(table)
        _, w_ideal = self.robot.twist_from_wheel_rates(col(train, "cmd_wl"), col(train, "cmd_wr"))
        den = float(w_ideal @ w_ideal)
        if den <= 0:
            raise ModelError(f"model {self.name}: the training table never turns; chi is undetermined")
        inv_chi = float(w_ideal @ col(train, "wz")) / den
        if inv_chi <= 0:
            raise ModelError(f"model {self.name}: fitted 1/chi = {inv_chi:.3g} <= 0")
        self.params = {"chi": 1.0 / inv_chi}
        self.fit_loss_ = mse(self.predict(train), targets(train))
        return self

    def predict(self, table: pd.DataFrame) -> np.ndarray:
        self.check_columns(table)
        chi = float(self.params.get("chi", 1.0))
        v, w = self.robot.twist_from_wheel_rates(col(table, "cmd_wl"), col(table, "cmd_wr"))
        return np.column_stack([v, np.zeros_like(v), w / chi])  # eq. (1)


class FullLinear(KinematicModel):
    """Eq. (2): (vx, vy, wz) = A (wl, wr), A a 3x2 matrix fitted by linear least squares (row-major
    ``A`` in params). The ideal model is A = r [[1/2, 1/2], [0, 0], [-1/B, 1/B]]."""

    name = "full_linear"
    version = "1.0"
    required_columns = ("cmd_wl", "cmd_wr")
    calibrated_constants = ()  # A absorbs radius and track width (they only enter its unfitted default)
    calibration_usage = "neither: its matrix A absorbs radius and track width"

    def ideal_matrix(self) -> np.ndarray:
        r, B = self.robot.wheel_radius, self.robot.track_width
        return r * np.array([[0.5, 0.5], [0.0, 0.0], [-1.0 / B, 1.0 / B]])

    def fit(self, table: pd.DataFrame) -> FullLinear:
        self.check_columns(table, fitting=True)
        train = training_rows(table)
        U = np.column_stack([col(train, "cmd_wl"), col(train, "cmd_wr")])
        if np.linalg.matrix_rank(U) < 2:
            raise ModelError(f"model {self.name}: wheel commands in the training table are collinear")
        A, *_ = np.linalg.lstsq(U, targets(train), rcond=None)  # eq. (2), (2, 3) = A^T
        self.params = {"A": A.T.tolist()}
        self.fit_loss_ = mse(self.predict(train), targets(train))
        return self

    def predict(self, table: pd.DataFrame) -> np.ndarray:
        self.check_columns(table)
        A = np.asarray(self.params["A"], dtype=float) if "A" in self.params else self.ideal_matrix()
        U = np.column_stack([col(table, "cmd_wl"), col(table, "cmd_wr")])
        return U @ A.T  # eq. (2)
