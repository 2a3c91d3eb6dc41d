"""What a fitted model is, as a run records it: the package that provides it, its fit's description
(robot constants, options, fitted values) and diagnostics as MLflow params and metrics, and the fitted model
logged as an MLflow Model. Evaluate's child runs call these (benchmark/evaluate/evaluation.py
``_fit_and_log``)."""

from __future__ import annotations

import importlib.metadata as md
import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from skidbench.benchmark.scoring.predictions import TestSequence
from skidbench.benchmark.tracking import store as trk
from skidbench.benchmark.tracking import tags as run_tags
from skidbench.models.fitting import fit as fitting
from skidbench.models.registry import plugins as registry
from skidbench.pipeline.calibrate.wheel_response import WheelResponse
from skidbench.pipeline.core.errors import one_line
from skidbench.pipeline.runner import environment

log = logging.getLogger(__name__)


def installed_models() -> dict[str, md.EntryPoint]:
    return {ep.name: ep for ep in registry.entry_points(group=registry.GROUP)}


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


def model_code(model_name: str, model: Any) -> environment.CodeIdentity:
    """The code of a fitted model (pipeline/runner/environment.py): its entry point's distribution, version
    and
    the digest of the files it runs."""
    ep = installed_models().get(model_name)
    dist = ep.dist if ep is not None else None
    return environment.code_identity(type(model), *((dist.name, dist.version) if dist else ()))


def default_fit_fn() -> Callable[[fitting.FitSettings, str, str], Any]:
    return fitting.fit_model


def fit_description(fit: Any, response: WheelResponse | None = None) -> dict[str, Any]:
    """What a fitted model is beyond its config, as MLflow params: the robot constants it was fitted with
    (``robot_used.<c>`` and its ``.source``: calibrated or the spec sheet's), the options it was built with
    (``model_options.*``), the model's own ``tracking_params()`` (an augmented model's base and effects),
    the wheel response that drove every model (``wheel_response.*``) and the fitted values (``fitted.*``)."""
    model = fit.model
    described = {}
    for c, rec in (fit_json(fit).get("robot_constants") or {}).items():
        described[f"robot_used.{c}"] = rec.get("value")
        described[f"robot_used.{c}.source"] = rec.get("source")
    for k, v in run_tags.flatten(dict(getattr(model, "options", None) or {}), "model_options.").items():
        described[k] = v  # the options the model was built with (config and +model.options.*)
    if callable(getattr(model, "tracking_params", None)):
        described.update(model.tracking_params())
    resolved = fit_json(fit).get("resolved") or {}
    if resolved.get("selected_on"):  # `discovered`: what its effects were selected on (Train only)
        described["discovered.selected_on"] = resolved["selected_on"]
        described["discovered.spec"] = resolved.get("spec")
    if response is not None:  # the calibration's wheel response that drove every model
        described.update({f"wheel_response.{k}": v for k, v in response.__dict__.items()})
    described.update(run_tags.flatten(getattr(model, "params", None) or {}, "fitted."))  # the fitted values
    for f in (fit_json(fit).get("fit_info") or {}).get("at_bound") or []:  # a fit at a bound: a finding
        described[f"at_bound.{f['param']}"] = f"{f['side']} bound {f.get('bound', 'inf')}: {f['finding']}"
    return described


