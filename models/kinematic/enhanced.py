"""Enhanced kinematic model (Seegmiller et al.): zero-slip prediction plus a linear slip residual,

    v_x,slip  = p1 (f_lon/N) v_x + p2 v_x
    v_y,slip  = p3 (f_lat/N) v_x
    w_slip    = p4 (f_lat/N) v_x + p5 v_x + p6 w

with (v_x, w) the zero-slip (ideal) prediction and f_lon, f_lat the centrifugal plus gravitational forces at
the CG in the body frame, N the normal force. Centrifugal: -M (w x v_CG) = (M w v_CGy, -M w v_CGx) with v_CG =
(v_x - y_CG w, x_CG w). Gravity (standard gravity, ``pipeline/core/constants.py``): zero on flat ground;
options
``slope_pitch`` / ``slope_roll`` (rad, constant) configure a slope. Linear in p, fitted by least squares per
component.

Identifiability: on flat ground with the CG on the centre line (x_CG = 0) f_lon is zero, so p1 is not
identifiable (the minimum-norm fit sets it to 0); it needs a slope or an x_CG offset.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from skidbench.models.base import KinematicModel
from skidbench.models.columns import col, mse, targets, training_rows
from skidbench.pipeline.core.constants import STANDARD_GRAVITY

PARAMS = ("p1", "p2", "p3", "p4", "p5", "p6")


class EnhancedKinematic(KinematicModel):
    name = "enhanced"
    version = "1.0"
    required_columns = ("cmd_wl", "cmd_wr")
    #: slips beyond the calibrated kinematics (p2 and p6 would absorb a radius and a track scale anyway)
    calibrated_constants = ("wheel_radius", "track_width")
    calibration_usage = (
        "calibrated radius and track width (p1..p6 are slips beyond the calibrated kinematics)"
    )

    def features(self, table: pd.DataFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(v_x, w) zero-slip prediction and (f_lon/N, f_lat/N), each (T,)."""
        vx, w = self.robot.twist_from_wheel_rates(col(table, "cmd_wl"), col(table, "cmd_wr"))
        x_cg, y_cg = self.robot.cg_offset
        pitch = float(self.options.get("slope_pitch", 0.0))
        roll = float(self.options.get("slope_roll", 0.0))
        g = STANDARD_GRAVITY
        n = g * np.cos(pitch) * np.cos(roll)  # N / M
        f_lon = (w * (x_cg * w) - g * np.sin(pitch)) / n
        f_lat = (-w * (vx - y_cg * w) + g * np.cos(pitch) * np.sin(roll)) / n
        return vx, w, f_lon, f_lat

    def fit(self, table: pd.DataFrame) -> EnhancedKinematic:
        self.check_columns(table, fitting=True)
        train = training_rows(table)
        vx, w, f_lon, f_lat = self.features(train)
        y = targets(train)

        def lsq(X, t):
            return np.linalg.lstsq(X, t, rcond=None)[0]

        p1, p2 = lsq(np.column_stack([f_lon * vx, vx]), y[:, 0] - vx)
        (p3,) = lsq((f_lat * vx)[:, None], y[:, 1])
        p4, p5, p6 = lsq(np.column_stack([f_lat * vx, vx, w]), y[:, 2] - w)
        self.params = dict(zip(PARAMS, map(float, (p1, p2, p3, p4, p5, p6)), strict=True))
        self.fit_loss_ = mse(self.predict(train), y)
        return self

    def predict(self, table: pd.DataFrame) -> np.ndarray:
        self.check_columns(table)
        p1, p2, p3, p4, p5, p6 = (float(self.params.get(k, 0.0)) for k in PARAMS)
        vx, w, f_lon, f_lat = self.features(table)
        return np.column_stack(
            [
                vx + p1 * f_lon * vx + p2 * vx,
                p3 * f_lat * vx,
                w + p4 * f_lat * vx + p5 * vx + p6 * w,
            ]
        )
