"""``skidbench calibrate``: effective wheel radius and track width from the Train split (closed-form data).

The simulated robot's wheels follow their commands with a 3 % steady tracking error (the encoders see
it), and the body moves by an effective radius and an effective track width unlike the spec sheet's:
calibration must recover both from the encoders and the ground truth to 1 %, fall back to the commanded
rates for the radius (and say it cannot identify the track width) without encoders, and every model must
be fitted with the calibrated constants it takes, or with the spec sheet's under ``calibrate.use=false``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import discover_data as dd  # noqa: E402

from skidbench.pipeline.calibrate.calibration import calibrate_table  # noqa: E402
from skidbench.pipeline.calibrate.settings import CalibrationSettings  # noqa: E402
from skidbench.pipeline.core.schema import concat_sequences, write_split

R_TRUE = dd.R_WHEEL * 1.06  # effective radius, 6 % over the spec sheet (dd.R_WHEEL = the Jackal's)
B_TRUE = dd.TRACK * 1.45  # effective track (ICR spread), 45 % over the spec sheet
TRACKING = 0.97  # the wheels hold 97 % of their commanded rate


def _sequence(rng, duration: float, kind: str = "train", lag: tuple[float, float] | None = None):
    """Split table of one sequence: commands converted to wheel rates with the spec constants, wheels at
    TRACKING x command (encoders: that plus 0.05 rad/s noise), body by R_TRUE / B_TRUE, VO-like poses.
    ``lag`` = (dead time, time constant) in s: the encoders read the wheels' response to the commands
    instead, a dead time then a first-order lag integrated exactly on the 180 Hz simulation clock."""
    dt = 1.0 / 180.0
    t, v, w = dd.joystick(rng, duration, dt, kind)
    step = 4  # 45 Hz commands, held
    hold = (np.arange(len(t)) // step) * step
    wl = TRACKING * (v[hold] - w[hold] * dd.TRACK / 2) / dd.R_WHEEL
    wr = TRACKING * (v[hold] + w[hold] * dd.TRACK / 2) / dd.R_WHEEL
    vx = R_TRUE * (wl + wr) / 2
    wz = R_TRUE * (wr - wl) / B_TRUE
    pose = dd.integrate(t, vx, np.zeros_like(vx), wz)
    tl, loc = dd.vo_poses(rng, t, pose)
    import pandas as pd

    cmd = pd.DataFrame({"t": t[::step], "v": v[::step], "w": w[::step]})
    df = dd.to_split(cmd, pd.DataFrame({"t": tl, "x": loc[:, 0], "y": loc[:, 1], "yaw": loc[:, 2]}))
    t_grid = df["t"].to_numpy() + max(cmd.t.iloc[0], tl[0])
    idx = np.clip(np.searchsorted(t, t_grid, side="right") - 1, 0, len(t) - 1)
    if lag is not None:
        delay_s, tau_s = lag
        k = int(round(delay_s / dt))
        u = np.column_stack([wl, wr])
        u = np.vstack([np.repeat(u[:1], k, axis=0), u[: len(u) - k]])  # the command delay_s earlier
        y = np.empty_like(u)
        y[0] = u[0]
        a = 1.0 - np.exp(-dt / tau_s)  # exact for a command held over each simulation step
        for i in range(1, len(u)):
            y[i] = y[i - 1] + a * (u[i - 1] - y[i - 1])
        wl, wr = y[:, 0], y[:, 1]
    df["enc_wl"] = wl[idx] + rng.normal(0, 0.05, len(df))
    df["enc_wr"] = wr[idx] + rng.normal(0, 0.05, len(df))
    return df


@pytest.fixture(scope="module")
def calib_root(tmp_path_factory) -> Path:
    """An output root with dataset ``calib``: splits of one terrain (6 Train sequences, one CV, one LD)."""
    from skidbench.pipeline.core.manifest import Manifest, Sequence

    root = tmp_path_factory.mktemp("calib")
    rng = np.random.default_rng(5)
    seqs = []
    for split, n, dur in (("train", 6, 40.0), ("cv", 1, 30.0), ("ld", 1, 40.0)):
        for i in range(n):
            name = f"tile_{split}_{i:02d}"
            meta = {"sequence": name, "terrain": "tile", "split": split, "robot": "jackal", "sources": {},
                    "rate_hz": 30.0}  # fmt: skip
            df = _sequence(rng, dur, "cv" if split == "cv" else "train")
            write_split(df, root / "calib" / "splits" / "tile" / split / f"{name}.parquet", meta)
            seqs.append(Sequence(name, "tile", split, f"{name}.bag"))
    # stages take their sequences from the manifest (pipeline/core/layout.py)
    Manifest(seqs, base=root / "calib" / "raw").write(root / "calib" / "raw" / "manifest.json")
    return root


def _train_table(root: Path, encoders: bool = True):
    from skidbench.pipeline.core.schema import load_split_tables

    tables = load_split_tables(root / "calib" / "splits", "tile", "train")
    table = concat_sequences(tables)
    if not encoders:
        table["enc_wl"] = np.nan
        table["enc_wr"] = np.nan
    return table


def test_calibration_recovers_injected_radius_and_track_width_to_one_percent(calib_root, jackal):
    doc = calibrate_table(_train_table(calib_root), jackal, CalibrationSettings())
    assert doc["source"] == "encoders"
    r, B = doc["wheel_radius"], doc["track_width"]
    assert r["identified"] and B["identified"]
    assert r["value"] == pytest.approx(R_TRUE, rel=0.01), r
    assert B["value"] == pytest.approx(B_TRUE, rel=0.01), B
    # the spec sheet's values are far outside the intervals; the intervals are honest (not zero width)
    assert r["ci"][0] < r["value"] < r["ci"][1] and r["ci"][1] < 1.02 * R_TRUE
    assert B["ci"][0] < B["value"] < B["ci"][1] and B["ci"][1] - B["ci"][0] < 0.05 * B_TRUE
    assert not (r["ci"][0] <= jackal.wheel_radius <= r["ci"][1])
    assert doc["not_identified"] == []


def test_without_encoders_radius_comes_from_commands_and_track_width_is_not_identified(calib_root, jackal):
    doc = calibrate_table(_train_table(calib_root, encoders=False), jackal, CalibrationSettings())
    assert doc["source"] == "commands"
    # the commanded rates are 1/TRACKING of the real ones: the radius from commands carries the tracking error
    assert doc["wheel_radius"]["identified"]
    assert doc["wheel_radius"]["value"] == pytest.approx(R_TRUE * TRACKING, rel=0.01)
    assert "commanded" in doc["wheel_radius"]["note"]
    tw = doc["track_width"]
    assert not tw["identified"] and tw["value"] == jackal.track_width
    assert "no wheel encoders" in tw["reason"]
    assert doc["not_identified"] == ["track_width"]


def test_calibration_identifies_an_injected_dead_time_and_lag_of_the_wheels(jackal):
    """The wheel response ``calibrate`` writes next to the radius and track width recovers the encoders'
    dead time (to one 30 Hz clock step) and lag (to 10 %), with its structure chosen on held-out blocks and
    an uncertainty per parameter; the ``response`` inputs built from it then match the encoders."""
    from skidbench.pipeline.calibrate.calibration import wheel_response_of
    from skidbench.pipeline.core.protocol import model_inputs

    rng = np.random.default_rng(11)
    tables = [(_sequence(rng, 40.0, lag=(0.2, 0.35)), {"sequence": f"s{i}"}) for i in range(4)]
    table = concat_sequences(tables)
    doc = calibrate_table(table, jackal, CalibrationSettings(bootstrap=50))
    wr = doc["wheel_response"]
    # the wheels also hold TRACKING of their command: the held-out choice adds the static gain
    assert wr["identified"] and wr["structure"].startswith("delay+lag"), wr["structure"]
    assert wr["delay_s"] == pytest.approx(0.2, abs=1 / 30), wr
    assert wr["tau_s"] == pytest.approx(0.35, rel=0.10), wr
    assert wr["gain_s"] == pytest.approx(TRACKING, abs=0.02) and wr["gain_d"] == pytest.approx(
        TRACKING, abs=0.02
    )
    assert wr["rmse_response"] < 0.3 * wr["rmse_command"]
    assert {"delay_s", "tau_s"} <= set(wr["param_se"]) and wr["heldout_rmse"] > 0
    resp = wheel_response_of(doc)
    got = model_inputs(table, "response", jackal, resp)[["cmd_wl", "cmd_wr"]].to_numpy()
    enc = table[["enc_wl", "enc_wr"]].to_numpy()
    assert np.sqrt(np.mean((got - enc) ** 2)) < 0.1  # the encoders' noise is 0.05 rad/s
    # without encoders: not identified, and said so (inputs=response unavailable for the terrain)
    none = calibrate_table(
        table.assign(enc_wl=np.nan, enc_wr=np.nan), jackal, CalibrationSettings(bootstrap=50)
    )
    assert (
        not none["wheel_response"]["identified"] and "no wheel encoders" in none["wheel_response"]["reason"]
    )
    assert wheel_response_of(none) is None


def _cfg(root: Path, *over: str):
    from hydra import compose, initialize_config_module

    with initialize_config_module("skidbench.conf", version_base="1.3"):
        return compose("evaluate", [f"out_root={root}", "dataset=calib", *over])


def test_models_take_the_calibrated_constants_unless_calibrate_use_is_false(calib_root, jackal):
    from omegaconf import OmegaConf

    from skidbench.models.fitting.fit import FitSettings, fit_model
    from skidbench.pipeline.calibrate.calibration import (
        MissingCalibrationError,
        calibrate_terrain,
    )
    from skidbench.pipeline.core.layout import layout_from_cfg

    cfg = _cfg(calib_root)
    # fit never calibrates: without `skidbench calibrate` it stops and says to run it
    with pytest.raises(MissingCalibrationError, match="skidbench calibrate"):
        fit_model(FitSettings.from_cfg(cfg), "ideal", "tile")
    calibrate_terrain(layout_from_cfg(cfg), "tile", jackal, OmegaConf.to_object(cfg.calibrate), "calib")
    ideal = fit_model(FitSettings.from_cfg(cfg), "ideal", "tile")
    assert ideal.model.robot.wheel_radius == pytest.approx(R_TRUE, rel=0.01)
    assert ideal.model.robot.track_width == pytest.approx(B_TRUE, rel=0.01)
    saved = json.loads(ideal.path.read_text())
    assert saved["robot_constants"]["track_width"]["source"] == "calibrated"
    # edd: chi absorbs the track width, so it keeps the spec sheet's and chi is the calibrated ratio
    # (from commanded rates, so it also absorbs the wheels' 3 % tracking error)
    edd = fit_model(FitSettings.from_cfg(cfg), "edd", "tile")
    assert edd.model.robot.track_width == jackal.track_width
    assert edd.model.robot.wheel_radius == pytest.approx(R_TRUE, rel=0.01)
    assert edd.model.params["chi"] == pytest.approx(B_TRUE / (TRACKING * jackal.track_width), rel=0.01)
    assert "absorbed" in json.loads(edd.path.read_text())["robot_constants"]["track_width"]["source"]
    # calibrate.use=false: the spec sheet, and the fit is redone (its stamp includes the constants)
    off = fit_model(FitSettings.from_cfg(_cfg(calib_root, "calibrate.use=false")), "ideal", "tile")
    assert not off.reused
    assert (off.model.robot.wheel_radius, off.model.robot.track_width) == (
        jackal.wheel_radius,
        jackal.track_width,
    )
    assert json.loads(off.path.read_text())["robot_constants"]["wheel_radius"]["source"].startswith("spec")
    # a calibration made for another robot spec is stale: the fit stops rather than recalibrating
    with pytest.raises(MissingCalibrationError, match="stale"):
        fit_model(
            FitSettings.from_cfg(_cfg(calib_root, f"robot.wheel_radius={jackal.wheel_radius * 1.1}")),
            "ideal",
            "tile",
        )
    # the ideal model's yaw rate with the calibrated track is close to the truth (off by the 3 % tracking
    # error of the commanded rates it predicts from), with the spec sheet's 45 % off
    table = _train_table(calib_root)
    ok = table["valid"].to_numpy(bool)
    true = table["wz"].to_numpy()[ok]
    err_cal = np.abs(ideal.model.predict(table)[ok, 2] - true).mean()
    err_spec = np.abs(off.model.predict(table)[ok, 2] - true).mean()
    assert err_cal < 0.2 * err_spec, (err_cal, err_spec)


def test_a_changed_calibration_refits_and_a_stale_one_is_one_line(calib_root, tmp_path, jackal):
    """The fit reads the calibration only when its stamp says it is current (whatever its settings), and
    refits when it changed."""
    import dataclasses
    import shutil

    from omegaconf import OmegaConf

    from skidbench.models.fitting.fit import FitSettings, fit_model
    from skidbench.pipeline.calibrate.calibration import (
        Calibrations,
        MissingCalibrationError,
        calibrate_terrain,
        calibration_doc,
    )
    from skidbench.pipeline.core.layout import layout_from_cfg
    from skidbench.pipeline.core.schema import read_split

    for part in ("splits", "raw"):  # a copy: this test changes its Train files
        shutil.copytree(calib_root / "calib" / part, tmp_path / "calib" / part)
    for f in (tmp_path / "calib" / "splits" / "tile" / "train").glob("*.parquet"):
        df, meta = read_split(
            f
        )  # without encoders: the radius only, no wheel response (seconds, not a minute)
        write_split(df.assign(enc_wl=np.nan, enc_wr=np.nan), f, meta)
    cfg = _cfg(tmp_path)
    layout = layout_from_cfg(cfg)
    settings = dataclasses.replace(OmegaConf.to_object(cfg.calibrate), bootstrap=20)
    calibrate_terrain(layout, "tile", jackal, settings, "calib")
    assert (
        not fit_model(FitSettings.from_cfg(cfg), "edd", "tile").reused
        and fit_model(FitSettings.from_cfg(cfg), "edd", "tile").reused
    )
    # calibrated with other settings: other constants (edd takes the radius; the track width too is part
    # of the fit's inputs)
    settings = dataclasses.replace(settings, settle_s=1.5)
    doc, recomputed = calibrate_terrain(layout, "tile", jackal, settings, "calib")
    assert recomputed and doc == calibration_doc(
        Calibrations.from_cfg(cfg), "tile"
    )  # settings: not a reader's concern
    assert (
        not fit_model(FitSettings.from_cfg(cfg), "edd", "tile").reused
        and fit_model(FitSettings.from_cfg(cfg), "edd", "tile").reused
    )

    def stale(c) -> str:
        with pytest.raises(MissingCalibrationError) as err:
            fit_model(FitSettings.from_cfg(c), "edd", "tile")
        msg = str(err.value)
        assert len(msg.splitlines()) == 1 and "run `skidbench calibrate` first" in msg and "(stale: " in msg
        return msg

    # another robot spec
    assert "made with another robot" in stale(_cfg(tmp_path, "robot.track_width=0.5"))
    # other Train split files (one changed)
    f = sorted((tmp_path / "calib" / "splits" / "tile" / "train").glob("*.parquet"))[0]
    df, meta = read_split(f)
    write_split(df.iloc[:-10].reset_index(drop=True), f, meta)
    assert f"input(s) changed since ({f}" in stale(cfg)
    calibrate_terrain(layout, "tile", jackal, settings, "calib")
    assert fit_model(FitSettings.from_cfg(cfg), "edd", "tile").n_train > 0
    # a calibration stamped by an older version (schema 1: the same key, without what it was made of) is
    # stale to a reader; calibrate finds it up to date and upgrades its stamp instead of recomputing
    stamp = tmp_path / "calib" / ".stamps" / "calibrate" / "tile.json"
    old = {k: v for k, v in json.loads(stamp.read_text()).items() if k not in ("inputs", "config")}
    stamp.write_text(json.dumps({**old, "schema": 1}))
    assert "schema 1" in stale(cfg)
    assert not calibrate_terrain(layout, "tile", jackal, settings, "calib")[1]
    assert calibration_doc(Calibrations.from_cfg(cfg), "tile") is not None
    assert fit_model(
        FitSettings.from_cfg(cfg), "edd", "tile"
    ).reused  # the same calibration: its fit is still up to date


@pytest.mark.slow
def test_calibrate_stage_writes_json_prints_spec_next_to_calibrated_and_logs_mlflow(
    calib_root, jackal, capsys
):
    from hydra import compose, initialize_config_module

    from skidbench.pipeline.calibrate import app as calibrate_app

    with initialize_config_module("skidbench.conf", version_base="1.3"):
        cfg = compose("calibrate", [f"out_root={calib_root}", "dataset=calib", "force=true"])
    calibrate_app.run(cfg)
    out = capsys.readouterr().out
    doc = json.loads((calib_root / "calib" / "calibration" / "tile.json").read_text())
    assert doc["wheel_radius"]["value"] == pytest.approx(R_TRUE, rel=0.01)
    line = next(x for x in out.splitlines() if x.startswith("tile") and "track_width" in x)
    assert f"{jackal.track_width:.4f}" in line and f"{doc['track_width']['value']:.4f}" in line
    import mlflow

    client = mlflow.MlflowClient(f"sqlite:///{calib_root}/mlflow.db")
    exp = client.get_experiment_by_name("skidbench-calib")
    runs = client.search_runs([exp.experiment_id], "tags.`skidbench.role` = 'calibration'")
    assert len(runs) >= 1
    assert runs[0].data.metrics["track_width_tile"] == pytest.approx(doc["track_width"]["value"])
    # what it read (the Train split, as an MLflow dataset input), what it is and how to run it again
    inputs = runs[0].inputs.dataset_inputs
    assert [d.dataset.name for d in inputs] == ["calib/tile/train"]
    assert "skidbench calibrate" in runs[0].data.tags["mlflow.note.content"]
    assert runs[0].info.run_name.startswith("calibrate calib 20")
    cfg.force = False
    calibrate_app.run(cfg)
    assert "up to date, skipped" in capsys.readouterr().out


@pytest.mark.slow
def test_drive_fixtures_run_through_calibrate(shared_real, tmp_path):
    from hydra import compose, initialize_config_module

    from skidbench.pipeline.calibrate import app as calibrate_app
    from skidbench.pipeline.cli.api import prepare_splits

    for robot in ("husky", "warthog"):
        with initialize_config_module("skidbench.conf", version_base="1.3"):
            cfg = compose(
                "calibrate",
                [f"out_root={tmp_path}", "source=drive_df", f"robot={robot}",
                 f"source.root={shared_real / 'drive'}", f"source.file={robot}_windows.parquet"],
            )  # fmt: skip
        prepare_splits(cfg)
        docs = calibrate_app.run(cfg)
        doc = docs["unspecified"]
        assert doc["source"] == "encoders"
        for c in ("wheel_radius", "track_width"):
            d = doc[c]
            assert d["identified"], (robot, c, d)
            assert d["ci"][0] <= d["value"] <= d["ci"][1]
            assert 0.3 < d["ratio_to_spec"] < 4.0
        # skid-steer: the effective track is wider than the physical one
        assert doc["track_width"]["value"] > doc["spec"]["track_width"]
