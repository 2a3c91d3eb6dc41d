"""``skidbench publish <dataset> <dir>`` (benchmark/publish.py) as a Hydra app (``conf/publish.yaml``)."""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

from skidbench.pipeline.cli import stage


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="publish")
@stage("publish", home=False)
def main(cfg: DictConfig) -> None:
    from skidbench.pipeline.imported import named_dataset
    from skidbench.pipeline.layout import layout_from_cfg

    from . import tracking as trk
    from .publish import PublishSettings, describe, publish

    layout, rec = named_dataset(layout_from_cfg(cfg), cfg.get("robot"), "publish")
    tracker = trk.tracker_from_cfg(cfg, layout, dataset_id=str(rec.get("fingerprint") or ""))
    site = Path(str(cfg.publish.dir))
    print(describe(publish(PublishSettings.from_cfg(cfg), layout, rec, tracker, site)), flush=True)


main.positional = (("dataset", "publish.dir"), {})


if __name__ == "__main__":
    main()
