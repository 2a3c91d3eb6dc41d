"""The friction model on real robots: the actuator (dead time + lag) it is driven by, the steady-state
closed forms its fit starts from, recovery of known parameters on Husky geometry, and the DRIVE Husky
fit with every parameter off its bounds."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from skidbench.models import actuator
from skidbench.models.friction import PARAM_RANGES, FrictionBased, bound_report
from skidbench.models.friction_solver import FrictionGeometry, body_velocity, solve
from skidbench.models.synthetic import command_table, label_with
from skidbench.pipeline.robot import load_robot

#: physically plausible friction on a Husky-sized robot; lambda |s| stays under mu_x (mu_x identifiable
#: only at saturation, so it is not asserted)
HUSKY_FRICTION = {"mu_r": 0.06, "mu_x": 2.5, "mu_y": 0.7, "lambda": 2.5, "C": 0.3}


@pytest.fixture(scope="module")
def husky():
    return load_robot("husky")


def _step_table(n=3000, rate=30.0, seed=0, delay_s=0.3, tau_s=0.45):
    """Held wheel commands changing every 2 s, and encoders = the closed-form response of a dead time
    ``delay_s`` followed by a first-order lag ``tau_s`` (sum of delayed exponential step responses)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate
    k_step = int(2 * rate)
    levels = rng.uniform(-6, 6, size=(n // k_step + 1, 2))
    cmd = np.repeat(levels, k_step, axis=0)[:n]
    enc = np.repeat(cmd[:1], n, axis=0).astype(float)
    for j in range(1, len(levels)):
        ts = j * k_step / rate
        if ts >= t[-1]:
            break
        du = levels[j] - levels[j - 1]
        arg = t - ts - delay_s
        enc += np.where(arg[:, None] >= 0, du * (1 - np.exp(-np.clip(arg, 0, None) / tau_s))[:, None], 0.0)
    v = (cmd[:, 0] + cmd[:, 1]) / 2
    return pd.DataFrame(
        {"t": t, "cmd_v": v, "cmd_w": cmd[:, 1] - cmd[:, 0], "cmd_wl": cmd[:, 0], "cmd_wr": cmd[:, 1],
         "cmd_dwl": np.gradient(cmd[:, 0], t), "cmd_dwr": np.gradient(cmd[:, 1], t),
         "enc_wl": enc[:, 0], "enc_wr": enc[:, 1]}
    )  # fmt: skip


def test_actuator_identifies_an_injected_dead_time_and_lag():
    table = _step_table(delay_s=0.3, tau_s=0.45)
    fit = actuator.identify(table)
    assert fit.delay_s == pytest.approx(0.3, abs=1e-6)  # a multiple of the 1/30 s clock
    assert fit.tau_s == pytest.approx(0.45, rel=0.02)
    assert fit.rmse_actuator < 0.02 * fit.rmse_command
    out = actuator.apply(table, fit.delay_s, fit.tau_s)
    # the output's derivative is the lag's own: (u(t - d) - w) / tau, finite where the command steps
    assert np.abs(out["cmd_dwl"]).max() < 12.0 / 0.45 + 1e-6 < np.abs(table["cmd_dwl"]).max()


def test_actuator_is_not_identified_without_encoders():
    table = _step_table().assign(enc_wl=np.nan, enc_wr=np.nan)
    assert actuator.identify(table) is None


def test_actuator_restarts_at_each_sequence():
    a = _step_table(n=600, seed=1).assign(sequence="a")
    b = _step_table(n=600, seed=2).assign(sequence="b", t=lambda d: d["t"])
    out = actuator.apply(pd.concat([a, b], ignore_index=True), 0.2, 0.4)
    # b's first rows hold b's own first command, not a's last output
    assert out["cmd_wl"].iloc[600] == pytest.approx(b["cmd_wl"].iloc[0])


def test_husky_steady_slips_match_the_closed_forms(husky):
    """No acceleration: driving straight, lambda s = mu_r; turning in place about the centre, lambda s = mu_r
    + (a/b) mu_y (1 - exp(-atan(a/b)/C)) and x_ICR = 0 (the relations the fit's start is computed from)."""
    p = HUSKY_FRICTION
    geo = FrictionGeometry.from_robot(husky)
    a, b = np.abs(geo.wheel_xy[0])
    straight = solve(np.array([5.0]), np.array([5.0]), np.zeros(1), np.zeros(1), p, geo)
    assert straight.status[0] == 1
    assert straight.theta[0, :2] == pytest.approx([p["mu_r"] / p["lambda"]] * 2, rel=1e-8)
    spin = solve(np.array([-5.0]), np.array([5.0]), np.zeros(1), np.zeros(1), p, geo)
    s_spin = (p["mu_r"] + (a / b) * p["mu_y"] * (1 - np.exp(-np.arctan2(a, b) / p["C"]))) / p["lambda"]
    assert spin.status[0] == 1
    assert spin.theta[0, :2] == pytest.approx([s_spin, s_spin], rel=1e-8)
    assert spin.theta[0, 2] == pytest.approx(0.0, abs=1e-9)
    v = body_velocity(spin.theta, np.array([-5.0]), np.array([5.0]), geo.r, geo.B)
    assert v[0, 2] == pytest.approx((1 - s_spin) * geo.r * 10 / geo.B, rel=1e-8)


def test_steady_state_start_inverts_the_closed_forms(husky):
    """Steady straight and spin rows labelled by the model: the start recovers lambda and mu_r exactly
    when mu_y and C are the configured ones."""
    p = HUSKY_FRICTION
    n = 200
    wl = np.r_[np.full(n, 4.0), np.full(n, -4.0)]
    wr = np.r_[np.full(n, 4.0), np.full(n, 4.0)]
    z = np.zeros(2 * n)
    truth = FrictionBased(husky, p)
    y, _ = truth.velocities((wl, wr, z, z))
    start = {**p, "lambda": 10.0, "mu_r": 0.01}
    m = FrictionBased(husky, start)
    info = m.steady_state_start((wl, wr, z, z), y, ["mu_r", "mu_x", "mu_y", "lambda", "C"])
    assert info["source"] == "steady_state"
    assert m.params["lambda"] == pytest.approx(p["lambda"], rel=1e-6)
    assert m.params["mu_r"] == pytest.approx(p["mu_r"], rel=1e-6)


def test_friction_fit_on_husky_geometry_recovers_known_parameters_inside_the_bounds(husky):
    """Noise-free data labelled by the model with known parameters on the Husky's geometry (no actuator):
    the fit, started 30 % away, recovers them, inside the bounds, with small Jacobian standard errors."""
    table = command_table(husky, 500, seed=3, v_max=0.9, w_max=1.2)
    truth = FrictionBased(husky, HUSKY_FRICTION, actuator="none")
    data = label_with(table, truth.predict(table))
    assert not truth.last_solve_.saturated(table["cmd_wl"], table["cmd_wr"], HUSKY_FRICTION).any()
    names = ["mu_r", "mu_y", "lambda", "C"]
    start = {k: v * (1.3 if k in names else 1.0) for k, v in HUSKY_FRICTION.items()}
    fitted = FrictionBased(husky, start, actuator="none", start="config", fit_params=names).fit(data)
    for k in names:
        assert fitted.params[k] == pytest.approx(HUSKY_FRICTION[k], rel=0.02), k
        assert fitted.fit_info_["param_bound_margin"][k] > 0.01, k
        assert 0 <= fitted.fit_info_["param_stderr"][k] < 0.1 * fitted.params[k], k


def test_bound_report_margins_and_gauss_newton_stderr():
    """Margins in log space (0 on a bound, 0.5 in the middle); the standard error of a linear problem in
    z = log p is sigma sqrt((J^T J)^-1), turned into p by p * se."""
    lo, hi = PARAM_RANGES["mu_y"]
    mid = float(np.sqrt(lo * hi))
    J = np.array([[1.0, 0.0], [0.0, 2.0], [1.0, 0.0], [0.0, 2.0], [1.0, 1.0]])
    res = type("R", (), {"jac": J, "cost": 0.5 * 3.0})()  # sum of squares 3 over 5 - 2 dof -> s2 = 1
    out = bound_report({"mu_y": mid, "C": PARAM_RANGES["C"][0]}, ["mu_y", "C"], PARAM_RANGES, res)
    assert out["param_bound_margin"]["mu_y"] == pytest.approx(0.5)
    assert out["param_bound_margin"]["C"] == pytest.approx(0.0, abs=1e-12)
    cov = np.linalg.inv(J.T @ J)
    assert out["param_stderr"]["mu_y"] == pytest.approx(mid * np.sqrt(cov[0, 0]))


@pytest.fixture(scope="module")
def drive_husky_fit(shared_real, tmp_path_factory):
    """The friction model fitted on the first 120 s of the DRIVE Husky's Train split (real data)."""
    from drive_data import drive_splits

    from skidbench.models.base import concat_sequences
    from skidbench.pipeline.schema import read_split

    splits = drive_splits(shared_real / "drive", tmp_path_factory.mktemp("drive"), "husky")
    table, _ = read_split(splits / "unspecified" / "train" / "husky_train_00.parquet")
    return FrictionBased(load_robot("husky"), max_nfev=40).fit(concat_sequences([table.iloc[:3600]]))


def test_drive_husky_fit_identifies_the_actuator_and_keeps_mu_r_lambda_c_off_their_bounds(drive_husky_fit):
    """Real data: the wheels' dead time and lag come from the encoders, and the parameters 1.5 pressed
    against a bound (mu_r at 0.499 of 0.5) lie more than 1 % of their (log) range inside."""
    m = drive_husky_fit
    info = m.fit_info_
    assert info["actuator"]["source"] == "encoders"
    assert 0.1 < m.params["actuator_delay_s"] < 0.6
    # friction 1.7: a lag per sum/difference mode (a slew limit may carry most of the sum mode's response)
    assert 0.01 <= m.params["actuator_tau_s"] < 1.5 and 0.1 < m.params["actuator_tau_d_s"] < 1.5
    assert info["actuator"]["rmse_response"] <= info["actuator"]["candidates"]["delay+lag"]["train_rmse"]
    margins = info["param_bound_margin"]
    assert min(margins[n] for n in ("mu_r", "mu_x", "lambda", "C")) > 0.01, margins


def test_fit_quality_metrics_flatten_margins_and_stderr_for_mlflow():
    from types import SimpleNamespace

    from skidbench.benchmark.evaluate import fit_quality_metrics

    info = {"param_bound_margin": {"mu_r": 0.3}, "param_stderr": {"mu_r": 0.01, "C": float("nan")}}
    fit = SimpleNamespace(model=SimpleNamespace(fit_info_=info), path=None)
    assert fit_quality_metrics(fit) == {"param_bound_margin.mu_r": 0.3, "param_stderr.mu_r": 0.01}
    assert fit_quality_metrics(SimpleNamespace(model=object(), path=None)) == {}
