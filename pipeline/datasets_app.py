"""``skidbench datasets``: what the output root holds, one line per dataset: name, source, root,
terrains, last evaluate (from each ``<ds>/dataset.json`` and ``<ds>/eval/last_evaluate.json``)."""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

from .cli import stage
from .dataset import format_datasets, list_datasets


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="datasets")
@stage("datasets", home=False)
def main(cfg: DictConfig) -> None:
    out_root = Path(str(cfg.out_root)).absolute()
    print(format_datasets(list_datasets(out_root), out_root))


if __name__ == "__main__":
    main()
