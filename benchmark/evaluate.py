"""The 6 s horizon benchmark (SPEC.md "Evaluation"): fit every model on each terrain's Train split,
predict the CV and LD sequences, score every window with :func:`~skidbench.benchmark.horizon.window_errors`
and log RMSRE per model, terrain, split and horizon to MLflow (:mod:`skidbench.benchmark.tracking`).

:func:`run_benchmark` is the stage without Hydra; ``evaluate_app.main`` is the CLI. Data problems that
make the benchmark meaningless (no splits, an empty test split, a horizon longer than every sequence) are
raised as one-line :class:`EvaluationError` before any run is created; a model that fails to fit or
predict gets its child run marked FAILED with the reason, and the others carry on.
"""

from __future__ import annotations

import importlib.metadata as md
import json
import logging
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa

from skidbench.pipeline.errors import SkidbenchError, one_line
from skidbench.pipeline.io import fingerprint_obj, write_json_atomic, write_parquet_atomic
from skidbench.pipeline.layout import Layout, layout_from_cfg, split_terrains
from skidbench.pipeline.manifest import Manifest
from skidbench.pipeline.protocol import ProtocolError, model_inputs, protocol_of, sequences_without_encoders
from skidbench.pipeline.robot import Robot
from skidbench.pipeline.schema import read_split
from skidbench.pipeline.wheel_response import WheelResponse

from . import mlflow_ui as mu
from . import tracking as trk
from .horizon import (
    CHI2_95_1DOF,
    CHI2_95_2DOF,
    EvaluationError,
    HorizonConfig,
    count_windows,
    horizon_steps,
    rmsre,
    window_errors,
)
from .report_data import write_report_data, write_wheel_response_steps
from .transfer import training_layout

log = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "skidbench.models"
TRAIN = "train"
KINDS = {"translational": "rel_trans", "rotational": "rel_rot"}


class ProtocolSkipped(EvaluationError):
    """No terrain of the dataset can be driven by the input protocol (e.g. ``measured`` without encoders):
    the protocol is skipped for the dataset, which is not an error of the run (``skidbench evaluate``
    prints the line and exits 0)."""


# -- data -------------------------------------------------------------------------------------------
@dataclass
class TestSequence:
    name: str
    path: Path
    table: pd.DataFrame
    meta: dict[str, Any]

    @property
    def duration_s(self) -> float:
        t = self.table["t"].to_numpy()
        return float(t[-1] - t[0]) if len(t) > 1 else 0.0


def current_manifest(layout: Layout) -> Manifest:
    """The dataset's current manifest: the one source of its terrains and sequences."""
    if not layout.manifest.is_file():
        raise EvaluationError(
            f"{layout.splits}: no splits; run `skidbench split` first ({layout.manifest} is absent)"
        )
    try:
        return Manifest.read(layout.manifest)
    except SkidbenchError as exc:
        raise EvaluationError(one_line(str(exc))) from None


def split_files(
    layout: Layout, terrain: str, split: str | None, manifest: Manifest | None = None
) -> list[Path]:
    """The split files of the manifest's ``terrain``/``split`` sequences; EvaluationError if one is
    missing."""
    return layout.require_split_files(manifest or current_manifest(layout), terrain, split, EvaluationError)


def find_terrains(layout: Layout) -> list[str]:
    """The manifest's terrains with train/cv/ld sequences, sorted."""
    terrains = split_terrains(current_manifest(layout))
    if not terrains:
        raise EvaluationError(f"{layout.manifest}: no train/cv/ld sequences; nothing to evaluate")
    return terrains


def load_test_split(layout: Layout, terrain: str, split: str) -> list[TestSequence]:
    """The sequences of one test split; EvaluationError when there are none or all are empty."""
    where = layout.splits / terrain / split
    files = split_files(layout, terrain, split)
    if not files:
        raise EvaluationError(
            f"{where}: empty {split} split (no sequences) for terrain {terrain}; re-run `skidbench split`, "
            f"or leave it out with splits=[...] / terrains=[...]"
        )
    seqs = []
    for p in files:
        try:
            df, meta = read_split(p)
        except SkidbenchError as exc:
            raise EvaluationError(one_line(str(exc))) from None
        seqs.append(TestSequence(str(meta.get("sequence") or p.stem), p, df, meta))
    if all(len(s.table) == 0 for s in seqs):
        raise EvaluationError(
            f"{where}: empty {split} split (every sequence has 0 rows) for terrain {terrain}"
        )
    return seqs


def check_horizons(terrain: str, split: str, seqs: Sequence[TestSequence], horizons: Sequence[float]) -> None:
    """EvaluationError when a horizon is longer than every sequence of a split (no window at all)."""
    for h in horizons:
        if not h > 0:
            raise EvaluationError(f"horizon {h} s is not positive; set horizons=[6.0]")
        if not any(len(s.table) > horizon_steps(s.table["t"].to_numpy(), h) >= 1 for s in seqs):
            longest = max(s.duration_s for s in seqs)
            raise EvaluationError(
                f"splits/{terrain}/{split}: horizon {h:g} s is longer than every sequence "
                f"(longest {longest:.1f} s); lower horizons=[...]"
            )


