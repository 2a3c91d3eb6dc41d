"""The 6 s horizon benchmark (SPEC.md "Evaluation"): fit every model on each terrain's Train split,
predict and score the CV and LD sequences (:mod:`skidbench.benchmark.scoring.predictions`, pure) and log
every metric
of :mod:`skidbench.benchmark.scoring.metrics` per model, terrain, split and horizon to MLflow
(:mod:`skidbench.benchmark.tracking.store`).

:func:`run_benchmark` is the stage without Hydra (its settings: benchmark/evaluate/settings.py);
``evaluate_app.main`` is the CLI (``evaluate_app.benchmark``: the settings from the config). Data problems
that make the benchmark meaningless (no splits, an empty test split, a horizon longer than every sequence) are
raised as one-line :class:`EvaluationError` before any run is created; a model that fails to fit or
predict gets its child run marked FAILED with the reason, and the others carry on.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa

from skidbench.benchmark.board import results as rt
from skidbench.benchmark.board.strata import strata_records
from skidbench.benchmark.errors import EvaluationError
from skidbench.benchmark.evaluate import reuse
from skidbench.benchmark.evaluate.failures import fail_run, kill_run
from skidbench.benchmark.evaluate.fit_record import (
    default_fit_fn,
    fit_description,
    fit_quality_metrics,
    installed_models,
    log_model,
    model_code,
    num,
    options_digest,
    options_tags,
    plugin_package,
)
from skidbench.benchmark.evaluate.mlflow_views import describe_run, save_views, split_inputs
from skidbench.benchmark.evaluate.references import log_floor, seed_spread
from skidbench.benchmark.evaluate.settings import EvaluateSettings
from skidbench.benchmark.evaluate.testsets import (
    EvaluationData,
    load_evaluation_data,
    split_fingerprint,
)
from skidbench.benchmark.evaluate.transfer import training_layout
from skidbench.benchmark.report.data import write_report_data, write_wheel_response_steps
from skidbench.benchmark.report.settings import ReportDataSettings
from skidbench.benchmark.scoring.floor import FLOOR
from skidbench.benchmark.scoring.horizon import HorizonConfig
from skidbench.benchmark.scoring.predictions import Inputs, TestSequence, predict_and_score
from skidbench.benchmark.scoring.settings import IntervalConfig
from skidbench.benchmark.tracking import mlflow_ui as mu
from skidbench.benchmark.tracking import store as trk
from skidbench.benchmark.tracking import tags as run_tags
from skidbench.models.fitting.fit import FitSettings, model_config
from skidbench.pipeline.core.errors import one_line
from skidbench.pipeline.core.io import write_json_atomic, write_parquet_atomic
from skidbench.pipeline.core.layout import Layout
from skidbench.pipeline.runner import environment

log = logging.getLogger(__name__)


class ProtocolSkipped(EvaluationError):
    """No terrain of the dataset can be driven by the input protocol (e.g. ``measured`` without encoders):
    the protocol is skipped for the dataset, which is not an error of the run (``skidbench evaluate``
    prints the line and exits 0)."""


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
    traceback: str = ""  # where a FAILED run's traceback is (MLflow artifact, file, stage log)
    reused: bool = False  # the run of an earlier evaluate, unchanged (evaluate/reuse.py)


@dataclass
class BenchmarkResult:
    tracking_uri: str
    experiment: str
    parent_run_id: str
    children: list[ChildResult]
    inputs: str = "commanded"
    skipped: list[str] = field(default_factory=list)  # one line per (terrain, split) the protocol skipped
    floor: dict[str, dict[str, float]] = field(default_factory=dict)  # terrain -> the floor's metrics
    horizons: list[float] = field(default_factory=list)  # s, the board's first (the console shows it)

    @property
    def failed(self) -> list[ChildResult]:
        return [c for c in self.children if c.status != "FINISHED"]

    def table(self) -> pd.DataFrame:
        rows = [
            {"model": c.model, "inputs": c.inputs, "terrain": c.terrain, "status": c.status, **c.metrics}
            for c in self.children
        ]
        return pd.DataFrame(rows)


def run_benchmark(
    es: EvaluateSettings,
    fit_fn: Callable[[FitSettings, str, str], Any] | None = None,
    log_figures: bool | None = None,
) -> BenchmarkResult:
    """Fit, predict and score every (model, terrain); log to MLflow. ``fit_fn(settings, model, terrain)``
    (``settings`` a :class:`FitSettings`) returns a FitResult-like object (``model``, ``path``, ``fit_loss``,
    ``fit_time_s``, ``n_train``); default :func:`skidbench.models.fitting.fit.fit_model`. ``log_figures``:
    None for the settings'."""
    layout, models, terrains, splits, horizons = es.layout, es.models, es.terrains, es.splits, es.horizons
    protocol = es.protocol
    log_figures = es.log_figures if log_figures is None else log_figures
    keyed = fit_fn is None and not es.transfer.on  # results keyed by what made them (evaluate/reuse.py)
    fit_fn = fit_fn or _checked_default_fit_fn(models)
    # transfer (train_dataset / train_terrain): fit elsewhere, own experiment and tags
    # (benchmark/evaluate/transfer.py)
    fit_fn, transfer_tags = training_layout(es.transfer, es.fit, fit_fn)

    # 1. the data, checked before anything is logged
    data = load_evaluation_data(layout, es.fit.calibrations, terrains, splits, horizons, protocol, es.hcfg)
    data.inputs_of = {t: dataclasses.replace(i, state=es.state) for t, i in data.inputs_of.items()}
    tests, files_of = data.tests, data.files_of
    skipped, terrains = data.skipped, data.terrains
    for line in skipped:
        log.warning("%s", line)
        print(line, flush=True)
    if not terrains:
        raise ProtocolSkipped(f"inputs={protocol}: nothing to evaluate under this protocol: {skipped[0]}")

    # 2. the store (an unreachable server is one line, here)
    tracker = trk.open_store(es.store)
    params = run_tags.config_params(es.conf)  # no model's config on the parent: each child logs its own
    commit = environment.git_commit()
    # what made the numbers: skidbench's version and commit, the libraries, lock, platform, code paths
    env_tags = environment.run_tags()
    common_tags = {run_tags.TAG_DATASET: es.dataset, **env_tags, run_tags.TAG_GIT: commit, **transfer_tags}
    children: list[ChildResult] = []
    from mlflow.exceptions import MlflowException

    from skidbench.benchmark.tracking.sweep import run_key

    job_key = run_key()
    try:
        done = tracker.claim_key(job_key) if job_key else None
        if done:  # a retried job whose earlier attempt finished: its runs are the result
            return _write_last(layout, BenchmarkResult(tracker.uri, tracker.experiment_name, done,
                                                       _logged_children(tracker, done), protocol,
                                                       skipped, horizons=list(horizons)))  # fmt: skip
        about, _ = describe_run(layout, es.protocol, models, terrains, splits, horizons)
        plan = reuse.plan_reuse(es, tracker, files_of, terrains) if keyed else reuse.ReusePlan()
        parent_tags = {
            **common_tags,
            **({run_tags.TAG_RUN_KEY: job_key} if job_key else {}),
            run_tags.TAG_ROLE: "parent",
            run_tags.TAG_FINGERPRINT: split_fingerprint(sum(files_of.values(), []), layout.splits),
            run_tags.TAG_INPUTS: protocol,
            "skidbench.models": ",".join(models),
            "skidbench.terrains": ",".join(terrains),
            run_tags.TAG_NOTE: about,
            **plan.tags(),
        }
        name = tracker.unique_run_name(run_tags.parent_run_name("evaluate", es.dataset, protocol))
        with tracker.run(name, parent_tags) as parent_id:
            tracker.log(parent_id, params=params)
            if skipped:
                tracker.log(parent_id, tags={"skidbench.inputs_skipped": " | ".join(skipped)})
            datasets_of = {t: split_inputs(layout, t, files_of[t], tests[t]) for t in terrains}
            tracker.log_datasets(parent_id, [d for t in terrains for d in datasets_of[t]])
            ctx = ChildContext(es.protocol, es.report_data, tracker, parent_id, layout, horizons, es.hcfg,
                               fit_fn, es.fit, es.conf, common_tags, log_figures, es.intervals,
                               es.seeds, plan, rt.Writer(layout, parent_id),
                               es.row_facts(parent_id, tracker, env_tags, commit))  # fmt: skip
            with ctx.results.until_done(lambda path: tracker.artifact(parent_id, path, "results")):
                floor = _run_terrains(ctx, models, data, datasets_of, protocol, children)
                _log_board(ctx, children, splits, protocol, about)
                save_views(tracker, parent_id, splits, horizons, protocol, children)
    except MlflowException as exc:
        raise EvaluationError(f"MLflow store {tracker.uri}: {one_line(exc.message)[:300]}") from None
    return _write_last(layout, BenchmarkResult(tracker.uri, tracker.experiment_name, parent_id, children,
                                               protocol, skipped, floor, list(horizons)))  # fmt: skip


