"""What evaluate reads of the config. :class:`EvaluateOptions` declares evaluate's own root keys (``models``,
``horizons``, ...: their types, defaults and ranges; stored in Hydra's ConfigStore as
``schema/root/evaluate``, ``pipeline/cli/config_schema.py``, and checked as Hydra composes). The evaluate app
makes :class:`EvaluateSettings` once (:meth:`EvaluateSettings.from_cfg`), reading each key and section once:
the dataset's layout, the models, terrains, splits and horizons, the windows and intervals, the input
protocol, the fit, transfer, report-data settings, the MLflow store (:class:`StoreSettings`) and the config
as plain data the parent run's params are logged from. :func:`~skidbench.benchmark.evaluate.evaluation.
run_benchmark` takes it. This module imports nothing heavy at its top (the schema is registered before
every composition).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from skidbench.benchmark.report.settings import ReportDataSettings
from skidbench.benchmark.scoring.settings import IntervalConfig, StateSettings
from skidbench.benchmark.tracking.settings import StoreSettings
from skidbench.pipeline.core.layout import CommonSettings, Layout, root_from_cfg
from skidbench.pipeline.core.manifest import SPLITS

if TYPE_CHECKING:
    from skidbench.benchmark.board.results import RunFacts
    from skidbench.benchmark.evaluate.transfer import TransferSettings
    from skidbench.benchmark.scoring.horizon import HorizonConfig
    from skidbench.benchmark.tracking import store as trk
    from skidbench.models.fitting.fit import FitSettings

BUILT_IN = ["ideal", "edd", "full_linear", "roc", "enhanced", "friction", "drive_blr", "gp_residual"]


@dataclass(frozen=True)
class EvaluateOptions:
    """evaluate's own root keys (``conf/evaluate.yaml`` lists their schema, ``/schema/root/evaluate``)."""

    # any installed model (`skidbench models`)
    models: list[str] = field(default_factory=lambda: list(BUILT_IN), metadata={"min_len": 1})
    # evaluated after `models`: extra_models=[myplugin] adds a plugin to the default list
    extra_models: list[str] = field(default_factory=list)
    # null: every terrain of the dataset's manifest (raw/manifest.json)
    terrains: list[str] | None = field(default=None, metadata={"min_len": 1})
    # test splits (Train is for fitting)
    splits: list[str] = field(
        default_factory=lambda: ["cv", "ld"], metadata={"min_len": 1, "item": {"choices": SPLITS}}
    )
    # the first is the board's (the paper's 6 s), the others the error-against-horizon curve (compare:
    # reports/horizons.md)
    horizons: list[float] = field(
        default_factory=lambda: [6.0, 0.5, 1.0, 2.0, 4.0],
        metadata={"min_len": 1, "item": {"gt": 0}, "what": "s"},
    )
    # windows that travel less in 6 s are left out of the translational RMSRE (scaled: h/6 s of it at
    # horizon h)
    min_distance_m: float = field(default=0.5, metadata={"lo": 0, "what": "m"})
    # windows that turn less in 6 s are left out of the rotational RMSRE (scaled as min_distance_m)
    min_rotation_deg: float = field(default=10.0, metadata={"lo": 0, "what": "deg"})
    log_figures: bool = True  # a per-window error figure per (model, terrain) as a run artifact
    # fits per model with random parts (a `seed` option: gp_residual, plugins declaring one), seeds seed,
    # seed+1, ...; >1: each cell reports the spread over seeds
    seeds: int = field(default=1, metadata={"lo": 1, "hi": 100})
    force: bool = False  # true: re-run even when the inputs (splits, fits, config) are unchanged
    # transfer (benchmark/evaluate/transfer.py): fit on another dataset's (same robot) and/or terrain's Train
    # split and score this dataset's CV/LD; its runs go to the experiment <experiment>-transfer
    train_dataset: str | None = field(default=None, metadata={"what": "a dataset under out_root to fit on"})
    train_terrain: str | None = field(
        default=None, metadata={"what": "the terrain of train_dataset to fit on"}
    )

    @property
    def all_models(self) -> list[str]:
        """``models``, then each of ``extra_models`` not among them (``extra_models=[myplugin]``: the default
        list and a plugin, without retyping the list)."""
        return list(dict.fromkeys(str(m) for m in [*self.models, *self.extra_models]))


