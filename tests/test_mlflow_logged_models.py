"""What `evaluate` logs to MLflow for a user of the UI or of ``mlflow`` in Python: every fitted model an
MLflow Model (pyfunc) that loads and predicts in a plain Python process, run descriptions, dataset inputs,
fitted values as params, only the run's own model config, creator/source tags, unique parent names."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import textwrap

import mlflow
import numpy as np
import pandas as pd
import pytest
from _bench_data import compose, sequence_table, write_splits

from skidbench.benchmark.evaluate.app import benchmark as run_benchmark
from skidbench.benchmark.tracking import tags as run_tags
from skidbench.benchmark.tracking.mlflow_model import INPUT_COLUMNS
from skidbench.benchmark.tracking.tags import current_user
from skidbench.models.fitting.fit import FitSettings, load_fitted

DS = "sim-mini"
pytestmark = pytest.mark.slow  # real fits, logged models, a fresh interpreter importing MLflow: 86 s (loaded)


@pytest.fixture(scope="module")
def real_models(tmp_path_factory):
    """Two installed models (ideal, roc) fitted and scored on synthetic splits of one terrain; the config
    carries `+model=roc` (roc's initial values), which must reach roc's run only."""
    mp = pytest.MonkeyPatch()
    mp.delenv("MLFLOW_TRACKING_URI", raising=False)
    out = tmp_path_factory.mktemp("logged_models")
    write_splits(out / DS, terrains=("tile",), counts={"train": 1, "cv": 1, "ld": 1}, duration_s=20.0)
    cfg = compose("evaluate", out, ["models=[ideal,roc]", "calibrate.use=false", "+model=roc"])
    res = run_benchmark(cfg, log_figures=False)
    client = mlflow.MlflowClient(f"sqlite:///{out / 'mlflow.db'}")
    runs = {c.model: client.get_run(c.run_id) for c in res.children}
    yield out, cfg, res, client, runs
    mp.undo()


def test_a_logged_model_loads_and_predicts_in_a_plain_python_process(real_models, tmp_path):
    out, cfg, res, client, runs = real_models
    run = runs["roc"]
    assert run.info.status == "FINISHED"
    model_id = run.data.tags["skidbench.logged_model"]
    model = client.get_logged_model(model_id)
    assert model.source_run_id == run.info.run_id and model.experiment_id == run.info.experiment_id
    table = sequence_table(seed=42, duration_s=5.0)
    table["sequence"] = "s0"
    table[list(INPUT_COLUMNS)].to_parquet(tmp_path / "inputs.parquet")
    # a fresh interpreter that knows only mlflow's API and the store: no skidbench call, no Hydra
    script = textwrap.dedent(
        f"""
        import json, sys
        import mlflow, pandas as pd
        mlflow.set_tracking_uri({f"sqlite:///{out / 'mlflow.db'}"!r})
        m = mlflow.pyfunc.load_model("models:/{model_id}")
        sig = m.metadata.signature
        pred = m.predict(pd.read_parquet({str(tmp_path / "inputs.parquet")!r}))
        json.dump({{"inputs": sig.inputs.input_names(), "outputs": sig.outputs.input_names(),
                   "columns": list(pred.columns), "values": pred.to_numpy().tolist()}}, sys.stdout)
        """
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    got = json.loads(done.stdout.strip().splitlines()[-1])
    assert got["inputs"] == list(INPUT_COLUMNS) and got["outputs"] == ["vx", "vy", "wz"]
    assert got["columns"] == ["vx", "vy", "wz"]
    # the same numbers as the fitted model skidbench itself predicts with
    expected = load_fitted(FitSettings.from_cfg(cfg), "roc", "tile").predict(table)
    np.testing.assert_allclose(np.array(got["values"]), expected, rtol=1e-12, atol=1e-12)


def test_a_logged_models_requirements_pin_skidbench_and_the_libraries_it_ran_with(real_models):
    from pathlib import Path

    from skidbench.pipeline.runner.environment import version_of

    out, cfg, res, client, runs = real_models
    mlflow.set_tracking_uri(f"sqlite:///{out / 'mlflow.db'}")
    reqs = Path(
        mlflow.pyfunc.get_model_dependencies(f"models:/{runs['roc'].data.tags['skidbench.logged_model']}")
    )
    lines = set(reqs.read_text().split())
    for dist in ("skidbench", "mlflow", "numpy", "scipy", "pandas", "numba"):
        assert f"{dist}=={version_of(dist)}" in lines, (dist, lines)
    assert runs["roc"].data.tags["skidbench.code.distribution"] == "skidbench"


def test_runs_describe_themselves_and_carry_only_their_own_models_config(real_models):
    out, cfg, res, client, runs = real_models
    roc_run, ideal = runs["roc"], runs["ideal"]
    # only roc's run carries roc's config (its initial values); ideal's carries ideal's, which has none
    assert (
        roc_run.data.params["model.name"] == "roc" and roc_run.data.params["model.options.b1_init"] == "1.0"
    )
    assert ideal.data.params["model.name"] == "ideal"
    assert not any(k.startswith(("model.options.", "model.params.")) for k in ideal.data.params)
    parent = client.get_run(res.parent_run_id)
    assert not any(k.startswith("model.") for k in parent.data.params)
    # fitted values as params, equal to the fit JSON's
    fitted = {k.removeprefix("fitted."): v for k, v in roc_run.data.params.items() if k.startswith("fitted.")}
    saved = json.loads((out / DS / "fits" / "roc" / "tile.json").read_text())["params"]
    assert fitted and {k: float(v) for k, v in fitted.items()} == pytest.approx(saved)
    # a description with dataset, protocol, horizon and the command that reproduces the run
    note = roc_run.data.tags[run_tags.TAG_NOTE]
    for part in (f"`{DS}`", "`commanded`", "6 s", "skidbench fit", "models=[roc]", "terrains=[tile]"):
        assert part in note
    # who and what created it
    for r in (parent, roc_run):
        assert r.data.tags["mlflow.user"] and r.data.tags["mlflow.source.type"] == "LOCAL"
        assert r.data.tags["mlflow.source.name"]
    # the splits as dataset inputs: Train, CV and LD of the terrain, with their fingerprints
    inputs = {d.dataset.name: d for d in roc_run.inputs.dataset_inputs}
    assert set(inputs) == {f"{DS}/tile/train", f"{DS}/tile/cv", f"{DS}/tile/ld"}
    ld = inputs[f"{DS}/tile/ld"]
    assert {t.key: t.value for t in ld.tags}["mlflow.data.context"] == "ld"
    assert json.loads(ld.dataset.source)["uri"].endswith("splits/tile/ld")
    assert json.loads(ld.dataset.profile)["num_rows"] == 600  # 20 s at 30 Hz
    # the experiment opens on its runs in the MLflow 3 UI
    exp = client.get_experiment(parent.info.experiment_id)
    assert exp.tags[run_tags.TAG_EXPERIMENT_KIND] == "custom_model_development"


def test_parent_runs_are_unique_and_searchable(real_models):
    out, cfg, res, client, runs = real_models
    again = run_benchmark(cfg, log_figures=False)
    names = [client.get_run(r).info.run_name for r in (res.parent_run_id, again.parent_run_id)]
    user = f"{current_user()}@{socket.gethostname().split('.')[0]}"
    assert all(n.startswith(f"evaluate {DS} commanded {user} 20") for n in names)  # what, whose, when
    assert names[0] != names[1]
    exp = client.get_experiment_by_name(f"skidbench-{DS}")
    found = client.search_runs(
        [exp.experiment_id], f"attributes.run_name LIKE 'evaluate {DS} commanded %'", max_results=10
    )
    assert {r.info.run_id for r in found} == {res.parent_run_id, again.parent_run_id}


def test_pyfunc_signature_rejects_a_table_without_the_protocols_columns(real_models):
    out, cfg, res, client, runs = real_models
    mlflow.set_tracking_uri(f"sqlite:///{out / 'mlflow.db'}")
    m = mlflow.pyfunc.load_model(f"models:/{runs['ideal'].data.tags['skidbench.logged_model']}")
    table = sequence_table(seed=1, duration_s=2.0).drop(columns=["cmd_dwl"])
    table["sequence"] = "s0"
    with pytest.raises(mlflow.exceptions.MlflowException, match="cmd_dwl"):
        m.predict(table[[c for c in INPUT_COLUMNS if c != "cmd_dwl"]])
    pred = m.predict(pd.concat([table, pd.DataFrame({"cmd_dwl": np.zeros(len(table))})], axis=1))
    assert list(pred.columns) == ["vx", "vy", "wz"] and len(pred) == len(table)


def test_a_fit_runs_model_is_logged_too(real_models):
    from skidbench.models.fitting.app import log_fit_run
    from skidbench.models.fitting.fit import FitSettings, fit_model
    from skidbench.pipeline.core.layout import layout_from_cfg

    out, _, _, client, runs = real_models
    cfg = compose("fit", out, ["model=roc", "terrain=tile", "calibrate.use=false"])
    res = fit_model(FitSettings.from_cfg(cfg), "roc", "tile")  # the evaluate's fit, reused
    run = client.get_run(log_fit_run(cfg, layout_from_cfg(cfg), "roc", "tile", res, "train"))
    assert run.data.params["fitted.b1"] == runs["roc"].data.params["fitted.b1"]
    model = client.get_logged_model(run.data.tags["skidbench.logged_model"])
    assert model.source_run_id == run.info.run_id
    assert "skidbench fit model=roc terrain=tile" in run.data.tags[run_tags.TAG_NOTE]
