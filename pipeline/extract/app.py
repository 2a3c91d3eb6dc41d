"""``skidbench extract``: every sequence of the configured source -> ``<ds>/extracted/<seq>/``.

``source.kind`` names the source: an entry point of the group ``skidbench.sources``
(:mod:`skidbench.pipeline.sources.registry`; the built-in ``bag``, ``amrl_txt`` and ``drive_df`` and any
installed plugin). The app turns the config into what a source takes (docs/sources.md): its settings
object (from ``source.*``) and a context (the robot, the dataset's folders, the ``extract.*`` options).
"""

from __future__ import annotations

import logging
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from skidbench.pipeline.cli.main import stage
from skidbench.pipeline.core.layout import layout_from_cfg, prune_stale
from skidbench.pipeline.core.manifest import Manifest
from skidbench.pipeline.core.robot import robot_from_hydra
from skidbench.pipeline.datasets.identity import identity_from_cfg, record
from skidbench.pipeline.sources import registry
from skidbench.pipeline.sources.contract import SourceContext

log = logging.getLogger("skidbench.extract")


def source_section(cfg: DictConfig) -> dict[str, Any]:
    """``cfg.source`` as a plain mapping (a mandatory value still unset stays ``???``)."""
    return OmegaConf.to_container(cfg.source, resolve=True, throw_on_missing=False)


def run(cfg: DictConfig) -> Any:
    """Extract the configured source into ``<out_root>/<dataset>/extracted``."""
    layout = layout_from_cfg(cfg)
    source, settings = registry.load(source_section(cfg))
    options = OmegaConf.to_object(cfg.extract)
    ctx = SourceContext(robot=robot_from_hydra(cfg.robot), layout=layout, options=options)
    records = source.extract(settings, ctx)
    # the manifest just written is the current one: outputs of sequences it lacks go, and the identity
    # record (pipeline/datasets/identity.py) lists its terrains
    removed = prune_stale(layout, Manifest.read(layout.manifest))
    if removed:
        log.info("extract: removed %d output(s) of sequences no longer in %s", len(removed), layout.manifest)
    record(layout, identity_from_cfg(cfg))
    return records


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="extract")
@stage("extract")
def main(cfg: DictConfig) -> None:
    run(cfg)
    print(f"extracted: {layout_from_cfg(cfg).extracted}")
