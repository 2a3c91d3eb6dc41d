"""Learned models: DRIVE's slip BLR and the residual GP recover what generated the data, their fitted
arrays round-trip through files and MLflow artifacts exactly, and the plugin contract's edges (arrays in
params, options on evaluate) are clear errors or work."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from skidbench.models.base import ModelError
from skidbench.models.fitting.fit import FitSettings, ModelConfigs, fit_model, load_fitted, model_config
from skidbench.models.fitting.synthetic import command_table, label_with, write_train_splits
from skidbench.models.kinematic.ideal import IdealDifferentialDrive
from skidbench.models.kinematic.linear import ExtendedDifferentialDrive
from skidbench.models.learned.drive_blr import DriveBLR
from skidbench.models.learned.gp_residual import GPResidual, recent_wheel_acceleration
from skidbench.models.registry.saved import load_arrays, save_arrays
from skidbench.pipeline.core.schema import concat_sequences

NOISE = np.array([0.05, 0.02, 0.04])  # injected velocity noise std (vx m/s, vy m/s, wz rad/s)


def slip_law_table(robot, n_seq=4, n=2500, seed=1):
    """DRIVE's slip law with known weights plus white Gaussian noise of std NOISE."""
    rng = np.random.default_rng(seed)
    tabs = []
    for i in range(n_seq):
        tab = command_table(robot, n, seed=i)
        v, w = robot.twist_from_wheel_rates(tab.cmd_wl.to_numpy(), tab.cmd_wr.to_numpy())
        slip = np.column_stack([0.1 * v, 0.05 * v * w, 0.02 * v * w + 0.03 * v + 0.2 * w])
        vel = np.column_stack([v, np.zeros_like(v), w]) - slip + rng.normal(size=(n, 3)) * NOISE
        tabs.append(label_with(tab, vel))
    return concat_sequences(tabs)


def test_drive_blr_recovers_a_known_slip_law_and_its_noise(jackal):
    table = slip_law_table(jackal)
    m = DriveBLR(jackal).fit(table)
    assert m.params["x"]["weights"]["v"] == pytest.approx(0.1, abs=2e-3)
    assert m.params["y"]["weights"]["v_w"] == pytest.approx(0.05, abs=2e-3)
    yaw = m.params["yaw"]["weights"]
    assert [yaw["v_w"], yaw["v"], yaw["w"]] == pytest.approx([0.02, 0.03, 0.2], abs=4e-3)
    std = np.sqrt(np.diagonal(m.predict_cov(table), axis1=1, axis2=2))
    assert std.mean(0) == pytest.approx(NOISE, rel=0.03)  # predictive variance = injected noise
    rho = m.error_autocorrelation_
    assert rho[0] == pytest.approx(1.0) and np.all(np.abs(rho[1:20]) < 0.05)  # white noise
    steady = DriveBLR(jackal, train_rows="steady", steady_accel_max=5.0).fit(table)  # DRIVE's row choice
    assert steady.params["x"]["weights"]["v"] == pytest.approx(0.1, abs=3e-3)


def test_gp_residual_recovers_a_smooth_residual_of_edd_and_beats_it(jackal):
    rng = np.random.default_rng(2)
    tabs, truth = [], []
    for i in range(4):
        tab = command_table(jackal, 2500, seed=20 + i)
        base = ExtendedDifferentialDrive(jackal, {"chi": 1.5}).predict(tab)
        v, w = tab.cmd_v.to_numpy(), tab.cmd_w.to_numpy()
        res = np.column_stack([0.1 * np.sin(2 * v), 0.05 * np.tanh(v * w), 0.2 * np.sin(w) * np.cos(v)])
        truth.append(base + res)
        tabs.append(label_with(tab, base + res + rng.normal(size=base.shape) * 0.01))
    table, truth = concat_sequences(tabs), np.concatenate(truth)
    gp = GPResidual(jackal, n_inducing=120, max_opt_iter=60).fit(table)
    edd = ExtendedDifferentialDrive(jackal).fit(table)
    err_gp = np.sqrt(np.mean((gp.predict(table) - truth) ** 2, 0))
    err_edd = np.sqrt(np.mean((edd.predict(table) - truth) ** 2, 0))
    assert np.all(err_gp < 0.01) and np.all(err_gp < 0.3 * err_edd)  # the residual is recovered
    std = np.sqrt(np.diagonal(gp.predict_cov(table), axis1=1, axis2=2)).mean(0)
    assert std == pytest.approx([0.01, 0.01, 0.01], rel=0.25)  # noise, plus little posterior variance


