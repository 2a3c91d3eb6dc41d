"""In-process entry points for the stages that consume splits (``evaluate``, ``discover``).

:func:`prepare_splits` runs extract -> groundtruth -> split for the configured source, skipping a stage
whose outputs exist and are newer than its inputs (by modification time; content-fingerprint caching
comes later). A config that lacks a stage's section (``groundtruth``, ``split``, ``extract``) gets the
defaults of that stage's primary config.
"""

from __future__ import annotations

import logging
from pathlib import Path

from omegaconf import DictConfig, OmegaConf, open_dict

from .layout import layout_from_cfg

log = logging.getLogger("skidbench.api")

CONF = Path(__file__).resolve().parents[1] / "conf"


def _with_stage(cfg: DictConfig, stage: str) -> DictConfig:
    """``cfg`` plus the stage's own section from ``conf/<stage>.yaml`` when ``cfg`` lacks it."""
    if stage in cfg:
        return cfg
    import importlib.resources

    text = (importlib.resources.files("skidbench.conf") / f"{stage}.yaml").read_text()
    section = OmegaConf.create(text).get(stage)
    out = cfg.copy()
    with open_dict(out):
        out[stage] = section
    return out


def _newest(paths) -> float:
    times = [p.stat().st_mtime for p in paths if p.exists()]
    return max(times) if times else 0.0


def _oldest(paths) -> float:
    times = [p.stat().st_mtime for p in paths]
    return min(times) if times else 0.0


def _source_inputs(cfg: DictConfig, layout) -> list[Path]:
    src = cfg.source
    root = Path(str(src.get("root", layout.raw))).expanduser()
    if src.get("file"):
        return [root / str(src.file)]
    if root.is_file():
        return [root]
    return [p for p in root.rglob("*") if p.is_file()] if root.is_dir() else []


def prepare_splits(cfg: DictConfig) -> Path:
    """Make ``<ds>/splits`` up to date for ``cfg.source``; returns the splits folder."""
    from .groundtruth import app as gt_app
    from .splits import app as split_app

    layout = layout_from_cfg(cfg)
    inputs = _source_inputs(cfg, layout)
    extracted = list(layout.extracted.glob("*/_extract.json"))
    if not extracted or not layout.manifest.is_file() or _oldest(extracted) < _newest(inputs):
        from .extract.app import run as extract

        log.info("prepare_splits: extract")
        extract(_with_stage(cfg, "extract"))
        extracted = list(layout.extracted.glob("*/_extract.json"))
    gt_out = [layout.groundtruth / "loop_closure.json"]
    gt_in = [p for p in layout.extracted.rglob("*") if p.is_file()]
    if not gt_out[0].is_file() or _oldest(gt_out) < _newest(gt_in):
        log.info("prepare_splits: groundtruth")
        gt_app.run(_with_stage(cfg, "groundtruth"))
    split_out = [layout.splits / "card.md"]
    split_in = [p for p in layout.groundtruth.glob("*") if p.is_file()]
    if not split_out[0].is_file() or _oldest(split_out) < _newest(split_in):
        log.info("prepare_splits: split")
        split_app.run(_with_stage(cfg, "split"))
    return layout.splits
