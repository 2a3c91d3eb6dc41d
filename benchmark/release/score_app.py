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
    from skidbench.benchmark.release.predictions_file import read_predictions
    from skidbench.benchmark.release.score import (
        check_name,
        check_predictions,
        default_name,
        format_check,
        format_score,
        score_predictions,
    )
    from skidbench.benchmark.release.submission import submission
    from skidbench.benchmark.tracking import store as trk
    from skidbench.pipeline.core.layout import layout_from_cfg
    from skidbench.pipeline.core.protocol import protocol_from_cfg
    from skidbench.pipeline.datasets.imported import named_dataset

    path = Path(str(cfg.score.predictions))
    sc = cfg.score
    if sc.get("check"):  # the shape only: no test truth needed, nothing logged
        layout, _ = named_dataset(layout_from_cfg(cfg), cfg.get("robot"), "score.check")
        print(format_check(check_predictions(layout, path, protocol_from_cfg(cfg))), flush=True)
        return
    layout, rec = named_dataset(layout_from_cfg(cfg), cfg.get("robot"), "score")
    read_predictions(path)  # a file that cannot be scored, an entry without identity: before the store opens
    name = check_name(str(sc.name) if sc.get("name") is not None else default_name(path))
    entry = submission(name, sc.get("link"), sc.get("submitter"), sc.get("date"), sc.get("description"))
    tracker = trk.tracker_from_cfg(cfg, layout, dataset_id=str(rec.get("fingerprint") or ""))
    print(format_score(score_predictions(layout, tracker, path, entry, protocol_from_cfg(cfg))), flush=True)


main.positional = (("dataset",), {"--predictions": "score.predictions"})


if __name__ == "__main__":
    main()