def test_gp_residual_reverts_to_its_base_outside_the_training_inputs(jackal):
    """Trained on slow commands, asked about fast ones (beyond the Train range in speed, turn rate and
    acceleration): the residual GP's mean decays to 0 away from its data, so it is never much worse than the
    base it corrects, wherever the held-out inputs are."""
    rng = np.random.default_rng(3)

    def labelled(tab):
        base = ExtendedDifferentialDrive(jackal, {"chi": 1.5}).predict(tab)
        v, w = tab.cmd_v.to_numpy(), tab.cmd_w.to_numpy()
        truth = base + np.column_stack(
            [0.1 * np.sin(2 * v), 0.05 * np.tanh(v * w), 0.2 * np.sin(w) * np.cos(v)]
        )
        return label_with(tab, truth + rng.normal(size=base.shape) * 0.01), truth

    train, _ = labelled(command_table(jackal, 3000, seed=30, v_max=0.4, w_max=0.5))
    test, truth = labelled(command_table(jackal, 3000, seed=31, v_max=1.5, w_max=2.0))
    gp = GPResidual(jackal, n_inducing=60, max_opt_iter=40).fit(train)
    edd = ExtendedDifferentialDrive(jackal).fit(train)
    err_gp = np.sqrt(np.mean((gp.predict(test) - truth) ** 2, 0))
    err_edd = np.sqrt(np.mean((edd.predict(test) - truth) ** 2, 0))
    assert np.all(err_gp <= 1.05 * err_edd + 0.005)


def turning_one_way(tab: pd.DataFrame, sign: float) -> pd.DataFrame:
    """``tab`` with the rows whose sign(v w) is not ``sign`` mirrored left-right (wheels swapped), so that
    forward driving turns one way and reverse driving the other (as the DRIVE Warthog's Train drives)."""
    out = tab.copy()
    flip = np.sign(out.cmd_v * out.cmd_w) == -sign
    for a, b in (("cmd_wl", "cmd_wr"), ("cmd_dwl", "cmd_dwr")):
        out.loc[flip, [a, b]] = out.loc[flip, [b, a]].to_numpy()
    out.loc[flip, "cmd_w"] = -out.loc[flip, "cmd_w"]
    return out


def test_gp_residual_carries_a_correction_to_the_mirrored_turns_train_lacks(jackal):
    """A symmetric robot's residual is odd in the turn (wz = 0.2 sin w) and Train only turns right going
    forward and left in reverse: trained on each row and its mirror image (``mirror_outputs``, by default
    all three), the GP corrects the other turns too (without the mirror images it extrapolates Train's v-w
    coupling there: the DRIVE Warthog's LD regression, CHANGELOG.md gp_residual 2.1), and predicts no wz
    correction driving straight (without them: up to 9e-4 rad/s here)."""
    rng = np.random.default_rng(4)

    def labelled(tab):
        base = ExtendedDifferentialDrive(jackal, {"chi": 1.5}).predict(tab)
        v, w = tab.cmd_v.to_numpy(), tab.cmd_w.to_numpy()
        truth = base + np.column_stack([0.1 * np.sin(2 * v), 0.05 * np.tanh(v * w), 0.2 * np.sin(w)])
        return label_with(tab, truth + rng.normal(size=base.shape) * 0.01), truth

    train, _ = labelled(
        concat_sequences([turning_one_way(command_table(jackal, 2500, seed=s), -1.0) for s in (50, 51)])
    )
    test, truth = labelled(turning_one_way(command_table(jackal, 2500, seed=52), 1.0))
    edd = ExtendedDifferentialDrive(jackal).fit(train)
    err_edd = np.sqrt(np.mean((edd.predict(test) - truth) ** 2, 0))
    err = {}
    for mirror in (True, False):
        gp = GPResidual(
            jackal, n_inducing=100, max_opt_iter=60, mirror_outputs=["vx", "vy", "wz"] if mirror else []
        ).fit(train)
        err[mirror] = np.sqrt(np.mean((gp.predict(test) - truth) ** 2, 0))
    assert err[True][2] < 0.3 * err_edd[2] and err[True][2] < 0.5 * err[False][2]
    straight = test.iloc[:50].copy()
    straight["cmd_wr"], straight["cmd_dwr"], straight["cmd_w"] = straight.cmd_wl, straight.cmd_dwl, 0.0
    gp = GPResidual(jackal, n_inducing=100, max_opt_iter=60).fit(train)
    assert np.abs(gp.predict(straight)[:, 2] - edd.predict(straight)[:, 2]).max() < 1e-4  # odd in (w, dw)


