"""Fitting a model on a terrain's Train split: the function the ``fit``, ``evaluate`` and ``discover``
stages call, and the reader of saved fits.

    settings = FitSettings.from_cfg(cfg)                    # in the app
    fit_model(settings, "friction", "grass") -> FitResult   # writes <ds>/fits/friction/grass.json
    load_fitted(settings, "friction", "grass") -> KinematicModel

:class:`FitSettings` is what fitting reads of a composed skidbench config that brings ``common`` (robot,
out_root, dataset, inputs, calibrate): the apps make it. The model's own config (``model/<name>.yaml``:
``params`` = initial parameters, ``options``) is the config's ``model`` group when its name matches, else
it is composed from the Hydra search path (so a plugin's config is found too), else the model's class
defaults are used (:class:`ModelConfigs`, :func:`model_config`).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import json
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from skidbench.models.base import KinematicModel, ModelError, calibrated_constants
from skidbench.models.registry.plugins import DISCOVERED, discover
from skidbench.models.registry.saved import arrays_file, fit_findings, from_saved, save_arrays
from skidbench.models.registry.specs import get_model_class
from skidbench.pipeline.calibrate.calibration import (
    CONSTANTS,
    Calibrations,
    load_calibration,
    response_for,
    robot_for_model,
)
from skidbench.pipeline.calibrate.wheel_response import WheelResponse
from skidbench.pipeline.core.cache import Stamp, stamp_file
from skidbench.pipeline.core.io import write_json_atomic
from skidbench.pipeline.core.layout import CommonSettings, Layout, root_from_cfg
from skidbench.pipeline.core.manifest import Manifest
from skidbench.pipeline.core.protocol import INPUT_COLUMNS, ProtocolError, fit_protocol, fit_table
from skidbench.pipeline.core.robot import Robot, robot_from_hydra
from skidbench.pipeline.core.schema import concat_sequences, read_split
from skidbench.pipeline.runner.environment import CodeIdentity, code_change, code_identity

log = logging.getLogger(__name__)

FIT_SCHEMA = 2  # 2: fitted under an input protocol (``inputs``, pipeline/core/protocol.py)


@dataclass
class FitResult:
    model: KinematicModel  # fitted instance
    path: Path  # the JSON written (or reused)
    fit_loss: float | None  # mean squared velocity error on the training rows
    fit_time_s: float
    n_train: int  # training rows used (valid)
    reused: bool = False
    code: CodeIdentity | None = None  # the model's code (pipeline/runner/environment.py), in its fingerprint
    refit_reason: str | None = None  # why an earlier fit was not reused: its code changed (digest a -> b)


@dataclass(frozen=True)
class ModelConfigs:
    """What a run's config says of its models: ``node``, its ``model`` entry (resolved; None without one),
    which is the model config group of a one-model stage (``fit``), or, on a stage that evaluates a list
    of models (``models``, not None: the config's ``models`` then each of ``extra_models`` not among them),
    the ``+model.params/options.*`` overrides of its command line. ``from_cfg(cfg, models)``: the list
    evaluate read (``EvaluateOptions.all_models``); None: the config's."""

    node: Any = None
    models: tuple[str, ...] | None = None

    @classmethod
    def from_cfg(cls, cfg: Any, models: Sequence[str] | None = None) -> ModelConfigs:
        from omegaconf import OmegaConf

        node = cfg.get("model") if hasattr(cfg, "get") else None
        if OmegaConf.is_config(node):
            node = OmegaConf.to_container(node, resolve=True)
        if models is None and hasattr(cfg, "get") and cfg.get("models") is not None:
            models = [*cfg.get("models"), *(cfg.get("extra_models") or [])]
        return cls(node, None if models is None else tuple(dict.fromkeys(str(m) for m in models)))

    @property
    def overrides_only(self) -> bool:
        """True when ``node`` is a command-line override on a stage that evaluates a list of models
        (``skidbench evaluate +model.options.x=...``), not the model config group of ``fit``."""
        return self.models is not None


@dataclass(frozen=True)
class FitSettings:
    """What fitting reads of a run's config: the dataset's layout, the spec sheet's robot, the input
    protocol a model is fitted under (:func:`~skidbench.pipeline.core.protocol.fit_protocol`), the
    calibrations (``calibrate.use``) and the models' configs. The apps make it
    (:meth:`from_cfg`)."""

    layout: Layout
    robot: Robot
    inputs: str
    calibrations: Calibrations
    models: ModelConfigs

    @classmethod
    def from_cfg(cls, cfg: Any, common: CommonSettings | None = None, models: Sequence[str] | None = None):
        """``common``: the root keys if the caller read them; ``models``: :meth:`ModelConfigs.from_cfg`."""
        common = common if common is not None else root_from_cfg(cfg, CommonSettings)
        layout, robot = Layout(Path(common.out_root), common.dataset), robot_from_hydra(cfg.robot)
        calib, configs = Calibrations(layout, robot, cfg.calibrate.use), ModelConfigs.from_cfg(cfg, models)
        return cls(layout, robot, fit_protocol(common.inputs), calib, configs)


def model_config(configs: ModelConfigs, model_name: str) -> dict[str, Any]:
    """``{"name", "params", "options"}`` for ``model_name`` (see module docstring). An augmented spec
    ``base+effect+...`` gets its base model's params and options as ``base_params``/``base_options``."""
    if model_name == DISCOVERED:
        return {"name": model_name, "params": {}, "options": {}}
    if "+" in model_name:
        base = model_config(configs, model_name.split("+")[0].strip())
        return {
            "name": model_name,
            "params": {},
            "options": {"base_params": base["params"], "base_options": base["options"]},
        }

    node = configs.node
    if isinstance(node, dict) and node.get("name") == model_name and not configs.overrides_only:
        data = copy.deepcopy(node)
    else:
        data = _compose_model_config(model_name)
    data = dict(data or {})
    out = {
        "name": model_name,
        "params": dict(data.get("params") or {}),
        "options": dict(data.get("options") or {}),
    }
    over = model_overrides(configs, model_name)
    unknown = sorted(set(over.get("options") or {}) - set(out["options"]))
    if unknown and data:  # the model's config lists its options: an unknown one would be ignored
        raise ModelError(
            f"model.options.{unknown[0]}: model {model_name} has no such option "
            f"(its options: {', '.join(sorted(out['options'])) or 'none'})"
        )
    out["params"].update(over.get("params") or {})
    out["options"].update(over.get("options") or {})
    return out


def model_overrides(configs: ModelConfigs, model_name: str) -> dict[str, Any]:
    """``{"params", "options"}`` set on the command line of a multi-model stage (``evaluate``):
    ``+model.options.x=1`` (one model evaluated, or ``+model.name=<m>`` says which one). Anything else
    under ``model`` is refused (ModelError), never silently ignored."""
    if not configs.overrides_only or configs.node is None:
        return {}
    node = copy.deepcopy(configs.node) or {}
    if not isinstance(node, dict):
        raise ModelError(f"model={node!r}: on evaluate, set models=[...] and +model.options.<key>=<value>")
    unknown = sorted(set(node) - {"name", "params", "options"})
    if unknown:
        raise ModelError(
            f"model.{unknown[0]}: unknown key; evaluate takes +model.options.* and +model.params.*"
        )
    models = list(configs.models or ())
    target = node.get("name")
    if target is None:
        if len(models) != 1:
            raise ModelError(
                f"+model.options/params apply to one model, and models={models}; add +model.name=<model>"
            )
        target = models[0]
    elif str(target) not in models:
        raise ModelError(f"model.name={target}: not among models={models}")
    if str(target) != model_name:
        return {}
    for key in ("params", "options"):
        if node.get(key) is not None and not isinstance(node[key], dict):
            raise ModelError(f"model.{key}: must be a mapping (+model.{key}.<key>=<value>)")
    return {"params": node.get("params") or {}, "options": node.get("options") or {}}


def _compose_model_config(model_name: str) -> dict[str, Any] | None:
    """``model/<name>.yaml`` composed on the current config search path (None: not on it). A compose
    takes about 0.2 s, and an evaluate asks for each model's config twice per terrain, so it is kept per
    (model, search path) for the life of the process; callers get their own copy."""
    from hydra.core.global_hydra import GlobalHydra

    gh = GlobalHydra.instance()
    if gh.is_initialized():
        sources = tuple((s.provider, s.path) for s in gh.config_loader().get_sources())
    else:
        sources = None
    return copy.deepcopy(_compose_cached(model_name, sources))


@functools.lru_cache(maxsize=64)
def _compose_cached(model_name: str, sources: tuple | None) -> dict[str, Any] | None:
    from hydra import compose, initialize_config_module
    from omegaconf import OmegaConf

    try:
        if sources is not None:
            c = compose(config_name="fit", overrides=[f"model={model_name}", "terrain=_"])
        else:
            with initialize_config_module("skidbench.conf", version_base="1.3"):
                c = compose(config_name="fit", overrides=[f"model={model_name}", "terrain=_"])
    except Exception:  # no model/<name>.yaml on the search path: class defaults
        return None
    return OmegaConf.to_container(c.model, resolve=True)


def build_model(configs: ModelConfigs, model_name: str, robot: Robot) -> KinematicModel:
    """An unfitted instance on ``robot`` with its configured initial params and options."""
    cls = get_model_class(model_name)
    mc = model_config(configs, model_name)
    try:
        return cls(robot, mc["params"] or None, **mc["options"])
    except ModelError:
        raise
    except Exception as exc:
        raise ModelError(f"model {model_name}: cannot be built ({type(exc).__name__}: {exc})") from exc


def _training_files(layout: Layout, model_name: str, terrain: str, split: str) -> list[Path]:
    """The split files of the current manifest's ``terrain``/``split`` sequences (pipeline/core/layout.py)."""
    if not layout.manifest.is_file():
        raise ModelError(
            f"model {model_name}: no manifest {layout.manifest}; run `skidbench extract` and `split`"
        )
    manifest = Manifest.read(layout.manifest)
    files = layout.require_split_files(manifest, terrain, split, ModelError, f"model {model_name}: ")
    if not files:
        raise ModelError(
            f"model {model_name}: no {split} sequences of terrain {terrain} in {layout.manifest} "
            f"(terrains: {', '.join(manifest.terrains)}); check terrain={terrain}"
        )
    return files


def resolve_model_spec(
    layout: Layout, inputs: str, model_name: str, terrain: str
) -> tuple[str, dict[str, Any]]:
    """The model spec a name stands for on ``terrain`` of the dataset at ``layout``, under input protocol
    ``inputs``: itself, except ``discovered``, which is the base model and effects ``skidbench discover``
    found for the terrain (``<ds>/discovery/discovery.json``; the base model alone when it found none).
    Returns (spec, what the discovery said)."""
    if model_name != DISCOVERED:
        return model_name, {}
    path = layout.discovery / "discovery.json"
    if not path.is_file():
        raise ModelError(
            f"model {DISCOVERED}: {path} not found; run `skidbench discover` on this dataset first"
        )
    try:
        doc = json.loads(path.read_text())
        entry = doc["terrains"][terrain]
        base = str(entry["base_model"])  # model_effects: the members as fitted (the speed scale too)
        effects = [str(e) for e in entry.get("model_effects", entry["effects"])]
        effects += [str(k) for k in entry.get("terms", [])]  # open-ended terms, after the catalogue's
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ModelError(
            f"model {DISCOVERED}: {path} has no discovery for terrain {terrain} ({type(exc).__name__}: {exc})"
        ) from None
    found_under = str(doc.get("inputs", "commanded"))
    if found_under != inputs:  # what is missing depends on the inputs the search was given
        raise ModelError(
            f"model {DISCOVERED}: {path} was found under inputs={found_under}, this run is inputs={inputs}; "
            f"run `skidbench discover inputs={inputs}` (or evaluate it under inputs={found_under})"
        )
    sel = entry.get("selected_on") or {}
    seen = [s for s in sel.get("splits", []) if s != "train"]
    if seen or "added to the pool" in str((entry.get("base") or {}).get("pool_note") or ""):
        raise ModelError(  # a discovery made before selection kept to Train (CV/LD added to its pool) too
            f"model {DISCOVERED}: {path} selected terrain {terrain}'s effects on its "
            f"{'/'.join(seen) or 'CV/LD'} sequences too, so its score there would not be held out; "
            "run `skidbench discover` (it selects on Train only) again"
        )
    spec = "+".join([base, *effects])
    return spec, {
        "discovery": str(path),
        "spec": spec,
        "message": entry.get("message", ""),
        "selected_on": sel.get("text", "train"),
    }


def protocol_inputs(settings: FitSettings, terrain: str) -> tuple[str, Robot, WheelResponse | None]:
    """(protocol, robot the inputs are converted with, the terrain's wheel response) of a run: the
    protocol ``inputs``; the spec sheet's robot (the split's own commanded ``cmd_v``/``cmd_w`` come
    from it); the response ``calibrate`` identified (``response`` protocol only; ProtocolError when
    there is none)."""
    inputs = settings.inputs
    response = None
    if inputs == "response":
        response = response_for(settings.calibrations, terrain)
        if response is None:
            raise ProtocolError(
                f"inputs=response: no wheel response identified for terrain {terrain} (the Train split has "
                "no wheel encoders, or too few readings; `skidbench calibrate` says which)"
            )
    return inputs, settings.robot, response


def check_inputs(model: Any, model_name: str) -> None:
    """ModelError when a model needs a column no model is given at predict time (``INPUT_COLUMNS``)."""
    extra = [c for c in getattr(model, "required_columns", ()) if c not in INPUT_COLUMNS]
    if extra:
        raise ModelError(
            f"model {model_name}: requires column(s) {extra}, but a model is given only the protocol's "
            f"inputs {list(INPUT_COLUMNS)} at predict time"
        )


@dataclass
class _FitPlan:
    """Everything a fit of one model on one terrain is made from, and its stamp."""

    spec: str  # the model spec fitted (``discovered`` resolved)
    resolved: dict[str, Any]
    cls: type
    files: list[Path]  # the Train split files
    inputs: str  # input protocol
    spec_robot: Robot  # the spec sheet's (converts the protocol's wheel rates to cmd_v/cmd_w)
    response: WheelResponse | None
    robot: Robot  # the robot the model is built with (the calibrated constants it takes)
    constants: dict[str, Any]  # where each constant came from (robot_for_model)
    code: CodeIdentity  # the model's code: distribution, version, digest of the files it runs
    path: Path  # the fit JSON
    stamp: Stamp
    key: str


def _plan(settings: FitSettings, model_name: str, terrain: str, split: str) -> _FitPlan:
    layout = settings.layout
    spec, resolved = resolve_model_spec(layout, settings.inputs, model_name, terrain)
    cls = get_model_class(spec)
    files = _training_files(layout, model_name, terrain, split)
    inputs, spec_robot, response = protocol_inputs(settings, terrain)
    cal = settings.calibrations
    robot, constants = robot_for_model(cal, calibrated_constants(cls), terrain)
    calibration = load_calibration(cal, terrain)  # None with calibrate.use=false
    info = discover().get(spec.split("+")[0])
    code = code_identity(cls, *((info.package, info.package_version) if info else ()))
    path = layout.fit_file(model_name, terrain, inputs)
    # one stamp per model, terrain and input protocol, as the fit file (a fit under one protocol is never
    # another's; pipeline/core/protocol.py)
    stamp = Stamp(stamp_file(layout.root, "fit", model_name, path.name), "fit")
    key = stamp.key(
        files,  # the manifest's Train files of the terrain, exactly those fitted on
        {
            "model": model_config(settings.models, spec),
            "version": getattr(cls, "version", "?"),
            # the code itself (distribution, version and a digest of the files it runs): a plugin
            # edited in place, or a release that forgets to bump a version, still invalidates old fits
            "code": code.key(),
            "robot": robot.to_dict(),  # as built, with the calibrated constants the model takes
            "spec_robot": spec_robot.to_dict(),
            "terrain": terrain,
            "split": split,
            "inputs": inputs,
            "response": dataclasses.asdict(response) if response is not None else None,
            "calibration": {c: ((calibration or {}).get(c) or {}).get("value") for c in CONSTANTS},
            "schema": FIT_SCHEMA,
        },
    )
    return _FitPlan(
        spec, resolved, cls, files, inputs, spec_robot, response, robot, constants, code, path, stamp, key
    )


def fit_stamp(
    settings: FitSettings, model_name: str, terrain: str, split: str = "train"
) -> tuple[Stamp, str]:
    """The stamp of the fit of ``model_name`` on ``terrain``'s ``split`` (``<ds>/.stamps/fit/<model>/
    <terrain>[.<inputs>].json``) and the key of its current inputs: the split files (content), the model's
    config, class version, its code (distribution, version and the digest of the files it runs:
    ``pipeline/runner/environment.py``), the robot it is built with (calibrated constants
    included) and the spec sheet's, terrain, split, input protocol, wheel response, the calibration's
    constants and ``FIT_SCHEMA``. ``stamp.is_fresh(key)``: the saved fit is up to date."""
    plan = _plan(settings, model_name, terrain, split)
    return plan.stamp, plan.key


def fit_model(
    settings: FitSettings,
    model_name: str,
    terrain: str,
    *,
    reuse: bool = True,
    split: str = "train",
    hooks: Sequence[Callable] = (),
) -> FitResult:
    """Fit ``model_name`` on ``terrain``'s Train split and write its JSON (and fitted arrays) atomically.

    With ``reuse`` the saved fit is loaded instead when its stamp (:func:`fit_stamp`, the one definition
    of "up to date" of a fit, whichever stage made it: a fit ``evaluate`` made is up to date for ``fit``
    and the other way round) is fresh: same inputs, and the fit JSON and its arrays intact (a corrupted
    or truncated one is refitted). The model is fitted on the Train table of the input protocol
    ``settings.inputs`` (:func:`skidbench.pipeline.core.protocol.fit_table`: the protocol's inputs and the
    targets, nothing else). ``hooks``: called after a fit (not a reuse) as ``hook(result, model_name,
    terrain)``, passed by the caller (the fit stage its MLflow logging; fitting stays free of MLflow). The
    stamp is recorded after the hooks: a job killed before its hooks finished is refitted when retried."""
    plan = _plan(settings, model_name, terrain, split)
    if reuse and plan.stamp.is_fresh(plan.key):
        saved = _saved_fit(plan)
        if saved is not None:
            return saved
    if why := code_change(plan.stamp.changed(plan.key)):
        log.info("%s on %s: %s; refitting", model_name, terrain, why)
    model, n_train, fit_time = _fit_on_train(settings.models, plan, model_name, terrain)
    arrays = _model_arrays(model, model_name)
    data = _fit_doc(model, plan, model_name, terrain, split, settings.layout.dataset, n_train, fit_time)
    apath = _write_fit(plan.path, data, arrays, model_name)
    for line in fit_findings(data):  # a fit at a bound is a finding (compare notes it too)
        log.warning("%s on %s: %s", model_name, terrain, line)
    result = FitResult(model, plan.path, data.get("fit_loss"), fit_time, n_train, code=plan.code,
                       refit_reason=why)  # fmt: skip
    for hook in hooks:
        hook(result, model_name, terrain)
    # recorded last: a fit whose hooks (the fit stage's MLflow run) did not finish is not up to date
    plan.stamp.record(plan.key, [plan.path, *([apath] if arrays else [])])
    return result


def _saved_fit(plan: _FitPlan) -> FitResult | None:
    """The saved fit of an up-to-date ``plan`` (None when its JSON or arrays cannot be read: refit)."""
    try:
        saved = json.loads(plan.path.read_text())
        model = from_saved(plan.cls, plan.robot, saved, plan.spec, plan.path)
    except (OSError, ValueError, ModelError):
        return None
    return FitResult(
        model,
        plan.path,
        saved.get("fit_loss"),
        saved.get("fit_time_s", 0.0),
        int(saved.get("n_train", 0)),
        reused=True,
        code=plan.code,
    )


def _fit_on_train(
    configs: ModelConfigs, plan: _FitPlan, model_name: str, terrain: str
) -> tuple[KinematicModel, int, float]:
    """(the model built as configured and fitted on the plan's Train table, its valid training rows, the
    fit's seconds). A model's exception other than ModelError is its fit failing, in one line."""
    table = fit_table(
        concat_sequences([read_split(p) for p in plan.files]), plan.inputs, plan.spec_robot, plan.response
    )
    model = build_model(configs, plan.spec, plan.robot)
    check_inputs(model, model_name)
    n_train = int(table["valid"].sum()) if "valid" in table else 0
    t0 = time.perf_counter()
    try:
        model.fit(table)
    except ModelError:
        raise
    except Exception as exc:  # a plugin's bug is reported as that model's problem, in one line
        raise ModelError(
            f"model {model_name}: fit failed on terrain {terrain} ({type(exc).__name__}: {exc})"
        ) from exc
    return model, n_train, time.perf_counter() - t0


def _fit_doc(
    model: KinematicModel,
    plan: _FitPlan,
    model_name: str,
    terrain: str,
    split: str,
    dataset: str,
    n_train: int,
    fit_time: float,
) -> dict[str, Any]:
    """The fit JSON of a fitted model: the model's own record and what it was fitted on, with."""
    data = model.to_json() if hasattr(model, "to_json") else {"model": model_name, "params": model.params}
    info = discover().get(plan.spec.split("+")[0])
    data.update(
        {
            "schema": FIT_SCHEMA,
            "terrain": terrain,
            "dataset": dataset,
            "robot": plan.robot.name,
            "split": split,
            "sequences": [p.stem for p in plan.files],
            "n_train": n_train,
            "fit_time_s": fit_time,
            "fit_info": getattr(model, "fit_info_", {}),
            "robot_constants": plan.constants,
            "inputs": plan.inputs,
            **({"wheel_response": dataclasses.asdict(plan.response)} if plan.response is not None else {}),
            **({"resolved": plan.resolved} if plan.resolved else {}),
            "package": info.package if info else "?",
            "code": plan.code.to_dict(),
        }
    )
    return data


def _write_fit(path: Path, data: dict[str, Any], arrays: dict[str, np.ndarray], model_name: str) -> Path:
    """Write a fit's arrays (when it has any; their record goes into ``data``), then its JSON, atomically;
    a refit without arrays removes an older fit's arrays file. Returns the arrays file's path."""
    apath = arrays_file(path)
    if arrays:
        fp_arrays = save_arrays(apath, arrays)
        data["arrays"] = {"file": apath.name, "fingerprint": fp_arrays, "names": sorted(arrays)}
    try:
        write_json_atomic(path, data)  # after the arrays: a JSON on disk always has its arrays
    except TypeError as exc:
        raise ModelError(f"model {model_name}: parameters are not JSON-serialisable ({exc})") from exc
    if not arrays and apath.is_file():
        apath.unlink()  # a refit without arrays leaves no stale file
    return apath


def is_seeded(model: Any) -> bool:
    """Does a model have random parts it declares (a ``seed`` among its options: gp_residual, a plugin's)?"""
    return "seed" in (getattr(model, "options", None) or {})


@dataclass
class Refit:
    """What fitting a model again with another seed takes (evaluate's ``seeds``): its class, the robot it
    is built with, its configured params and options, and the Train table of its input protocol."""

    name: str
    terrain: str
    cls: type
    robot: Robot
    params: dict[str, Any] | None
    options: dict[str, Any]
    table: pd.DataFrame

    def fit(self, seed: int) -> KinematicModel:
        """The model fitted as :func:`fit_model` fits it, with its option ``seed`` set to ``seed``; nothing is
        written or reused (the saved fit stays the configured seed's)."""
        try:
            return self.cls(self.robot, self.params, **{**self.options, "seed": int(seed)}).fit(self.table)
        except ModelError:
            raise
        except Exception as exc:
            raise ModelError(
                f"model {self.name}: fit with seed {seed} failed on terrain {self.terrain} "
                f"({type(exc).__name__}: {exc})"
            ) from exc


def refit_from_cfg(cfg: Any, model_name: str, terrain: str, split: str = "train") -> Refit:
    """The door from the config to :func:`refit_of`."""
    return refit_of(FitSettings.from_cfg(cfg), model_name, terrain, split)


def refit_of(settings: FitSettings, model_name: str, terrain: str, split: str = "train") -> Refit:
    """A :class:`Refit` of ``model_name`` on ``terrain``'s Train split."""
    plan = _plan(settings, model_name, terrain, split)
    table = fit_table(
        concat_sequences([read_split(p) for p in plan.files]), plan.inputs, plan.spec_robot, plan.response
    )
    mc = model_config(settings.models, plan.spec)
    return Refit(model_name, terrain, plan.cls, plan.robot, mc["params"] or None, dict(mc["options"]), table)


def _model_arrays(model: Any, model_name: str) -> dict[str, np.ndarray]:
    arrays = dict(getattr(model, "arrays", None) or {})
    for k, v in arrays.items():
        if not isinstance(k, str) or not k.isidentifier():
            raise ModelError(f"model {model_name}: arrays key {k!r} must be a Python identifier")
        a = np.asarray(v)
        if a.dtype == object:
            raise ModelError(f"model {model_name}: arrays[{k!r}] is not numeric (dtype object)")
        arrays[k] = a
    return arrays


def load_fitted(settings: FitSettings, model_name: str, terrain: str) -> KinematicModel:
    """The fitted model saved by :func:`fit_model` (ModelError if there is none)."""
    inputs = settings.inputs
    path = settings.layout.fit_file(model_name, terrain, inputs)
    if not path.is_file():
        raise ModelError(
            f"model {model_name}: no fit for terrain {terrain} under inputs={inputs} at {path}; run "
            f"`skidbench fit model={model_name} terrain={terrain} inputs={inputs}`"
        )
    try:
        saved = json.loads(path.read_text())
    except ValueError as exc:
        raise ModelError(f"model {model_name}: unreadable fit {path} ({exc})") from exc

    spec = str((saved.get("resolved") or {}).get("spec") or model_name)
    cls = get_model_class(spec)
    robot, _ = robot_for_model(settings.calibrations, calibrated_constants(cls), terrain)
    return from_saved(cls, robot, saved, spec, path)
