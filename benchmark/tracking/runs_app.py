"""``skidbench runs [--reap]``: the MLflow runs left RUNNING in the store, and (``--reap``) those whose
process is gone marked KILLED, from any machine that reaches the store (benchmark/tracking/bookkeeping.py)."""

from __future__ import annotations

from typing import Any

import hydra
from omegaconf import DictConfig

from skidbench.benchmark.errors import EvaluationError
from skidbench.benchmark.tracking import bookkeeping as bk
from skidbench.benchmark.tracking import store as trk
from skidbench.benchmark.tracking.settings import RunsOptions, mlflow_from_cfg, tracking_uri
from skidbench.pipeline.cli.main import stage
from skidbench.pipeline.core.errors import one_line
from skidbench.pipeline.core.layout import layout_from_cfg, root_from_cfg


def store_client(uri: str, timeout_s: float = 5.0) -> Any | None:
    """An ``MlflowClient`` of the store ``uri`` with skidbench's HTTP settings (a server health-checked
    first), for commands that read a whole store; None for a local store that does not exist yet."""
    if not trk.has_store(uri):
        return None
    trk.quiet_mlflow_logs()
    if trk.is_server(uri):
        trk.use_http_defaults()
    trk.check_reachable(uri, timeout_s)
    from mlflow.tracking import MlflowClient

    return MlflowClient(tracking_uri=uri)


def call_store(uri: str, fn: Any, *args: Any, **kwargs: Any) -> Any:
    """``fn(*args, **kwargs)`` (calls to the store ``uri``) with its errors as one line: a server that stops
    answering names the server and what to do; another MLflow error its message."""
    from mlflow.exceptions import MlflowException

    try:
        return fn(*args, **kwargs)
    except MlflowException as exc:
        reason = trk.unreachable(exc)
        if reason:
            raise trk.StoreUnreachable(
                f"MLflow tracking server {uri} does not answer ({reason}); check it "
                f"({uri.rstrip('/')}/health) and run the command again"
            ) from None
        raise EvaluationError(f"MLflow store {uri}: {one_line(exc.message)[:300]}") from None


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="runs")
@stage("runs", home=False)
def main(cfg: DictConfig) -> None:
    ms = mlflow_from_cfg(cfg)
    uri = tracking_uri(ms, layout_from_cfg(cfg))
    client = store_client(uri, ms.timeout_s)
    if client is None:
        print(f"no MLflow store at {uri}: nothing was evaluated under this output root")
        return
    experiments = call_store(uri, client.search_experiments, filter_string="name LIKE 'skidbench-%'")
    opts = root_from_cfg(cfg, RunsOptions)
    lines = call_store(uri, bk.runs_report, client, experiments, opts.reap, opts.stale_after_s)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
