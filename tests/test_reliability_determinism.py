"""Determinism: the same seed and config give the same MLflow metrics, to the last digit, when evaluate
runs again in a fresh output root (fits recomputed, a new MLflow store)."""

from __future__ import annotations

import json
import math

import pytest
from _bench_data import calibrate_splits
from hydra import compose, initialize_config_module
from mlflow.tracking import MlflowClient
from reliability_data import SCALE, copy_splits

# subprocess pipelines, servers and sweeps: part of `make test`, not of `make test-fast`
pytestmark = pytest.mark.slow


TIMINGS = {"fit_time_s", "predict_time_s"}  # wall-clock: the only metrics allowed to differ


def _same(metrics: dict) -> dict:
    """The metrics to compare for equality: the timings left out, NaN (an interval a cell with too few
    independent blocks does not have) as the string 'nan', since NaN != NaN."""
    return {k: ("nan" if math.isnan(v) else v) for k, v in metrics.items() if k not in TIMINGS}


def _evaluate(micro_root, root):
    from skidbench.benchmark.evaluate.app import benchmark as run_benchmark

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
        out[(child.model, child.terrain)] = _same(run.data.metrics)
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
    first = skidbench("evaluate", tmp_path, here=True)
    assert "skipped" not in first.stdout
    again = skidbench("evaluate", tmp_path, here=True)
    assert "inputs unchanged" in again.stdout and "skipped" in again.stdout, again.stdout[-1500:]
    starts = ("ideal", "edd", "floor (reference)")
    rows = lambda out: [ln.split() for ln in out.splitlines() if ln.strip().startswith(starts)]  # noqa: E731
    table = rows(first.stdout)
    assert any(r[0] == "floor" for r in table)  # the first print shows the floor of each terrain
    assert table == rows(again.stdout)  # the reprint is the same board, its floor rows included


def _mlflow_metrics(root) -> dict:
    client = MlflowClient(f"sqlite:///{root}/mlflow.db")
    ids = [e.experiment_id for e in client.search_experiments()]
    runs = client.search_runs(ids, "tags.`skidbench.role` = 'child'")
    return {
        (r.data.tags["skidbench.model"], r.data.tags["skidbench.terrain"]): _same(r.data.metrics)
        for r in runs
    }, runs


def test_physical_scores_are_equal_under_one_and_two_threads(micro_root, tmp_path):
    """OpenMP, OpenBLAS and Numba on 1 thread, then on 2, each in a fresh output root: every physical
    model's metrics equal to the last digit, and each run records its thread settings and code paths."""
    from reliability_data import STAGE_ARGS, skidbench

    out = {}
    for n in ("1", "2"):
        root = tmp_path / f"threads{n}"
        copy_splits(micro_root, root)
        env = {v: n for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")}
        skidbench("evaluate", root, "models=[ideal,edd,friction]", env=env, base=STAGE_ARGS["evaluate"])
        out[n], runs = _mlflow_metrics(root)
        assert all(f"OPENBLAS_NUM_THREADS={n}" in r.data.tags["skidbench.env.threads"] for r in runs)
        assert all("openblas=" in r.data.tags["skidbench.env.code_paths"] for r in runs)
    assert len(out["1"]) == 3 and all(any(k.endswith("_rmsre_pct") for k in m) for m in out["1"].values())
    assert out["1"] == out["2"]  # exact float equality, every metric


PLUGIN = """
import numpy as np
from skidbench.models.base import KinematicModel

GAIN = {gain}


class Scaled(KinematicModel):
    name = "scaled"
    version = "1.0"

    def fit(self, table):
        self.params = {{"gain": GAIN}}
        self.fit_loss_ = 0.0
        return self

    def predict(self, table):
        v = self.params["gain"] * self.robot.wheel_radius * (table["cmd_wl"] + table["cmd_wr"]) / 2
        return np.column_stack([v, 0 * v, 0 * v])
"""


def test_a_plugin_edited_in_place_without_a_version_bump_is_refitted(micro_root, tmp_path, monkeypatch):
    import sys
    from importlib.metadata import EntryPoint

    from skidbench.models.fitting.fit import FitSettings, fit_model
    from skidbench.models.registry import plugins as registry

    pkg = tmp_path / "site" / "scaled_plugin"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "model.py").write_text(PLUGIN.format(gain=1.0))
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    real = registry.entry_points
    ep = EntryPoint("scaled", "scaled_plugin.model:Scaled", registry.GROUP)
    monkeypatch.setattr(registry, "entry_points", lambda group: [*real(group=group), ep])

    root = tmp_path / "out"
    copy_splits(micro_root, root)
    with initialize_config_module("skidbench.conf", version_base="1.3"):
        cfg = compose("fit", overrides=[f"out_root={root}", *SCALE, "terrain=tile", "calibrate.use=false"])
    first = fit_model(FitSettings.from_cfg(cfg), "scaled", "tile")
    again = fit_model(FitSettings.from_cfg(cfg), "scaled", "tile")
    assert not first.reused and again.reused  # nothing changed: the saved fit is up to date
    assert first.code.digest == again.code.digest != "?"

    (pkg / "model.py").write_text(PLUGIN.format(gain=2.0))  # same name, same version, other code
    for mod in ("scaled_plugin.model", "scaled_plugin"):  # a new process would import it anew
        monkeypatch.delitem(sys.modules, mod, raising=False)
    edited = fit_model(FitSettings.from_cfg(cfg), "scaled", "tile")
    assert not edited.reused and edited.model.params == {"gain": 2.0}
    assert edited.code.digest != first.code.digest and edited.code.version == first.code.version
    saved = json.loads(edited.path.read_text())
    assert saved["code"]["digest"] == edited.code.digest  # the fit names the code that made it