def test_recent_wheel_acceleration_is_the_rms_over_its_time_constant_per_sequence():
    """Constant wheel accelerations a_l, a_r give sqrt((a_l^2 + a_r^2) / 2) from the first row; a step from
    0 to a reaches sqrt(1 - exp(-t / tau)) * a (the average of a^2 rises as a first-order lag); each
    sequence starts afresh."""
    t = np.arange(300) / 30.0
    one = pd.DataFrame({"t": t, "cmd_dwl": 3.0, "cmd_dwr": 4.0, "sequence": "a"})
    assert recent_wheel_acceleration(one, 1.0) == pytest.approx(np.full(300, np.sqrt(12.5)))
    step = pd.DataFrame({"t": t, "cmd_dwl": np.where(t >= 2.0, 2.0, 0.0), "sequence": "b"})
    step["cmd_dwr"] = step["cmd_dwl"]
    got = recent_wheel_acceleration(pd.concat([one, step], ignore_index=True), 1.0)
    assert got[:300] == pytest.approx(np.sqrt(12.5))  # the first sequence's level does not leak into the next
    after = t >= 2.0
    lag = t[after] - 2.0 + 1.0 / 30.0  # the first row at 2.0 s is already in the average (discrete step)
    expected = 2.0 * np.sqrt(1.0 - np.exp(-1.0 / 30.0) ** np.round(lag * 30.0))
    assert got[300:][after] == pytest.approx(expected, rel=1e-9)
    assert np.all(got[300:][~after] == 0.0)


def ar1_noise(rng, n: int, steps: float) -> np.ndarray:
    """(n, 3) unit-variance AR(1) noise with correlation time ``steps`` rows, times NOISE."""
    a = np.exp(-1.0 / steps)
    x = np.zeros((n, 3))
    x[0] = rng.normal(size=3)
    e = rng.normal(size=(n, 3)) * np.sqrt(1.0 - a * a)
    for i in range(1, n):
        x[i] = a * x[i - 1] + e[i]
    return x * NOISE


@pytest.mark.parametrize("steps", [1.0, 30.0])
def test_gp_residual_learns_nothing_from_a_residual_that_is_noise_and_covers_it(jackal, steps):
    """The residual of the base is noise independent of the inputs (white, or correlated over 1 s like a
    drive's errors): held-out blocks of Train show that no correction carries over, so the GP's mean is ~0
    (it predicts as its base) and its 95 % interval covers the noise of new drives 95 % of the time. Fitted
    by the marginal likelihood alone (``cv_folds=0``, version 1), the correlated case gave corrections of
    0.34-0.38 noise std that raised the error by 9-18 %, and the white case covered vy 91 %."""
    rng = np.random.default_rng(5)

    def drives(seeds):
        tabs = []
        for s in seeds:
            tab = command_table(jackal, 2500, seed=s)
            base = ExtendedDifferentialDrive(jackal, {"chi": 1.5}).predict(tab)
            tabs.append(label_with(tab, base + ar1_noise(rng, len(tab), steps)))
        return concat_sequences(tabs)

    train, test = drives([40, 41, 42]), drives([43, 44])
    gp = GPResidual(jackal, n_inducing=100, max_opt_iter=60).fit(train)
    edd = ExtendedDifferentialDrive(jackal).fit(train)
    correction = np.sqrt(np.mean((gp.predict(test) - edd.predict(test)) ** 2, 0))
    assert np.all(correction < 0.1 * NOISE)  # predicts as its base
    err = test[["vx", "vy", "wz"]].to_numpy() - gp.predict(test)
    std = np.sqrt(np.diagonal(gp.predict_cov(test), axis1=1, axis2=2))
    coverage = np.mean(np.abs(err) < 1.96 * std, 0)
    # sampling error of a 95 % coverage on 5,000 rows: 0.3 % (white), 2.4 % (1 s correlation: ~80 independent)
    assert coverage == pytest.approx([0.95] * 3, abs=0.015 if steps == 1.0 else 0.07)