def _run_terrains(
    ctx: ChildContext, models: list[str], data: EvaluationData, datasets_of: dict, protocol: str,
    children: list[ChildResult],
) -> dict[str, dict[str, float]]:  # fmt: skip
    """Every terrain's references (wheel-response steps, the floor) and every model's child run on it
    (appended to ``children``, as they finish), then every run's cells per aggressiveness stratum;
    returns the floor's metrics per terrain."""
    floor: dict[str, dict[str, float]] = {}
    for terrain in data.terrains:
        td = TerrainData(terrain, data.tests[terrain], data.inputs_of[terrain], datasets_of[terrain],
                         split_fingerprint(data.files_of[terrain], ctx.layout.splits))  # fmt: skip
        floor[terrain] = _log_terrain_references(ctx, td, protocol)
        for m in models:  # a run of an earlier evaluate taken as it is (evaluate/reuse.py), or made
            taken = ctx.plan.taken.get((m, terrain))
            if taken is not None:  # its rows join this evaluate's results file: this evaluate's board
                ctx.results.add(ctx.plan.carried(taken.info.run_id, ctx.parent_id, models))
            children.append(_child_of(taken, reused=True) if taken is not None else _run_child(ctx, m, td))
    _score_strata(ctx, protocol)
    return floor


def _checked_default_fit_fn(models: list[str]) -> Callable[[Any, str, str], Any]:
    """The default fit function, once every model named is installed (an augmented spec
    ``base+effect+...``: a known base and known effects); EvaluationError (one line) otherwise."""
    from skidbench.models.registry.plugins import is_model_spec
    from skidbench.models.registry.specs import get_model_class

    known = installed_models()
    for m in models:
        if "+" in m:
            get_model_class(m)
    unknown = [m for m in models if known and m not in known and not is_model_spec(m)]
    if unknown:
        raise EvaluationError(
            f"unknown model(s) {unknown}; installed: {sorted(known)} (`skidbench models` lists them)"
        )
    return default_fit_fn()


