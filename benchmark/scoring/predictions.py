"""The benchmark's scoring, pure: from a model's predictions and the test splits to the errors of every
window and their summaries (the metrics of :mod:`skidbench.benchmark.scoring.metrics`). No MLflow, no files:
:mod:`skidbench.benchmark.evaluate.evaluation` loads the splits, fits the models and logs what this computes.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pandas as pd

from skidbench.benchmark.errors import EvaluationError
from skidbench.benchmark.scoring.horizon import HorizonConfig, window_errors
from skidbench.benchmark.scoring.intervals import Sample, cell, estimate, stratum_key
from skidbench.benchmark.scoring.metrics import BY_NAME, METRICS
from skidbench.benchmark.scoring.rollout import model_rollout, state_windows
from skidbench.benchmark.scoring.settings import IntervalConfig, StateSettings
from skidbench.pipeline.calibrate.wheel_response import WheelResponse
from skidbench.pipeline.core.protocol import model_inputs
from skidbench.pipeline.core.robot import Robot
from skidbench.pipeline.core.schema import concat_sequences


@dataclass
class TestSequence:
    """One test sequence of a split: its name, file, table (pipeline/core/schema.py columns) and metadata."""

    __test__ = False  # not a test class (pytest collects names starting with Test)

    name: str
    path: Path
    table: pd.DataFrame
    meta: dict[str, Any]

    @property
    def duration_s(self) -> float:
        t = self.table["t"].to_numpy()
        return float(t[-1] - t[0]) if len(t) > 1 else 0.0


@dataclass(frozen=True)
class Inputs:
    """What drives every model of a run on one terrain: the input protocol (pipeline/core/protocol.py), the
    robot its wheel rates are converted to ``cmd_v``/``cmd_w`` with, the terrain's wheel response and the
    ``state`` protocol's windows (benchmark/scoring/rollout.py)."""

    protocol: str = "commanded"
    robot: Robot | None = None
    response: WheelResponse | None = None
    state: StateSettings = StateSettings()  # noqa: RUF009 (frozen: shared safely)


def predict_split(
    model: Any, seqs: Sequence[TestSequence], inputs: Inputs | None = None, with_cov: bool = False
) -> tuple[list[np.ndarray], float] | tuple[list[np.ndarray], float, list[np.ndarray] | None]:
    """Predict every sequence of a split in one batched call; returns per-sequence (T, 3) and seconds
    (and with ``with_cov`` the per-sequence (T, 3, 3) predictive covariances of a model that has
    ``predict_cov``, else None; its time is included).
    The model gets ONLY the protocol's input columns (:func:`skidbench.pipeline.core.protocol.model_inputs`:
    time, sequence and the protocol's wheel rates), never the pose, the targets or the encoders."""
    inputs = inputs or Inputs()
    nonempty = [s for s in seqs if len(s.table)]
    full = concat_sequences([(s.table, {"sequence": s.name}) for s in nonempty])
    robot = inputs.robot
    if robot is None:
        robot = getattr(model, "robot", None)
    table = model_inputs(full, inputs.protocol, robot, inputs.response)
    name = getattr(model, "name", type(model).__name__)
    t0 = time.perf_counter()
    vel = np.asarray(model.predict(table), dtype=float)
    cov = None
    if with_cov and callable(getattr(model, "predict_cov", None)):
        cov = np.asarray(model.predict_cov(table), dtype=float)
        if cov.shape != (len(table), 3, 3):
            raise EvaluationError(
                f"model {name}: predict_cov returned shape {cov.shape}, expected ({len(table)}, 3, 3)"
            )
        if not np.all(np.isfinite(cov)):
            raise EvaluationError(f"model {name}: predict_cov returned non-finite value(s)")
    dt = time.perf_counter() - t0
    if vel.shape != (len(table), 3):
        raise EvaluationError(f"model {name}: predict returned shape {vel.shape}, expected ({len(table)}, 3)")
    bad = int(np.sum(~np.isfinite(vel)))
    if bad:
        raise EvaluationError(f"model {name}: predict returned {bad} non-finite value(s)")
    out, covs, i = [], [], 0
    for s in seqs:
        out.append(vel[i : i + len(s.table)])
        if cov is not None:
            covs.append(cov[i : i + len(s.table)])
        i += len(s.table)
    if with_cov:
        return out, dt, (covs if cov is not None else None)
    return out, dt


