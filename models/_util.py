"""Small helpers the built-in models share (column access, valid rows, loss)."""

from __future__ import annotations

import numpy as np
import pandas as pd

TARGETS = ("vx", "vy", "wz")


def col(table: pd.DataFrame, name: str) -> np.ndarray:
    return table[name].to_numpy(dtype=float, na_value=np.nan)


def training_rows(table: pd.DataFrame) -> pd.DataFrame:
    """The rows a fit may use: ``valid`` True."""
    return table.loc[table["valid"].to_numpy(bool)]


def targets(table: pd.DataFrame) -> np.ndarray:
    """(T, 3) ground-truth body velocities (vx, vy, wz)."""
    return np.column_stack([col(table, c) for c in TARGETS])


def mse(pred: np.ndarray, true: np.ndarray) -> float:
    """Mean squared velocity error over rows and the three components (m^2/s^2 and rad^2/s^2 mixed)."""
    return float(np.mean((np.asarray(pred) - np.asarray(true)) ** 2))