def _log_terrain_references(ctx: ChildContext, td: TerrainData, protocol: str) -> dict[str, float]:
    """What the parent run holds of a terrain beside its models' runs: the wheel response's steps (report
    data) and the floor (a perfect model: the simulator's exact velocities), whose cells are the results
    file's floor rows (role ``floor``, the parent run's id); returns the floor's metrics."""
    steps = write_wheel_response_steps(ctx.fit.calibrations, ctx.layout, td.terrain)
    ctx.tracker.artifact(ctx.parent_id, steps, "report_data")
    stem = ctx.layout.eval_stem(FLOOR, td.terrain, protocol)
    h = ctx.horizons
    metrics, scores = log_floor(ctx.tracker, ctx.parent_id, stem, td.terrain, td.tests, h, ctx.hcfg,
                                ctx.intervals, protocol, td.inputs, ctx.layout.extracted)  # fmt: skip
    if scores and ctx.results is not None and ctx.base is not None:
        facts = replace(ctx.base, run_id=ctx.parent_id, model=FLOOR, terrain=td.terrain, role=rt.REFERENCE)
        ctx.results.add(rt.rows(facts, scores))
    return metrics


def _score_strata(ctx: ChildContext, protocol: str) -> None:
    """Every finished run's cells on each aggressiveness tercile, into the results file (board/strata.py;
    the windows' accelerations with the robot's spec track width, as compare's)."""
    half_track = float((ctx.conf.get("robot") or {}).get("track_width") or 0.0) / 2.0
    records = ctx.results.records
    ctx.results.add_strata(
        strata_records(ctx.layout, records, protocol, ctx.horizons, ctx.intervals, half_track)
    )