def split_fingerprint(files: Sequence[Path], root: Path) -> str:
    """Fingerprint of a set of split files: the content fingerprints recorded by the split stage in
    the file metadata when present, else the files' own content hashes."""
    from skidbench.pipeline.cache import Fingerprints

    fp = Fingerprints()
    return fingerprint_obj({str(Path(p).relative_to(root)): fp(p) for p in sorted(files)})


# -- model plumbing ---------------------------------------------------------------------------------
def installed_models() -> dict[str, md.EntryPoint]:
    return {ep.name: ep for ep in md.entry_points(group=ENTRY_POINT_GROUP)}


def plugin_package(model_name: str, model: Any = None) -> str:
    """``distribution==version`` that provides a model (its entry point, else its top-level module)."""
    ep = installed_models().get(model_name)
    if ep is not None and ep.dist is not None:
        return f"{ep.dist.name}=={ep.dist.version}"
    if model is not None:
        top = type(model).__module__.split(".")[0]
        dists = md.packages_distributions().get(top) or []
        if dists:
            name = dists[0]
            try:
                return f"{name}=={md.version(name)}"
            except md.PackageNotFoundError:
                return name
        return f"module:{type(model).__module__}"
    return "unknown"


def default_fit_fn() -> Callable[[Any, str, str], Any]:
    try:
        from skidbench.models.fitting import fit_model
    except ImportError as exc:
        raise EvaluationError(f"model fitting is not available ({exc})") from None
    return fit_model


@dataclass(frozen=True)
class Inputs:
    """What drives every model of a run on one terrain: the input protocol (pipeline/protocol.py), the
    robot its wheel rates are converted to ``cmd_v``/``cmd_w`` with, and the terrain's wheel response."""

    protocol: str = "commanded"
    robot: Robot | None = None
    response: WheelResponse | None = None


