"""End to end through the real CLI on a tiny simulated dataset: simulate -> extract -> groundtruth ->
split -> calibrate -> evaluate -> compare in a tmp output root; the MLflow runs and metrics exist and are
finite."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

MODELS = ("ideal", "edd", "full_linear", "roc", "enhanced", "friction", "drive_blr", "gp_residual")
TERRAIN = "grass"  # one terrain keeps evaluate/compare short; the split stage still builds all three


def _skidbench(out: Path, *args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    env["SKIDBENCH_OUT"] = str(out)
    exe = Path(sys.executable).with_name("skidbench")
    proc = subprocess.run([str(exe), *args], env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, f"skidbench {' '.join(args)} failed:\n{proc.stderr[-3000:]}"
    return proc


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory):
    out = tmp_path_factory.mktemp("e2e")
    for stage in ("simulate", "extract", "groundtruth", "split", "calibrate"):
        _skidbench(out, stage, "scale=tiny")
    ev = _skidbench(out, "evaluate", "scale=tiny", f"terrains=[{TERRAIN}]", "report_data.fig7_windows=2")
    cmp_ = _skidbench(out, "compare", "scale=tiny")
    return out, ev, cmp_


def test_every_model_has_a_finished_run_with_finite_metrics(pipeline):
    out, ev, _ = pipeline
    from mlflow import MlflowClient

    client = MlflowClient(f"sqlite:///{out / 'mlflow.db'}")
    exp = client.get_experiment_by_name("skidbench-sim-tiny")
    assert exp is not None
    parents = client.search_runs([exp.experiment_id], "tags.`skidbench.role` = 'parent'")
    assert len(parents) == 1 and parents[0].info.status == "FINISHED"
    parent = parents[0]
    assert parent.data.params["scale.name"] == "tiny"
    children = client.search_runs([exp.experiment_id], f"tags.mlflow.parentRunId = '{parent.info.run_id}'")
    by_model = {c.data.tags["skidbench.model"]: c for c in children}
    assert set(by_model) == set(MODELS)
    for name, run in by_model.items():
        assert run.info.status == "FINISHED", (name, run.data.tags.get("skidbench.failure_reason"))
        assert run.data.tags["skidbench.terrain"] == TERRAIN
        for key in (
            "cv_6s_trans_rmsre_pct",
            "cv_6s_rot_rmsre_pct",
            "ld_6s_trans_rmsre_pct",
            "ld_6s_rot_rmsre_pct",
            "fit_time_s",
            "predict_time_s",
        ):
            assert math.isfinite(run.data.metrics[key]), (name, key)
        assert run.data.tags["skidbench.plugin_package"].startswith("skidbench")
        learned = name in ("drive_blr", "gp_residual")  # predictive covariance: uncertainty scored
        assert ("coverage95_position_cv_6s" in run.data.metrics) == learned, name
        if learned:
            assert 0 <= run.data.metrics["coverage95_position_ld_6s"] <= 1
    assert parent.info.run_id in ev.stdout


def test_models_are_fitted_with_the_calibration_of_their_terrain(pipeline):
    import json

    out, _, _ = pipeline
    doc = json.loads((out / "sim-tiny" / "calibration" / f"{TERRAIN}.json").read_text())
    assert doc["source"] == "encoders" and doc["wheel_radius"]["identified"]
    ideal = json.loads((out / "sim-tiny" / "fits" / "ideal" / f"{TERRAIN}.json").read_text())
    friction = json.loads((out / "sim-tiny" / "fits" / "friction" / f"{TERRAIN}.json").read_text())
    for c in ("wheel_radius", "track_width"):
        if doc[c]["identified"]:
            assert ideal["robot_constants"][c] == {
                "value": doc[c]["value"], "spec": doc["spec"][c], "source": "calibrated"
            }  # fmt: skip
    # the friction model's wheel positions are physical: it keeps the spec sheet's track width
    assert friction["robot_constants"]["track_width"]["value"] == doc["spec"]["track_width"]


def test_compare_writes_the_report_with_figures_and_prints_the_leaderboard(pipeline):
    out, _, cmp_ = pipeline
    reports = out / "sim-tiny" / "reports"
    report = reports / "report.md"
    assert report.is_file()
    text = report.read_text()
    for fig in (
        "fig3_translational_rmsre.png",
        "fig4_rotational_rmsre.png",
        "fig5_residual_vs_acceleration.png",
        "fig6_yaw_rate_surfaces.png",
        "fig7_trajectories.png",
    ):
        assert (reports / fig).stat().st_size > 10_000, fig
        assert f"]({fig})" in text
    assert (reports / "leaderboard.csv").is_file()
    assert "Leaderboard" in cmp_.stdout and f"report: {report}" in cmp_.stdout
    for m in MODELS:
        assert f"| {m} |" in cmp_.stdout
