"""``skidbench compare``: leaderboard and the paper's figures as a Hydra app (``conf/compare.yaml``)."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from skidbench.pipeline.cli import stage


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="compare")
@stage("compare", home=False)  # the dataset is the one named (benchmark/selection.py)
def main(cfg: DictConfig) -> None:
    from .compare import format_console, run_compare

    print(format_console(run_compare(cfg)), flush=True)


if __name__ == "__main__":
    main()
