"""``skidbench score <dataset> --predictions <file>`` (benchmark/release/score.py) as a Hydra app
(``conf/score.yaml``)."""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

from skidbench.pipeline.cli.main import stage


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="score")
@stage("score", home=False)
def main(cfg: DictConfig) -> None:
    from skidbench.benchmark.release.score import format_score, read_predictions, score_predictions
    from skidbench.benchmark.tracking import store as trk
    from skidbench.pipeline.core.layout import layout_from_cfg
    from skidbench.pipeline.core.protocol import protocol_from_cfg
    from skidbench.pipeline.datasets.imported import named_dataset

    layout, rec = named_dataset(layout_from_cfg(cfg), cfg.get("robot"), "score")
    read_predictions(Path(str(cfg.score.predictions)))  # a file that cannot be scored: before the store opens
    tracker = trk.tracker_from_cfg(cfg, layout, dataset_id=str(rec.get("fingerprint") or ""))
    res = score_predictions(layout, tracker, Path(str(cfg.score.predictions)), cfg.score.get("name"),
                            protocol_from_cfg(cfg))  # fmt: skip
    print(format_score(res), flush=True)


main.positional = (("dataset",), {"--predictions": "score.predictions"})


if __name__ == "__main__":
    main()