def test_fitted_arrays_round_trip_through_the_fit_files_exactly(tmp_path, jackal, monkeypatch):
    write_train_splits(tmp_path, jackal, terrains=("tile",), n=800)
    cfg = compose_fit(
        tmp_path,
        # calibrate.use=false: the arrays' round trip, not the calibration
        ["model=gp_residual", "terrain=tile", "model.options.n_inducing=40", "model.options.max_opt_iter=20",
         "calibrate.use=false"],
    )  # fmt: skip
    res = fit_model(FitSettings.from_cfg(cfg), "gp_residual", "tile")
    saved = json.loads(res.path.read_text())
    npz = res.path.with_name("tile.arrays.npz")
    assert saved["arrays"]["file"] == npz.name and npz.is_file()
    again = load_fitted(FitSettings.from_cfg(cfg), "gp_residual", "tile")
    assert set(again.arrays) == set(res.model.arrays)
    for k, a in res.model.arrays.items():
        assert np.array_equal(again.arrays[k], a) and again.arrays[k].dtype == a.dtype
    tab = command_table(jackal, 300, seed=5)
    assert np.array_equal(again.predict(tab), res.model.predict(tab))
    assert np.array_equal(again.predict_cov(tab), res.model.predict_cov(tab))
    assert fit_model(FitSettings.from_cfg(cfg), "gp_residual", "tile").reused
    npz.unlink()  # the cache treats the arrays like the JSON: missing arrays refit
    assert not fit_model(FitSettings.from_cfg(cfg), "gp_residual", "tile").reused and npz.is_file()
    npz.write_bytes(npz.read_bytes()[:100])  # and truncated ones
    assert (
        not fit_model(FitSettings.from_cfg(cfg), "gp_residual", "tile").reused
        and fit_model(FitSettings.from_cfg(cfg), "gp_residual", "tile").reused
    )

    import dataclasses

    import skidbench.models.fitting.fit as fitting

    infos = fitting.discover()
    bumped = {**infos, "gp_residual": dataclasses.replace(infos["gp_residual"], package_version="9.9")}
    monkeypatch.setattr(fitting, "discover", lambda: bumped)
    assert not fit_model(
        FitSettings.from_cfg(cfg), "gp_residual", "tile"
    ).reused  # a new package release refits


def test_fitted_arrays_round_trip_through_mlflow_artifacts_exactly(tmp_path):
    from skidbench.benchmark.tracking.store import Tracker

    arrays = {"w": np.random.default_rng(0).normal(size=(7, 3)), "idx": np.arange(5, dtype=np.int32)}
    path = tmp_path / "tile.arrays.npz"
    fp = save_arrays(path, arrays)
    tracker = Tracker(f"sqlite:///{tmp_path / 'mlflow.db'}", "t", tmp_path / "artifacts")
    run_id = tracker.start("r", {})
    tracker.artifact(run_id, path, "fit")
    tracker.end(run_id)
    local = tracker.client.download_artifacts(run_id, "fit/tile.arrays.npz", str(tmp_path / "dl"))
    back = load_arrays(__import__("pathlib").Path(local), fp)
    assert set(back) == set(arrays)
    for k in arrays:
        assert np.array_equal(back[k], arrays[k]) and back[k].dtype == arrays[k].dtype


