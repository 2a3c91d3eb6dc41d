"""``source.kind=bag``: ROS1/ROS2/MCAP bags (the simulated dataset and a user's own), one sequence per bag.

Registered in the entry-point group ``skidbench.sources`` like any other source; it subclasses
:class:`~skidbench.pipeline.sources.contract.Source` rather than ``TableSource`` because it streams each
bag's topics to Parquet (images included) instead of reading whole tables (:func:`.bag.extract_bag`).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from skidbench.pipeline.core.errors import ConfigError
from skidbench.pipeline.core.manifest import Manifest
from skidbench.pipeline.runner.tasks import map_items
from skidbench.pipeline.sources.contract import Source, SourceContext

log = logging.getLogger("skidbench.extract")
AUTO = "auto"  # source.topics=auto: each bag's topics chosen by `skidbench inspect`'s proposal
COMMANDS = "cmd_vel"  # the topic key of the commands: what drives every model, so every bag needs it


@dataclass(frozen=True)
class BagSettings:
    """``source.*`` of a bag source (conf/source/bag.yaml, sim.yaml): where the bags are, which topics
    play which role (a mapping of topic keys, or ``auto``), and the terrain and category of a single bag
    or of bags not under ``<terrain>/<category>/``."""

    root: str
    topics: Any = None
    terrain: str | None = None
    category: str | None = None


class BagSource(Source):
    """Every bag under ``root`` (or the one bag ``root`` is) -> ``<ds>/extracted/<seq>/``."""

    kind = "bag"
    Settings = BagSettings

    def extract(self, settings: BagSettings, ctx: SourceContext) -> list[dict[str, Any]]:
        """Extract every sequence of a bag source; returns the ``_extract.json`` records in order.

        For a user's bags (no ``manifest.json`` in ``root``) the manifest built from the folder tree is
        written to ``<ds>/raw/manifest.json``, so later stages find terrain and category the same way for
        every source."""
        # deferred: the bag readers (rosbags) take seconds to import, and every stage loads this class
        # to check its settings (pipeline/datasets/identity.py)
        from skidbench.pipeline.extract.reader import bag_format, discover_sequences, topic_specs

        layout, opts = ctx.layout, ctx.options
        topics = settings.topics or {}
        auto = topics == AUTO
        if isinstance(topics, str) and not auto:
            raise ConfigError(f"source.topics={topics!r}: expected {AUTO!r} or a mapping of topic keys")
        specs = None if auto else topic_specs(topics)
        if not auto and not specs:
            raise ConfigError("source.topics is empty: nothing to extract")
        if not auto:
            check_commands(specs)
        manifest, found = discover_sequences(dataclasses.asdict(settings))
        if not found:  # paths made absolute: the manifest is written away from the bags
            seqs = [dataclasses.replace(s, path=str(manifest.resolve(s))) for s in manifest.sequences]
            formats = {bag_format(Path(s.path)) for s in seqs}
            fmt = formats.pop() if len(formats) == 1 else "mixed"
            Manifest(seqs, format=fmt or "ros1", base=layout.raw).write(layout.manifest)
        elif manifest.base.resolve() != layout.raw.resolve():  # a user's manifest.json: ours is current
            seqs = [dataclasses.replace(s, path=str(manifest.resolve(s))) for s in manifest.sequences]
            Manifest(seqs, manifest.robot, manifest.format, base=layout.raw).write(layout.manifest)
        seqs = manifest.sequences
        # one bar, over the bags: the workers' per-bag message bars would overwrite each other
        bag_opts = dataclasses.replace(opts, progress=False) if len(seqs) > 1 else opts
        calls = []
        for seq in seqs:
            meta = {"sequence": seq.name, "terrain": seq.terrain, "category": seq.category}
            bag = manifest.resolve(seq)
            calls.append((bag, layout.extracted / seq.name, specs, auto, bag_opts, meta))

        def done(i: int, info: dict[str, Any]) -> None:
            verb = "up to date" if info.get("skipped") else "extracted"
            counts = ", ".join(f"{k} {v['count']}" for k, v in info["topics"].items())
            log.info("%s %s: %s", verb, seqs[i].name, counts)

        # the bags are independent (each its own tables and stamp): tasks (pipeline/tasks.py), forked
        # workers one per core, or Ray tasks on a cluster; each streams its bag to its tables
        names = [seq.name for seq in seqs]
        records = map_items(
            _extract_one, calls, names, what="extract", unit="bag", done=done, progress=opts.progress
        )
        n_skipped = sum(bool(r.get("skipped")) for r in records)
        if records and n_skipped == len(records):
            log.info("extract: %d sequences up to date, skipped", len(records))
        return records


def check_commands(specs) -> None:
    """ConfigError unless the topics name the commands (``source.topics.cmd_vel``), required: without them
    nothing drives the models, and the dataset could not be split or scored (refused here, before a file
    is written, not at split)."""
    spec = next((s for s in specs if s.key == COMMANDS), None)
    if spec is None:
        raise ConfigError(
            f"source.topics.{COMMANDS} is not set: a dataset without commands cannot be split or scored (the "
            f"commands drive every model); set source.topics.{COMMANDS}.topic=<the Twist topic the robot "
            f"obeyed> and source.topics.{COMMANDS}.type (`skidbench inspect <bag>` lists a bag's topics)"
        )
    if not spec.required:
        raise ConfigError(
            f"source.topics.{COMMANDS}.required=false: a bag without its commands could not be split or "
            f"scored; drop the setting (commands are required) and leave such bags out of source.root"
        )


def _extract_one(bag: Path, out: Path, specs, auto: bool, opts, meta: dict[str, Any]) -> dict[str, Any]:
    """One bag's tables (:func:`.bag.extract_bag`; its topics proposed by ``skidbench inspect`` when
    ``auto``); its ``_extract.json`` record."""
    from skidbench.pipeline.extract.bag import extract_bag
    from skidbench.pipeline.extract.inspect import auto_specs

    return extract_bag(bag, out, auto_specs(bag, opts.typestores) if auto else specs, opts, meta)
