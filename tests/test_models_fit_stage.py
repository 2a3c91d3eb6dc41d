"""``skidbench fit`` and ``fit_model``/``load_fitted`` on split files generated here."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from _bench_data import calibrate_splits
from reliability_data import in_process

from skidbench.models.base import ModelError
from skidbench.models.fitting.synthetic import write_train_splits as make_splits
from skidbench.pipeline.core.schema import write_split


def compose(out_root: Path, overrides=()):
    from hydra import compose as hcompose
    from hydra import initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    with initialize_config_module("skidbench.conf", version_base="1.3"):
        return hcompose("fit", overrides=[f"out_root={out_root}", *overrides])


def test_fit_model_writes_json_and_load_fitted_reads_it(tmp_path, jackal):
    from skidbench.models.fitting.fit import FitSettings, fit_model, load_fitted

    make_splits(tmp_path, jackal)
    cfg = compose(tmp_path, ["model=edd", "terrain=tile"])
    calibrate_splits(cfg)
    res = fit_model(FitSettings.from_cfg(cfg), "edd", "tile")
    assert res.path == tmp_path / "sim-mini" / "fits" / "edd" / "tile.json"
    saved = json.loads(res.path.read_text())
    assert saved["params"]["chi"] == pytest.approx(1.5) and saved["n_train"] == res.n_train == 1200
    assert load_fitted(FitSettings.from_cfg(cfg), "edd", "tile").params["chi"] == pytest.approx(1.5)
    # another model than cfg.model: its config comes from the search path
    assert fit_model(FitSettings.from_cfg(cfg), "roc", "grass").path.name == "grass.json"
    assert fit_model(FitSettings.from_cfg(cfg), "edd", "tile").reused  # unchanged inputs: reused
    assert not fit_model(FitSettings.from_cfg(cfg), "edd", "tile", reuse=False).reused


def test_fit_on_a_split_without_the_needed_columns_names_the_model(tmp_path, jackal):
    from skidbench.models.fitting.fit import FitSettings, fit_model

    make_splits(tmp_path, jackal, terrains=("tile",))
    cfg = compose(tmp_path, ["terrain=tile"])
    with pytest.raises(ModelError, match="no train sequences of terrain sand"):
        fit_model(FitSettings.from_cfg(cfg), "edd", "sand")
    with pytest.raises(ModelError, match="model nope: not installed"):
        fit_model(FitSettings.from_cfg(cfg), "nope", "tile")


def run_cli(args, out_root: Path):
    """``skidbench <args>`` in this process (tests/reliability_data.py ``in_process``)."""
    return in_process(list(args), {**os.environ, "SKIDBENCH_OUT": str(out_root)}, cwd=out_root)


def test_cli_sweep_fits_every_model_and_terrain(tmp_path, jackal):
    make_splits(tmp_path, jackal)
    # fit never calibrates: before `skidbench calibrate` it stops with one line saying to run it
    p = run_cli(["fit", "model=edd", "terrain=tile", "track=false"], tmp_path)
    assert p.returncode == 2
    last = p.stderr.strip().splitlines()[-1]
    assert last.startswith("skidbench fit: error: ") and "run `skidbench calibrate` first" in last
    assert not (tmp_path / "sim-mini" / "fits").exists()
    calibrate_splits(compose(tmp_path))
    p = run_cli(["fit", "-m", "model=edd,full_linear", "terrain=tile,grass", "track=false"], tmp_path)
    assert p.returncode == 0, p.stderr
    fits = sorted(
        str(f.relative_to(tmp_path / "sim-mini" / "fits"))
        for f in (tmp_path / "sim-mini" / "fits").rglob("*.json")
    )
    assert fits == ["edd/grass.json", "edd/tile.json", "full_linear/grass.json", "full_linear/tile.json"]


def test_cli_error_is_one_line_naming_the_model(tmp_path, jackal):
    make_splits(tmp_path, jackal, terrains=("tile",))
    f = next((tmp_path / "sim-mini" / "splits" / "tile" / "train").glob("*.parquet"))
    import pandas as pd

    from skidbench.pipeline.core.schema import read_split

    df, meta = read_split(f)
    df.loc[3, "cmd_wl"] = np.nan
    write_split(pd.DataFrame(df), f, meta)
    # calibrate.use=false: this test is about the model's input check, not the calibration
    p = run_cli(["fit", "model=edd", "terrain=tile", "track=false", "calibrate.use=false"], tmp_path)
    assert p.returncode == 2
    assert (
        p.stderr.strip().splitlines()[-1]
        == "skidbench fit: error: model edd: column cmd_wl holds 1 non-finite value(s)"
    )


def test_a_manifest_sequence_without_its_split_file_is_one_error_naming_it(tmp_path, jackal):
    """One split lookup (Layout.require_split_files): fit and evaluate say the same of a missing file."""
    from skidbench.benchmark.errors import EvaluationError
    from skidbench.benchmark.evaluate.testsets import split_files
    from skidbench.models.fitting.fit import FitSettings, fit_model
    from skidbench.pipeline.core.layout import layout_from_cfg

    make_splits(tmp_path, jackal, terrains=("tile",))
    gone = sorted((tmp_path / "sim-mini" / "splits" / "tile" / "train").glob("*.parquet"))[0]
    gone.unlink()
    cfg = compose(tmp_path, ["terrain=tile", "calibrate.use=false"])
    msg = f"{gone}: no split file for sequence {gone.stem} of "
    with pytest.raises(ModelError, match="run `skidbench split`") as fit_err:
        fit_model(FitSettings.from_cfg(cfg), "edd", "tile")
    assert str(fit_err.value).startswith(f"model edd: {msg}")
    with pytest.raises(EvaluationError) as eval_err:
        split_files(layout_from_cfg(cfg), "tile", "train")
    assert str(eval_err.value).startswith(msg) and str(eval_err.value).endswith("run `skidbench split`")


def test_a_fit_is_reused_until_one_of_its_inputs_changes(tmp_path, jackal, monkeypatch):
    """One definition of up to date (fitting.fit_stamp): each input of a fit refits when it changes."""
    import dataclasses

    from skidbench.models.fitting import fit as fitting
    from skidbench.pipeline.calibrate.wheel_response import WheelResponse

    make_splits(tmp_path, jackal, terrains=("tile",))
    base = ["model=edd", "terrain=tile", "calibrate.use=false"]  # the calibration: the next test

    def fit(*over: str):
        return fitting.fit_model(
            fitting.FitSettings.from_cfg(compose(tmp_path, [*base, *over])), "edd", "tile"
        )

    assert not fit().reused and fit().reused  # unchanged inputs: reused
    changes = {
        "model config": ["+model.params.chi=1.2"],
        "robot constant": [f"robot.wheelbase={jackal.wheelbase * 1.1}"],
        "robot (any key)": [f"robot.mass={jackal.mass + 1}"],
    }
    for what, over in changes.items():
        assert not fit(*over).reused, what
        assert fit(*over).reused, what
        assert not fit().reused, what  # and back
    # another input protocol (inputs=response: the wheel response calibrate identified, given here
    # directly, as the synthetic splits have no encoders): its own fit, which leaves this one up to date
    responses = iter([WheelResponse(), WheelResponse(), WheelResponse(tau_s=0.05)])
    monkeypatch.setattr(fitting, "response_for", lambda cfg, terrain: next(responses))
    other = fit("inputs=response")
    assert not other.reused and other.path.name == "tile.response.json" and fit().reused
    assert fit("inputs=response").reused
    assert not fit("inputs=response").reused  # another wheel response
    # a new release of the model's package (its class version unchanged)
    infos = fitting.discover()
    bumped = {**infos, "edd": dataclasses.replace(infos["edd"], package_version="9.9")}
    monkeypatch.setattr(fitting, "discover", lambda: bumped)
    assert not fit().reused and fit().reused
    # a truncated fit file is refitted, not read
    path = fit().path
    path.write_text(path.read_text()[:40])
    res = fit()
    assert not res.reused and json.loads(path.read_text())["params"] == res.model.params
    # a changed split file
    f = sorted((tmp_path / "sim-mini" / "splits" / "tile" / "train").glob("*.parquet"))[0]
    from skidbench.pipeline.core.schema import read_split

    df, meta = read_split(f)
    write_split(df.iloc[:-10].reset_index(drop=True), f, meta)
    assert not fit().reused and fit().reused


def test_a_fit_whose_hooks_did_not_finish_is_not_up_to_date(tmp_path, jackal):
    from skidbench.models.fitting.fit import FitSettings, fit_model

    make_splits(tmp_path, jackal, terrains=("tile",))
    cfg = compose(tmp_path, ["model=edd", "terrain=tile", "calibrate.use=false"])

    def killed(*_):
        raise KeyboardInterrupt  # the job killed while logging its run

    with pytest.raises(KeyboardInterrupt):
        fit_model(FitSettings.from_cfg(cfg), "edd", "tile", hooks=[killed])
    assert (tmp_path / "sim-mini" / "fits" / "edd" / "tile.json").is_file()
    logged = []
    assert not fit_model(
        FitSettings.from_cfg(cfg), "edd", "tile", hooks=[lambda *a: logged.append(a[1:])]
    ).reused
    assert logged == [("edd", "tile")]
    assert (
        fit_model(FitSettings.from_cfg(cfg), "edd", "tile", hooks=[lambda *a: logged.append(a)]).reused
        and len(logged) == 1
    )


def test_skidbench_fit_after_evaluate_is_up_to_date_and_the_other_way_round(tmp_path, jackal):
    """A fit evaluate made (its default fit function) is the fit stage's, and vice versa."""
    from hydra import compose as hcompose
    from hydra import initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    from skidbench.benchmark.evaluate.fit_record import default_fit_fn
    from skidbench.models.fitting.fit import FitSettings

    make_splits(tmp_path, jackal, terrains=("tile",))
    GlobalHydra.instance().clear()
    with initialize_config_module("skidbench.conf", version_base="1.3"):
        ev = hcompose("evaluate", [f"out_root={tmp_path}", "dataset=sim-mini", "calibrate.use=false"])
        assert not default_fit_fn()(FitSettings.from_cfg(ev), "edd", "tile").reused
    # one command: edd (evaluate's fit) is up to date, roc is fitted
    p = run_cli(
        ["fit", "-m", "model=edd,roc", "terrain=tile", "track=false", "calibrate.use=false"], tmp_path
    )
    assert p.returncode == 0, p.stderr
    assert "fit: edd/tile up to date, skipped" in p.stdout and "roc/tile up to date" not in p.stdout
    with initialize_config_module("skidbench.conf", version_base="1.3"):
        ev = hcompose("evaluate", [f"out_root={tmp_path}", "dataset=sim-mini", "calibrate.use=false"])
        assert default_fit_fn()(FitSettings.from_cfg(ev), "roc", "tile").reused