def predict_split(
    model: Any, seqs: Sequence[TestSequence], inputs: Inputs | None = None, with_cov: bool = False
) -> tuple[list[np.ndarray], float] | tuple[list[np.ndarray], float, list[np.ndarray] | None]:
    """Predict every sequence of a split in one batched call; returns per-sequence (T, 3) and seconds
    (and with ``with_cov`` the per-sequence (T, 3, 3) predictive covariances of a model that has
    ``predict_cov``, else None; its time is included).
    The model gets ONLY the protocol's input columns (:func:`skidbench.pipeline.protocol.model_inputs`:
    time, sequence and the protocol's wheel rates), never the pose, the targets or the encoders."""
    from skidbench.pipeline.schema import concat_sequences

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
    uncertainty columns of :data:`~skidbench.benchmark.horizon.UNCERTAINTY_COLUMNS`)."""
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


def summarise(windows: pd.DataFrame, split: str, horizons: Sequence[float]) -> dict[str, float]:
    """RMSRE metrics in % (names from :func:`tracking.metric_key`) and window counts of one split."""
    out: dict[str, float] = {}
    for h in horizons:
        w = windows[windows["horizon_s"] == float(h)] if len(windows) else windows
        for kind, col in KINDS.items():
            vals = w[col].to_numpy(float) if len(w) else np.array([])
            # percent, as every table shows it; to 0.001 % so that the UI's columns read as numbers
            out[trk.metric_key(kind, split, h)] = round(100.0 * rmsre(vals), 3)
            out[trk.windows_key(kind, split, h)] = float(np.isfinite(vals).sum())
        if len(w) and "pos_d2" in w:
            out[f"coverage95_position_{split}_{h:g}s"] = float(np.mean(w["pos_d2"] <= CHI2_95_2DOF))
            out[f"coverage95_yaw_{split}_{h:g}s"] = float(np.mean(w["yaw_z2"] <= CHI2_95_1DOF))
            out[f"nll_position_{split}_{h:g}s"] = float(np.mean(w["nll_pos"]))
    return out


# -- the benchmark ----------------------------------------------------------------------------------
@dataclass
class ChildResult:
    model: str
    terrain: str
    run_id: str
    status: str
    metrics: dict[str, float] = field(default_factory=dict)
    reason: str = ""
    inputs: str = "commanded"


@dataclass
class BenchmarkResult:
    tracking_uri: str
    experiment: str
    parent_run_id: str
    children: list[ChildResult]
    inputs: str = "commanded"
    skipped: list[str] = field(default_factory=list)  # one line per (terrain, split) the protocol skipped

    @property
    def failed(self) -> list[ChildResult]:
        return [c for c in self.children if c.status != "FINISHED"]

    def table(self) -> pd.DataFrame:
        rows = [
            {"model": c.model, "inputs": c.inputs, "terrain": c.terrain, "status": c.status, **c.metrics}
            for c in self.children
        ]
        return pd.DataFrame(rows)


def _as_container(cfg: Any) -> dict[str, Any]:
    try:
        from omegaconf import OmegaConf

        if OmegaConf.is_config(cfg):
            return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]
    except ImportError:  # pragma: no cover
        pass
    return dict(cfg)


def settings_from_cfg(cfg: Any) -> tuple[list[str], list[str] | None, list[str], list[float], HorizonConfig]:
    models = [str(m) for m in (cfg.models or [])]
    if not models:
        raise EvaluationError("no models to evaluate; set models=[ideal,friction,...]")
    terrains = [str(t) for t in cfg.terrains] if cfg.get("terrains") else None
    splits = [str(s) for s in (cfg.splits or [])]
    if not splits:
        raise EvaluationError("no test splits; set splits=[cv,ld]")
    horizons = [float(h) for h in (cfg.horizons or [])]
    if not horizons:
        raise EvaluationError("no horizons; set horizons=[6.0]")
    hcfg = HorizonConfig(
        horizons[0], float(cfg.min_distance_m), float(np.deg2rad(float(cfg.min_rotation_deg)))
    )
    return models, terrains, splits, horizons, hcfg


def run_benchmark(
    cfg: Any,
    fit_fn: Callable[[Any, str, str], Any] | None = None,
    log_figures: bool | None = None,
) -> BenchmarkResult:
    """Fit, predict and score every (model, terrain); log to MLflow. ``fit_fn(cfg, model, terrain)``
    returns a FitResult-like object (``model``, ``path``, ``fit_loss``, ``fit_time_s``, ``n_train``);
    default :func:`skidbench.models.fitting.fit_model`."""
    layout = layout_from_cfg(cfg)
    models, terrains, splits, horizons, hcfg = settings_from_cfg(cfg)
    try:
        protocol = protocol_of(cfg)
    except ProtocolError as exc:
        raise EvaluationError(str(exc)) from None
    if log_figures is None:
        log_figures = bool(cfg.get("log_figures", True))
    if fit_fn is None:
        from skidbench.models.registry import is_model_spec
        from skidbench.models.specs import get_model_class

        known = installed_models()
        for m in models:  # an augmented spec "base+effect+..." must name a known base and known effects
            if "+" in m:
                get_model_class(m)
        unknown = [m for m in models if known and m not in known and not is_model_spec(m)]
        if unknown:
            raise EvaluationError(
                f"unknown model(s) {unknown}; installed: {sorted(known)} (`skidbench models` lists them)"
            )
        fit_fn = default_fit_fn()
    # transfer (train_dataset / train_terrain): fit elsewhere, own experiment and tags (benchmark/transfer.py)
    cfg, fit_fn, transfer_tags = training_layout(cfg, fit_fn)

    # 1. the data, checked before anything is logged
    found = find_terrains(layout)
    if terrains is None:
        terrains = found
    missing = [t for t in terrains if t not in found]
    if missing:
        raise EvaluationError(f"{layout.manifest}: no sequences of terrain(s) {missing}; it has {found}")
    tests: dict[str, dict[str, list[TestSequence]]] = {}
    files_of: dict[str, list[Path]] = {}
    inputs_of: dict[str, Inputs] = {}
    skipped: list[str] = []
    for terrain in terrains:
        train_files = split_files(layout, terrain, TRAIN)
        if not train_files:
            raise EvaluationError(
                f"{layout.splits / terrain / TRAIN}: empty train split for terrain {terrain}"
            )
        tests[terrain] = {}
        for split in splits:
            seqs = load_test_split(layout, terrain, split)
            check_horizons(terrain, split, seqs, horizons)
            for h in horizons:  # short sequences: say how many windows each horizon has (compare shows n)
                n_win, n_seq, short = count_windows([s.table for s in seqs], h)
                log.info("%s/%s: %g s horizon: %d windows from %d sequence(s), %d shorter than it",
                         terrain, split, h, n_win, n_seq, short)  # fmt: skip
            tests[terrain][split] = seqs
        files_of[terrain] = train_files + [s.path for sp in splits for s in tests[terrain][sp]]
        why = _protocol_unavailable(cfg, layout, protocol, terrain, train_files, tests[terrain], inputs_of)
        skipped += why
    for line in skipped:
        log.warning("%s", line)
        print(line, flush=True)
    terrains = [t for t in terrains if t in inputs_of and tests[t]]
    if not terrains:
        raise ProtocolSkipped(f"inputs={protocol}: nothing to evaluate under this protocol: {skipped[0]}")

    # 2. the store (an unreachable server is one line, here)
    tracker = trk.tracker_from_cfg(cfg, layout)
    conf = _as_container(cfg)
    params = trk.config_params(conf)  # no model's config on the parent: each child logs its own
    commit = trk.git_commit()
    all_files = [p for fs in files_of.values() for p in fs]
    common_tags = {trk.TAG_DATASET: str(cfg.dataset), trk.TAG_GIT: commit, **transfer_tags}
    children: list[ChildResult] = []
    from mlflow.exceptions import MlflowException

    from .sweep import run_key

    job_key = run_key()
    try:
        done = tracker.claim_key(job_key) if job_key else None
        if done:  # a retried job whose earlier attempt finished: its runs are the result
            return _write_last(layout, BenchmarkResult(tracker.uri, tracker.experiment_name, done,
                                                       _logged_children(tracker, done), protocol,
                                                       skipped))  # fmt: skip
        inputs = protocol
        with tracker.run(
            tracker.unique_run_name(trk.parent_run_name("evaluate", str(cfg.dataset), inputs)),
            {
                **common_tags,
                **({trk.TAG_RUN_KEY: job_key} if job_key else {}),
                trk.TAG_ROLE: "parent",
                trk.TAG_FINGERPRINT: split_fingerprint(all_files, layout.splits),
                trk.TAG_INPUTS: protocol,
                "skidbench.models": ",".join(models),
                "skidbench.terrains": ",".join(terrains),
                trk.TAG_NOTE: _describe(cfg, models, terrains, splits, horizons),
            },
        ) as parent_id:
            tracker.log(parent_id, params=params)
            if skipped:
                tracker.log(parent_id, tags={"skidbench.inputs_skipped": " | ".join(skipped)})
            datasets_of = {t: _split_inputs(cfg, layout, t, files_of[t], tests[t]) for t in terrains}
            tracker.log_datasets(parent_id, [d for t in terrains for d in datasets_of[t]])
            ctx = ChildContext(
                cfg, tracker, parent_id, layout, horizons, hcfg, fit_fn, conf, common_tags, log_figures
            )
            for terrain in terrains:
                tracker.artifact(parent_id, write_wheel_response_steps(cfg, layout, terrain), "report_data")
                td = TerrainData(terrain, tests[terrain], inputs_of[terrain], datasets_of[terrain],
                                 split_fingerprint(files_of[terrain], layout.splits))  # fmt: skip
                children += [_run_child(ctx, model_name, td) for model_name in models]
            n_failed = sum(c.status != "FINISHED" for c in children)
            board, board_metrics = leaderboard(children, splits, horizons, protocol)
            tracker.log(
                parent_id,
                metrics={"n_children": len(children), "n_failed": n_failed, **board_metrics},
                tags={
                    trk.TAG_STATUS: "FINISHED" if not n_failed else f"{n_failed} model run(s) FAILED",
                    trk.TAG_NOTE: board + _describe(cfg, models, terrains, splits, horizons),
                },  # fmt: skip
            )
            save_views(tracker, parent_id, splits, horizons, protocol)
    except MlflowException as exc:
        raise EvaluationError(f"MLflow store {tracker.uri}: {one_line(exc.message)[:300]}") from None
    return _write_last(
        layout, BenchmarkResult(tracker.uri, tracker.experiment_name, parent_id, children, protocol, skipped)
    )


def _protocol_unavailable(
    cfg: Any, layout: Layout, protocol: str, terrain: str, train_files: Sequence[Path],
    tests: dict[str, list[TestSequence]], inputs_of: dict[str, Inputs],
) -> list[str]:  # fmt: skip
    """Checks the protocol can drive the models on ``terrain``: sets ``inputs_of[terrain]``, drops from
    ``tests`` the test splits it cannot drive (``measured`` on a split without encoders) and returns one
    line per (terrain, split) skipped (the whole terrain: no response identified, no Train encoders)."""
    from skidbench.pipeline.calibration import response_for
    from skidbench.pipeline.robot import robot_from_hydra

    where = f"{layout.splits / terrain}"
    response = None
    if protocol == "response":
        response = response_for(cfg, terrain)
        if response is None:
            return [f"inputs=response: {where}: no wheel response identified (no wheel encoders in its Train "
                    "split, see `skidbench calibrate`); terrain skipped under this protocol"]  # fmt: skip
    if protocol == "measured":
        for p in train_files:
            df, _ = read_split(p)
            if sequences_without_encoders(df):
                return [
                    f"inputs=measured: {p}: no wheel encoders; terrain {terrain} skipped under this protocol"
                ]
        lines = []
        for split in list(tests):
            lacking = [s.name for s in tests[split] if len(s.table) and sequences_without_encoders(s.table)]
            if lacking:
                lines.append(f"inputs=measured: {where}/{split}: no wheel encoders in {lacking[0]}"
                             f"{f' (and {len(lacking) - 1} more)' if len(lacking) > 1 else ''}; "
                             "split skipped under this protocol")  # fmt: skip
                del tests[split]
        if not tests:
            return lines
        inputs_of[terrain] = Inputs(protocol, robot_from_hydra(cfg.robot), None)
        return lines
    inputs_of[terrain] = Inputs(protocol, robot_from_hydra(cfg.robot), response)
    return []


def last_file(layout: Layout, protocol: str = "commanded") -> Path:
    """``eval/last_evaluate[.<protocol>].json``: the last result under a protocol."""
    return layout.eval / (
        "last_evaluate.json" if protocol == "commanded" else f"last_evaluate.{protocol}.json"
    )


def _write_last(layout: Layout, result: BenchmarkResult) -> BenchmarkResult:
    write_json_atomic(
        last_file(layout, result.inputs),
        {
            "tracking_uri": result.tracking_uri,
            "experiment": result.experiment,
            "parent_run_id": result.parent_run_id,
            "inputs": result.inputs,
            "skipped": result.skipped,
            "children": [c.__dict__ for c in result.children],
        },
    )
    return result


def _logged_children(tracker, parent_id: str) -> list[ChildResult]:
    """The child runs of a finished parent run, as results (a retried job that had already finished)."""
    runs = tracker.client.search_runs(
        [tracker.experiment_id], filter_string=f"tags.`{trk.TAG_PARENT}` = '{parent_id}'", max_results=10000
    )
    return [
        ChildResult(
            r.data.tags.get(trk.TAG_MODEL, "?"),
            r.data.tags.get(trk.TAG_TERRAIN, "?"),
            r.info.run_id,
            r.info.status,
            dict(r.data.metrics),
            r.data.tags.get(trk.TAG_REASON, ""),
            r.data.tags.get(trk.TAG_INPUTS, "commanded"),
        )
        for r in sorted(runs, key=lambda r: r.info.start_time)
    ]


# -- one child run: a model on a terrain ------------------------------------------------------------
@dataclass(frozen=True)
class ChildContext:
    """What every child run of one evaluate parent run shares: the config (and its plain-container form
    ``conf`` the params are logged from), the store, the parent run, the output layout, the horizons and
    window thresholds, the fit function, the tags every child carries and whether to draw figures."""

    cfg: Any
    tracker: Any
    parent_id: str
    layout: Layout
    horizons: Sequence[float]
    hcfg: HorizonConfig
    fit_fn: Callable[[Any, str, str], Any]
    conf: dict[str, Any]
    tags: dict[str, str]
    log_figures: bool


@dataclass(frozen=True)
class TerrainData:
    """What every model of one terrain is scored on: the test sequences per split, the inputs that drive
    the models, the splits as MLflow dataset inputs and the fingerprint of the terrain's split files."""

    terrain: str
    tests: dict[str, list[TestSequence]]
    inputs: Inputs = field(default_factory=Inputs)
    datasets: Sequence[trk.SplitData] = ()
    fingerprint: str = ""


