"""Determinism: the same seed and config give the same MLflow metrics, to the last digit, when evaluate
runs again in a fresh output root (fits recomputed, a new MLflow store)."""

from __future__ import annotations

import shutil

from hydra import compose, initialize_config_module
from mlflow.tracking import MlflowClient
from reliability_data import DATASET, SCALE

TIMINGS = {"fit_time_s", "predict_time_s"}  # wall-clock: the only metrics allowed to differ


def _evaluate(micro_root, root):
    from skidbench.benchmark.evaluate import run_benchmark

    shutil.copytree(micro_root / DATASET / "splits", root / DATASET / "splits")
    with initialize_config_module("skidbench.conf", version_base="1.3"):
        cfg = compose(
            "evaluate", overrides=[f"out_root={root}", *SCALE, "models=[ideal,edd]", "log_figures=false"]
        )
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
    assert first and all(any(k.startswith("rmsre_") for k in m) for m in first.values())
    assert first == second  # exact float equality, every metric
