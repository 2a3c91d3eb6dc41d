"""Fitting a model on a terrain's Train split: the function the ``fit``, ``evaluate`` and ``discover``
stages call, and the reader of saved fits.

    fit_model(cfg, "friction", "grass") -> FitResult   # writes <out_root>/<dataset>/fits/friction/grass.json
    load_fitted(cfg, "friction", "grass") -> KinematicModel

``cfg`` is any composed skidbench config that brings ``common`` (robot, out_root, dataset). The model's own
config (``model/<name>.yaml``: ``params`` = initial parameters, ``options``) is ``cfg.model`` when its
name matches, else it is composed from the Hydra search path (so a plugin's config is found too), else
the model's class defaults are used.
"""

from __future__ import annotations

import copy
import functools
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from skidbench.pipeline.io import fingerprint_file, fingerprint_obj, write_json_atomic
from skidbench.pipeline.layout import layout_from_cfg
from skidbench.pipeline.manifest import Manifest
from skidbench.pipeline.robot import Robot, robot_from_hydra
from skidbench.pipeline.schema import read_split

from .base import KinematicModel, ModelError, concat_sequences
from .registry import DISCOVERED, discover, get_model_class

FIT_SCHEMA = 1


@dataclass
class FitResult:
    model: KinematicModel  # fitted instance
    path: Path  # the JSON written (or reused)
    fit_loss: float | None  # mean squared velocity error on the training rows
    fit_time_s: float
    n_train: int  # training rows used (valid)
    reused: bool = False


#: Called after every fit as ``hook(result, cfg, model_name, terrain)``; the evaluate stage may register
#: its MLflow logging here (fit itself stays free of MLflow).
FIT_HOOKS: list[Callable[[FitResult, Any, str, str], None]] = []


def model_config(cfg: Any, model_name: str) -> dict[str, Any]:
    """``{"name", "params", "options"}`` for ``model_name`` (see module docstring). An augmented spec
    ``base+effect+...`` gets its base model's params and options as ``base_params``/``base_options``."""
    from omegaconf import OmegaConf

    if model_name == DISCOVERED:
        return {"name": model_name, "params": {}, "options": {}}
    if "+" in model_name:
        base = model_config(cfg, model_name.split("+")[0].strip())
        return {
            "name": model_name,
            "params": {},
            "options": {"base_params": base["params"], "base_options": base["options"]},
        }

    node = cfg.get("model") if hasattr(cfg, "get") else None
    if node is not None and node.get("name") == model_name:
        data = OmegaConf.to_container(node, resolve=True)
    else:
        data = _compose_model_config(model_name)
    data = dict(data or {})
    return {
        "name": model_name,
        "params": dict(data.get("params") or {}),
        "options": dict(data.get("options") or {}),
    }


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


def build_model(cfg: Any, model_name: str, robot: Robot | None = None) -> KinematicModel:
    """An unfitted instance with its configured initial params and options."""
    cls = get_model_class(model_name)
    mc = model_config(cfg, model_name)
    robot = robot or robot_from_hydra(cfg.robot)
    try:
        return cls(robot, mc["params"] or None, **mc["options"])
    except ModelError:
        raise
    except Exception as exc:
        raise ModelError(f"model {model_name}: cannot be built ({type(exc).__name__}: {exc})") from exc


def _training_files(cfg: Any, model_name: str, terrain: str, split: str) -> list[Path]:
    """The split files of the current manifest's ``terrain``/``split`` sequences (pipeline/layout.py)."""
    layout = layout_from_cfg(cfg)
    root = layout.splits
    if not layout.manifest.is_file():
        raise ModelError(
            f"model {model_name}: no manifest {layout.manifest}; run `skidbench extract` and `split`"
        )
    manifest = Manifest.read(layout.manifest)
    files = layout.split_files(manifest, terrain, split)
    if not files:
        raise ModelError(
            f"model {model_name}: no {split} sequences of terrain {terrain} in {layout.manifest} "
            f"(terrains: {', '.join(manifest.terrains)}); check terrain={terrain}"
        )
    missing = [p for p in files if not p.is_file()]
    if missing:
        raise ModelError(
            f"model {model_name}: no split files in {root / terrain / split} for {missing[0].stem}; "
            "run `skidbench split`"
        )
    return files