class _Stage:
    """The step a child run is at; a failure's reason reads ``"<stage> failed: <Type>: <message>"``."""

    def __init__(self, name: str) -> None:
        self.name = name

    def __call__(self, name: str) -> None:
        self.name = name


def _run_child(ctx: ChildContext, model_name: str, td: TerrainData) -> ChildResult:
    """Fit ``model_name`` on ``td.terrain``'s Train split, score it on every test split and log it all to
    one child run; an exception of the model (fit, predict, scoring, its outputs) ends that run FAILED with
    the reason and the benchmark carries on (an MLflow store error or an interrupt does not)."""
    protocol = td.inputs.protocol
    run_id = _start_child(ctx, model_name, td)
    stage = _Stage("fit")
    try:
        stem = ctx.layout.eval_stem(model_name, td.terrain, protocol)
        fit = _fit_and_log(ctx, run_id, model_name, td, stem)
        stage("logging the model")
        record_path = stem.with_name(stem.name + ".mlflow_model.json")
        _log_model(ctx.cfg, ctx.tracker, run_id, fit, model_name, td.terrain, record_path,
                   next(iter(td.tests.values()))[0])  # fmt: skip
        stage("predict")
        metrics, windows, velocities = predict_and_score(
            fit.model, td.tests, ctx.horizons, ctx.hcfg, td.inputs, on_step=stage
        )
        stage("logging")
        _log_windows(ctx, run_id, model_name, td, stem, windows)
        stage("report data")  # what compare draws beyond the metrics (Figs. 5-7), from this model
        _log_report_data(ctx, run_id, model_name, td, stem, fit.model, windows, velocities)
        _finish_child(ctx.tracker, run_id, metrics)
        log.info("%s/%s: %s", model_name, td.terrain, _brief(metrics))
        return ChildResult(model_name, td.terrain, run_id, "FINISHED", metrics, inputs=protocol)
    except KeyboardInterrupt:
        ctx.tracker.fail(run_id, "interrupted")
        raise
    except Exception as exc:
        from mlflow.exceptions import MlflowException

        if isinstance(exc, MlflowException):
            raise
        reason = f"{stage.name} failed: {type(exc).__name__}: {one_line(str(exc))}"
        log.warning("%s/%s FAILED: %s", model_name, td.terrain, reason)
        log.debug("%s", traceback.format_exc())
        ctx.tracker.fail(run_id, reason)
        return ChildResult(model_name, td.terrain, run_id, "FAILED", reason=reason, inputs=protocol)