def _log_board(
    ctx: ChildContext, children: list[ChildResult], splits: list[str], protocol: str, about: str
) -> None:
    """The parent run's leaderboard metrics, run counts, status and note (the board, then ``about``)."""
    n_failed = sum(c.status != "FINISHED" for c in children)
    rows = [(c.model, c.terrain, c.status, c.metrics) for c in children]
    board, board_metrics = mu.evaluate_leaderboard(rows, splits, ctx.horizons[0], protocol)
    n_reused = sum(c.reused for c in children)  # runs of earlier evaluates taken as they are
    counts = {"n_children": len(children) - n_reused, "n_reused": n_reused, "n_failed": n_failed}
    ctx.tracker.log(
        ctx.parent_id,
        metrics={**counts, **board_metrics},
        tags={
            run_tags.TAG_STATUS: "FINISHED" if not n_failed else f"{n_failed} model run(s) FAILED",
            run_tags.TAG_NOTE: board + about,
        },
    )


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
            "floor": result.floor,
            "horizons": result.horizons,
        },
    )
    return result


def _logged_children(tracker, parent_id: str) -> list[ChildResult]:
    """The child runs of a finished parent run, as results (a retried job that had already finished)."""
    runs = tracker.client.search_runs(
        [tracker.experiment_id],
        filter_string=f"tags.`{run_tags.TAG_PARENT}` = '{parent_id}'",
        max_results=10000,
    )
    return [_child_of(r) for r in sorted(runs, key=lambda r: r.info.start_time)]


def _child_of(run: Any, reused: bool = False) -> ChildResult:
    """A logged child run as a result."""
    t = run.data.tags
    return ChildResult(t.get(run_tags.TAG_MODEL, "?"), t.get(run_tags.TAG_TERRAIN, "?"), run.info.run_id,
                       run.info.status, dict(run.data.metrics), t.get(run_tags.TAG_REASON, ""),
                       t.get(run_tags.TAG_INPUTS, "commanded"), reused=reused)  # fmt: skip


# -- one child run: a model on a terrain ------------------------------------------------------------
@dataclass(frozen=True)
class ChildContext:
    """What every child run of one evaluate parent run shares: the config (and its plain-container form
    ``conf`` the params are logged from), the store, the parent run, the output layout, the horizons and
    window thresholds, the fit function, the tags every child carries and whether to draw figures."""

    protocol: str  # the checked input protocol (``inputs``)
    report_data: ReportDataSettings
    tracker: Any
    parent_id: str
    layout: Layout
    horizons: Sequence[float]
    hcfg: HorizonConfig
    fit_fn: Callable[[FitSettings, str, str], Any]
    fit: FitSettings  # what fit_fn is called with
    conf: dict[str, Any]
    tags: dict[str, str]
    log_figures: bool
    intervals: IntervalConfig = field(default_factory=IntervalConfig)
    seeds: int = 1  # fits of a model with random parts (evaluate's ``seeds``)
    plan: reuse.ReusePlan = field(default_factory=reuse.ReusePlan)  # runs taken, result keys of the others
    results: rt.Writer | None = None  # the evaluate's results file (benchmark/board/results.py)
    base: rt.RunFacts | None = None  # what every row of the evaluate carries


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
    """Fit ``model_name`` on ``td.terrain``'s Train split, score it on every test split, write its rows to
    the results table and log it all to one child run (its metrics from the rows); an exception of the
    model (fit, predict, scoring, its outputs) ends that run FAILED with the reason and its traceback
    (benchmark/evaluate/failures.py) and the benchmark carries on (an MLflow store error does not; an
    interrupt ends the run KILLED and stops the benchmark)."""
    protocol = td.inputs.protocol
    run_id, facts = _start_child(ctx, model_name, td)
    stage = _Stage("fit")
    stem = ctx.layout.eval_stem(model_name, td.terrain, protocol)
    try:
        fit, fit_metrics = _fit_and_log(ctx, run_id, model_name, td, stem, facts)
        stage("logging the model")
        record_path = stem.with_name(stem.name + ".mlflow_model.json")
        log_model(ctx.protocol, ctx.tracker, run_id, fit, model_name, td.terrain,
                  record_path, next(iter(td.tests.values()))[0])  # fmt: skip
        # after the model: Model.log logs the run's metrics so far again, for the model (duplicate keys)
        ctx.tracker.log(run_id, metrics=fit_metrics)
        stage("predict")
        scores, windows, velocities, facts.predict_time_s = predict_and_score(
            fit.model, td.tests, ctx.horizons, ctx.hcfg, td.inputs, on_step=stage, intervals=ctx.intervals
        )
        spread = None
        if ctx.seeds > 1 and "seed" in (getattr(fit.model, "options", None) or {}):  # random parts
            stage("other seeds")
            from skidbench.models.fitting.fit import refit_of

            refit = refit_of(ctx.fit, model_name, td.terrain)
            spread = seed_spread(
                refit, fit.model, td.tests, ctx.horizons, ctx.hcfg, td.inputs, ctx.seeds, scores
            )
        stage("logging")
        outputs = [_log_windows(ctx, run_id, model_name, td, stem, windows)]
        stage("report data")  # what compare draws beyond the metrics (Figs. 5-7), from this model
        outputs += _log_report_data(ctx, run_id, model_name, td, stem, fit.model, windows, velocities)
        rows = pd.DataFrame(rt.rows(facts, scores, spread, ctx.seeds))
        ctx.results.add(rows.to_dict("records"))
        metrics = rt.mlflow_metrics(rows)
        _finish_child(ctx.tracker, run_id, metrics, rt.nan_cells(rows))
        rk = ctx.plan.keys.get((model_name, td.terrain))
        if rk is not None:  # the next evaluate takes this run while what made it is unchanged
            outputs += [stem.with_name(stem.name + s) for s in (".params.json", ".arrays.npz")]
            reuse.record(rk, outputs, run_id, ctx.parent_id, ctx.tracker)
        log.info("%s/%s: %s", model_name, td.terrain, rt.headline(rows))
        return ChildResult(model_name, td.terrain, run_id, "FINISHED", metrics, inputs=protocol)
    except KeyboardInterrupt:
        ctx.results.add(rt.unscored(facts, list(td.tests), ctx.horizons, "KILLED", trk.INTERRUPTED))
        kill_run(ctx.tracker, run_id)
        raise
    except Exception as exc:
        from mlflow.exceptions import MlflowException

        if isinstance(exc, MlflowException):
            raise
        reason, where = fail_run(ctx.tracker, run_id, stem, f"{model_name}/{td.terrain}", stage.name, exc)
        ctx.results.add(rt.unscored(facts, list(td.tests), ctx.horizons, "FAILED", reason))
        return ChildResult(model_name, td.terrain, run_id, "FAILED", reason=reason, inputs=protocol,
                           traceback=where)  # fmt: skip


