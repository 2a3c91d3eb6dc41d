"""The release stages as Hydra apps: ``skidbench export <dataset> <dir>`` (benchmark/release/bundle.py),
``skidbench import <dir>`` (benchmark/release/importer.py), ``skidbench score <dataset> --predictions <file>``
(benchmark/release/score.py) and ``skidbench publish <dataset> <dir>`` (benchmark/release/publish.py); their
configs ``conf/export.yaml``, ``conf/import.yaml``, ``conf/score.yaml``, ``conf/publish.yaml``."""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from skidbench.pipeline.cli.main import stage


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="export")
@stage("export", home=False)
def export_main(cfg: DictConfig) -> None:
    from skidbench.benchmark.release.bundle import ExportSettings, describe_export, export_bundle
    from skidbench.benchmark.release.settings import ExportBundle
    from skidbench.benchmark.tracking import store as trk
    from skidbench.pipeline.calibrate.calibration import Calibrations
    from skidbench.pipeline.core.layout import layout_from_cfg
    from skidbench.pipeline.core.robot import robot_from_hydra
    from skidbench.pipeline.datasets.imported import named_dataset

    layout, rec = named_dataset(layout_from_cfg(cfg), cfg.get("robot"), "export")
    tracker = None  # export reads the store: it does not create an empty one to find nothing in
    if trk.has_store(trk.tracking_uri_from_cfg(cfg, layout)):
        tracker = trk.tracker_from_cfg(cfg, layout, dataset_id=str(rec.get("fingerprint") or ""))
    b: ExportBundle = OmegaConf.to_object(cfg.bundle)
    robot, calibrations = robot_from_hydra(cfg.robot), Calibrations.from_cfg(cfg)
    settings = ExportSettings(robot, calibrations, b.release, b.licence or None, b.provenance or None)
    print(describe_export(export_bundle(settings, layout, Path(b.dir), tracker)), flush=True)


export_main.positional = (("dataset", "bundle.dir"), {})


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="import")
@stage("import", home=False)
def import_main(cfg: DictConfig) -> None:
    from skidbench.benchmark.release.importer import describe_import, import_bundle
    from skidbench.benchmark.release.settings import ImportBundle
    from skidbench.pipeline.core.layout import CommonSettings, root_from_cfg

    b: ImportBundle = OmegaConf.to_object(cfg.bundle)
    folder, out_root = Path(b.dir), Path(root_from_cfg(cfg, CommonSettings).out_root)
    replace = bool(cfg.source.get("replace"))
    res = import_bundle(folder, out_root, b.name, replace, Path(b.answers) if b.answers else None)
    print(describe_import(res, folder), flush=True)


import_main.positional = (("bundle.dir",), {})


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="score")
@stage("score", home=False)
def score_main(cfg: DictConfig) -> None:
    from skidbench.benchmark.release.predictions_file import read_predictions
    from skidbench.benchmark.release.score import (
        check_name,
        check_predictions,
        default_name,
        format_check,
        format_score,
        score_predictions,
    )
    from skidbench.benchmark.release.settings import ScoreOptions
    from skidbench.benchmark.release.submission import submission
    from skidbench.benchmark.tracking import store as trk
    from skidbench.pipeline.core.layout import CommonSettings, layout_from_cfg, root_from_cfg
    from skidbench.pipeline.core.protocol import check_protocol
    from skidbench.pipeline.datasets.imported import named_dataset

    sc: ScoreOptions = OmegaConf.to_object(cfg.score)
    protocol = check_protocol(root_from_cfg(cfg, CommonSettings).inputs)
    path = Path(sc.predictions)
    if sc.check:  # the shape only: no test truth needed, nothing logged
        layout, _ = named_dataset(layout_from_cfg(cfg), cfg.get("robot"), "score.check")
        print(format_check(check_predictions(layout, path, protocol)), flush=True)
        return
    layout, rec = named_dataset(layout_from_cfg(cfg), cfg.get("robot"), "score")
    read_predictions(path)  # a file that cannot be scored, an entry without identity: before the store opens
    name = check_name(sc.name if sc.name is not None else default_name(path))
    entry = submission(name, sc.link, sc.submitter, sc.date, sc.description)
    tracker = trk.tracker_from_cfg(cfg, layout, dataset_id=str(rec.get("fingerprint") or ""))
    print(format_score(score_predictions(layout, tracker, path, entry, protocol)), flush=True)


score_main.positional = (("dataset",), {"--predictions": "score.predictions"})


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="publish")
@stage("publish", home=False)
def publish_main(cfg: DictConfig) -> None:
    from skidbench.benchmark.board.settings import RankOptions
    from skidbench.benchmark.release.publish import PublishSettings, describe, publish
    from skidbench.benchmark.tracking import store as trk
    from skidbench.pipeline.core.layout import layout_from_cfg, root_from_cfg
    from skidbench.pipeline.datasets.imported import named_dataset

    layout, rec = named_dataset(layout_from_cfg(cfg), cfg.get("robot"), "publish")
    tracker = trk.tracker_from_cfg(cfg, layout, dataset_id=str(rec.get("fingerprint") or ""))
    settings = PublishSettings(
        OmegaConf.to_object(cfg.publish),
        root_from_cfg(cfg, RankOptions).rank_by,
        OmegaConf.to_object(cfg.intervals),
    )
    print(describe(publish(settings, layout, rec, tracker, Path(settings.page.dir))), flush=True)


publish_main.positional = (("dataset", "publish.dir"), {})


if __name__ == "__main__":
    export_main()