def _start_child(ctx: ChildContext, model_name: str, td: TerrainData) -> str:
    """Starts the child run of ``model_name`` on the terrain (tags, config params, dataset inputs)."""
    protocol = td.inputs.protocol
    run_id = ctx.tracker.start(
        f"{model_name}/{td.terrain}" + ("" if protocol == "commanded" else f" [{protocol}]"),
        {**ctx.tags, trk.TAG_FINGERPRINT: td.fingerprint, trk.TAG_ROLE: "child", trk.TAG_MODEL: model_name,
         trk.TAG_TERRAIN: td.terrain, trk.TAG_INPUTS: protocol,
         trk.TAG_NOTE: _describe(ctx.cfg, [model_name], [td.terrain], list(td.tests), ctx.horizons)},
        ctx.parent_id,
    )  # fmt: skip
    params = trk.config_params(ctx.conf, _model_config(ctx.cfg, model_name))  # this model's config only
    ctx.tracker.log(run_id, params={**params, "model": model_name, "terrain": td.terrain, "inputs": protocol})
    ctx.tracker.log_datasets(run_id, td.datasets)
    return run_id


def _fit_and_log(ctx: ChildContext, run_id: str, model_name: str, td: TerrainData, stem: Path) -> Any:
    """Fits the model (``ctx.fit_fn``) and logs what the fit is: its loss, time and size, the model's
    version and package, its fit diagnostics, the parameters of :func:`fit_description`, and the fitted
    model's files (``<stem>.params.json``, a learned model's ``<stem>.arrays.npz``). Returns the fit."""
    tracker = ctx.tracker
    fit = ctx.fit_fn(ctx.cfg, model_name, td.terrain)
    model = fit.model
    tracker.log(
        run_id,
        metrics={
            "fit_loss": _num(getattr(fit, "fit_loss", None)),
            "fit_time_s": _num(getattr(fit, "fit_time_s", None)),
            "n_train": _num(getattr(fit, "n_train", None)),
        },
        tags={
            trk.TAG_MODEL_VERSION: getattr(model, "version", "unknown"),
            trk.TAG_PLUGIN: plugin_package(model_name, model),
        },
    )
    bound_metrics = fit_quality_metrics(fit)
    if bound_metrics:
        tracker.log(run_id, metrics=bound_metrics)
    described = fit_description(fit, td.inputs.response)
    if described:
        tracker.log(run_id, params=described)
    params_json = stem.with_name(stem.name + ".params.json")
    write_json_atomic(params_json, model.to_json())
    tracker.artifact(run_id, params_json, "fit")
    arrays = dict(getattr(model, "arrays", None) or {})
    if arrays:  # a learned model's fitted arrays, as the fit stage saved them
        from skidbench.models.saved import save_arrays

        arrays_npz = stem.with_name(stem.name + ".arrays.npz")
        save_arrays(arrays_npz, arrays)
        tracker.artifact(run_id, arrays_npz, "fit")
    return fit


