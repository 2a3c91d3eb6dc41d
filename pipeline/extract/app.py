"""``skidbench extract``: every sequence of the configured source -> ``<ds>/extracted/<seq>/``.

Dispatches on ``source.kind``: ``bag`` (the simulated dataset and a user's own bags) is handled here;
any other kind (``amrl_txt``, ``drive_df``, ...) by ``skidbench.pipeline.sources.<kind>.extract_source``.
"""

from __future__ import annotations

import dataclasses
import importlib
import logging
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from ..cli import stage
from ..errors import ConfigError
from ..layout import Layout, layout_from_cfg, prune_stale
from ..manifest import Manifest
from .bag import ExtractOptions, extract_bag
from .inspect import auto_specs
from .reader import bag_format, discover_sequences, topic_specs

log = logging.getLogger("skidbench.extract")
AUTO = "auto"  # source.topics=auto: each bag's topics chosen by `skidbench inspect`'s proposal


def options_from_cfg(cfg: DictConfig) -> ExtractOptions:
    ext = OmegaConf.to_container(cfg.extract, resolve=True)
    return ExtractOptions(
        images=str(ext["images"]),
        batch_rows=int(ext["batch_rows"]),
        batch_bytes=int(ext["batch_bytes"]),
        force=bool(ext["force"]),
        progress=bool(ext["progress"]),
        typestores=dict(ext["typestores"]),
    )


def extract_bags(cfg: DictConfig, layout: Layout) -> list[dict[str, Any]]:
    """Extract every sequence of a bag source; returns the ``_extract.json`` records in order.

    For a user's bags (no ``manifest.json`` in ``source.root``) the manifest built from the folder tree
    is written to ``<ds>/raw/manifest.json``, so later stages find terrain and category the same way for
    every source.
    """
    source = OmegaConf.to_container(cfg.source, resolve=True)
    topics = source.get("topics") or {}
    auto = topics == AUTO
    if isinstance(topics, str) and not auto:
        raise ConfigError(f"source.topics={topics!r}: expected {AUTO!r} or a mapping of topic keys")
    specs = None if auto else topic_specs(topics)
    if not auto and not specs:
        raise ConfigError("source.topics is empty: nothing to extract")
    opts = options_from_cfg(cfg)
    manifest, found = discover_sequences(source)
    if not found:  # paths made absolute: the manifest is written away from the bags
        seqs = [dataclasses.replace(s, path=str(manifest.resolve(s))) for s in manifest.sequences]
        formats = {bag_format(Path(s.path)) for s in seqs}
        fmt = formats.pop() if len(formats) == 1 else "mixed"
        Manifest(seqs, format=fmt or "ros1", base=layout.raw).write(layout.manifest)
    elif manifest.base.resolve() != layout.raw.resolve():  # a user's manifest.json: the current one is ours
        seqs = [dataclasses.replace(s, path=str(manifest.resolve(s))) for s in manifest.sequences]
        Manifest(seqs, manifest.robot, manifest.format, base=layout.raw).write(layout.manifest)
    records = []
    seqs = manifest.sequences
    for seq in tqdm(seqs, desc="extract", unit="bag", disable=not opts.progress or len(seqs) < 2):
        meta = {"sequence": seq.name, "terrain": seq.terrain, "category": seq.category}
        bag = manifest.resolve(seq)
        seq_specs = auto_specs(bag, opts.typestores) if auto else specs
        info = extract_bag(bag, layout.extracted / seq.name, seq_specs, opts, meta)
        verb = "up to date" if info.get("skipped") else "extracted"
        counts = ", ".join(f"{k} {v['count']}" for k, v in info["topics"].items())
        log.info("%s %s: %s", verb, seq.name, counts)
        records.append(info)
    n_skipped = sum(bool(r.get("skipped")) for r in records)
    if records and n_skipped == len(records):
        log.info("extract: %d sequences up to date, skipped", len(records))
    return records


def run(cfg: DictConfig) -> Any:
    """Extract the configured source into ``<out_root>/<dataset>/extracted``."""
    layout = layout_from_cfg(cfg)
    kind = str(cfg.source.get("kind", "bag"))
    if kind == "bag":
        records = extract_bags(cfg, layout)
    else:
        try:
            module = importlib.import_module(f"skidbench.pipeline.sources.{kind}")
        except ImportError as exc:
            raise ConfigError(f"source.kind={kind!r}: no reader for this kind of source ({exc})") from exc
        records = module.extract_source(cfg, layout)
    # the manifest just written is the current one: outputs of sequences it lacks go, and the identity
    # record (pipeline/dataset.py) lists its terrains
    from ..dataset import identity_from_cfg, record

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
