"""A real `mlflow server` on 127.0.0.1 (SQLite backend in tmp): evaluate and compare log through it the
same way they log to the local store."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest
from _bench_data import compose, fit_fn, write_splits

from skidbench.benchmark.compare import run_compare
from skidbench.benchmark.evaluate import run_benchmark

DS = "sim-mini"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    root = tmp_path_factory.mktemp("mlflow_server")
    port = _free_port()
    mlflow_bin = Path(sys.executable).with_name("mlflow")
    cmd = [
        str(mlflow_bin), "server", "--host", "127.0.0.1", "--port", str(port), "--workers", "1",
        "--backend-store-uri", f"sqlite:///{root / 'server.db'}",
        "--artifacts-destination", str(root / "artifacts"),
    ]  # fmt: skip
    log = open(root / "server.log", "wb")  # noqa: SIM115
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True, cwd=root)
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
                pytest.fail(f"mlflow server did not start: {(root / 'server.log').read_text()[-2000:]}")
            time.sleep(0.5)
        yield uri, root
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
        log.close()


def test_benchmark_logs_through_a_real_tracking_server(server, tmp_path, monkeypatch):
    uri, root = server
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    write_splits(tmp_path / DS, terrains=("tile",), counts={"train": 1, "cv": 1, "ld": 1}, duration_s=20.0)
    cfg = compose("evaluate", tmp_path, ["models=[chi,broken]"])
    res = run_benchmark(cfg, fit_fn=fit_fn, log_figures=False)
    assert res.tracking_uri == uri
    assert not (tmp_path / "mlflow.db").exists()  # nothing went to the local store

    from mlflow import MlflowClient

    client = MlflowClient(uri)
    exp = client.get_experiment_by_name(f"skidbench-{DS}")
    runs = client.search_runs([exp.experiment_id], f"tags.mlflow.parentRunId = '{res.parent_run_id}'")
    by_model = {r.data.tags["skidbench.model"]: r for r in runs}
    assert set(by_model) == {"chi", "broken"}
    chi = by_model["chi"]
    assert chi.info.status == "FINISHED"
    assert chi.data.metrics["rmsre_translational_cv_6s"] >= 0
    assert chi.data.params["model"] == "chi"
    assert by_model["broken"].info.status == "FAILED"
    assert "singular" in by_model["broken"].data.tags["skidbench.failure_reason"]
    # artifacts go through the server's proxy into its --artifacts-destination
    arts = [a.path for a in client.list_artifacts(chi.info.run_id, "windows")]
    assert arts == ["windows/tile.windows.parquet"]
    assert list((root / "artifacts").rglob("tile.windows.parquet"))

    ccfg = compose("compare", tmp_path, ["figures.enabled=false"])
    out = run_compare(ccfg)
    assert out.parent_run_id == res.parent_run_id
    assert "| chi |" in out.leaderboard_md and "FAILED" in out.report.read_text()
    report_arts = [a.path for a in client.list_artifacts(res.parent_run_id, "report")]
    assert "report/report.md" in report_arts
