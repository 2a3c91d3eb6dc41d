"""A dataset imported from a bundle (``skidbench import``, benchmark/release/bundle.py): what its folder
holds and
which stages may run on it.

An imported dataset is ``<out_root>/<name>/`` with the layout every stage reads (pipeline/core/layout.py):
``dataset.json`` (``source: bundle``, ``root``: the bundle folder it came from, ``fingerprint``: the
sha256 of the bundle's checksum manifest, so its identity is its content), ``raw/manifest.json`` (the
bundle's sequences, each ``path`` pointing at its split file), ``splits/`` (the bundle's Parquet files as
they are), ``calibration/`` (the bundle's calibration and wheel response per terrain, with the stamps
``calibrate`` would have written) and ``bundle/`` (the bundle's own record: ``bundle.json``, its checksum
manifest and the exported board; from a public half also its CV/LD model inputs and window list, and the
private half's ``answers.json`` when imported with it). Its splits are frozen: the stages upstream of them
(``simulate``, ``extract``, ``groundtruth``, ``split``) refuse to run on it, in one line; ``calibrate``,
``fit``, ``evaluate``, ``compare``, ``score``, ``export`` and ``publish`` treat it like any other dataset,
with ``source=bundle dataset=<name>``, except that without its test answers (a public half imported alone)
``evaluate`` and ``score`` refuse it in one line (``score.check=true`` checks a predictions file there).

The bundle records the robot its calibration was made with; a stage run with another robot config is
refused in one line naming the one to set (``robot=<name>``), instead of a stale calibration later.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from skidbench.pipeline.core.cache import StaleInputError
from skidbench.pipeline.core.errors import ConfigError

if TYPE_CHECKING:
    from skidbench.pipeline.core.layout import Layout

SOURCE = "bundle"  # dataset.json's ``source`` of an imported dataset
RECORD_DIR = "bundle"  # <ds>/bundle/: the bundle's record (bundle.json, SHA256SUMS, board/)
#: the stages whose outputs a bundle replaces: they never run on an imported dataset
FROZEN_STAGES = ("simulate", "extract", "groundtruth", "split")
#: the stages that score against the CV/LD ground truth: not on the public half of a bundle alone
TRUTH_STAGES = ("evaluate", "score")


class ImportedDatasetError(StaleInputError):
    """A stage that cannot run on an imported dataset, or with other settings than the bundle's: refused
    before it runs, so it records no failure (the stages downstream still run)."""


def bundle_record(root: str | Path) -> dict[str, Any] | None:
    """``<root>/bundle/bundle.json`` of an imported dataset folder, else None."""
    path = Path(root) / RECORD_DIR / "bundle.json"
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def truth_withheld(root: str | Path) -> bool:
    """True for a dataset imported from the public half of a bundle without its private half (the CV/LD
    answers: ``<root>/bundle/answers.json``)."""
    rec = bundle_record(root)
    answers = Path(root) / RECORD_DIR / "answers.json"
    return bool(rec) and rec.get("release") == "withheld" and not answers.is_file()


def is_imported(root: str | Path) -> bool:
    """True for a dataset folder made by ``skidbench import``."""
    try:
        rec = json.loads((Path(root) / "dataset.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(rec, dict) and rec.get("source") == SOURCE


def check_stage(robot_conf: Mapping[str, Any] | None, stage: str, root: str | Path) -> None:
    """Before ``stage`` runs on the dataset folder ``root``: nothing for a dataset that was not imported;
    for an imported one, ImportedDatasetError when the stage would rebuild its frozen splits, or when the
    configured robot (``robot_conf``: the ``robot`` config group; None: not checked) is not the bundle's
    (its calibration and board were made with that one)."""
    if not is_imported(root):
        return
    name = Path(root).name
    if stage in FROZEN_STAGES:
        raise ImportedDatasetError(
            f"{root}: dataset {name!r} was imported from a bundle: its splits are frozen and `{stage}` does "
            f"not run on it; run calibrate, evaluate, compare, score or publish with source=bundle "
            f"dataset={name}"
        )
    if stage in TRUTH_STAGES and truth_withheld(root):
        raise ImportedDatasetError(
            f"{root}: dataset {name!r} was imported from the public half of a bundle: its CV/LD ground truth "
            f"is withheld (the maintainer keeps it), so `{stage}` cannot score here; check a predictions "
            f"file with `skidbench score {name} --predictions <file> score.check=true`, or import with the "
            "private half (bundle.answers=<dir>)"
        )
    rec = bundle_record(root) or {}
    robot = rec.get("robot") or {}
    want = robot.get("spec")
    if not want or robot_conf is None:
        return
    from skidbench.pipeline.core.robot import robot_from_hydra

    have = robot_from_hydra(robot_conf).to_dict()
    if json.dumps(have, sort_keys=True, default=str) != json.dumps(want, sort_keys=True, default=str):
        raise ImportedDatasetError(
            f"{root}: dataset {name!r} was imported from a bundle made with robot {robot.get('name')!r} "
            f"(its calibration and board were made with it), not the configured robot {have.get('name')!r} "
            f"with these constants; set robot={robot.get('name')}"
        )


def named_dataset(
    layout: Layout, robot_conf: Mapping[str, Any] | None, stage: str
) -> tuple[Layout, dict[str, Any]]:
    """The dataset a stage names by its folder (``skidbench export <dataset> ...``: ``layout``, the config's
    ``dataset`` under its ``out_root``, whatever ``source`` says): its Layout and ``dataset.json`` record.
    ConfigError (one line) when there is no such dataset; the checks of ``@stage`` otherwise (a failed
    producer, an imported dataset's robot: ``robot_conf``, the ``robot`` config group)."""
    from skidbench.pipeline.core.cache import check_producers
    from skidbench.pipeline.datasets.identity import read_record

    rec = read_record(layout)
    if rec is None or not layout.manifest.is_file():
        raise ConfigError(
            f"{layout.root}: no dataset {layout.dataset!r} under {layout.out_root} (no dataset.json or "
            "manifest); `skidbench datasets` lists them"
        )
    check_producers(layout.root, stage)
    check_stage(robot_conf, stage, layout.root)
    return layout, rec