def fit_description(fit: Any, response: WheelResponse | None = None) -> dict[str, Any]:
    """What a fitted model is beyond its config, as MLflow params: the robot constants it was fitted with
    (``robot_used.<c>`` and its ``.source``: calibrated or the spec sheet's), the options it was built with
    (``model_options.*``), the model's own ``tracking_params()`` (an augmented model's base and effects),
    the wheel response that drove every model (``wheel_response.*``) and the fitted values (``fitted.*``)."""
    model = fit.model
    described = {}
    for c, rec in (_fit_json(fit).get("robot_constants") or {}).items():
        described[f"robot_used.{c}"] = rec.get("value")
        described[f"robot_used.{c}.source"] = rec.get("source")
    for k, v in trk.flatten(dict(getattr(model, "options", None) or {}), "model_options.").items():
        described[k] = v  # the options the model was built with (config and +model.options.*)
    if callable(getattr(model, "tracking_params", None)):
        described.update(model.tracking_params())
    resolved = _fit_json(fit).get("resolved") or {}
    if resolved.get("selected_on"):  # `discovered`: what its effects were selected on (Train only)
        described["discovered.selected_on"] = resolved["selected_on"]
        described["discovered.spec"] = resolved.get("spec")
    if response is not None:  # the calibration's wheel response that drove every model
        described.update({f"wheel_response.{k}": v for k, v in response.__dict__.items()})
    described.update(trk.flatten(getattr(model, "params", None) or {}, "fitted."))  # the fitted values
    return described


def predict_and_score(
    model: Any,
    tests: dict[str, Sequence[TestSequence]],
    horizons: Sequence[float],
    hcfg: HorizonConfig,
    inputs: Inputs | None = None,
    on_step: Callable[[str], None] | None = None,
) -> tuple[dict[str, float], pd.DataFrame, dict[str, list[np.ndarray]]]:
    """Predicts every test split with ``model`` (:func:`predict_split`, with its covariances when it has
    ``predict_cov``) and scores every window of every horizon (:func:`score_split`). Returns the metrics
    (:func:`summarise` of each split, plus ``predict_time_s``: the seconds spent in predict), the windows
    of every split in one frame (first column ``split``; empty when no split has a window) and the
    predicted body velocities per split (per sequence (T, 3): vx, vy in m/s, wz in rad/s). Logs nothing;
    ``on_step`` is told the step it is at ("predict", "score <split>") before each."""
    step = on_step or (lambda _name: None)
    metrics: dict[str, float] = {}
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
        metrics.update(summarise(w, split, horizons))
        step("predict")
    metrics["predict_time_s"] = predict_time
    windows = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    return metrics, windows, velocities


def _log_windows(
    ctx: ChildContext, run_id: str, model_name: str, td: TerrainData, stem: Path, windows: pd.DataFrame
) -> None:
    """Writes the per-window table ``<stem>.windows.parquet`` (what compare reads) and logs it."""
    win_path = stem.with_name(stem.name + ".windows.parquet")
    write_parquet_atomic(
        pa.Table.from_pandas(windows, preserve_index=False),
        win_path,
        {
            "model": model_name,
            "terrain": td.terrain,
            "horizons": list(ctx.horizons),
            "run_id": run_id,
            "inputs": td.inputs.protocol,
        },  # fmt: skip
    )
    ctx.tracker.artifact(run_id, win_path, "windows")