def _start_child(ctx: ChildContext, model_name: str, td: TerrainData) -> tuple[str, rt.RunFacts]:
    """Starts the child run of ``model_name`` on the terrain (tags, config params, dataset inputs);
    returns its id and the facts its rows will carry."""
    protocol = td.inputs.protocol
    model_conf = model_config(ctx.fit.models, model_name)
    rk = ctx.plan.keys.get((model_name, td.terrain))
    keyed = {reuse.TAG_RESULT_KEY: rk.key, reuse.TAG_SCORING: rk.made_of["scoring"]} if rk else {}
    note, cmd = describe_run(
        ctx.layout, ctx.protocol, [model_name], [td.terrain], list(td.tests), ctx.horizons
    )
    start = dt.datetime.now(dt.UTC)
    run_id = ctx.tracker.start(
        f"{model_name}/{td.terrain}" + ("" if protocol == "commanded" else f" [{protocol}]"),
        {
            **ctx.tags,
            run_tags.TAG_FINGERPRINT: td.fingerprint,
            run_tags.TAG_ROLE: "child",
            run_tags.TAG_MODEL: model_name,
            run_tags.TAG_TERRAIN: td.terrain,
            run_tags.TAG_INPUTS: protocol,
            **keyed,
            **options_tags(ctx.conf, model_conf, protocol),
            run_tags.TAG_NOTE: note,
        },
        ctx.parent_id,
    )
    params = run_tags.config_params(ctx.conf, model_conf)  # this model's config only
    ctx.tracker.log(run_id, params={**params, "model": model_name, "terrain": td.terrain, "inputs": protocol})
    ctx.tracker.log_datasets(run_id, td.datasets)
    facts = replace(ctx.base, run_id=run_id, model=model_name, terrain=td.terrain, inputs=protocol,
                    start_time=start, splits_fingerprint=td.fingerprint, reproduce=cmd,
                    options_digest=options_digest(ctx.conf, model_conf, protocol))  # fmt: skip
    ctx.results.add(rt.unscored(facts, list(td.tests), ctx.horizons, "RUNNING", ""))
    return run_id, facts


