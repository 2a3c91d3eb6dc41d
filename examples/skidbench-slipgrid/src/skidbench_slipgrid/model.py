"""A slip table: mean and variance of (measured - ideal) body velocity per cell of the commanded (v, w).

predict gets only the input protocol's columns (t, sequence, cmd_v, cmd_w, cmd_wl, cmd_wr, cmd_dwl,
cmd_dwr); fit also gets vx, vy, wz, valid. Fitted values are arrays (self.arrays), not JSON lists.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from skidbench.models.base import KinematicModel, ModelError
from skidbench.models.columns import col, mse, targets, training_rows


class SlipGrid(KinematicModel):
    name = "slipgrid"
    version = "0.1.0"
    required_columns = ("cmd_wl", "cmd_wr")

    def _ideal(self, table: pd.DataFrame) -> np.ndarray:
        v, w = self.robot.twist_from_wheel_rates(col(table, "cmd_wl"), col(table, "cmd_wr"))
        return np.column_stack([v, np.zeros_like(v), w])

    def _cells(self, ideal: np.ndarray) -> np.ndarray:
        ev, ew = self.arrays["v_edges"], self.arrays["w_edges"]
        iv = np.clip(np.searchsorted(ev, ideal[:, 0]) - 1, 0, len(ev) - 2)
        iw = np.clip(np.searchsorted(ew, ideal[:, 2]) - 1, 0, len(ew) - 2)
        return iv * (len(ew) - 1) + iw

    def fit(self, table: pd.DataFrame) -> SlipGrid:
        self.check_columns(table, fitting=True)
        bins, min_count = int(self.options.get("bins", 12)), int(self.options.get("min_count", 20))
        if bins < 1:
            raise ModelError(f"model {self.name}: options.bins must be >= 1, got {bins}")
        train = training_rows(table)
        ideal = self._ideal(train)
        slip = targets(train) - ideal
        self.arrays = {
            "v_edges": np.quantile(ideal[:, 0], np.linspace(0, 1, bins + 1)),
            "w_edges": np.quantile(ideal[:, 2], np.linspace(0, 1, bins + 1)),
        }
        cell = self._cells(ideal)
        n_cells = bins * bins
        count = np.bincount(cell, minlength=n_cells).astype(float)
        mean = np.stack([np.bincount(cell, slip[:, j], n_cells) for j in range(3)], 1)
        sq = np.stack([np.bincount(cell, slip[:, j] ** 2, n_cells) for j in range(3)], 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean, var = mean / count[:, None], sq / count[:, None] - (mean / count[:, None]) ** 2
        sparse = count < min_count
        mean[sparse], var[sparse] = slip.mean(0), slip.var(0)
        self.arrays.update({"mean": mean, "var": np.maximum(var, 1e-12), "count": count})
        self.params = {"bins": bins, "cells_used": int((~sparse).sum())}
        self.fit_loss_ = mse(self.predict(train), targets(train))
        return self

    def predict(self, table: pd.DataFrame) -> np.ndarray:
        self.check_columns(table)
        ideal = self._ideal(table)
        return ideal + self.arrays["mean"][self._cells(ideal)]

    def predict_cov(self, table: pd.DataFrame) -> np.ndarray:
        """(T, 3, 3): the cell's slip variance on the diagonal."""
        var = self.arrays["var"][self._cells(self._ideal(table))]
        cov = np.zeros((len(table), 3, 3))
        cov[:, [0, 1, 2], [0, 1, 2]] = var
        return cov
