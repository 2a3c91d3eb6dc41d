"""The floor: a reference row that is not a model (docs/intervals.md, "The floor").

A perfect model: the simulator's exact body velocities (its ``true_pose`` stream, ``vx vy wz`` in the body
frame) on the split's clock, through the same horizon machinery and the same windows as every model
(:func:`~skidbench.benchmark.scoring.horizon.window_errors`), scored against the ground truth the board
uses (VO, ORB-SLAM or a pose topic). Its error is what that ground truth's own drift, scale and heading error,
its resampling and the machinery cost a model that knows the robot's motion exactly: no model can be
expected below it. Where the data hold no independent truth (a real recording scored against its own
ICP or SLAM poses) the floor is unknown, and the board says so and why (:func:`unknown_reason`); it is
never estimated from the ground truth's own velocities, whose errors cancel in that round trip (it
checks the machinery: tests/test_evaluate_intervals.py). Shown on every board, never ranked. Pure.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
import pandas as pd

from skidbench.benchmark.scoring.horizon import HorizonConfig, window_errors

#: the floor's row name on every board (not a model name: no model may be registered under it)
FLOOR = "floor"
FLOOR_LABEL = "floor (a perfect model: the simulator's exact velocities against this ground truth)"
#: the extracted table of the simulator's truth (``groundtruth.truth_key``'s default)
TRUTH_KEY = "true_pose"
VELOCITY_COLUMNS = ("vx", "vy", "wz")
UNKNOWN = "floor unknown"


def truth_velocities(stamp_ns: np.ndarray, truth: pd.DataFrame, where: str = "") -> np.ndarray:
    """(T, 3) the truth table's body velocities (``vx vy wz``; stamps ``bag_time_ns`` or ``stamp_ns``)
    interpolated linearly at ``stamp_ns`` (the split's clock). ValueError naming ``where`` when the truth
    lacks a column or does not cover the clock."""
    col = "bag_time_ns" if "bag_time_ns" in truth else "stamp_ns"
    missing = [c for c in (col, *VELOCITY_COLUMNS) if c not in truth]
    if missing:
        raise ValueError(f"{where}: the truth table has no {missing} column(s)")
    ts = truth[col].to_numpy(np.int64)
    order = np.argsort(ts, kind="stable")
    ts = ts[order]
    t = np.asarray(stamp_ns, dtype=np.int64)
    if len(ts) < 2 or t[0] < ts[0] or t[-1] > ts[-1]:
        raise ValueError(f"{where}: the truth table does not cover the split's clock")
    x = (t - ts[0]).astype(float)
    xs = (ts - ts[0]).astype(float)
    return np.column_stack([np.interp(x, xs, truth[c].to_numpy(float)[order]) for c in VELOCITY_COLUMNS])


def floor_windows(
    sequences: Iterable[tuple[str, pd.DataFrame, np.ndarray]], horizons: Sequence[float], hcfg: HorizonConfig
) -> pd.DataFrame:
    """Per-window errors of the floor over ``sequences`` (``(name, split table, exact velocities (T, 3))``)
    at every horizon: the columns of :func:`window_errors` after ``horizon_s`` and ``sequence``, as a
    model's windows."""
    frames = []
    seqs = list(sequences)
    for h in horizons:
        cfg_h = HorizonConfig(float(h), hcfg.min_distance_m, hcfg.min_rotation_rad)
        for name, df, vel in seqs:
            if not len(df):
                continue
            w = window_errors(
                df["t"].to_numpy(float),
                df[["x", "y", "yaw"]].to_numpy(float),
                np.asarray(vel, dtype=float),
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


def unknown_reason(sequence: str, why: str) -> str:
    """The board's line for a floor that cannot be measured: what is missing and what it means."""
    return (
        f"{UNKNOWN}: no independent truth of the ground truth ({sequence}: {why}); every model's error "
        "includes the ground truth's own, of unmeasured size"
    )
