"""Horizon evaluation: the O(T) relative composition (``window_errors``) vs integrating every window
separately (``naive_window_errors``), on an hour of 30 Hz data at the 6 s horizon."""

from __future__ import annotations

import time

import numpy as np

from skidbench.benchmark.scoring.horizon import naive_window_errors, window_errors
from skidbench.pipeline.core.geometry import integrate_body_velocity, wrap_angle

from . import register

RATE_HZ = 30.0
HORIZON_S = 6.0


def drive(duration_s: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A smooth random drive: times (T,) s, ground-truth poses (T, 3) and a model's velocities (T, 3)
    that differ from the truth (so the errors are not all zero)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration_s, 1.0 / RATE_HZ)
    knots = np.arange(0.0, duration_s + 3.0, 3.0)
    v = np.interp(t, knots, rng.uniform(0.0, 1.5, len(knots)))
    w = np.interp(t, knots, rng.uniform(-1.5, 1.5, len(knots)))
    true = np.column_stack([v, 0.03 * w, 0.8 * w])
    gt = integrate_body_velocity(np.zeros(3), true[:-1], np.diff(t))
    model = np.column_stack([v, np.zeros_like(v), w])
    return t, gt, model


@register(
    "horizon",
    "6 s window errors: O(T) composition vs per-window integration, 1 h of 30 Hz data",
    targets={"speedup": (">=", 50.0), "max_abs_diff": ("<", 1e-9)},
)
def horizon(quick: bool) -> dict[str, float]:
    t, gt, vel = drive(360.0 if quick else 3600.0)
    start = time.perf_counter()
    fast = window_errors(t, gt, vel, HORIZON_S)
    fast_s = time.perf_counter() - start
    start = time.perf_counter()
    naive = naive_window_errors(t, gt, vel, HORIZON_S)
    naive_s = time.perf_counter() - start
    pred = fast[["pred_x", "pred_y", "pred_yaw"]].to_numpy()
    diff = np.abs(pred - naive)
    diff[:, 2] = np.abs(wrap_angle(pred[:, 2] - naive[:, 2]))
    return {
        "windows": int(len(naive)),
        "fast_s": fast_s,
        "naive_s": naive_s,
        "speedup": naive_s / fast_s,
        "max_abs_diff": float(diff.max()),
    }
