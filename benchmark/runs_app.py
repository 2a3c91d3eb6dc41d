"""``skidbench runs [--reap]``: the MLflow runs left RUNNING in the store, and (``--reap``) those whose
process is gone marked KILLED, from any machine that reaches the store (benchmark/bookkeeping.py)."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from skidbench.pipeline.cli import stage
from skidbench.pipeline.layout import layout_from_cfg

from . import bookkeeping as bk
from . import tracking as trk


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="runs")
@stage("runs", home=False)
def main(cfg: DictConfig) -> None:
    uri = trk.resolve_tracking_uri(cfg, layout_from_cfg(cfg))
    client = trk.store_client(uri, float(cfg.mlflow.get("timeout_s", 5.0)))
    if client is None:
        print(f"no MLflow store at {uri}: nothing was evaluated under this output root")
        return
    experiments = trk.call_store(uri, client.search_experiments, filter_string="name LIKE 'skidbench-%'")
    lines = trk.call_store(uri, bk.runs_report, client, experiments, bool(cfg.reap), float(cfg.stale_after_s))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
