"""``skidbench export <dataset> <dir>`` (benchmark/release/bundle.py) and ``skidbench import <dir>``
(benchmark/release/importer.py) as Hydra apps (``conf/export.yaml``, ``conf/import.yaml``)."""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

from skidbench.pipeline.cli.main import stage


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="export")
@stage("export", home=False)
def export_main(cfg: DictConfig) -> None:
    from skidbench.benchmark.release.bundle import ExportSettings, describe_export, export_bundle
    from skidbench.benchmark.tracking import store as trk
    from skidbench.pipeline.core.layout import layout_from_cfg
    from skidbench.pipeline.datasets.imported import named_dataset

    layout, rec = named_dataset(layout_from_cfg(cfg), cfg.get("robot"), "export")
    tracker = None  # export reads the store: it does not create an empty one to find nothing in
    if trk.has_store(trk.tracking_uri_from_cfg(cfg, layout)):
        tracker = trk.tracker_from_cfg(cfg, layout, dataset_id=str(rec.get("fingerprint") or ""))
    settings = ExportSettings.from_cfg(cfg)
    print(describe_export(export_bundle(settings, layout, Path(str(cfg.bundle.dir)), tracker)), flush=True)


export_main.positional = (("dataset", "bundle.dir"), {})


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="import")
@stage("import", home=False)
def import_main(cfg: DictConfig) -> None:
    from skidbench.benchmark.release.importer import describe_import, import_bundle

    folder = Path(str(cfg.bundle.dir))
    answers = cfg.bundle.get("answers")
    res = import_bundle(
        folder,
        Path(str(cfg.out_root)),
        cfg.bundle.get("name"),
        bool(cfg.source.get("replace")),
        Path(str(answers)) if answers else None,
    )
    print(describe_import(res, folder), flush=True)


import_main.positional = (("bundle.dir",), {})


if __name__ == "__main__":
    export_main()