def _log_report_data(
    ctx: ChildContext,
    run_id: str,
    model_name: str,
    td: TerrainData,
    stem: Path,
    model: Any,
    windows: pd.DataFrame,
    velocities: dict[str, list[np.ndarray]],
) -> None:
    """Writes and logs what compare draws from this model beyond the metrics (report_data.py), and the
    window-error figure when figures are logged and there is a window."""
    for p in write_report_data(ctx.cfg, ctx.layout, stem, model, td.terrain, td.tests, velocities,
                               ctx.horizons[0]):  # fmt: skip
        ctx.tracker.artifact(run_id, p, "report_data")
    if ctx.log_figures and len(windows):
        from .figures import window_error_figure  # matplotlib: imported only when a figure is drawn

        fig_path = stem.with_name(stem.name + ".errors.png")
        window_error_figure(windows, f"{model_name} on {td.terrain} (inputs={td.inputs.protocol})", fig_path)
        ctx.tracker.artifact(run_id, fig_path, "figures")


def _finish_child(tracker, run_id: str, metrics: dict[str, float]) -> None:
    """Logs the metrics, the status tag (and a warning when a split/horizon had no window) and ends the
    run FINISHED."""
    nan_metrics = [k for k, v in metrics.items() if k.endswith("_rmsre_pct") and not np.isfinite(v)]
    tracker.log(
        run_id,
        metrics=metrics,
        tags={
            trk.TAG_STATUS: "FINISHED",
            **(
                {"skidbench.warning": f"no window over the minimum distance/rotation for {nan_metrics}"}
                if nan_metrics
                else {}
            ),
        },
    )
    tracker.end(run_id, "FINISHED")


# -- what MLflow shows of a run (descriptions, inputs, the logged model, the saved view) ----------------
def _describe(cfg, models, terrains, splits, horizons) -> str:
    """The description of an evaluate run (parent: every model and terrain; child: one of each)."""
    one = len(models) == 1 and len(terrains) == 1
    cmd = trk.reproduce_command(
        "evaluate", [f"models=[{','.join(models)}]", f"terrains=[{','.join(terrains)}]"] if one else [],
        drop=("force",),
    )  # fmt: skip
    if one:
        cmd = trk.reproduce_command("fit", [f"model={models[0]}", f"terrain={terrains[0]}"],
                                    drop=("models", "terrains", "force")) + "\n" + cmd  # fmt: skip
    title = (f"**{models[0]}** on **{terrains[0]}**, fitted on Train, scored on {'/'.join(splits).upper()}"
             if one else f"Benchmark of {len(models)} models on {len(terrains)} terrains")  # fmt: skip
    facts = {
        "dataset": f"`{cfg.dataset}` ({layout_from_cfg(cfg).root})",
        "input protocol": f"`{cfg.get('inputs', 'commanded')}` (what a model is given at predict time)",
        "horizon": ", ".join(f"{h:g} s" for h in horizons),
        "models": None if one else ", ".join(models),
        "terrains": None if one else ", ".join(terrains),
        "metrics": "`<split>_<horizon>_<trans|rot>_rmsre_pct`: RMSRE of the relative translational / "
        "rotational error over every window of the horizon, in %, lower is better",
    }
    return trk.describe(title, facts, cmd)


def _split_inputs(cfg, layout, terrain, files, tests) -> list[trk.SplitData]:
    """The Train split and the test splits of one terrain as MLflow dataset inputs."""
    from skidbench.pipeline.schema import concat_sequences

    out = []
    for split in [TRAIN, *tests]:
        fs = [p for p in files if p.parent.name == split]
        tables = (
            [(s.table, {"sequence": s.name}) for s in tests[split]]
            if split in tests
            else [read_split(p) for p in fs]
        )
        out.append(trk.SplitData(f"{cfg.dataset}/{terrain}/{split}", split, layout.splits / terrain / split,
                                 split_fingerprint(fs, layout.splits), concat_sequences(tables)))  # fmt: skip
    return out


def _model_config(cfg, model_name: str) -> dict[str, Any] | None:
    try:
        from skidbench.models.fitting import model_config
    except ImportError:  # pragma: no cover
        return None
    return model_config(cfg, model_name)


def _log_model(cfg, tracker, run_id, fit, model_name, terrain, record_path: Path, seq: TestSequence) -> None:
    """The fitted model as an MLflow Model of the run (tag ``skidbench.logged_model``: its id, or why not:
    a model object that is no installed skidbench model cannot be rebuilt outside this process)."""
    from skidbench.models.base import ModelError
    from skidbench.models.specs import get_model_class

    from .mlflow_model import INPUT_COLUMNS, write_model_record

    model = fit.model
    spec = str((_fit_json(fit).get("resolved") or {}).get("spec") or model_name)
    try:
        cls = get_model_class(spec)  # an augmented spec's class is made anew on each call: compare names
        if not hasattr(model, "robot") or (type(model) is not cls and getattr(model, "name", "") != cls.name):
            raise ModelError(f"{type(model).__name__} is not the installed model {spec}")
        record = write_model_record(record_path, spec, model.to_json(),
                                    model.robot, str(cfg.get("inputs", "commanded")))  # fmt: skip
        example = seq.table.head(30).assign(sequence=seq.name)[list(INPUT_COLUMNS)]  # 1 s of a test sequence
        arrays = record_path.with_name(record_path.name.replace(".mlflow_model.json", ".arrays.npz"))
        arrays = arrays if getattr(model, "arrays", None) and arrays.is_file() else None
        model_id = tracker.log_model(run_id, f"{model_name}-{terrain}", record, example, arrays)
    except trk.StoreUnreachable:  # the store is gone: nothing more can be logged
        raise
    except Exception as exc:  # the benchmark's numbers stand without it: say why, on the run (and console)
        model_id = f"not logged: {type(exc).__name__}: {one_line(str(exc))[:300]}"
        if not isinstance(exc, ModelError):
            log.warning("%s/%s: model %s", model_name, terrain, model_id)
    tracker.log(run_id, tags={"skidbench.logged_model": model_id})


