"""The rows evaluate logs beside a model's own scores (docs/intervals.md): the floor of each terrain (a
perfect model, the simulator's exact velocities, through the same windows:
:mod:`skidbench.benchmark.scoring.floor`) and the spread of a model with random parts over several seeds
(``evaluate seeds=N``)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa

from skidbench.benchmark.scoring import metrics as mt
from skidbench.benchmark.scoring.floor import (
    FLOOR,
    TRUTH_KEY,
    floor_windows,
    truth_velocities,
    unknown_reason,
)
from skidbench.benchmark.scoring.horizon import HorizonConfig
from skidbench.benchmark.scoring.predictions import (
    Inputs,
    Score,
    TestSequence,
    keyed,
    predict_and_score,
    score_cells,
)
from skidbench.benchmark.scoring.rollout import state_windows
from skidbench.benchmark.scoring.settings import IntervalConfig
from skidbench.pipeline.core.io import write_parquet_atomic


def exact_velocities(
    truth_dir: Path, tests: Mapping[str, Sequence[TestSequence]]
) -> tuple[dict[str, list[tuple[str, pd.DataFrame, np.ndarray]]], str]:
    """Per test split, ``(name, split table, the simulator's exact velocities on its clock)`` of every
    sequence, from ``<truth_dir>/<sequence>/true_pose.parquet`` (the extracted truth of a simulated
    recording); or ``({}, reason)`` when one sequence has none (a real recording: the floor is unknown)."""
    out: dict[str, list[tuple[str, pd.DataFrame, np.ndarray]]] = {}
    for split, seqs in tests.items():
        out[split] = []
        for s in seqs:
            path = truth_dir / s.name / f"{TRUTH_KEY}.parquet"
            if not path.is_file():
                return {}, unknown_reason(s.name, f"no simulator truth table {path.name}")
            if not len(s.table):
                continue
            try:
                stamps = s.table["stamp_ns"].to_numpy(np.int64)
                vel = truth_velocities(stamps, pd.read_parquet(path), str(path))
            except (OSError, ValueError) as exc:
                return {}, unknown_reason(s.name, str(exc).removeprefix(f"{path}: "))
            out[split].append((s.name, s.table, vel))
    return out, ""


def log_floor(
    tracker: Any,
    parent_id: str,
    stem: Path,
    terrain: str,
    tests: Mapping[str, Sequence[TestSequence]],
    horizons: Sequence[float],
    hcfg: HorizonConfig,
    intervals: IntervalConfig,
    protocol: str,
    inputs: Inputs | None = None,
    truth_dir: Path | None = None,
) -> tuple[dict[str, float], list[Score]]:
    """The floor of one terrain, scored as a model is (every metric and its interval): its windows written
    next to the models' (``<stem>.windows.parquet``, ``<ds>/eval/floor/<terrain>[.<inputs>]``: what
    compare reads) and its metrics logged on the parent run as ``floor.<terrain>.<metric>``. Not a child
    run: it is never ranked. Under ``state`` (``inputs``' settings) its windows are the state windows, each
    rolled out with the exact velocities. Where the data hold no simulator truth (``truth_dir``: the
    dataset's extracted tables) the windows file is empty, its metadata and the parent run's tag
    ``floor.<terrain>.unknown`` say why, and no metric is logged. Returns the metrics and the cells they
    are (the results table's floor rows; none when the floor is unknown)."""
    frames, scores = [], []
    exact, unknown = exact_velocities(truth_dir, tests) if truth_dir is not None else ({}, "no truth folder")
    for split, seqs in exact.items():
        if protocol == "state":
            inputs = inputs or Inputs("state")
            vel = [v for _, _, v in seqs]
            w = state_windows([n for n, _, _ in seqs], [t for _, t, _ in seqs],
                              lambda b, v=vel: v[b.seq][b.ahead], horizons, hcfg, inputs.state,
                              inputs.robot)  # fmt: skip
        else:
            w = floor_windows(seqs, horizons, hcfg)
        if len(w):
            w.insert(0, "split", split)
            frames.append(w)
        scores += score_cells(w, split, horizons, intervals)
    metrics = keyed(scores)
    windows = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    stem.parent.mkdir(parents=True, exist_ok=True)
    path = stem.with_name(stem.name + ".windows.parquet")
    meta = {"model": FLOOR, "terrain": terrain, "horizons": list(horizons), "inputs": protocol}
    if unknown:
        meta["floor_unknown"] = unknown
    write_parquet_atomic(pa.Table.from_pandas(windows, preserve_index=False), path, meta)
    tracker.artifact(parent_id, path, "floor")
    if unknown:
        tracker.log(parent_id, tags={f"{FLOOR}.{terrain}.unknown": unknown})
        return {}, []
    finite = {k: v for k, v in metrics.items() if np.isfinite(v)}
    tracker.log(parent_id, metrics={f"{FLOOR}.{terrain}.{k}": v for k, v in finite.items()})
    return metrics, scores


def seed_spread(
    refit: Any,
    model: Any,
    tests: Mapping[str, Sequence[TestSequence]],
    horizons: Sequence[float],
    hcfg: HorizonConfig,
    inputs: Inputs,
    seeds: int,
    scores: Sequence[Score],
) -> dict[tuple[str, str, float], tuple[float, float, float]]:
    """A model with random parts (a ``seed`` option) fitted with ``seeds - 1`` more seeds (its seed + 1,
    + 2, ...; ``refit.fit(seed)``: models/fitting ``Refit``) and scored on the same windows: per cell
    ``(metric, split, horizon_s)`` of a metric with an interval, ``(sd, min, max)`` over the seeds (the
    configured one's included; the standard deviation rounded as an interval is), when at least two seeds
    gave a value. The other seeds' fits are not saved: they cost a fit each, every evaluate
    (docs/intervals.md, "Seeds")."""
    cell = lambda s: (s.metric, s.split, s.horizon_s)  # noqa: E731
    values = {cell(s): [s.estimate] for s in scores if mt.get(s.metric).bootstrap is not None}
    base = int(model.options["seed"])
    for k in range(1, seeds):
        got, _, _, _ = predict_and_score(refit.fit(base + k), tests, horizons, hcfg, inputs, intervals=None)
        by_cell = {cell(s): s.estimate for s in got}
        for key in values:
            values[key].append(by_cell.get(key, np.nan))
    out: dict[tuple[str, str, float], tuple[float, float, float]] = {}
    for key, v in values.items():
        arr = np.asarray(v, dtype=float)
        if np.isfinite(arr).sum() >= 2:
            out[key] = (round(float(np.nanstd(arr, ddof=1)), 4), float(np.nanmin(arr)), float(np.nanmax(arr)))
    return out
