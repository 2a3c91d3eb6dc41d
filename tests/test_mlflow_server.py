"""A real `mlflow server` on 127.0.0.1 (SQLite backend in tmp): evaluate and compare log through it the
same way they log to the local store."""

from __future__ import annotations

import pytest
from _bench_data import compose, fit_fn, write_splits
from mlflow_server import running_mlflow_server

from skidbench.benchmark.compare import run_compare
from skidbench.benchmark.evaluate import run_benchmark

# subprocess pipelines, servers and sweeps: part of `make test`, not of `make test-fast`
pytestmark = pytest.mark.slow


DS = "sim-mini"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    root = tmp_path_factory.mktemp("mlflow_server")
    with running_mlflow_server(root) as uri:
        yield uri, root


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
    assert chi.data.metrics["cv_6s_trans_rmsre_pct"] >= 0
    assert chi.data.params["model"] == "chi"
    assert by_model["broken"].info.status == "FAILED"
    assert "singular" in by_model["broken"].data.tags["skidbench.failure_reason"]
    # artifacts go through the server's proxy into its --artifacts-destination
    arts = [a.path for a in client.list_artifacts(chi.info.run_id, "windows")]
    assert arts == ["windows/tile.windows.parquet"]
    assert list((root / "artifacts").rglob("tile.windows.parquet"))

    ccfg = compose("compare", tmp_path, ["figures.enabled=false"])
    out = run_compare(ccfg)
    assert out.parents == [res.parent_run_id]  # every row from that evaluate
    assert "| chi |" in out.leaderboard_md and "FAILED" in out.report.read_text()
    report_arts = [a.path for a in client.list_artifacts(res.parent_run_id, "report")]
    assert "report/report.md" in report_arts
