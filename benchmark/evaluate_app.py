"""``skidbench evaluate``: the horizon benchmark as a Hydra app (config ``conf/evaluate.yaml``)."""

from __future__ import annotations

import logging

import hydra
from omegaconf import DictConfig

from skidbench.pipeline.cli import stage

log = logging.getLogger(__name__)


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="evaluate")
@stage("evaluate")
def main(cfg: DictConfig) -> None:
    from .evaluate import format_result, run_benchmark

    result = run_benchmark(cfg)
    print(format_result(result), flush=True)
    if result.failed:
        log.warning(
            "%d of %d model run(s) FAILED (marked FAILED in MLflow with the reason)",
            len(result.failed),
            len(result.children),
        )


if __name__ == "__main__":
    main()
