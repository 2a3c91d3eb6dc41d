"""The floor: a reference row that is not a model (docs/intervals.md, "The floor").

The ground truth's own body velocities, as the split holds them (``vx vy wz``: the smoothing
differentiator of pipeline/splits/build.py applied to the ground-truth poses), through the same horizon
machinery and the same windows as every model (:func:`~skidbench.benchmark.scoring.horizon.window_errors`).
Its
error is what the ground truth, its resampling, its differentiation and its chaining cost a perfect
model: no model can be expected below it. On the simulator's exact truth it is a few hundredths of a
percent (tested), which checks the machinery; on real data it says how much of every model's error is
the ground truth's own. It is shown on every board and never ranked.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
import pandas as pd

from skidbench.benchmark.scoring.horizon import HorizonConfig, window_errors

#: the floor's row name on every board (not a model name: no model may be registered under it)
FLOOR = "floor"
FLOOR_LABEL = "floor (ground truth's own velocities)"
VELOCITY_COLUMNS = ("vx", "vy", "wz")


def floor_velocities(table: pd.DataFrame) -> np.ndarray:
    """(T, 3) the split table's ground-truth body velocities (vx, vy in m/s, wz in rad/s)."""
    return table[list(VELOCITY_COLUMNS)].to_numpy(dtype=float)


def floor_windows(
    sequences: Iterable[tuple[str, pd.DataFrame]], horizons: Sequence[float], hcfg: HorizonConfig
) -> pd.DataFrame:
    """Per-window errors of the floor over ``sequences`` (``(name, split table)``) at every horizon: the
    columns of :func:`window_errors` after ``horizon_s`` and ``sequence``, as a model's windows."""
    frames = []
    seqs = list(sequences)
    for h in horizons:
        cfg_h = HorizonConfig(float(h), hcfg.min_distance_m, hcfg.min_rotation_rad)
        for name, df in seqs:
            if not len(df):
                continue
            w = window_errors(
                df["t"].to_numpy(float),
                df[["x", "y", "yaw"]].to_numpy(float),
                floor_velocities(df),
                float(h),
                df["valid"].to_numpy(bool),
                cfg_h,
            )
            if len(w) == 0:
                continue
            w.insert(0, "sequence", name)
            w.insert(0, "horizon_s", float(h))
            frames.append(w)
    if not frames:
        return pd.DataFrame()
    return pd.concat(frames, ignore_index=True)
