"""What evaluate reads of the config, made once by the evaluate app (:meth:`EvaluateSettings.from_cfg`):
the dataset's layout, the models, terrains, splits and horizons, the windows and intervals, the input
protocol, the fit, transfer, report-data settings, the MLflow store (:class:`StoreSettings`) and the
config as plain data the parent run's params are logged from. :func:`~skidbench.benchmark.evaluate.evaluation.
run_benchmark` takes it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import OmegaConf

from skidbench.benchmark.board.results import RunFacts
from skidbench.benchmark.errors import EvaluationError
from skidbench.benchmark.evaluate.transfer import TransferSettings, scored_from_cfg
from skidbench.benchmark.report.settings import ReportDataSettings
from skidbench.benchmark.scoring.floor import FLOOR
from skidbench.benchmark.scoring.horizon import HorizonConfig
from skidbench.benchmark.scoring.intervals import block_length
from skidbench.benchmark.scoring.settings import IntervalConfig, StateSettings
from skidbench.benchmark.tracking import store as trk
from skidbench.benchmark.tracking import tags as run_tags
from skidbench.models.fitting.fit import FitSettings, ModelConfigs
from skidbench.pipeline.core.layout import Layout, layout_from_cfg
from skidbench.pipeline.core.protocol import ProtocolError, check_protocol


@dataclass(frozen=True)
class StoreSettings:
    """The MLflow store and experiment of a run (``mlflow.*``): what :func:`tracking.tracker_from_cfg`
    reads, opened later (:meth:`open`) so that an unreachable store is reported where the stage meets it."""

    uri: str
    experiment: str
    artifact_root: Path
    timeout_s: float
    dataset_id: str | None
    out_root: Any

    @classmethod
    def from_cfg(cls, cfg: Any, layout: Layout) -> StoreSettings:
        node = cfg.mlflow
        dataset_id = None
        if cfg.get("source") is not None:
            from skidbench.pipeline.datasets.identity import identity_from_cfg

            dataset_id = identity_from_cfg(cfg).fingerprint
        return cls(
            trk.tracking_uri_from_cfg(cfg, layout),
            str(node.experiment),
            Path(str(node.get("artifact_root") or layout.mlflow_artifacts)),
            float(node.get("timeout_s", 5.0)),
            dataset_id,
            cfg.get("out_root"),
        )

    def open(self) -> trk.Tracker:
        """The tracker (its dead runs reaped); EvaluationError (one line) for a store that cannot be
        opened."""
        return trk.open_tracker(self.uri, self.experiment, artifact_root=self.artifact_root,
                                timeout_s=self.timeout_s, dataset_id=self.dataset_id,
                                out_root=self.out_root)  # fmt: skip


@dataclass(frozen=True)
class EvaluateSettings:
    """What :func:`~skidbench.benchmark.evaluate.evaluation.run_benchmark` reads of the config. With a
    transfer
    (``train_dataset``/``train_terrain``) it is the scored runs' config: the transfer experiment
    (:func:`transfer.scored_from_cfg`)."""

    layout: Layout
    dataset: str
    models: list[str]
    terrains: list[str] | None
    splits: list[str]
    horizons: list[float]
    hcfg: HorizonConfig
    intervals: IntervalConfig
    protocol: str  # the checked input protocol (``inputs``)
    inputs_text: str  # ``inputs`` as the config spells it (``commanded`` when the key is absent)
    log_figures: bool
    seeds: int
    fit: FitSettings
    transfer: TransferSettings
    report_data: ReportDataSettings
    store: StoreSettings
    conf: dict[str, Any]  # the config as plain data (resolved): the parent run's params
    state: StateSettings = StateSettings()  # noqa: RUF009 (frozen) the ``state`` protocol's windows (``state.*``)
    force: bool = False  # run every model again, even one whose earlier run is unchanged (evaluate/reuse.py)

    @classmethod
    def from_cfg(cls, cfg: Any) -> EvaluateSettings:
        models, terrains, splits, horizons, hcfg = _lists_from_cfg(cfg)
        intervals = OmegaConf.to_object(cfg.intervals)
        for h in horizons:  # blocks shorter than a horizon: one line before anything runs
            block_length(intervals, h)
        protocol = _checked_protocol(cfg.get("inputs"), models)
        transfer = TransferSettings.from_cfg(cfg)
        fit = FitSettings.from_cfg(cfg)
        cfg = scored_from_cfg(cfg, transfer)
        layout = layout_from_cfg(cfg)
        return cls(
            layout, str(cfg.dataset), models, terrains, splits, horizons, hcfg, intervals,
            protocol, str(cfg.get("inputs", "commanded")), bool(cfg.get("log_figures", True)),
            int(cfg.get("seeds") or 1),
            fit, transfer, OmegaConf.to_object(cfg.report_data), StoreSettings.from_cfg(cfg, layout),
            _container_from_cfg(cfg), OmegaConf.to_object(cfg.state), bool(cfg.get("force", False)),
        )  # fmt: skip

    def row_facts(
        self, evaluate_id: str, tracker: trk.Tracker, env_tags: dict[str, str], commit: str
    ) -> RunFacts:
        """What every row of an evaluate's results table carries (benchmark/board/results.py): the
        settings it scores with, the dataset and the environment (``env_tags``: the run tags of
        :func:`skidbench.pipeline.runner.environment.run_tags`)."""
        env = "skidbench.env."
        return RunFacts(
            evaluate_id=evaluate_id, run_id="", model="", inputs=self.protocol, terrain="",
            min_distance_m=float(self.hcfg.min_distance_m),
            min_rotation_deg=float(self.conf["min_rotation_deg"]), horizons=list(self.horizons),
            splits=list(self.splits), models=list(self.models), dataset=self.dataset,
            dataset_id=tracker.dataset_id or "", experiment=tracker.experiment_name,
            skidbench_version=env_tags.get("skidbench.version", ""), git_commit=commit,
            versions={k[len(env):]: str(v) for k, v in env_tags.items() if k.startswith(env)},
            user=run_tags.current_user(),
        )  # fmt: skip


def models_from_cfg(cfg: Any) -> list[str]:
    """The models an evaluate evaluates (models/fitting/fit.py ``ModelConfigs``): ``models``, then each of
    ``extra_models`` not among them (``extra_models=[myplugin]``: the default list and a plugin, without
    retyping the list)."""
    return list(ModelConfigs.from_cfg(cfg).models or ())


def _lists_from_cfg(cfg: Any) -> tuple[list[str], list[str] | None, list[str], list[float], HorizonConfig]:
    models = models_from_cfg(cfg)
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


def _checked_protocol(inputs: str | None, models: list[str]) -> str:
    """The run's input protocol (``inputs``; ``commanded`` when unset); EvaluationError (one line) for a bad
    one, or the floor named a model."""
    if FLOOR in models:
        raise EvaluationError(f"models=[...]: {FLOOR!r} is the reference row (a perfect model against "
                              "the ground truth, on every board), not a model name")  # fmt: skip
    try:
        return check_protocol(inputs if inputs is not None else "commanded")
    except ProtocolError as exc:
        raise EvaluationError(str(exc)) from None


def _container_from_cfg(cfg: Any) -> dict[str, Any]:
    """The config as plain data (resolved): what the parent run's params are logged from."""
    try:
        from omegaconf import OmegaConf

        if OmegaConf.is_config(cfg):
            return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]
    except ImportError:  # pragma: no cover
        pass
    return dict(cfg)