def resolve_model_spec(cfg: Any, model_name: str, terrain: str) -> tuple[str, dict[str, Any]]:
    """The model spec a name stands for on ``terrain``: itself, except ``discovered``, which is the base
    model and effects ``skidbench discover`` found for the terrain (``<ds>/discovery/discovery.json``;
    the base model alone when it found none). Returns (spec, what the discovery said)."""
    if model_name != DISCOVERED:
        return model_name, {}
    path = layout_from_cfg(cfg).discovery / "discovery.json"
    if not path.is_file():
        raise ModelError(
            f"model {DISCOVERED}: {path} not found; run `skidbench discover` on this dataset first"
        )
    try:
        doc = json.loads(path.read_text())
        entry = doc["terrains"][terrain]
        base, effects = str(entry["base_model"]), [str(e) for e in entry["effects"]]
        effects += [str(k) for k in entry.get("terms", [])]  # open-ended terms, after the catalogue's
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ModelError(
            f"model {DISCOVERED}: {path} has no discovery for terrain {terrain} ({type(exc).__name__}: {exc})"
        ) from None
    spec = "+".join([base, *effects])
    return spec, {"discovery": str(path), "spec": spec, "message": entry.get("message", "")}


def _fingerprint(cfg: Any, model_name: str, files: list[Path], robot: Robot, cls: type) -> str:
    return fingerprint_obj(
        {
            "model": model_config(cfg, model_name),
            "version": getattr(cls, "version", "?"),
            "robot": robot.to_dict(),
            "files": [fingerprint_file(p) for p in files],
        }
    )


def fit_model(
    cfg: Any,
    model_name: str,
    terrain: str,
    *,
    reuse: bool = True,
    split: str = "train",
    hooks: Sequence[Callable] = (),
) -> FitResult:
    """Fit ``model_name`` on ``terrain``'s Train split and write its JSON atomically. With ``reuse`` an
    existing fit whose inputs (split files, model config and version, robot) are unchanged is loaded."""
    from skidbench.pipeline.calibration import robot_for_model

    layout = layout_from_cfg(cfg)
    spec, resolved = resolve_model_spec(cfg, model_name, terrain)
    cls = get_model_class(spec)
    files = _training_files(cfg, model_name, terrain, split)
    robot, constants = robot_for_model(cfg, cls, terrain)  # the calibrated constants the model takes
    fp = _fingerprint(cfg, spec, files, robot, cls)
    path = layout.fit_file(model_name, terrain)
    if reuse and path.is_file():
        try:
            saved = json.loads(path.read_text())
            if saved.get("inputs_fingerprint") == fp:
                model = _from_saved(cls, robot, saved, spec)
                return FitResult(
                    model,
                    path,
                    saved.get("fit_loss"),
                    saved.get("fit_time_s", 0.0),
                    int(saved.get("n_train", 0)),
                    reused=True,
                )
        except (OSError, ValueError, ModelError):
            pass  # unreadable or stale: refit
    table = concat_sequences([read_split(p) for p in files])
    model = build_model(cfg, spec, robot)
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
    fit_time = time.perf_counter() - t0
    data = model.to_json() if hasattr(model, "to_json") else {"model": model_name, "params": model.params}
    info = discover().get(spec.split("+")[0])
    data.update(
        {
            "schema": FIT_SCHEMA,
            "terrain": terrain,
            "dataset": str(cfg.dataset),
            "robot": robot.name,
            "split": split,
            "sequences": [p.stem for p in files],
            "n_train": n_train,
            "fit_time_s": fit_time,
            "fit_info": getattr(model, "fit_info_", {}),
            "robot_constants": constants,
            **({"resolved": resolved} if resolved else {}),
            "package": info.package if info else "?",
            "inputs_fingerprint": fp,
        }
    )
    try:
        write_json_atomic(path, data)
    except TypeError as exc:
        raise ModelError(f"model {model_name}: parameters are not JSON-serialisable ({exc})") from exc
    result = FitResult(model, path, data.get("fit_loss"), fit_time, n_train)
    for hook in (*FIT_HOOKS, *hooks):
        hook(result, cfg, model_name, terrain)
    return result


def _from_saved(cls: type, robot: Robot, saved: dict, model_name: str) -> KinematicModel:
    if hasattr(cls, "from_json"):
        return cls.from_json(robot, saved)
    m = cls(robot, saved.get("params") or {}, **(saved.get("options") or {}))
    m.fit_loss_ = saved.get("fit_loss")
    return m


def load_fitted(cfg: Any, model_name: str, terrain: str) -> KinematicModel:
    """The fitted model saved by :func:`fit_model` (ModelError if there is none)."""
    path = layout_from_cfg(cfg).fit_file(model_name, terrain)
    if not path.is_file():
        raise ModelError(
            f"model {model_name}: no fit for terrain {terrain} at {path}; run `skidbench fit "
            f"model={model_name} terrain={terrain}`"
        )
    try:
        saved = json.loads(path.read_text())
    except ValueError as exc:
        raise ModelError(f"model {model_name}: unreadable fit {path} ({exc})") from exc
    from skidbench.pipeline.calibration import robot_for_model

    spec = str((saved.get("resolved") or {}).get("spec") or model_name)
    cls = get_model_class(spec)
    robot, _ = robot_for_model(cfg, cls, terrain)
    return _from_saved(cls, robot, saved, spec)