def _fit_and_log(
    ctx: ChildContext, run_id: str, model_name: str, td: TerrainData, stem: Path, facts: rt.RunFacts
) -> tuple[Any, dict[str, float | None]]:
    """Fits the model (``ctx.fit_fn``) and logs what the fit is: the model's version, package and code,
    the parameters of :func:`fit_description`, and the fitted model's files (``<stem>.params.json``, a
    learned model's ``<stem>.arrays.npz``); the run's ``facts`` (its rows of the results table) get the
    fit's numbers and the model's code. Returns the fit and its metrics (loss, time, size, fit
    diagnostics), which the caller logs after the logged model."""
    tracker = ctx.tracker
    fit = ctx.fit_fn(ctx.fit, model_name, td.terrain)
    model = fit.model
    code = model_code(model_name, model)
    metrics = {
        "fit_loss": num(getattr(fit, "fit_loss", None)),
        "fit_time_s": num(getattr(fit, "fit_time_s", None)),
        "n_train": num(getattr(fit, "n_train", None)),
        **fit_quality_metrics(fit),
    }
    facts.fitted(metrics, getattr(model, "version", "unknown"), plugin_package(model_name, model), code)
    tags = {run_tags.TAG_MODEL_VERSION: facts.model_version, run_tags.TAG_PLUGIN: facts.package}
    tracker.log(run_id, tags={**tags, **environment.code_tags(code)})
    described = fit_description(fit, td.inputs.response)
    if described:
        tracker.log(run_id, params=described)
    params_json = stem.with_name(stem.name + ".params.json")
    write_json_atomic(params_json, model.to_json())
    tracker.artifact(run_id, params_json, "fit")
    arrays = dict(getattr(model, "arrays", None) or {})
    if arrays:  # a learned model's fitted arrays, as the fit stage saved them
        from skidbench.models.registry.saved import save_arrays

        arrays_npz = stem.with_name(stem.name + ".arrays.npz")
        save_arrays(arrays_npz, arrays)
        tracker.artifact(run_id, arrays_npz, "fit")
    return fit, metrics


def _log_windows(
    ctx: ChildContext, run_id: str, model_name: str, td: TerrainData, stem: Path, windows: pd.DataFrame
) -> Path:
    """Writes the per-window table ``<stem>.windows.parquet`` (what compare reads), logs it, returns it."""
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
    return win_path


def _log_report_data(
    ctx: ChildContext,
    run_id: str,
    model_name: str,
    td: TerrainData,
    stem: Path,
    model: Any,
    windows: pd.DataFrame,
    velocities: dict[str, list[np.ndarray]],
) -> list[Path]:
    """Writes and logs what compare draws from this model beyond the metrics (report_data.py), and the
    window-error figure when figures are logged and there is a window; returns the report data files."""
    settings = ctx.report_data
    written = write_report_data(settings, ctx.layout, stem, model, td.terrain, td.tests, velocities,
                                ctx.horizons[0])  # fmt: skip
    for p in written:
        ctx.tracker.artifact(run_id, p, "report_data")
    if ctx.log_figures and len(windows):
        from skidbench.benchmark.report.figures import (
            window_error_figure,  # matplotlib: imported only when a figure is drawn
        )

        fig_path = stem.with_name(stem.name + ".errors.png")
        window_error_figure(windows, f"{model_name} on {td.terrain} (inputs={td.inputs.protocol})", fig_path)
        ctx.tracker.artifact(run_id, fig_path, "figures")
    return list(written)


def _finish_child(tracker, run_id: str, metrics: dict[str, float], nan_metrics: list[str]) -> None:
    """Logs the metrics, the status tag (and a warning when a split/horizon had no window over the minimum
    distance or rotation: ``nan_metrics``) and ends the run FINISHED."""
    warn = f"no window over the minimum distance/rotation for {nan_metrics}"
    tags = {run_tags.TAG_STATUS: "FINISHED", **({"skidbench.warning": warn} if nan_metrics else {})}
    tracker.log(run_id, metrics=metrics, tags=tags)
    tracker.end(run_id, "FINISHED")