@dataclass(frozen=True)
class EvaluateSettings:
    """What :func:`~skidbench.benchmark.evaluate.evaluation.run_benchmark` reads of the config. With a
    transfer (``train_dataset``/``train_terrain``) it is the scored runs' config: the transfer experiment
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
    log_figures: bool
    seeds: int
    fit: FitSettings
    transfer: TransferSettings
    report_data: ReportDataSettings
    store: StoreSettings  # benchmark/tracking/settings.py
    conf: dict[str, Any]  # the config as plain data (resolved): the parent run's params
    state: StateSettings = StateSettings()  # noqa: RUF009 (frozen) the ``state`` protocol's windows (``state.*``)
    force: bool = False  # run every model again, even one whose earlier run is unchanged (evaluate/reuse.py)

    @classmethod
    def from_cfg(cls, cfg: Any) -> EvaluateSettings:
        """Each key and section of ``cfg`` read once: evaluate's root keys (:class:`EvaluateOptions`), the
        common ones (``inputs``, ...) and the typed sections (``intervals``, ``report_data``, ``state``)."""
        from omegaconf import OmegaConf

        from skidbench.benchmark.evaluate.transfer import TransferSettings, scored_from_cfg
        from skidbench.benchmark.scoring.horizon import HorizonConfig
        from skidbench.benchmark.scoring.intervals import block_length
        from skidbench.models.fitting.fit import FitSettings

        opts, common = root_from_cfg(cfg, EvaluateOptions), root_from_cfg(cfg, CommonSettings)
        models, horizons = opts.all_models, [float(h) for h in opts.horizons]
        intervals = OmegaConf.to_object(cfg.intervals)
        for h in horizons:  # blocks shorter than a horizon: one line before anything runs
            block_length(intervals, h)
        protocol = _checked_protocol(common.inputs, models)
        fit = FitSettings.from_cfg(cfg, common, models)
        transfer = TransferSettings(opts.train_dataset, opts.train_terrain, common.dataset,
                                    str(cfg.robot.name), str(cfg.mlflow.experiment))  # fmt: skip
        cfg = scored_from_cfg(cfg, transfer)
        hcfg = HorizonConfig(horizons[0], opts.min_distance_m, math.radians(opts.min_rotation_deg))
        return cls(
            fit.layout, common.dataset, models, opts.terrains or None, list(opts.splits), horizons, hcfg,
            intervals, protocol, opts.log_figures, opts.seeds, fit, transfer,
            OmegaConf.to_object(cfg.report_data), StoreSettings.from_cfg(cfg, fit.layout),
            _container_from_cfg(cfg), OmegaConf.to_object(cfg.state), opts.force,
        )  # fmt: skip

    def row_facts(
        self, evaluate_id: str, tracker: trk.Tracker, env_tags: dict[str, str], commit: str
    ) -> RunFacts:
        """What every row of an evaluate's results table carries (benchmark/board/results.py): the
        settings it scores with, the dataset and the environment (``env_tags``: the run tags of
        :func:`skidbench.pipeline.runner.environment.run_tags`)."""
        from skidbench.benchmark.board.results import RunFacts
        from skidbench.benchmark.tracking import tags as run_tags

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


def _checked_protocol(inputs: str, models: list[str]) -> str:
    """The run's input protocol (``inputs``); EvaluationError (one line) for a bad one, or the floor named a
    model."""
    from skidbench.benchmark.errors import EvaluationError
    from skidbench.benchmark.scoring.floor import FLOOR
    from skidbench.pipeline.core.protocol import ProtocolError, check_protocol

    if FLOOR in models:
        raise EvaluationError(f"models=[...]: {FLOOR!r} is the reference row (a perfect model against "
                              "the ground truth, on every board), not a model name")  # fmt: skip
    try:
        return check_protocol(inputs)
    except ProtocolError as exc:
        raise EvaluationError(str(exc)) from None


def _container_from_cfg(cfg: Any) -> dict[str, Any]:
    """The config as plain data (resolved): what the parent run's params are logged from."""
    from omegaconf import OmegaConf

    if OmegaConf.is_config(cfg):
        return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]
    return dict(cfg)