def score_split(
    seqs: Sequence[TestSequence],
    velocities: Sequence[np.ndarray],
    horizons: Sequence[float],
    hcfg: HorizonConfig,
    covariances: Sequence[np.ndarray] | None = None,
    autocorr: np.ndarray | None = None,
) -> pd.DataFrame:
    """Per-window errors of every sequence and horizon (columns: horizon_s, sequence, window columns,
    and the true end pose gt_x, gt_y, gt_yaw; with ``covariances`` (per sequence (T, 3, 3)) the
    uncertainty columns of :data:`~skidbench.benchmark.scoring.horizon.UNCERTAINTY_COLUMNS`)."""
    frames = []
    covs = list(covariances) if covariances is not None else [None] * len(seqs)
    for h in horizons:
        cfg_h = HorizonConfig(h, hcfg.min_distance_m, hcfg.min_rotation_rad)
        for s, vel, cov in zip(seqs, velocities, covs, strict=True):
            df = s.table
            gt = df[["x", "y", "yaw"]].to_numpy(dtype=float)
            w = window_errors(
                df["t"].to_numpy(float), gt, vel, h, df["valid"].to_numpy(bool), cfg_h, cov, autocorr
            )
            if len(w) == 0:
                continue
            end = w["end"].to_numpy(int)
            w["gt_x"], w["gt_y"], w["gt_yaw"] = gt[end, 0], gt[end, 1], gt[end, 2]
            w.insert(0, "sequence", s.name)
            w.insert(0, "horizon_s", float(h))
            frames.append(w)
    if not frames:
        return pd.DataFrame()
    return pd.concat(frames, ignore_index=True)


class Score(NamedTuple):
    """One cell of a test split at a horizon: a metric's value (:attr:`Metric.aggregate` of its windows),
    the windows behind it and, when its interval was computed, the interval and the independent blocks
    behind it (``n_blocks`` None: no interval computed; NaN bounds and 0 blocks: no window)."""

    metric: str  # Metric.name
    split: str
    horizon_s: float
    estimate: float
    n_windows: int
    lo: float = float("nan")
    hi: float = float("nan")
    n_blocks: int | None = None


def score_cells(
    windows: pd.DataFrame,
    split: str,
    horizons: Sequence[float],
    intervals: IntervalConfig | None = IntervalConfig(),  # noqa: B008 (frozen: shared safely)
) -> list[Score]:
    """Every metric of :data:`~skidbench.benchmark.scoring.metrics.METRICS` on the windows of one split, per
    horizon (an optional metric only when the windows have its column: models with a predictive
    covariance). With ``intervals`` (the default), a metric with a
    :class:`~skidbench.benchmark.scoring.metrics.Bootstrap` also gets its confidence interval and the
    independent blocks behind it (:func:`interval_cells`)."""
    out: list[Score] = []
    for h in horizons:
        w = windows[windows["horizon_s"] == float(h)] if len(windows) else windows
        bounds = interval_cells(w, split, h, intervals) if intervals is not None else {}
        for metric in METRICS:
            has = bool(len(w)) and metric.column in w
            if metric.optional and not has:
                continue
            vals = w[metric.column].to_numpy(float) if has else np.array([])
            lo, hi, blocks = bounds.get(metric.name, (float("nan"), float("nan"), None))
            n = int(np.isfinite(vals).sum())
            out.append(Score(metric.name, split, float(h), metric.aggregate(vals), n, lo, hi, blocks))
    return out


def keyed(scores: Sequence[Score]) -> dict[str, float]:
    """The cells by their MLflow names (``ld_6s_trans_rmsre_pct``: :func:`Metric.metric_key`), per split
    and horizon each metric's value and window count, then each interval's bounds and blocks (``<key>_ci_lo``,
    ``<key>_ci_hi``, ``<split>_<h>s_<short>_blocks``): the metrics evaluate logs to MLflow."""
    out: dict[str, float] = {}
    groups: dict[tuple[str, float], list[Score]] = {}
    for s in scores:
        groups.setdefault((s.split, s.horizon_s), []).append(s)
    for (split, h), cells in groups.items():
        for s in cells:
            m = BY_NAME[s.metric]
            out[m.metric_key(split, h)] = s.estimate
            if m.count_key is not None:
                out[m.windows_key(split, h)] = float(s.n_windows)
        for s in cells:
            if s.n_blocks is not None:
                lo, hi, blocks = BY_NAME[s.metric].interval_keys(split, h)
                out.update({lo: s.lo, hi: s.hi, blocks: float(s.n_blocks)})
    return out


def summarise(
    windows: pd.DataFrame,
    split: str,
    horizons: Sequence[float],
    intervals: IntervalConfig | None = IntervalConfig(),  # noqa: B008 (frozen: shared safely)
) -> dict[str, float]:
    """:func:`score_cells` by their MLflow names (:func:`keyed`)."""
    return keyed(score_cells(windows, split, horizons, intervals))


