"""Discovered effects are first-class models: ``base+effect+...`` specs and ``discovered`` in evaluate.

Data with a hidden effect (tests/discover_data.py: yaw rate short by k x commanded angular acceleration):
the augmented model is fitted on Train only, scored on CV/LD like every row, logged to MLflow with its
effects as params, appears in compare's leaderboard, and beats its base there.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import discover_data as dd  # noqa: E402

from skidbench.models.base import ModelError  # noqa: E402
from skidbench.models.registry.specs import get_model_class  # noqa: E402

EFFECT = "angular_acceleration_slip"
SPEC = f"edd+{EFFECT}"


@pytest.fixture(scope="module")
def hidden_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("hidden")
    raw = dd.dataset(dd.hidden([EFFECT]), 31, n_train=6, duration=36.0)
    dd.write_splits(raw, root / "hidden" / "splits", "tile")
    return root


def _cfg(root: Path, *over: str):
    from hydra import compose, initialize_config_module

    with initialize_config_module("skidbench.conf", version_base="1.3"):
        # not about calibration: the spec sheet's constants (fit reads a calibration only `calibrate` makes)
        over = ("calibrate.use=false", *over)
        return compose("evaluate", [f"out_root={root}", "dataset=hidden", "log_figures=false", *over])


def test_model_spec_parses_base_and_effects_and_rejects_unknown_effects():
    cls = get_model_class("edd+actuator_lag+angular_acceleration_slip")
    assert cls.name == "edd+actuator_lag+angular_acceleration_slip"
    assert cls.base_name == "edd" and cls.effects == ("actuator_lag", "angular_acceleration_slip")
    assert cls.calibrated_constants == get_model_class("edd").calibrated_constants
    assert get_model_class("friction+actuator_lag").base_name == "friction"  # any base model
    with pytest.raises(ModelError, match="unknown effect"):
        get_model_class("edd+wheel_wobble")
    with pytest.raises(ModelError, match="not installed"):
        get_model_class("nosuch+actuator_lag")


@pytest.mark.slow
def test_augmented_and_discovered_rows_beat_their_base_in_mlflow_and_the_leaderboard(
    hidden_root, monkeypatch
):
    import mlflow

    # an earlier compare in this process exported its store (mlflow.set_tracking_uri): use this root's
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)

    from skidbench.benchmark.board.app import run as run_compare
    from skidbench.benchmark.evaluate.app import benchmark as run_benchmark

    # what `skidbench discover` writes (its contract: per terrain the base model and the effects)
    disc = hidden_root / "hidden" / "discovery" / "discovery.json"
    disc.parent.mkdir(parents=True)
    disc.write_text(
        json.dumps({"terrains": {"tile": {"base_model": "edd", "effects": [EFFECT], "message": ""}}})
    )
    cfg = _cfg(hidden_root, f"models=[edd,{SPEC},discovered]")
    result = run_benchmark(cfg)
    assert not result.failed, [c.reason for c in result.failed]
    rows = {c.model: c.metrics for c in result.children}
    for m in (SPEC, "discovered"):
        for split in ("cv", "ld"):
            for kind in ("trans", "rot"):
                key = f"{split}_6s_{kind}_rmsre_pct"
                assert rows[m][key] < rows["edd"][key], (m, key, rows[m][key], rows["edd"][key])
    # fitted on Train only: the fit JSON lists the Train sequences; discovered resolved to the spec
    fit = json.loads((hidden_root / "hidden" / "fits" / "discovered" / "tile.json").read_text())
    assert fit["resolved"]["spec"] == SPEC and all("_train_" in s for s in fit["sequences"])
    k = fit["params"]["effects"][EFFECT]["k"]
    assert k == pytest.approx(dd.DEFAULT_SIZES[EFFECT], rel=0.35)
    # MLflow: the child run carries its base and effects as params
    client = mlflow.MlflowClient(f"sqlite:///{hidden_root}/mlflow.db")
    exp = client.get_experiment_by_name("skidbench-hidden")
    runs = client.search_runs([exp.experiment_id], f"tags.`skidbench.model` = '{SPEC}'")
    assert len(runs) == 1
    params = runs[0].data.params
    assert params["augmented.base"] == "edd" and params["augmented.effects"] == EFFECT
    assert float(params[f"effect.{EFFECT}.k"]) == pytest.approx(k, rel=1e-4)
    # compare's leaderboard has the rows
    cmp_cfg = _compose_compare(hidden_root)
    run_compare(cmp_cfg)
    board = (hidden_root / "hidden" / "reports" / "leaderboard-commanded.csv").read_text()
    assert SPEC in board and "discovered" in board


def _compose_compare(root: Path):
    from hydra import compose, initialize_config_module

    with initialize_config_module("skidbench.conf", version_base="1.3"):
        return compose("compare", [f"out_root={root}", "dataset=hidden", "figures.enabled=false"])


def test_augmented_model_round_trips_through_its_json(hidden_root):
    from skidbench.models.fitting.fit import FitSettings, fit_model, load_fitted
    from skidbench.pipeline.core.schema import load_split_tables

    cfg = _cfg(hidden_root, "calibrate.use=false")  # the JSON round trip, not the calibration
    res = fit_model(FitSettings.from_cfg(cfg), "edd+actuator_lag", "tile")
    again = load_fitted(FitSettings.from_cfg(cfg), "edd+actuator_lag", "tile")
    df, _ = load_split_tables(hidden_root / "hidden" / "splits", "tile", "ld")[0]
    np.testing.assert_allclose(again.predict(df), res.model.predict(df), rtol=1e-12, atol=1e-12)
    assert res.model.params["effects"]["actuator_lag"]["tau"] > 0


def test_discovered_without_a_discovery_is_a_one_line_error(tmp_path):
    from skidbench.models.fitting.fit import FitSettings, fit_model

    raw = dd.dataset({}, 3, n_train=2, duration=20.0)
    dd.write_splits(raw, tmp_path / "hidden" / "splits", "tile")
    with pytest.raises(ModelError, match="run `skidbench discover`"):
        fit_model(FitSettings.from_cfg(_cfg(tmp_path)), "discovered", "tile")
