"""Parallel fit sweeps (Hydra joblib launcher, 2 worker processes) logging to one MLflow store: a SQLite
file and a real local ``mlflow server``; exactly one run per (model, terrain), none lost or duplicated."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest
from mlflow_server import running_mlflow_server
from reliability_data import DATASET, SCALE, skidbench

# subprocess pipelines, servers and sweeps: part of `make test`, not of `make test-fast`
pytestmark = pytest.mark.slow


MODELS = ("ideal", "edd", "full_linear")  # 3 jobs on 2 workers
TERRAINS = ("tile",)  # the micro dataset has one terrain


def _sweep(micro_root: Path, launcher: str, uri: str, env: dict | None = None):
    args = [
        "-m",
        *SCALE,
        f"model={','.join(MODELS)}",
        f"terrain={','.join(TERRAINS)}",
        f"hydra/launcher={launcher}",
        "hydra.launcher.n_jobs=2",
        "reuse=false",  # fit again even when an earlier test left an up-to-date fit
        "calibrate.use=false",  # the sweep, not the calibration, is under test
    ]
    if uri and not uri.startswith("http"):
        args.append(f"mlflow.tracking_uri={uri}")
    return skidbench("fit", micro_root, *args, base=[], env=env)


def _runs(uri: str):
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=uri)
    exp = client.get_experiment_by_name(f"skidbench-{DATASET}")
    assert exp is not None
    return client.search_runs([exp.experiment_id], max_results=1000)


def _assert_one_run_per_job(runs) -> None:
    keys = Counter((r.data.tags["skidbench.model"], r.data.tags["skidbench.terrain"]) for r in runs)
    assert keys == Counter({(m, t): 1 for m in MODELS for t in TERRAINS}), keys
    assert {r.info.status for r in runs} == {"FINISHED"}
    assert len({r.data.tags["skidbench.sweep_id"] for r in runs}) == 1
    assert all("fit_loss" in r.data.metrics and r.data.params["model"] for r in runs)


def test_a_joblib_sweep_logs_one_run_per_model_and_terrain_to_a_sqlite_store(micro_root, tmp_path):
    uri = f"sqlite:///{tmp_path / 'sweep.db'}"
    proc = _sweep(micro_root, "joblib", uri)
    assert "Joblib.Parallel(n_jobs=2" in proc.stdout + proc.stderr
    _assert_one_run_per_job(_runs(uri))


@pytest.fixture
def mlflow_server(tmp_path):
    with running_mlflow_server(tmp_path) as uri:
        yield uri


def test_a_parallel_sweep_logs_one_run_per_model_and_terrain_to_an_mlflow_server(micro_root, mlflow_server):
    # hydra/launcher=parallel: our joblib config (conf/hydra/launcher/parallel.yaml)
    _sweep(micro_root, "parallel", "", env={"MLFLOW_TRACKING_URI": mlflow_server})
    _assert_one_run_per_job(_runs(mlflow_server))
