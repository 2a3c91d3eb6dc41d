"""``skidbench publish <dataset> <dir>`` (benchmark/release/publish.py) as a Hydra app
(``conf/publish.yaml``)."""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

from skidbench.pipeline.cli.main import stage


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="publish")
@stage("publish", home=False)
def main(cfg: DictConfig) -> None:
    from skidbench.benchmark.release.publish import PublishSettings, describe, publish
    from skidbench.benchmark.tracking import store as trk
    from skidbench.pipeline.core.layout import layout_from_cfg
    from skidbench.pipeline.datasets.imported import named_dataset

    layout, rec = named_dataset(layout_from_cfg(cfg), cfg.get("robot"), "publish")
    tracker = trk.tracker_from_cfg(cfg, layout, dataset_id=str(rec.get("fingerprint") or ""))
    site = Path(str(cfg.publish.dir))
    print(describe(publish(PublishSettings.from_cfg(cfg), layout, rec, tracker, site)), flush=True)


main.positional = (("dataset", "publish.dir"), {})


if __name__ == "__main__":
    main()
