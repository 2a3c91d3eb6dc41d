"""``skidbench fit``'s own root keys (``conf/fit.yaml``): :class:`FitOptions` is their schema and defaults
(stored in Hydra's ConfigStore as ``schema/root/fit``, ``pipeline/cli/config_schema.py``); the app reads
them once, ``root_from_cfg(cfg, FitOptions)``. Imports nothing heavy (the schema is registered before every
composition)."""

from __future__ import annotations

from dataclasses import dataclass, field

from skidbench.pipeline.core.manifest import SPLITS


@dataclass(frozen=True)
class FitOptions:
    """The terrain fitted (its folder under ``<out_root>/<dataset>/splits/``; ``conf/fit.yaml`` makes it
    mandatory), the split fitted on, ``reuse`` (skip a fit whose stamp, i.e. split files, model config and
    version, robot, is up to date) and ``track`` (log one MLflow run per fit, tagged model, terrain and
    sweep id; a skipped fit logs none)."""

    terrain: str | None = None
    split: str = field(default="train", metadata={"choices": SPLITS})
    reuse: bool = True
    track: bool = True
