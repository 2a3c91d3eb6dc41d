"""Determinism: the same seed and config give the same MLflow metrics, to the last digit, when evaluate
runs again in a fresh output root (fits recomputed, a new MLflow store)."""

from __future__ import annotations

import pytest
from _bench_data import calibrate_splits
from hydra import compose, initialize_config_module
from mlflow.tracking import MlflowClient
from reliability_data import SCALE, copy_splits

# subprocess pipelines, servers and sweeps: part of `make test`, not of `make test-fast`
pytestmark = pytest.mark.slow


TIMINGS = {"fit_time_s", "predict_time_s"}  # wall-clock: the only metrics allowed to differ


def _evaluate(micro_root, root):
    from skidbench.benchmark.evaluate import run_benchmark

    copy_splits(micro_root, root)
    with initialize_config_module("skidbench.conf", version_base="1.3"):
        cfg = compose(
            "evaluate", overrides=[f"out_root={root}", *SCALE, "models=[ideal,edd]", "log_figures=false"]
        )
    calibrate_splits(cfg)  # each fresh root is calibrated again too (only `calibrate` computes it)
    result = run_benchmark(cfg)
    client = MlflowClient(result.tracking_uri)
    out = {}
    for child in result.children:
        run = client.get_run(child.run_id)
        assert run.info.status == "FINISHED"
        out[(child.model, child.terrain)] = {k: v for k, v in run.data.metrics.items() if k not in TIMINGS}
    return out


def test_evaluate_twice_in_fresh_roots_gives_identical_mlflow_metrics(micro_root, tmp_path, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    first = _evaluate(micro_root, tmp_path / "a")
    second = _evaluate(micro_root, tmp_path / "b")
    assert first and all(any(k.endswith("_rmsre_pct") for k in m) for m in first.values())
    assert first == second  # exact float equality, every metric


def test_evaluate_again_with_nothing_changed_is_skipped_and_reprints(micro_root, tmp_path):
    from reliability_data import skidbench

    copy_splits(micro_root, tmp_path)
    first = skidbench("evaluate", tmp_path)
    assert "skipped" not in first.stdout
    again = skidbench("evaluate", tmp_path)
    assert "inputs unchanged" in again.stdout and "skipped" in again.stdout, again.stdout[-1500:]
    table = [ln for ln in first.stdout.splitlines() if ln.strip().startswith(("ideal", "edd"))]
    assert table and all(ln in again.stdout for ln in table)  # compare-style reprint of the same result
