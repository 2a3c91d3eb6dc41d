"""``skidbench datasets``: what the output root holds, one line per dataset: name, source, root,
terrains, last evaluate (from each ``<ds>/dataset.json`` and ``<ds>/eval/last_evaluate.json``); then, per
dataset with results (its results table, ``<ds>/results/``), one line per input protocol: its board's latest
runs (the newest complete run of each (model, terrain), across evaluates: what ``skidbench compare
dataset=<name>`` ranks)."""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

from skidbench.pipeline.cli.main import stage
from skidbench.pipeline.datasets.identity import format_datasets, list_datasets


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="datasets")
@stage("datasets", home=False)
def main(cfg: DictConfig) -> None:
    from skidbench.benchmark.board.selection import dataset_boards

    out_root = Path(str(cfg.out_root)).absolute()
    rows = list_datasets(out_root)
    print(format_datasets(rows, out_root))
    boards = dataset_boards(out_root, {r["name"]: r["fingerprint"] for r in rows if r["fingerprint"] != "?"})
    for name, lines in boards.items():
        print(f"\n{name} (`skidbench compare dataset={name}`):")
        print("\n".join(f"  {line}" for line in lines))


if __name__ == "__main__":
    main()