def board_columns(splits, horizons) -> tuple[list[str], list[str]]:
    """The RMSRE metrics of the first horizon (LD first, translational before rotational) and their labels:
    the columns of an evaluate's saved views and of its parent run's leaderboard."""
    h = horizons[0]
    order = sorted(splits, key=lambda s: s != "ld")
    pairs = [(s, k) for s in order for k in ("translational", "rotational")]
    return [trk.metric_key(k, s, h) for s, k in pairs], [f"{s.upper()} {trk.SHORT[k]} %" for s, k in pairs]


def leaderboard(
    children: Sequence[ChildResult], splits, horizons, protocol: str
) -> tuple[str, dict[str, float]]:
    """The leaderboard of an evaluate for its parent run (:func:`mlflow_ui.leaderboard`): Markdown to put at
    the top of its description, and per model its mean over terrains and gap to the next as metrics."""
    cols, labels = board_columns(splits, horizons)
    md, metrics = mu.leaderboard([(c.model, c.terrain, c.status, c.metrics) for c in children], cols, labels)
    title = (f"**Leaderboard**, inputs={protocol}: {horizons[0]:g} s RMSRE in % (mean over terrains; lower "
             "is better; ranked by the first column)")  # fmt: skip
    return f"{title}\n\n{md}\n\n", metrics


def save_views(tracker, parent_id: str, splits, horizons, protocol: str) -> list[str]:
    """The UI's saved views of an evaluate (:func:`mlflow_ui.save_evaluate_views`): its child runs with the
    RMSRE columns of the first horizon (LD first), best LD translational first. Returns their keys."""
    cols, _ = board_columns(splits, horizons)
    name = tracker.client.get_run(parent_id).info.run_name
    return mu.save_evaluate_views(tracker.client, tracker.experiment_id, parent_id, name, cols, protocol,
                                  horizons[0])  # fmt: skip


#: per-parameter fit diagnostics a model may report in its fit JSON's ``fit_info`` (friction: bound margins,
#: Jacobian standard errors, identified 1 / held 0); each is logged as the metric ``<key>.<parameter>``
FIT_QUALITY_KEYS = ("param_bound_margin", "param_bound_margin_linear", "param_stderr", "param_identified")


def fit_quality_metrics(fit: Any) -> dict[str, float]:
    """``{"param_bound_margin.mu_r": ...}`` from the fit's ``fit_info`` (the model's, or the saved fit
    JSON's when the fit was reused); empty for models that report none."""
    info = getattr(getattr(fit, "model", None), "fit_info_", None) or {}
    if not any(k in info for k in FIT_QUALITY_KEYS):
        info = _fit_json(fit).get("fit_info") or {}
    out = {}
    for key in FIT_QUALITY_KEYS:
        for name, value in (info.get(key) or {}).items():
            v = _num(value)
            if v is not None and np.isfinite(v):
                out[f"{key}.{name}"] = v
    return out


def _fit_json(fit: Any) -> dict[str, Any]:
    """The fit's saved JSON (FitResult.path), or {} when there is none."""
    path = getattr(fit, "path", None)
    try:
        return json.loads(Path(path).read_text()) if path else {}
    except (OSError, ValueError):
        return {}


def _num(v: Any) -> float | None:
    try:
        return None if v is None else float(v)
    except (TypeError, ValueError):
        return None


def _brief(metrics: dict[str, float]) -> str:
    return ", ".join(f"{k}={v:.4g}" for k, v in metrics.items() if k.endswith("_rmsre_pct"))


PROTOCOL_TEXT = {
    "commanded": "the commanded wheel rates and their derivatives (the paper's protocol)",
    "response": "the commands through the wheel response `calibrate` identified from the Train encoders",
    "measured": "the encoders' wheel rates and their derivatives (an oracle)",
}


def format_result(result: BenchmarkResult) -> str:
    """A short text summary for the console: RMSRE in % per (model, terrain) at each horizon."""
    df = result.table()
    cols = {}
    for c in sorted((c for c in df.columns if c.endswith("_rmsre_pct")), key=lambda c: "_rot_" in c):
        split, h, kind, _ = c.split("_", 3)
        cols[c] = f"{kind} {split.upper()} {h} %"
    show = df[["model", "inputs", "terrain", "status", *cols]].rename(columns=cols)
    lines = [
        f"MLflow: {result.tracking_uri}  experiment {result.experiment!r}  parent run {result.parent_run_id}",
        f"inputs={result.inputs}: every model driven by {PROTOCOL_TEXT.get(result.inputs, result.inputs)}",
        *result.skipped,
        show.to_string(index=False, float_format=lambda x: f"{x:.2f}", na_rep="-"),
    ]
    for c in result.failed:
        lines.append(f"FAILED {c.model}/{c.terrain}: {c.reason}")
    return "\n".join(lines)
