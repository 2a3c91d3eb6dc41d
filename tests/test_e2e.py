"""End to end through the real CLI on the tiny simulated dataset: the README's quick start (``make
reproduce``: simulate -> extract -> groundtruth -> split -> calibrate -> evaluate -> evaluate
inputs=response -> compare), run once per test session in a temporary output root (tests/conftest.py
``readme_reproduce``, also asserted by tests/test_docs_commands.py); the MLflow runs of both input protocols
and their metrics exist and are finite, fits use their terrain's calibration, the report has its figures."""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd
import pytest

pytestmark = pytest.mark.slow

MODELS = ("ideal", "edd", "full_linear", "roc", "enhanced", "friction", "drive_blr", "gp_residual")
TERRAINS = ("asphalt", "grass", "tile")  # scale=tiny simulates all three
PROTOCOLS = ("commanded", "response")  # make reproduce evaluates under both


@pytest.fixture(scope="module")
def pipeline(readme_reproduce) -> tuple[Path, str]:
    """(output root, stdout of every stage) of the session's ``make reproduce`` (SCALE=tiny)."""
    results = readme_reproduce["results"]
    for r in results:
        assert r["returncode"] == 0, f"{r['cmd']} failed:\n{r['stderr'][-3000:]}"
    assert results, "the README's quick start ran no command"
    return readme_reproduce["root"], "".join(r["stdout"] for r in results)


def test_every_model_has_a_finished_run_with_finite_metrics(pipeline):
    out, stdout = pipeline
    from mlflow import MlflowClient

    client = MlflowClient(f"sqlite:///{out / 'mlflow.db'}")
    exp = client.get_experiment_by_name("skidbench-sim-tiny")
    assert exp is not None
    parents = client.search_runs([exp.experiment_id], "tags.`skidbench.role` = 'parent'")
    by_protocol = {p.data.params["inputs"]: p for p in parents}
    assert len(parents) == len(PROTOCOLS) and set(by_protocol) == set(PROTOCOLS)  # one evaluate each
    for protocol, parent in by_protocol.items():
        assert parent.info.status == "FINISHED", protocol
        assert parent.data.params["scale.name"] == "tiny"
        assert parent.data.tags["skidbench.inputs"] == protocol
        children = client.search_runs(
            [exp.experiment_id], f"tags.mlflow.parentRunId = '{parent.info.run_id}'", max_results=1000
        )
        by_key = {(c.data.tags["skidbench.model"], c.data.tags["skidbench.terrain"]): c for c in children}
        assert len(children) == len(by_key)  # one run per model and terrain
        assert set(by_key) == {(m, t) for m in MODELS for t in TERRAINS}, protocol
        for (name, _), run in by_key.items():
            _check_child(name, run)
        assert parent.info.run_id in stdout


def _check_child(name, run):
    """The assertions on one model's run (one model, terrain and protocol)."""
    assert run.info.status == "FINISHED", (name, run.data.tags.get("skidbench.failure_reason"))
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


@pytest.mark.parametrize("terrain", TERRAINS)
def test_models_are_fitted_with_the_calibration_of_their_terrain(pipeline, terrain):
    import json

    out, _ = pipeline
    doc = json.loads((out / "sim-tiny" / "calibration" / f"{terrain}.json").read_text())
    assert doc["source"] == "encoders" and doc["wheel_radius"]["identified"]
    ideal = json.loads((out / "sim-tiny" / "fits" / "ideal" / f"{terrain}.json").read_text())
    friction = json.loads((out / "sim-tiny" / "fits" / "friction" / f"{terrain}.json").read_text())
    for c in ("wheel_radius", "track_width"):
        if doc[c]["identified"]:
            assert ideal["robot_constants"][c] == {
                "value": doc[c]["value"], "spec": doc["spec"][c], "source": "calibrated"
            }  # fmt: skip
    # the friction model's wheel positions are physical: it keeps the spec sheet's track width
    assert friction["robot_constants"]["track_width"]["value"] == doc["spec"]["track_width"]


def test_compare_writes_the_report_with_figures_and_prints_the_leaderboard(pipeline):
    out, stdout = pipeline
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
    # one leaderboard per protocol, every model, each row with its run and options digest; a stamped copy
    for protocol in ("commanded", "response"):
        board = pd.read_csv(reports / f"leaderboard-{protocol}.csv", dtype=str)
        assert sorted(board["model"].unique()) == sorted(MODELS) and (board["inputs"] == protocol).all()
        assert board["run_id"].str.fullmatch(r"[0-9a-f]{32}").all()
        assert board["options_digest"].str.fullmatch(r"[0-9a-f]{12}").all()
        (stamped,) = reports.glob(f"leaderboard-{protocol}-*.csv")
        assert stamped.read_text() == (reports / f"leaderboard-{protocol}.csv").read_text()
        assert f"leaderboard inputs={protocol}: {stamped.name}" in stdout
    assert "Leaderboard" in stdout and f"report: {report}" in stdout
    for m in MODELS:
        assert f"| {m} |" in stdout
