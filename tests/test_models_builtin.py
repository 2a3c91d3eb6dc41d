"""The six built-in models: closed forms, parameter recovery, the friction model's physics and solver."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from skidbench.benchmark.scoring.horizon import window_errors
from skidbench.models.base import ModelError
from skidbench.models.fitting.synthetic import command_table, label_with
from skidbench.models.friction.balance import FrictionGeometry, body_velocity
from skidbench.models.friction.model import FrictionBased
from skidbench.models.friction.solver import solve, solve_reference
from skidbench.models.kinematic.enhanced import EnhancedKinematic
from skidbench.models.kinematic.ideal import IdealDifferentialDrive
from skidbench.models.kinematic.linear import ExtendedDifferentialDrive, FullLinear
from skidbench.models.kinematic.roc import RocBased
from skidbench.models.registry.specs import get_model_class

TRUE_FRICTION = {"mu_r": 0.05, "mu_x": 0.9, "mu_y": 0.6, "lambda": 6.0, "C": 0.3}


@pytest.fixture(scope="module")
def table(jackal):
    return command_table(jackal, 1500, seed=3)


@pytest.fixture(scope="module")
def cg_robot(jackal):
    from dataclasses import replace

    return replace(jackal, cg_offset=(0.04, 0.0))


def ideal(robot, table):
    return IdealDifferentialDrive(robot).predict(table)


@pytest.mark.parametrize(
    "cls, params",
    [
        (ExtendedDifferentialDrive, {"chi": 1.0}),
        (RocBased, {"b1": 0.0, "b2": 3.0}),
        (EnhancedKinematic, {f"p{i}": 0.0 for i in range(1, 7)}),
    ],
)
def test_zero_slip_parameters_give_the_ideal_model(jackal, table, cls, params):
    np.testing.assert_allclose(cls(jackal, params).predict(table), ideal(jackal, table), atol=1e-12)


def test_full_linear_with_the_ideal_matrix_is_the_ideal_model(jackal, table):
    A = FullLinear(jackal).ideal_matrix().tolist()
    np.testing.assert_allclose(FullLinear(jackal, {"A": A}).predict(table), ideal(jackal, table), atol=1e-12)


def test_ideal_model_closed_form(jackal):
    df = pd.DataFrame({"cmd_wl": [10.0, -5.0], "cmd_wr": [10.0, 5.0]})
    r, B = jackal.wheel_radius, jackal.track_width
    np.testing.assert_allclose(ideal(jackal, df), [[10 * r, 0, 0], [0, 0, 10 * r / B]])


def test_friction_without_rolling_resistance_or_acceleration_drives_straight_without_slip(jackal):
    df = pd.DataFrame(
        {"cmd_wl": [8.0, -3.0], "cmd_wr": [8.0, -3.0], "cmd_dwl": [0.0, 0.0], "cmd_dwr": [0.0, 0.0]}
    )
    params = {**TRUE_FRICTION, "mu_r": 0.0}
    np.testing.assert_allclose(FrictionBased(jackal, params).predict(df), ideal(jackal, df), atol=1e-10)


def test_friction_with_stiff_longitudinal_contact_has_the_ideal_forward_and_yaw_rates(jackal, table):
    """lambda, mu_x -> infinity, mu_r = 0: slip ratios vanish and eq. (8) gives eq. (1)'s vx and wz. (vy is
    -x_ICR wz, the side slip that balances the centripetal force: a skid-steer robot must skid sideways to
    turn, so a lateral 'no slip' limit does not exist.)"""
    stiff = {"mu_r": 0.0, "mu_x": 1e9, "mu_y": 0.6, "lambda": 1e7, "C": 0.3}
    pred = FrictionBased(jackal, stiff).predict(table)
    np.testing.assert_allclose(pred[:, [0, 2]], ideal(jackal, table)[:, [0, 2]], atol=1e-5)


def test_edd_recovers_chi(jackal, table):
    truth = ExtendedDifferentialDrive(jackal, {"chi": 1.7})
    fitted = ExtendedDifferentialDrive(jackal).fit(label_with(table, truth.predict(table)))
    assert fitted.params["chi"] == pytest.approx(1.7, rel=1e-10)
    assert fitted.fit_loss_ < 1e-20


def test_full_linear_recovers_A(jackal, table):
    A = [[0.05, 0.047], [0.002, -0.001], [-0.21, 0.2]]
    fitted = FullLinear(jackal).fit(label_with(table, FullLinear(jackal, {"A": A}).predict(table)))
    np.testing.assert_allclose(fitted.params["A"], A, atol=1e-10)


def test_roc_recovers_b1_b2(jackal, table):
    truth = RocBased(jackal, {"b1": 0.8, "b2": 2.5})
    fitted = RocBased(jackal).fit(label_with(table, truth.predict(table)))
    assert fitted.params["b1"] == pytest.approx(0.8, rel=1e-6)
    assert fitted.params["b2"] == pytest.approx(2.5, rel=1e-6)


def test_roc_on_data_without_a_radius_effect_reports_b2_at_its_bound(jackal, table, tmp_path):
    """Turning that does not depend on the radius of curvature (edd's constant chi = 1.6): roc's best fit
    is b2 = 0, chi = 1 + b1 = edd's; the fit says so (fit_info_["at_bound"]), and compare's note names
    it with the terrain and value. A roc-shaped truth reports nothing."""
    from skidbench.benchmark.board.compare import _fit_findings
    from skidbench.models.registry.saved import fit_findings
    from skidbench.pipeline.core.layout import Layout

    fitted = RocBased(jackal).fit(
        label_with(table, ExtendedDifferentialDrive(jackal, {"chi": 1.6}).predict(table))
    )
    assert fitted.params["b1"] == pytest.approx(0.6, rel=1e-5) and fitted.params["b2"] < 1e-5
    (found,) = fitted.fit_info_["at_bound"]
    assert found["param"] == "b2" and found["side"] == "lower" and found["bound"] == 0.0
    assert found["finding"] == "roc degenerates to edd on this data: b2 at its bound"
    truth = RocBased(jackal, {"b1": 0.8, "b2": 2.5})
    assert RocBased(jackal).fit(label_with(table, truth.predict(table))).fit_info_ == {}
    # chi = 1 + 5 / sqrt|R| (b1, b2 -> infinity, b1/b2 = 5: the warthog_grass2_raw case): said too
    runaway = RocBased(jackal, {"b1": 5e7, "b2": 1e7})
    (off,) = RocBased(jackal).fit(label_with(table, runaway.predict(table))).fit_info_["at_bound"]
    assert off["side"] == "upper" and off["bound"] is None and "chi = 1 + 5 / sqrt|R|" in off["finding"]
    layout = Layout(tmp_path, "ds")
    path = layout.fit_file("roc", "grass")
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps({"fit_info": fitted.fit_info_}))
    assert fit_findings(json.loads(path.read_text()))[0].startswith(
        "roc degenerates to edd on this data: b2 at its bound (b2 = "
    )
    board = pd.DataFrame({"model": ["roc", "edd"], "terrain": ["grass", "grass"], "status": ["FINISHED"] * 2})
    (note,) = _fit_findings(layout, board, "commanded")
    assert note.startswith("roc degenerates to edd on this data: b2 at its bound (grass: b2 = ")
    # and under evaluate's board (its console print), for the runs that finished
    from skidbench.benchmark.evaluate import app as evaluate_app
    from skidbench.benchmark.evaluate.console import format_result
    from skidbench.benchmark.evaluate.evaluation import BenchmarkResult, ChildResult

    done = BenchmarkResult("uri", "ds", "p", [ChildResult(m, "grass", m, "FINISHED") for m in ("roc", "edd")])
    assert f"\nnote: {note}" in format_result(done, evaluate_app._findings(layout, done))
    done.children[0].status = "FAILED"
    assert evaluate_app._findings(layout, done) == []


def test_enhanced_recovers_p1_to_p6_with_a_cg_offset(cg_robot, table):
    """p1 multiplies f_lon/N, which on flat ground is the centrifugal M w^2 x_CG: it needs x_CG != 0."""
    p = {"p1": 0.5, "p2": -0.05, "p3": 0.1, "p4": 0.3, "p5": 0.02, "p6": -0.15}
    truth = EnhancedKinematic(cg_robot, p)
    fitted = EnhancedKinematic(cg_robot).fit(label_with(table, truth.predict(table)))
    for k, v in p.items():
        assert fitted.params[k] == pytest.approx(v, rel=1e-6, abs=1e-9), k


def test_enhanced_p1_is_not_identifiable_on_flat_ground_with_a_centred_cg(jackal, table):
    p = {"p1": 0.5, "p2": -0.05, "p3": 0.1, "p4": 0.3, "p5": 0.02, "p6": -0.15}
    fitted = EnhancedKinematic(jackal).fit(label_with(table, EnhancedKinematic(jackal, p).predict(table)))
    assert fitted.params["p1"] == 0.0  # f_lon = 0: the minimum-norm solution
    assert fitted.params["p2"] == pytest.approx(-0.05, rel=1e-8)


def test_friction_fit_recovers_its_identifiable_parameters(jackal, table):
    """mu_r, mu_y, lambda, C are recovered; mu_x is not identifiable here because the min() of eq. (6) never
    saturates on this data (lambda |s| stays below mu_x), so any mu_x above that bound fits equally well."""
    truth = FrictionBased(jackal, TRUE_FRICTION)
    data = label_with(table, truth.predict(table))
    assert not truth.last_solve_.saturated(table["cmd_wl"], table["cmd_wr"], TRUE_FRICTION).any()
    start = {"mu_r": 0.035, "mu_x": 0.8, "mu_y": 0.75, "lambda": 8.0, "C": 0.4}
    fitted = FrictionBased(jackal, start).fit(data)
    for k in ("mu_r", "mu_y", "lambda", "C"):
        assert fitted.params[k] == pytest.approx(TRUE_FRICTION[k], rel=0.02), k
    assert fitted.fit_info_["mu_x_identified"] is False
    assert fitted.params["mu_x"] >= fitted.fit_info_["mu_x_lower_bound"]
    json.dumps(fitted.to_json())


def test_friction_yaw_rate_falls_as_commanded_angular_acceleration_rises(jackal):
    """The paper's Fig. 6: fixed wheel rates, larger commanded angular acceleration -> lower yaw rate."""
    wl, wr = jackal.wheel_rates_from_twist(0.8, 1.0)
    dw = np.linspace(0.0, 8.0, 9)  # rad/s^2
    dwl, dwr = jackal.wheel_rates_from_twist(np.zeros_like(dw), dw)
    df = pd.DataFrame({"cmd_wl": wl, "cmd_wr": wr, "cmd_dwl": dwl, "cmd_dwr": dwr})
    wz = FrictionBased(jackal, TRUE_FRICTION).predict(df)[:, 2]
    assert np.all(np.diff(wz) < 0)


def random_steps(robot, n, seed):
    rng = np.random.default_rng(seed)
    wl, wr = robot.wheel_rates_from_twist(rng.uniform(-1.5, 1.5, n), rng.uniform(-2, 2, n))
    dwl, dwr = robot.wheel_rates_from_twist(rng.normal(0, 1.0, n), rng.normal(0, 3.0, n))
    return wl, wr, dwl, dwr


def test_batched_solve_agrees_with_per_step_trust_region_reference(jackal):
    geo = FrictionGeometry.from_robot(jackal)
    inp = random_steps(jackal, 200, seed=7)
    fast = solve(*inp, TRUE_FRICTION, geo)
    ref = solve_reference(*inp, TRUE_FRICTION, geo)
    both = (fast.status == 1) & (ref.status == 1)
    assert both.sum() >= 190
    vf = body_velocity(fast.theta, inp[0], inp[1], geo.r, geo.B)
    vr = body_velocity(ref.theta, inp[0], inp[1], geo.r, geo.B)
    assert np.max(np.abs(vf - vr)[both]) < 1e-6


def test_batched_solve_reports_non_converged_steps(jackal):
    geo = FrictionGeometry.from_robot(jackal)
    sol = solve(*random_steps(jackal, 50, seed=1), TRUE_FRICTION, geo, max_iter=1, restarts=False)
    assert sol.n_not_converged > 0 and sol.n_not_converged == int(np.sum(~sol.converged))


#: parameters like a real fit (the mini asphalt fit): lateral friction above longitudinal, so tight turns and
#: large commanded angular accelerations have no force-balance root (least-squares solutions)
FITTED_FRICTION = {"mu_r": 0.0305, "mu_x": 0.619, "mu_y": 1.03, "lambda": 3.55, "C": 0.207}


@pytest.mark.parametrize("params", [TRUE_FRICTION, FITTED_FRICTION], ids=["true", "fitted"])
def test_batched_solve_converges_on_the_fig6_grid(jackal, params):
    """Every point of a Fig. 6-like grid (wheel rates up to the robot's 2 m/s, both sides through zero,
    commanded angular accelerations -8, 0, +8 rad/s^2) converges: a root or a stationary point of F^T F;
    and where the first pass already found a root it agrees with the per-step reference."""
    geo = FrictionGeometry.from_robot(jackal)
    g = np.linspace(-2.0 / jackal.wheel_radius, 2.0 / jackal.wheel_radius, 21)
    wl, wr = (a.ravel() for a in np.meshgrid(g, g))
    inp = [[], [], [], []]
    for acc in (-8.0, 0.0, 8.0):
        dwl, dwr = jackal.wheel_rates_from_twist(0.0, acc)
        for k, a in enumerate((wl, wr, np.full(wl.size, dwl), np.full(wl.size, dwr))):
            inp[k].append(a)
    inp = [np.concatenate(a) for a in inp]
    sol = solve(*inp, params, geo)
    assert sol.n_not_converged == 0, sol.info
    assert np.all(np.isfinite(sol.theta))
    root = np.flatnonzero(sol.status == 1)
    assert root.size > 0.5 * sol.status.size
    # no-root steps really are no roots: the cost is well above the root tolerance
    assert np.all(np.sqrt(2 * sol.cost[sol.status == 2]) > 1e-9)
    pick = root[:: max(1, root.size // 60)]
    ref = solve_reference(*(a[pick] for a in inp), params, geo)
    both = ref.status == 1
    vf = body_velocity(sol.theta[pick], inp[0][pick], inp[1][pick], geo.r, geo.B)
    vr = body_velocity(ref.theta, inp[0][pick], inp[1][pick], geo.r, geo.B)
    unique = both & ~ref.saturated(inp[0][pick], inp[1][pick], params)
    assert both.mean() > 0.9
    assert np.max(np.abs(vf - vr)[unique], initial=0.0) < 1e-6


def test_standstill_and_one_side_stopped(jackal):
    geo = FrictionGeometry.from_robot(jackal)
    z = np.zeros(3)
    sol = solve(z, z, np.array([0.0, 5.0, -5.0]), np.array([0.0, 5.0, 5.0]), TRUE_FRICTION, geo)
    v = body_velocity(sol.theta, z, z, geo.r, geo.B)
    assert np.all(v == 0) and np.all(np.isfinite(sol.theta)) and np.all(sol.converged)
    # a side commanded to zero has no slip ratio (pinned to 0), and nothing is divided by zero
    sol = solve(np.array([0.0]), np.array([6.0]), np.array([0.0]), np.array([0.0]), TRUE_FRICTION, geo)
    assert sol.theta[0, 0] == 0.0 and np.all(np.isfinite(sol.theta))


@pytest.mark.parametrize("name", ["ideal", "edd", "full_linear", "roc", "enhanced", "friction"])
def test_every_builtin_is_registered_and_round_trips_through_json(jackal, table, name):
    cls = get_model_class(name)
    m = cls(jackal, max_nfev=5).fit(table.iloc[:400])  # max_nfev: only the friction fit iterates
    back = cls.from_json(jackal, json.loads(json.dumps(m.to_json())))
    np.testing.assert_allclose(back.predict(table.iloc[:50]), m.predict(table.iloc[:50]), atol=1e-9)


@pytest.mark.parametrize("name", ["edd", "friction"])
def test_missing_column_is_a_one_line_error_naming_the_model(jackal, table, name):
    with pytest.raises(ModelError, match=rf"model {name}: table lacks column\(s\) \['cmd_wr'\]"):
        get_model_class(name)(jackal).fit(table.drop(columns=["cmd_wr"]))


def test_non_finite_value_is_a_one_line_error_naming_the_model(jackal, table):
    bad = table.copy()
    bad.loc[5, "cmd_dwl"] = np.inf
    with pytest.raises(ModelError, match=r"model friction: column cmd_dwl holds 1 non-finite"):
        FrictionBased(jackal).predict(bad)


def test_invalid_rows_are_ignored_by_fit(jackal, table):
    df = label_with(table, ExtendedDifferentialDrive(jackal, {"chi": 1.4}).predict(table))
    df.loc[:100, "wz"] = np.nan
    df.loc[:100, "valid"] = False
    assert ExtendedDifferentialDrive(jackal).fit(df).params["chi"] == pytest.approx(1.4)


def test_friction_fit_with_some_no_root_steps_still_moves_and_recovers(jackal, table):
    """Steps whose commanded acceleration friction cannot deliver have no root; they are left out of the
    loss (only steps with a root at the start are scored, and stay scored), and must neither freeze the
    fit at its start nor blow up the mu_x bound."""
    truth = FrictionBased(jackal, TRUE_FRICTION)
    data = table.copy()
    rng = np.random.default_rng(5)
    rows = rng.choice(len(data), 25, replace=False)
    data.loc[data.index[rows], "cmd_dwl"] = 400.0  # an impossible wheel acceleration: no root
    data.loc[data.index[rows], "cmd_dwr"] = -400.0
    data = label_with(data, truth.predict(data))
    assert np.sum(truth.last_solve_.status == 2) >= 10
    start = {"mu_r": 0.035, "mu_x": 0.8, "mu_y": 0.75, "lambda": 8.0, "C": 0.4}
    fitted = FrictionBased(jackal, start).fit(data)
    info = fitted.fit_info_
    assert info["steps_excluded_from_loss"] >= 10
    assert info["moved_from_start"] and info["nfev"] > 10
    for k in ("mu_r", "mu_y", "lambda", "C"):
        assert fitted.params[k] == pytest.approx(TRUE_FRICTION[k], rel=0.05), k
    assert info["mu_x_lower_bound"] < 2.0  # from the rooted steps only


def test_a_step_friction_cannot_deliver_is_predicted_at_the_largest_balanced_acceleration(jackal):
    """A command step (a one-sample acceleration pulse of 300 rad/s^2, ~29 m/s^2 at the wheel) has no
    physical force balance: the prediction is the solve at the first fraction of the commanded
    acceleration (ACCEL_SCALES) that has a root with slip ratios in [-1, 1], so the body speed stays
    within 0..2 r omega; without the fallback the same step is not physical."""
    from skidbench.models.friction.model import ACCEL_SCALES

    geo = FrictionGeometry.from_robot(jackal)
    wl = np.array([6.0, 6.0, 6.0, -4.0])
    wr = np.array([6.0, 6.0, 6.0, 8.0])
    dwl = np.array([0.0, 300.0, 0.0, -300.0])
    dwr = np.array([0.0, 300.0, 0.0, 300.0])
    df = pd.DataFrame({"cmd_wl": wl, "cmd_wr": wr, "cmd_dwl": dwl, "cmd_dwr": dwr})
    model = FrictionBased(jackal, TRUE_FRICTION)
    pred = model.predict(df)
    sol = model.last_solve_
    raw = solve(wl, wr, dwl, dwr, TRUE_FRICTION, geo)
    physical = (raw.status == 1) & np.all(np.abs(raw.theta[:, :2]) <= 1, axis=1)
    assert physical[[0, 2]].all() and not physical[[1, 3]].any()  # the pulses are not physical
    np.testing.assert_array_equal(sol.status, raw.status)  # the commanded problem's status is kept
    assert sol.accel_scale[0] == sol.accel_scale[2] == 1.0
    for i in (1, 3):
        k = sol.accel_scale[i]
        assert k in ACCEL_SCALES and k < 1
        again = solve(wl[[i]], wr[[i]], k * dwl[[i]], k * dwr[[i]], TRUE_FRICTION, geo)
        assert again.status[0] == 1 and np.all(np.abs(again.theta[0, :2]) <= 1)
        np.testing.assert_allclose(pred[i], body_velocity(again.theta, wl[[i]], wr[[i]], geo.r, geo.B)[0])
    r = jackal.wheel_radius
    assert np.all(np.abs(pred[:, 0]) <= 2 * r * np.maximum(np.abs(wl), np.abs(wr)))
    off = FrictionBased(jackal, TRUE_FRICTION, accel_fallback=False)
    off.predict(df)
    np.testing.assert_array_equal(off.last_solve_.theta, raw.theta)


def test_label_with_dead_reckons_a_constant_twist_onto_its_circle(jackal, table):
    """Constant (v, w) from the origin: x = v/w sin(w t), y = v/w (1 - cos(w t)), yaw = w t (exact SE(2)
    steps; first-order Euler steps would miss by O(dt) over the run)."""
    v, w = 0.8, 0.5
    t = table["t"].to_numpy() - table["t"].iloc[0]
    labelled = label_with(table, np.tile([v, 0.0, w], (len(table), 1)))
    np.testing.assert_allclose(labelled["yaw"], w * t, atol=1e-9)
    np.testing.assert_allclose(labelled["x"], v / w * np.sin(w * t), atol=1e-9)
    np.testing.assert_allclose(labelled["y"], v / w * (1 - np.cos(w * t)), atol=1e-9)


def test_a_model_that_predicts_the_labelled_velocities_has_zero_horizon_error(jackal, table):
    """label_with integrates as the horizon evaluation does, so the truth model scores exactly zero."""
    vel = ExtendedDifferentialDrive(jackal, {"chi": 1.4}).predict(table)
    df = label_with(table, vel)
    err = window_errors(df["t"].to_numpy(), df[["x", "y", "yaw"]].to_numpy(), vel, 6.0)
    assert len(err) > 100
    assert err["trans_err"].abs().max() < 1e-9 and err["rot_err"].abs().max() < 1e-9
