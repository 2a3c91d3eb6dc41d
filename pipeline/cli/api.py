"""In-process entry points for the stages that consume splits (``evaluate``, ``discover``).

:func:`prepare_splits` runs extract -> groundtruth -> split for the configured source, each stage
skipping the sequences whose content-fingerprint stamps are up to date. A config that lacks a stage's
section (``groundtruth``, ``split``, ``extract``) gets the defaults of that stage's primary config.
"""

from __future__ import annotations

import importlib.resources
import logging
from pathlib import Path

from omegaconf import DictConfig, OmegaConf, open_dict

from skidbench.pipeline.core.layout import layout_from_cfg

log = logging.getLogger("skidbench.api")

CONF = Path(__file__).resolve().parents[1] / "conf"


def _with_stage(cfg: DictConfig, stage: str) -> DictConfig:
    """``cfg`` plus the stage's own section when ``cfg`` lacks it: its settings dataclass's defaults
    (:data:`~skidbench.pipeline.cli.config_schema.STRUCTURED`, the schema ``conf/<stage>.yaml`` lists)
    with the values ``conf/<stage>.yaml`` sets over them."""
    from skidbench.pipeline.cli.config_schema import STRUCTURED, schema_node

    if stage in cfg:
        return cfg

    text = (importlib.resources.files("skidbench.conf") / f"{stage}.yaml").read_text()
    section = OmegaConf.create(text).get(stage)
    if stage in STRUCTURED:
        node = schema_node(STRUCTURED[stage])
        section = node if section is None else OmegaConf.merge(node, section)
    out = cfg.copy()
    with open_dict(out):
        out[stage] = section
    return out


def prepare_splits(cfg: DictConfig) -> Path:
    """Make ``<ds>/splits`` up to date for ``cfg.source``; returns the splits folder. Each stage skips
    the units whose stamps (:mod:`skidbench.pipeline.core.cache`) say they are up to date, so a changed input
    or config re-runs exactly what depends on it."""
    from skidbench.pipeline.extract.app import run as extract
    from skidbench.pipeline.groundtruth import app as gt_app
    from skidbench.pipeline.splits import app as split_app

    layout = layout_from_cfg(cfg)
    extract(_with_stage(cfg, "extract"))
    gt_app.run(_with_stage(cfg, "groundtruth"))
    split_app.run(_with_stage(cfg, "split"))
    return layout.splits


def prepare_calibration(cfg: DictConfig) -> list[str]:
    """Make ``<ds>/calibration/<terrain>.json`` up to date for every terrain with Train files (the
    ``calibrate`` stage's computation, :func:`skidbench.pipeline.calibrate.calibration.calibrate_terrain`,
    skipped
    per terrain while its stamp is current; no MLflow run). For a one-command run from a raw source
    (``skidbench discover source=...``) after :func:`prepare_splits`. Returns the terrains."""
    from skidbench.pipeline.calibrate.calibration import calibrate_terrain, train_files
    from skidbench.pipeline.core.robot import robot_from_hydra

    layout = layout_from_cfg(cfg)
    spec, settings = robot_from_hydra(cfg.robot), OmegaConf.to_object(cfg.calibrate)
    terrains = sorted({p.parents[1].name for p in train_files(layout)})
    for terrain in terrains:
        calibrate_terrain(layout, terrain, spec, settings, str(cfg.dataset))
    return terrains
