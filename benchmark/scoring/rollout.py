"""Scoring under the ``state`` input protocol (issue 49): every window is rolled out from its own start.

Under the other protocols a model's velocities depend only on the inputs, so one dead-reckoned trajectory
serves every window (benchmark/horizon.py). Under ``state`` a model starts each window from the robot's
state at t0 (models/rollout.py), so every window is its own rollout: the model's ``rollout(history,
commands)`` returns (W, n+1, 3) body velocities for a batch of W windows, and each window is integrated
from the ground-truth pose at its start with the same exact SE(2) steps and trapezoidal twists as the
other protocols. A model without ``rollout`` (the kinematic ones) takes part unchanged: its ``predict`` of
the sequence's commanded inputs, gathered per window (the same numbers as under ``commanded`` on the same
windows).

One rollout per window to the longest horizon serves every horizon: each horizon is scored on the same
windows (those with a full history and the longest horizon of valid samples), so the error-against-horizon
curve compares like with like. Batches are cut per sequence, at most ``max_batch_samples`` window samples
each; there is no Python loop over windows.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from skidbench.benchmark.errors import EvaluationError
from skidbench.benchmark.scoring.aggressiveness import sample_acceleration, window_aggressiveness
from skidbench.benchmark.scoring.horizon import HorizonConfig, horizon_steps
from skidbench.benchmark.scoring.settings import StateSettings
from skidbench.models import rollout as st
from skidbench.pipeline.core.geometry import se2_exp


@dataclass(frozen=True)
class Batch:
    """One rollout call's windows: their History and Commands (what the model sees), and where they come
    from (the sequence's index in the split and the window's sample indices: the scorer's, never the
    model's)."""

    history: st.History
    commands: st.Commands
    seq: int
    starts: np.ndarray
    ahead: np.ndarray  # (W, n+1) sample indices of each window


RolloutFn = Callable[[Batch], np.ndarray]


def model_rollout(model: Any, velocities: Sequence[np.ndarray]) -> RolloutFn:
    """The rollout of ``model``: its own ``rollout(history, commands)`` when it has one (checked: shape
    (W, n+1, 3), finite), else its per-sequence predicted ``velocities`` gathered per window."""
    name = getattr(model, "name", type(model).__name__)
    own = getattr(model, "rollout", None)
    if not callable(own):
        return lambda b: np.asarray(velocities[b.seq], float)[b.ahead]

    def call(b: Batch) -> np.ndarray:
        out = np.asarray(own(b.history, b.commands), dtype=float)
        if out.shape != (*b.commands.t.shape, 3):
            raise EvaluationError(f"model {name}: rollout returned shape {out.shape}, "
                                  f"expected {(*b.commands.t.shape, 3)}")  # fmt: skip
        bad = int(np.sum(~np.isfinite(out)))
        if bad:
            raise EvaluationError(f"model {name}: rollout returned {bad} non-finite value(s)")
        return out

    return call


def batches(tables: Sequence[pd.DataFrame], horizon_s: float, settings: StateSettings):
    """Yields the :class:`Batch` es of every sequence (``tables``: split tables), windows with a full
    history and ``horizon_s`` of valid samples, ``settings.stride_s`` apart."""
    for k, df in enumerate(tables):
        t = df["t"].to_numpy(float)
        if len(t) < 2:
            continue
        dt = float(np.median(np.diff(t)))
        n = horizon_steps(t, horizon_s)
        m = st.history_steps(dt, settings.history_s)
        stride = max(int(round(settings.stride_s / dt)), 1)
        starts = st.window_starts(df["valid"].to_numpy(bool), m, n, stride)
        if not len(starts):
            continue
        seq = st.Sequence.of(df, settings.history_s)
        per = max(settings.max_batch_samples // (n + 1), 1)
        for a in range(0, len(starts), per):
            s = starts[a : a + per]
            history, commands = st.cut_windows(seq, s, m, n)
            yield Batch(history, commands, k, s, s[:, None] + np.arange(n + 1)[None, :])


def integrate_windows(pose0: np.ndarray, velocity: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(W, n+1, 3) poses of W windows integrated from ``pose0`` (W, 3) with body velocities ``velocity``
    (W, n+1, 3) at times ``t`` (W, n+1): exact SE(2) steps of each step's mean twist (the trapezoidal
    rule of benchmark/horizon.py), vectorised over windows."""
    dt = np.diff(t, axis=1)
    steps = se2_exp(0.5 * (velocity[:, :-1] + velocity[:, 1:]) * dt[..., None])
    zero = np.zeros((len(pose0), 1))
    yaw = pose0[:, 2:3] + np.concatenate([zero, np.cumsum(steps[..., 2], axis=1)], axis=1)
    c, s = np.cos(yaw[:, :-1]), np.sin(yaw[:, :-1])
    dx = np.concatenate([zero, np.cumsum(c * steps[..., 0] - s * steps[..., 1], axis=1)], axis=1)
    dy = np.concatenate([zero, np.cumsum(s * steps[..., 0] + c * steps[..., 1], axis=1)], axis=1)
    return np.stack([pose0[:, 0:1] + dx, pose0[:, 1:2] + dy, yaw], axis=-1)


def _batch_windows(df: pd.DataFrame, b: Batch, vel: np.ndarray, horizons: Sequence[float],
                   hcfg: HorizonConfig, robot: Any) -> list[pd.DataFrame]:  # fmt: skip
    """The window rows (one per window and horizon) of one batch, as :func:`horizon.window_errors`'."""
    gt = df[["x", "y", "yaw"]].to_numpy(float)
    pred = integrate_windows(gt[b.starts], vel, b.commands.t)
    step_len = np.hypot(np.diff(gt[:, 0]), np.diff(gt[:, 1]))
    cum_len = np.concatenate([[0.0], np.cumsum(step_len)])
    cum_rot = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(gt[:, 2])))])
    t = df["t"].to_numpy(float)
    acc = sample_acceleration(df, robot.track_width / 2.0 if robot is not None else 0.0)
    out = []
    for h in horizons:
        n = horizon_steps(t, h)
        ends = b.starts + n
        p = pred[:, n]
        pos_err = np.hypot(gt[ends, 0] - p[:, 0], gt[ends, 1] - p[:, 1])
        rot_err = gt[ends, 2] - p[:, 2]
        aggr = window_aggressiveness(acc, b.starts, n)
        distance, rotation = cum_len[ends] - cum_len[b.starts], cum_rot[ends] - cum_rot[b.starts]
        min_distance, min_rotation = hcfg.minimums(h)
        with np.errstate(divide="ignore", invalid="ignore"):
            rel_trans = np.where(distance >= min_distance, pos_err / distance, np.nan)
            rel_rot = np.where(rotation >= min_rotation, np.abs(rot_err) / rotation, np.nan)
        out.append(pd.DataFrame({
            "horizon_s": float(h), "start": b.starts, "t0": t[b.starts], "distance": distance,
            "rotation": rotation, "trans_err": pos_err, "rot_err": rot_err, "rel_trans": rel_trans,
            "rel_rot": rel_rot, "end": ends, "pred_x": p[:, 0], "pred_y": p[:, 1], "pred_yaw": p[:, 2],
            "gt_x": gt[ends, 0], "gt_y": gt[ends, 1], "gt_yaw": gt[ends, 2], "aggressiveness": aggr,
        }))  # fmt: skip
    return out


def state_windows(
    names: Sequence[str],
    tables: Sequence[pd.DataFrame],
    rollout: RolloutFn,
    horizons: Sequence[float],
    hcfg: HorizonConfig,
    settings: StateSettings,
    robot: Any = None,
) -> pd.DataFrame:
    """Per-window errors under ``state`` of the sequences ``tables`` (named ``names``) at every horizon:
    the columns of :func:`~skidbench.benchmark.scoring.score_split` (``horizon_s``, ``sequence``, the
    window columns, ``gt_x gt_y gt_yaw``) plus ``aggressiveness``
    (benchmark/scoring/aggressiveness.py, over each horizon's own samples; ``robot``'s track width),
    every horizon on the same windows; empty when no sequence has one."""
    longest = max(float(h) for h in horizons)
    frames = []
    for b in batches(tables, longest, settings):
        vel = rollout(b)
        for w in _batch_windows(tables[b.seq], b, vel, horizons, hcfg, robot):
            w.insert(1, "sequence", names[b.seq])
            frames.append(w)
    if not frames:
        return pd.DataFrame()
    out = pd.concat(frames, ignore_index=True)
    return out.sort_values("horizon_s", kind="stable").reset_index(drop=True)
