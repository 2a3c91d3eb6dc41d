"""The friction model on real robots: the wheel response (dead time + lag) the calibration identifies,
the steady-state closed forms its fit starts from, recovery of known parameters on Husky geometry, and
the DRIVE Husky fit with every parameter off its bounds."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from skidbench.models.fitting.synthetic import command_table, label_with
from skidbench.models.friction.balance import FrictionGeometry, body_velocity
from skidbench.models.friction.fit import PARAM_RANGES, bound_report
from skidbench.models.friction.model import FrictionBased
from skidbench.models.friction.solver import solve
from skidbench.pipeline.calibrate import actuator
from skidbench.pipeline.calibrate.wheel_response import identify_response
from skidbench.pipeline.core.robot import load_robot

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
    truth = FrictionBased(husky, HUSKY_FRICTION)
    data = label_with(table, truth.predict(table))
    assert not truth.last_solve_.saturated(table["cmd_wl"], table["cmd_wr"], HUSKY_FRICTION).any()
    names = ["mu_r", "mu_y", "lambda", "C"]
    start = {k: v * (1.3 if k in names else 1.0) for k, v in HUSKY_FRICTION.items()}
    fitted = FrictionBased(husky, start, start="config", fit_params=names).fit(data)
    for k in names:
        assert fitted.params[k] == pytest.approx(HUSKY_FRICTION[k], rel=0.02), k
        assert fitted.fit_info_["param_bound_margin"][k] > 0.01, k
        assert 0 <= fitted.fit_info_["param_stderr"][k] < 0.1 * fitted.params[k], k


def _wide_turns(robot, n=500, seed=3):
    """Forward driving (0.3-0.9 m/s) with yaw rates under 0.4 rad/s: turn radii of 0.75 m and more, so the
    wheels' slip angles stay small (under about 0.2 rad)."""
    table = command_table(robot, n, seed=seed, v_max=0.3, w_max=0.4)
    v = table["cmd_v"].to_numpy() + 0.6
    wl, wr = robot.wheel_rates_from_twist(v, table["cmd_w"].to_numpy())
    return table.assign(cmd_v=v, cmd_wl=wl, cmd_wr=wr)


def test_friction_fit_in_the_linear_lateral_regime_holds_mu_y_and_recovers_the_lateral_stiffness(husky):
    """Data from a lateral law that never saturates (C = 40 rad against slip angles under 0.2 rad: eq. (7)
    is mu_y / C |alpha| = 1.0 |alpha|): the free fit runs along mu_y / C to mu_y's upper bound, so mu_y is
    reported as not identified and held inside its range, the refit keeps every parameter more than 1 %
    of its (log) range from its bounds, and recovers the lateral stiffness mu_y / C, mu_r and lambda."""
    truth_p = {"mu_r": 0.06, "mu_x": 2.5, "mu_y": 40.0, "lambda": 2.5, "C": 40.0}
    table = _wide_turns(husky)
    truth = FrictionBased(husky, truth_p)
    data = label_with(table, truth.predict(table))
    start = {"mu_r": 0.08, "mu_x": 2.5, "mu_y": 0.8, "lambda": 3.2, "C": 0.4}
    names = ["mu_r", "mu_x", "mu_y", "lambda", "C"]
    fitted = FrictionBased(husky, start, start="config", fit_params=names).fit(data)
    info, p = fitted.fit_info_, fitted.params
    lateral = info["lateral"]
    assert lateral["mu_y_identified"] is False
    assert lateral["upper_bound_margin_free_fit"]["mu_y"] < 0.01  # where the free fit went
    assert info["param_identified"]["mu_y"] == 0.0 and info["param_identified"]["C"] == 1.0
    assert lateral["slip_angle_p95"] < 0.25 and lateral["lateral_reach"] < 0.1  # the law's linear part
    assert p["mu_y"] == pytest.approx(lateral["mu_y_held"])
    assert lateral["mu_y_lower_bound"] <= p["mu_y"] < PARAM_RANGES["mu_y"][1]
    assert min(info["param_bound_margin"].values()) > 0.01, info["param_bound_margin"]
    assert p["mu_y"] / p["C"] == pytest.approx(1.0, rel=0.05)
    assert p["mu_r"] == pytest.approx(0.06, rel=0.03)
    assert p["lambda"] == pytest.approx(2.5, rel=0.03)
    # a held parameter has no standard error of its own; the fitted ones keep theirs
    assert np.isnan(info["param_stderr"]["mu_y"]) and info["param_stderr"]["C"] > 0
    assert info["param_stderr_free_fit"]["mu_y"] > 0
    # holding mu_y costs little: the data cannot tell the held law from the free fit's
    assert lateral["robust_cost_held"] < 2.0 * lateral["robust_cost_free"] + 1e-6


