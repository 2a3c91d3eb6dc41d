"""``skidbench evaluate``: the horizon benchmark as a Hydra app (config ``conf/evaluate.yaml``)."""

from __future__ import annotations

import json
import logging

import hydra
from omegaconf import DictConfig

from skidbench.pipeline.cli.main import stage

log = logging.getLogger(__name__)


INTERRUPTED = (
    "its open MLflow runs are marked KILLED; what finished before stays, and `skidbench compare` ranks the "
    "complete runs (re-run evaluate to complete the others)"
)


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="evaluate")
@stage("evaluate", runs=True, interrupted=INTERRUPTED)
def main(cfg: DictConfig) -> None:
    from skidbench.benchmark.evaluate.failures import failure_summary
    from skidbench.pipeline.core.errors import PartialFailure

    result, _ = run(cfg)
    if result is not None and result.failed and not _in_sweep():
        raise PartialFailure(failure_summary(result))  # exit status 3 (pipeline/core/errors.py)


def _in_sweep() -> bool:
    """Is this a job of a Hydra multirun (``-m``)? Its failed runs do not stop the other jobs."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        return HydraConfig.get().mode == RunMode.MULTIRUN
    except (ImportError, ValueError):
        return False


def run(cfg: DictConfig):
    """The stage: skipped (the cached result) when its stamp is fresh and its parent run exists, else
    :func:`run_benchmark`. Returns ``(result, skipped)``. The config is read once, into
    :class:`~skidbench.benchmark.evaluate.settings.EvaluateSettings`."""
    from skidbench.benchmark.evaluate.console import format_result
    from skidbench.benchmark.evaluate.evaluation import ProtocolSkipped, last_file, run_benchmark
    from skidbench.benchmark.evaluate.settings import EvaluateSettings
    from skidbench.pipeline.core.cache import Stamp, stamp_file

    es = EvaluateSettings.from_cfg(cfg)
    layout, inputs = es.layout, es.protocol
    # one stamp per input protocol: evaluating under another protocol does not stale this one
    name = "evaluate.json" if inputs == "commanded" else f"evaluate.{inputs}.json"
    stamp = Stamp(stamp_file(layout.root, "evaluate", name), "evaluate")
    if not es.force and stamp.is_fresh(_stamp_key(es, stamp)):
        cached = _cached_result(es)
        if cached is not None:
            print(format_result(cached, _findings(layout, cached)), flush=True)
            print(
                f"evaluate: inputs unchanged (split files, fits, config, models' and scoring code) and "
                f"parent run {cached.parent_run_id} finished; skipped (force=true re-runs)",
                flush=True,
            )
            return cached, True
    try:
        result = run_benchmark(es)
    except ProtocolSkipped as exc:  # e.g. inputs=response on data without wheel encoders: said, not failed
        print(f"evaluate: {exc}", flush=True)
        return None, True
    print(format_result(result, _findings(layout, result)), flush=True)
    if result.failed:
        log.warning(
            "%d of %d model run(s) FAILED (marked FAILED in MLflow with the reason)",
            len(result.failed),
            len(result.children),
        )
    else:  # the key is taken after the run: the fits it (re)wrote are part of it
        stamp.record(_stamp_key(es, stamp), [last_file(layout, inputs)])
    return result, False


def benchmark(cfg: DictConfig, fit_fn=None, log_figures: bool | None = None):
    """:func:`~skidbench.benchmark.evaluate.evaluation.run_benchmark` with the config's settings
    (:meth:`~skidbench.benchmark.evaluate.settings.EvaluateSettings.from_cfg`), never skipped."""
    from skidbench.benchmark.evaluate.evaluation import run_benchmark
    from skidbench.benchmark.evaluate.settings import EvaluateSettings

    return run_benchmark(EvaluateSettings.from_cfg(cfg), fit_fn, log_figures)


def _findings(layout, result) -> list[str]:
    """What the fits behind the board found (a parameter at its bound), printed under it as compare does."""
    from skidbench.models.registry.saved import board_findings

    rows = [(c.model, c.terrain) for c in result.children if c.status == "FINISHED"]
    return board_findings(layout, rows, result.inputs)


def _stamp_key(es, stamp) -> str:
    """Evaluate's inputs: every split file, every fit of the configured models, the whole config, and
    each model's version and config."""
    from skidbench.benchmark.evaluate.reuse import scoring_digest
    from skidbench.models.fitting.fit import model_config
    from skidbench.models.registry.saved import arrays_file
    from skidbench.pipeline.core.layout import split_terrains
    from skidbench.pipeline.core.manifest import Manifest

    layout, inputs, models = es.layout, es.protocol, es.models
    # the current manifest's split files, fits and calibrations, never whatever else lies in the folders
    manifest = Manifest.read(layout.manifest) if layout.manifest.is_file() else Manifest([])
    files = [p for p in layout.split_files(manifest) if p.is_file()]
    terrains = split_terrains(manifest)
    files += [layout.fit_file(m, t, inputs) for m in models for t in terrains]
    files += [arrays_file(layout.fit_file(m, t, inputs)) for m in models for t in terrains]
    files += [layout.calibration_file(t) for t in terrains]  # a changed calibration refits and re-scores
    if "discovered" in models:
        files.append(layout.discovery / "discovery.json")
    files = [p for p in files if p.is_file()]
    conf = {k: v for k, v in es.conf.items() if k != "force"}  # force: how to run, not what
    # a model whose code changed (its version, or the digest of the files it runs: an edit without a
    # version bump) must be refitted and re-scored, even if its old fit file is intact; so must every model
    # when the scoring code changed (benchmark/evaluate/evaluation/reuse.py)
    conf["model_code"] = {m: _code_key(m) for m in models}
    conf["scoring_code"] = scoring_digest()
    # and one whose config (conf/model/<name>.yaml: initial params, options) changed must be refitted too
    conf["model_configs"] = {m: model_config(es.fit.models, m) for m in models}
    return stamp.key(files, conf)


