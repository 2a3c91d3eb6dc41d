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

import copy
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from omegaconf import OmegaConf, open_dict

from skidbench.benchmark.errors import EvaluationError
from skidbench.models.fitting.fit import FitSettings
from skidbench.pipeline.core.errors import SkidbenchError, one_line
from skidbench.pipeline.core.layout import Layout, split_terrains
from skidbench.pipeline.core.manifest import Manifest

TAG_TRANSFER = "skidbench.transfer"
TAG_TRAIN_DATASET = "skidbench.train_dataset"
TAG_TRAIN_TERRAIN = "skidbench.train_terrain"


@dataclass(frozen=True)
class TransferSettings:
    """What a transfer reads of the config: the training dataset and terrain (None: the scored ones), the
    scored dataset, its robot and the configured MLflow experiment
    (:meth:`~skidbench.benchmark.evaluate.settings.EvaluateSettings.from_cfg` makes it)."""

    train_dataset: str | None
    train_terrain: str | None
    scored: str
    robot: str
    experiment: str

    @property
    def on(self) -> bool:
        return bool(self.train_dataset or self.train_terrain)

    @property
    def scored_experiment(self) -> str:
        """The experiment the scored runs go to: ``<experiment>-transfer`` when the configured one is the
        default ``skidbench-<dataset>``."""
        default = f"skidbench-{self.scored}"
        return f"{default}-transfer" if self.on and self.experiment == default else self.experiment


def scored_from_cfg(cfg: Any, ts: TransferSettings) -> Any:
    """The door from the config to the scored runs' config: unchanged without a transfer, else (resolved)
    with the transfer experiment (:attr:`TransferSettings.scored_experiment`)."""
    if not ts.on:
        return cfg
    out = copy.deepcopy(cfg)  # its typed sections stay typed (OmegaConf.to_object gives their dataclasses)
    OmegaConf.resolve(out)
    with open_dict(out):
        out.mlflow.experiment = ts.scored_experiment
    return out


def training_layout(
    ts: TransferSettings, fit: FitSettings, fit_fn: Callable[[FitSettings, str, str], Any]
) -> tuple[Callable[[FitSettings, str, str], Any], dict[str, str]]:
    """``(fit_fn, tags)`` for :func:`~skidbench.benchmark.evaluate.evaluation.run_benchmark`: unchanged (tags
    ``skidbench.transfer=false``) without ``train_dataset``/``train_terrain``; else a ``fit_fn`` that fits
    with the training dataset's settings (its layout and calibrations; ``fit`` otherwise) on the training
    terrain, and the transfer tags. EvaluationError (one line) when the training dataset is absent, of
    another robot, or lacks the terrain."""
    if not ts.on:
        return fit_fn, {TAG_TRANSFER: "false"}
    scored = ts.scored
    train_ds = ts.train_dataset or scored
    train_terrain = ts.train_terrain
    train_layout = Layout(fit.layout.out_root, train_ds)
    try:
        manifest = Manifest.read(train_layout.manifest)
    except (OSError, SkidbenchError) as exc:
        raise EvaluationError(
            f"train_dataset={train_ds}: no dataset at {train_layout.root} ({one_line(str(exc))[:200]}); "
            "`skidbench datasets` lists them"
        ) from None
    if manifest.robot != ts.robot:
        raise EvaluationError(
            f"train_dataset={train_ds} holds robot {manifest.robot}, the scored dataset {scored} robot="
            f"{ts.robot}: a transfer needs the same robot"
        )
    terrains = split_terrains(manifest)
    if train_terrain is None and len(terrains) == 1:
        train_terrain = terrains[0]
    if train_terrain is not None and str(train_terrain) not in terrains:
        raise EvaluationError(
            f"train_terrain={train_terrain}: not a terrain of dataset {train_ds} (it has {terrains})"
        )
    train_fit = replace(fit, layout=train_layout, calibrations=replace(fit.calibrations, layout=train_layout))

    def fit_on_training(_fit: FitSettings, model: str, terrain: str) -> Any:
        return fit_fn(train_fit, model, str(train_terrain) if train_terrain is not None else terrain)

    tags = {
        TAG_TRANSFER: "true",
        TAG_TRAIN_DATASET: train_ds,
        TAG_TRAIN_TERRAIN: str(train_terrain) if train_terrain is not None else "(same as scored)",
    }
    return fit_on_training, tags
