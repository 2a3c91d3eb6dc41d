"""Ideal differential drive: eq. (1) with chi = 1 (no slip). No parameters.

This is the smallest complete model and the example to copy when writing a plugin.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from skidbench.models.base import KinematicModel
from skidbench.models.columns import col, mse, targets, training_rows


class IdealDifferentialDrive(KinematicModel):
    name = "ideal"
    version = "1.0"
    required_columns = ("cmd_wl", "cmd_wr")
    calibrated_constants = ("wheel_radius", "track_width")  # the calibrated kinematics, nothing fitted
    calibration_usage = "calibrated radius and track width (the ideal model is the calibrated kinematics)"

    def fit(self, table: pd.DataFrame) -> IdealDifferentialDrive:
        self.check_columns(table, fitting=True)
        train = training_rows(table)
        self.params = {}
        self.fit_loss_ = mse(self.predict(train), targets(train))
        return self

    def predict(self, table: pd.DataFrame) -> np.ndarray:
        self.check_columns(table)
        v, w = self.robot.twist_from_wheel_rates(col(table, "cmd_wl"), col(table, "cmd_wr"))  # eq. (1), chi=1
        return np.column_stack([v, np.zeros_like(v), w])
