"""Transfer evaluation: fit on one dataset's (or terrain's) Train split, score on another's CV/LD.

``skidbench evaluate train_dataset=<name>`` (a dataset under the same ``out_root``, e.g. another day's
recording of the same robot; ``skidbench datasets`` lists them) and/or ``train_terrain=<terrain>`` (of
that dataset, or of this one: fit on asphalt, score on sand). The question a lab asks before trusting a
model fitted last week. Top-level keys because they choose the *layout* a fit reads, like ``dataset``.

- The training dataset must hold the same robot (its manifest's ``robot``) and the terrain fitted on;
  a fit uses that dataset's calibration and writes its fit file there (the same file a same-recording
  evaluate of that dataset reuses).
- The runs go to their own MLflow experiment, ``<experiment>-transfer`` (unless ``mlflow.experiment`` is
  set to something else than its default), with tags ``skidbench.transfer=true``,
  ``skidbench.train_dataset`` and ``skidbench.train_terrain``, so a same-recording leaderboard
  (``skidbench compare``) never mixes them in; ``compare mlflow.experiment=skidbench-<name>-transfer``
  shows them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from omegaconf import OmegaConf

from skidbench.pipeline.errors import SkidbenchError, one_line
from skidbench.pipeline.layout import Layout, layout_from_cfg, split_terrains
from skidbench.pipeline.manifest import Manifest

from .horizon import EvaluationError

TAG_TRANSFER = "skidbench.transfer"
TAG_TRAIN_DATASET = "skidbench.train_dataset"
TAG_TRAIN_TERRAIN = "skidbench.train_terrain"


def training_layout(cfg: Any, fit_fn: Callable[[Any, str, str], Any]) -> tuple[Any, Callable, dict[str, str]]:
    """``(cfg, fit_fn, tags)`` for :func:`~skidbench.benchmark.evaluate.run_benchmark`: unchanged (tags
    ``skidbench.transfer=false``) without ``train_dataset``/``train_terrain``; else the config with the
    transfer experiment, a ``fit_fn`` that fits on the training dataset/terrain, and the transfer tags.
    EvaluationError (one line) when the training dataset is absent, of another robot, or lacks the
    terrain."""
    train_ds = cfg.get("train_dataset")
    train_terrain = cfg.get("train_terrain")
    if not train_ds and not train_terrain:
        return cfg, fit_fn, {TAG_TRANSFER: "false"}
    scored = str(cfg.dataset)
    train_ds = str(train_ds or scored)
    train_cfg = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    train_cfg.dataset = train_ds
    train_layout = Layout(layout_from_cfg(cfg).out_root, train_ds)
    try:
        manifest = Manifest.read(train_layout.manifest)
    except (OSError, SkidbenchError) as exc:
        raise EvaluationError(
            f"train_dataset={train_ds}: no dataset at {train_layout.root} ({one_line(str(exc))[:200]}); "
            "`skidbench datasets` lists them"
        ) from None
    if manifest.robot != str(cfg.robot.name):
        raise EvaluationError(
            f"train_dataset={train_ds} holds robot {manifest.robot}, the scored dataset {scored} robot="
            f"{cfg.robot.name}: a transfer needs the same robot"
        )
    terrains = split_terrains(manifest)
    if train_terrain is None and len(terrains) == 1:
        train_terrain = terrains[0]
    if train_terrain is not None and str(train_terrain) not in terrains:
        raise EvaluationError(
            f"train_terrain={train_terrain}: not a terrain of dataset {train_ds} (it has {terrains})"
        )

    def fit_on_training(_cfg: Any, model: str, terrain: str) -> Any:
        return fit_fn(train_cfg, model, str(train_terrain) if train_terrain is not None else terrain)

    out = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    default_experiment = f"skidbench-{scored}"
    if str(out.mlflow.experiment) == default_experiment:
        out.mlflow.experiment = f"{default_experiment}-transfer"
    tags = {
        TAG_TRANSFER: "true",
        TAG_TRAIN_DATASET: train_ds,
        TAG_TRAIN_TERRAIN: str(train_terrain) if train_terrain is not None else "(same as scored)",
    }
    return out, fit_on_training, tags
