"""``skidbench compare``: leaderboard and the paper's figures as a Hydra app (``conf/compare.yaml``)."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from skidbench.pipeline.cli.main import stage


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="compare")
@stage("compare", home=False)  # the dataset is the one named (benchmark/board/selection.py)
def main(cfg: DictConfig) -> None:
    from skidbench.benchmark.report.markdown import format_console

    print(format_console(run(cfg)), flush=True)


def run(cfg: DictConfig):
    """The stage: the settings compare reads of the config (each value once), the dataset, store and
    experiment they name (``open_target``), then :func:`run_compare`."""
    from dataclasses import asdict

    from skidbench.benchmark.board.compare import CompareSettings, open_target, run_compare
    from skidbench.pipeline.datasets.identity import identity_from_cfg

    cs = CompareSettings.from_cfg(cfg)
    robot = cfg.get("robot") if hasattr(cfg, "get") else None
    target, tracker = open_target(cs, robot, lambda: asdict(identity_from_cfg(cfg)))
    return run_compare(cs, target, tracker)


if __name__ == "__main__":
    main()