def test_a_numpy_array_in_params_is_a_clear_model_error(jackal):
    m = IdealDifferentialDrive(jackal)
    m.params = {"coef": np.zeros(3), "k": np.float64(2.0)}
    with pytest.raises(ModelError, match=r"params\['coef'\] is a numpy array.*self.arrays"):
        m.to_json()
    m.params = {"k": np.float64(2.0)}
    assert m.to_json()["params"] == {"k": 2.0}  # numpy scalars are plain numbers


def test_evaluate_model_options_apply_to_the_named_model_or_are_refused():
    cfg = OmegaConf.create({"models": ["drive_blr"], "model": {"options": {"train_rows": "steady"}}})
    assert model_config(ModelConfigs.from_cfg(cfg), "drive_blr")["options"]["train_rows"] == "steady"
    cfg = OmegaConf.create({"models": ["edd", "drive_blr"], "model": {"options": {"train_rows": "steady"}}})
    with pytest.raises(ModelError, match=r"\+model.name"):
        model_config(ModelConfigs.from_cfg(cfg), "drive_blr")
    cfg.model.name = "drive_blr"
    assert model_config(ModelConfigs.from_cfg(cfg), "drive_blr")["options"]["train_rows"] == "steady"
    assert "train_rows" not in model_config(ModelConfigs.from_cfg(cfg), "edd")["options"]
    cfg.model.name = "roc"
    with pytest.raises(ModelError, match="not among models"):
        model_config(ModelConfigs.from_cfg(cfg), "edd")
    cfg = OmegaConf.create({"models": ["drive_blr"], "model": {"options": {"train_row": "steady"}}})
    with pytest.raises(ModelError, match="has no such option"):  # a misspelt option is refused
        model_config(ModelConfigs.from_cfg(cfg), "drive_blr")


def test_unknown_options_of_the_learned_models_are_refused(jackal):
    with pytest.raises(ModelError, match="unknown option"):
        DriveBLR(jackal, train_row="steady")
    with pytest.raises(ModelError, match="unknown option"):
        GPResidual(jackal, inducing=10)


def compose_fit(out_root, overrides=()):
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    with initialize_config_module("skidbench.conf", version_base="1.3"):
        return compose("fit", overrides=[f"out_root={out_root}", *overrides])


def test_a_seeded_model_refits_with_another_seed_without_touching_its_saved_fit(tmp_path, jackal):
    """evaluate seeds=N (docs/intervals.md, "Seeds"): a model with a ``seed`` option is refitted with
    another seed on the same Train table; its inducing points differ, the saved fit stays the configured
    seed's, and a deterministic model declares no seed."""
    from skidbench.models.fitting.fit import is_seeded, refit_from_cfg

    write_train_splits(tmp_path, jackal, terrains=("tile",), n=800)
    cfg = compose_fit(
        tmp_path,
        ["model=gp_residual", "terrain=tile", "model.options.n_inducing=40", "model.options.max_opt_iter=20",
         "model.options.cv_folds=0", "calibrate.use=false"],
    )  # fmt: skip
    res = fit_model(FitSettings.from_cfg(cfg), "gp_residual", "tile")
    saved = res.path.read_bytes()
    refit = refit_from_cfg(cfg, "gp_residual", "tile")
    other = refit.fit(1)
    assert is_seeded(res.model) and other.options["seed"] == 1 and res.model.options["seed"] == 0
    assert set(other.arrays) == set(res.model.arrays)
    assert any(not np.array_equal(other.arrays[k], res.model.arrays[k]) for k in other.arrays)
    assert (
        res.path.read_bytes() == saved and fit_model(FitSettings.from_cfg(cfg), "gp_residual", "tile").reused
    )
    same = refit.fit(0)  # the configured seed: the saved fit, again
    tab = command_table(jackal, 300, seed=5)
    assert np.allclose(same.predict(tab), res.model.predict(tab))
    edd_cfg = compose_fit(tmp_path, ["model=edd", "terrain=tile", "calibrate.use=false"])
    assert not is_seeded(fit_model(FitSettings.from_cfg(edd_cfg), "edd", "tile").model)