def _code_key(model: str) -> dict | str:
    """The code of a model as a fit's fingerprint holds it (``CodeIdentity.key`` of
    pipeline/runner/environment.py: distribution, version, digest of the files it runs), or why there is
    none (not installed: the evaluate says so when it runs)."""
    from skidbench.models.base import ModelError
    from skidbench.models.registry.plugins import DISCOVERED, discover
    from skidbench.models.registry.specs import get_model_class
    from skidbench.pipeline.runner.environment import code_identity

    if model == DISCOVERED:  # resolved per terrain from discovery.json (a file of the key): its base's code
        return "discovered"
    try:
        cls = get_model_class(model)
    except ModelError as exc:
        return str(exc)
    info = discover().get(model.split("+")[0])
    code = code_identity(cls, *((info.package, info.package_version) if info else ())).key()
    return {**code, "class_version": str(getattr(cls, "version", "?"))}


def _cached_result(es):
    """The last result when its parent run still exists in the configured MLflow store, else None."""
    from skidbench.benchmark.evaluate.evaluation import BenchmarkResult, ChildResult, last_file
    from skidbench.benchmark.tracking import store as trk
    from skidbench.benchmark.tracking import tags as run_tags

    try:
        last = json.loads(last_file(es.layout, es.protocol).read_text())
        tracker = trk.open_store(es.store)
        if last.get("tracking_uri") != tracker.uri:
            return None
        run = tracker.client.get_run(last["parent_run_id"])
        if run.info.lifecycle_stage != "active" or run.info.experiment_id != tracker.experiment_id:
            return None
        if run.info.status != "FINISHED":  # killed or failed since (reaped): run again, never shown as done
            return None
        if tracker.dataset_id and run.data.tags.get(run_tags.TAG_DATASET_ID) != tracker.dataset_id:
            return None  # a run of another dataset at this name (source.replace=true), or an older one
    except Exception as exc:  # no such run / store: evaluate again
        log.info("evaluate: cached result not usable (%s); re-running", type(exc).__name__)
        return None
    children = [ChildResult(**c) for c in last.get("children", [])]
    return BenchmarkResult(
        last["tracking_uri"], last["experiment"], last["parent_run_id"], children,
        last.get("inputs", "commanded"), list(last.get("skipped") or []),
        {str(t): dict(m) for t, m in (last.get("floor") or {}).items()},  # every board shows the floor
        [float(h) for h in last.get("horizons") or []],
    )  # fmt: skip


if __name__ == "__main__":
    main()