def log_model(
    inputs: str, tracker, run_id, fit, model_name, terrain, record_path: Path, seq: TestSequence
) -> None:
    """The fitted model (under input protocol ``inputs``) as an MLflow Model of the run (tag
    ``skidbench.logged_model``: its id, or why not: a model object that is no installed skidbench model
    cannot be rebuilt outside this process)."""
    from skidbench.benchmark.tracking.mlflow_model import INPUT_COLUMNS, write_model_record
    from skidbench.models.base import ModelError
    from skidbench.models.registry.specs import get_model_class

    model = fit.model
    spec = str((fit_json(fit).get("resolved") or {}).get("spec") or model_name)
    try:
        cls = get_model_class(spec)  # an augmented spec's class is made anew on each call: compare names
        if not hasattr(model, "robot") or (type(model) is not cls and getattr(model, "name", "") != cls.name):
            raise ModelError(f"{type(model).__name__} is not the installed model {spec}")
        record = write_model_record(record_path, spec, model.to_json(),
                                    model.robot, inputs)  # fmt: skip
        example = seq.table.head(30).assign(sequence=seq.name)[list(INPUT_COLUMNS)]  # 1 s of a test sequence
        arrays = record_path.with_name(record_path.name.replace(".mlflow_model.json", ".arrays.npz"))
        arrays = arrays if getattr(model, "arrays", None) and arrays.is_file() else None
        requirements = environment.requirements_of(model_code(model_name, model))  # what loading it needs
        model_id = tracker.log_model(run_id, f"{model_name}-{terrain}", record, example, arrays, requirements)
    except trk.StoreUnreachable:  # the store is gone: nothing more can be logged
        raise
    except Exception as exc:  # the benchmark's numbers stand without it: say why, on the run (and console)
        model_id = f"not logged: {type(exc).__name__}: {one_line(str(exc))[:300]}"
        if not isinstance(exc, ModelError):
            log.warning("%s/%s: model %s", model_name, terrain, model_id)
    tracker.log(run_id, tags={"skidbench.logged_model": model_id})


#: per-parameter fit diagnostics a model may report in its fit JSON's ``fit_info`` (friction: bound margins,
#: Jacobian standard errors, identified 1 / held 0); each is logged as the metric ``<key>.<parameter>``
FIT_QUALITY_KEYS = ("param_bound_margin", "param_bound_margin_linear", "param_stderr", "param_identified")


def fit_quality_metrics(fit: Any) -> dict[str, float]:
    """``{"param_bound_margin.mu_r": ...}`` from the fit's ``fit_info`` (the model's, or the saved fit
    JSON's when the fit was reused); empty for models that report none."""
    info = getattr(getattr(fit, "model", None), "fit_info_", None) or {}
    if not any(k in info for k in FIT_QUALITY_KEYS):
        info = fit_json(fit).get("fit_info") or {}
    out = {}
    for key in FIT_QUALITY_KEYS:
        for name, value in (info.get(key) or {}).items():
            v = num(value)
            if v is not None and np.isfinite(v):
                out[f"{key}.{name}"] = v
    return out


def fit_json(fit: Any) -> dict[str, Any]:
    """The fit's saved JSON (FitResult.path), or {} when there is none."""
    path = getattr(fit, "path", None)
    try:
        return json.loads(Path(path).read_text()) if path else {}
    except (OSError, ValueError):
        return {}


def num(v: Any) -> float | None:
    try:
        return None if v is None else float(v)
    except (TypeError, ValueError):
        return None


#: the settings of an evaluate a child run's numbers depend on (with the model's config and the protocol)
OPTION_KEYS = ("horizons", "splits", "min_distance_m", "min_rotation_deg", "calibrate", "train_dataset",
               "train_terrain")  # fmt: skip


def options_tags(conf: dict[str, Any], model_conf: dict[str, Any], protocol: str) -> dict[str, str]:
    """The run tag ``skidbench.options_digest`` (:func:`options_digest`)."""
    from skidbench.benchmark.board.boards import TAG_OPTIONS

    return {TAG_OPTIONS: options_digest(conf, model_conf, protocol)}


def options_digest(conf: dict[str, Any], model_conf: dict[str, Any], protocol: str) -> str:
    """The digest (12 hex digits) of what a child run was made with besides its data and code: the
    model's config (name, params, options), the input protocol and :data:`OPTION_KEYS` of the evaluate's
    config. Two rows with one digest were made with the same options; it is the run's tag
    ``skidbench.options_digest`` and a column of compare's leaderboard files."""
    from skidbench.pipeline.core.io import fingerprint_obj

    return fingerprint_obj(
        {"model": model_conf, "inputs": protocol, **{k: conf.get(k) for k in OPTION_KEYS}}
    )[:12]