def test_friction_fit_in_the_saturating_regime_recovers_all_five_and_identifies_mu_y(husky):
    """Data from a law that saturates in both directions (slip angles beyond C = 0.3 in the turns, and
    lambda |s| reaching mu_x = 0.5 on some steps): all five parameters recovered from 30 % away, each
    identified, with small standard errors."""
    truth_p = {"mu_r": 0.06, "mu_x": 0.5, "mu_y": 0.7, "lambda": 2.5, "C": 0.3}
    table = command_table(husky, 500, seed=3, v_max=0.9, w_max=1.2)
    truth = FrictionBased(husky, truth_p)
    data = label_with(table, truth.predict(table))
    assert truth.last_solve_.saturated(table["cmd_wl"], table["cmd_wr"], truth_p).sum() > 50
    start = {k: v * 1.3 for k, v in truth_p.items()}
    fitted = FrictionBased(husky, start, start="config", fit_params=list(truth_p)).fit(data)
    info = fitted.fit_info_
    assert info["lateral"]["mu_y_identified"] is True and info["lateral"]["lateral_reach"] > 1.0
    for k, v in truth_p.items():
        assert fitted.params[k] == pytest.approx(v, rel=0.02), k
        assert info["param_identified"][k] == 1.0, k
        assert info["param_bound_margin"][k] > 0.01, k
        assert 0 < info["param_stderr"][k] < 0.1 * v, k


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
    # a held parameter: its margin is reported, its standard error is not (the fit did not move it)
    held = bound_report({"mu_y": mid, "C": 0.1, "mu_r": 0.5}, ["mu_y", "C"], PARAM_RANGES, res, held=["mu_r"])
    assert held["param_bound_margin"]["mu_r"] == pytest.approx(0.0, abs=1e-12)
    assert np.isnan(held["param_stderr"]["mu_r"])


@pytest.fixture(scope="module")
def drive_husky_fit(shared_real, tmp_path_factory):
    """The friction model fitted on the first 300 s of the DRIVE Husky's Train split (real data; its first
    sequences, cut where DRIVE's windows are not back to back)."""
    from drive_data import drive_splits, split_table

    from skidbench.pipeline.core.protocol import fit_table

    splits = drive_splits(shared_real / "drive", tmp_path_factory.mktemp("drive"), "husky")
    husky = load_robot("husky")
    table = split_table(splits, rows=6000)
    # the fair protocol: driven by the wheel response identified from the Train encoders, as any model
    response = identify_response(table)
    model = FrictionBased(husky, max_nfev=40).fit(fit_table(table, "response", husky, response.response))
    return model, response


@pytest.mark.slow
def test_drive_husky_fit_under_response_keeps_every_parameter_off_its_bounds(drive_husky_fit):
    """Real data: the wheels' dead time and lag come from the encoders (the calibration's wheel response,
    pipeline/calibrate/wheel_response.py), and the friction model driven by it has every parameter more than
    1 % of
    its (log) range inside its bounds: those 1.5 pressed against one (mu_r at 0.499 of 0.5) and mu_y,
    which 1.6 ran to 3.0 of 3.0 along mu_y / C (the Husky's lateral law is linear over its slip angles:
    1.7 holds mu_y, reported as not identified, and fits the lateral stiffness mu_y / C)."""
    m, response = drive_husky_fit
    info = m.fit_info_
    assert 0.1 < response.response.delay_s < 0.6
    assert 0.01 <= response.response.tau_s < 1.5 and 0.1 < response.response.tau_d_s < 1.5
    assert response.rmse_response <= response.candidates["delay+lag"]["train_rmse"]
    assert not any(k.startswith("actuator_") for k in m.params)  # 1.9: five parameters, the paper's
    margins = info["param_bound_margin"]
    assert set(margins) == {"mu_r", "mu_x", "mu_y", "lambda", "C"}
    assert min(margins.values()) > 0.01, margins
    lateral = info["lateral"]
    assert lateral["mu_y_identified"] is False and info["param_identified"]["mu_y"] == 0.0
    assert m.params["mu_y"] == pytest.approx(lateral["mu_y_held"])
    # the identified quantity: the lateral stiffness, pinned to better than 25 % (Gauss-Newton)
    assert 0 < lateral["lateral_stiffness_stderr"] < 0.25 * lateral["lateral_stiffness"]


def test_fit_quality_metrics_flatten_margins_and_stderr_for_mlflow():
    from types import SimpleNamespace

    from skidbench.benchmark.evaluate.fit_record import fit_quality_metrics

    info = {
        "param_bound_margin": {"mu_r": 0.3},
        "param_stderr": {"mu_r": 0.01, "C": float("nan")},
        "param_identified": {"mu_y": 0.0},
    }
    fit = SimpleNamespace(model=SimpleNamespace(fit_info_=info), path=None)
    assert fit_quality_metrics(fit) == {
        "param_bound_margin.mu_r": 0.3,
        "param_stderr.mu_r": 0.01,
        "param_identified.mu_y": 0.0,
    }
    assert fit_quality_metrics(SimpleNamespace(model=object(), path=None)) == {}
