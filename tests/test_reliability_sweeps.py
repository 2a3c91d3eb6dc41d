"""Parallel fit sweeps (Hydra joblib launcher, 2 worker processes) logging to one MLflow store: a SQLite
file and a real local ``mlflow server``; exactly one run per (model, terrain), none lost or duplicated."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
import urllib.request
from collections import Counter
from pathlib import Path

import pytest
from reliability_data import DATASET, SCALE, skidbench

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


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def mlflow_server(tmp_path):
    port = _free_port()
    mlflow = Path(sys.executable).with_name("mlflow")
    cmd = [
        str(mlflow), "server", "--host", "127.0.0.1", "--port", str(port), "--workers", "1",
        "--backend-store-uri", f"sqlite:///{tmp_path / 'server.db'}",
        "--artifacts-destination", str(tmp_path / "artifacts"),
    ]  # fmt: skip
    log = open(tmp_path / "server.log", "w")  # noqa: SIM115
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    uri = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                with urllib.request.urlopen(uri + "/health", timeout=2) as r:
                    if r.status == 200:
                        break
            except OSError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"mlflow server did not start: {(tmp_path / 'server.log').read_text()[-2000:]}")
            time.sleep(0.5)
        yield uri
    finally:
        os.killpg(proc.pid, 15)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, 9)
        log.close()


def test_a_parallel_sweep_logs_one_run_per_model_and_terrain_to_an_mlflow_server(micro_root, mlflow_server):
    # hydra/launcher=parallel: our joblib config (conf/hydra/launcher/parallel.yaml)
    _sweep(micro_root, "parallel", "", env={"MLFLOW_TRACKING_URI": mlflow_server})
    _assert_one_run_per_job(_runs(mlflow_server))