def interval_cells(
    windows: pd.DataFrame, split: str, horizon_s: float, settings: IntervalConfig
) -> dict[str, tuple[float, float, int]]:
    """Per metric name with a bootstrap: ``(lo, hi, blocks)`` of its interval (rounded as the value is),
    on the windows of one split at one horizon (:mod:`skidbench.benchmark.scoring.intervals`; a metric whose
    windows lack its column gets none; with no window, NaN and 0 blocks)."""
    metrics = [m for m in METRICS if m.bootstrap is not None and (not m.optional or m.column in windows)]
    if not len(windows):
        return {m.name: (float("nan"), float("nan"), 0) for m in metrics if not m.optional}
    key = stratum_key(split, horizon_s, windows["sequence"])
    sample = Sample(settings)
    sample.add(key, windows["sequence"], windows["t0"].to_numpy(float),
               {m.name: m.bootstrap.scale * m.window_values(windows) for m in metrics}, horizon_s,
               {m.name: m.bootstrap.aggregation for m in metrics})  # fmt: skip
    res = estimate(sample, [cell(m.name, key, m.name) for m in metrics])
    return {m.name: (round(float(row.lo), 4), round(float(row.hi), 4), int(row.n_blocks))
            for m, row in zip(metrics, res.itertuples(index=False), strict=True)}  # fmt: skip


def predict_and_score(
    model: Any,
    tests: dict[str, Sequence[TestSequence]],
    horizons: Sequence[float],
    hcfg: HorizonConfig,
    inputs: Inputs | None = None,
    on_step: Callable[[str], None] | None = None,
    intervals: IntervalConfig | None = IntervalConfig(),  # noqa: B008 (frozen: shared safely)
) -> tuple[list[Score], pd.DataFrame, dict[str, list[np.ndarray]], float]:
    """Predicts every test split with ``model`` (:func:`predict_split`, with its covariances when it has
    ``predict_cov``) and scores every window of every horizon (:func:`score_split`). Returns the cells
    (:func:`score_cells` of each split), the windows of every split in one frame (first column ``split``;
    empty when no split has a window), the predicted body velocities per split (per sequence (T, 3): vx,
    vy in m/s, wz in rad/s) and the seconds spent in predict. Logs nothing; ``on_step`` is told the step
    it is at ("predict", "score <split>") before each; ``intervals``: the confidence intervals' settings
    (:func:`score_cells`)."""
    step = on_step or (lambda _name: None)
    if inputs is not None and inputs.protocol == "state":
        return _state_predict_and_score(model, tests, horizons, hcfg, inputs, step, intervals)
    scores: list[Score] = []
    frames = []
    predict_time = 0.0
    autocorr = getattr(model, "error_autocorrelation_", None)
    velocities = {}
    for split, seqs in tests.items():
        vel, dt, cov = predict_split(model, seqs, inputs, with_cov=True)
        velocities[split] = vel
        predict_time += dt
        step(f"score {split}")
        w = score_split(seqs, vel, horizons, hcfg, cov, autocorr)
        if len(w):
            w.insert(0, "split", split)
            frames.append(w)
        scores += score_cells(w, split, horizons, intervals)
        step("predict")
    windows = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    return scores, windows, velocities, predict_time


def _state_predict_and_score(
    model: Any,
    tests: dict[str, Sequence[TestSequence]],
    horizons: Sequence[float],
    hcfg: HorizonConfig,
    inputs: Inputs,
    step: Callable[[str], None],
    intervals: IntervalConfig | None,
) -> tuple[list[Score], pd.DataFrame, dict[str, list[np.ndarray]], float]:
    """:func:`predict_and_score` under ``state``: every window rolled out from its start
    (:func:`~skidbench.benchmark.rollout.state_windows`); a model without ``rollout`` is driven by its
    ``predict`` of the commanded inputs. The velocities returned (compare's figures) are that ``predict``."""
    scores: list[Score] = []
    frames, velocities, spent = [], {}, 0.0
    commanded = Inputs("commanded", inputs.robot, None)
    for split, seqs in tests.items():
        vel, dt = predict_split(model, seqs, commanded)
        velocities[split] = vel
        step(f"rollout {split}")
        t0 = time.perf_counter()
        w = state_windows([s.name for s in seqs], [s.table for s in seqs], model_rollout(model, vel),
                          horizons, hcfg, inputs.state, inputs.robot)  # fmt: skip
        spent += dt + time.perf_counter() - t0
        if len(w):
            w.insert(0, "split", split)
            frames.append(w)
        scores += score_cells(w, split, horizons, intervals)
    windows = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    return scores, windows, velocities, spent
