"""The friction model's solver numerics: the analytic Jacobians of the force balance, the implicit-function
sensitivities of the solved slips, and the fit that uses them (issue 14)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import scipy.constants

from skidbench.models.fitting.synthetic import command_table, label_with
from skidbench.models.friction.balance import (
    FrictionGeometry,
    balance_jacobians,
    body_velocity,
    free_mask,
    residual,
    velocity_sensitivity,
)
from skidbench.models.friction.model import FrictionBased
from skidbench.models.friction.solver import solve, solve_reference
from skidbench.pipeline.core.constants import STANDARD_GRAVITY

PARAMS = np.array([0.05, 0.9, 0.6, 6.0, 0.3])  # mu_r, mu_x, mu_y, lambda, C


def random_steps(robot, n, seed):
    rng = np.random.default_rng(seed)
    wl, wr = robot.wheel_rates_from_twist(rng.uniform(-1.5, 1.5, n), rng.uniform(-2, 2, n))
    dwl, dwr = robot.wheel_rates_from_twist(rng.normal(0, 1.0, n), rng.normal(0, 3.0, n))
    return wl, wr, dwl, dwr


@pytest.fixture(scope="module")
def offset_geometry(jackal):
    """A CG off the centre and unequal normal loads, so every lever-arm term of eqs. (9)-(11) is exercised."""
    geo = FrictionGeometry.from_robot(jackal)
    return replace(geo, cg=np.array([0.03, -0.01]), normal=geo.normal * np.array([1.1, 0.9, 1.05, 0.95]))


def test_analytic_balance_jacobians_match_central_differences(jackal, offset_geometry):
    geo = offset_geometry
    rng = np.random.default_rng(1)
    n = 400
    wl, wr, dwl, dwr = random_steps(jackal, n, 3)
    th = rng.uniform(-0.3, 0.3, (n, 3))
    # keep away from the kinks of sgn()/clip() where no derivative exists (|ls| = mu_x, V_wx = 0, V_wy = 0)
    F, J, P = balance_jacobians(th, wl, wr, dwl, dwr, PARAMS, geo)
    np.testing.assert_array_equal(F, residual(th, wl, wr, dwl, dwr, PARAMS, geo))
    h = 1e-6
    Jfd = np.empty_like(J)
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        Jfd[:, :, k] = (
            residual(th + e, wl, wr, dwl, dwr, PARAMS, geo) - residual(th - e, wl, wr, dwl, dwr, PARAMS, geo)
        ) / (2 * h)
    Pfd = np.empty_like(P)
    for k in range(5):
        dp = np.zeros(5)
        dp[k] = h * PARAMS[k]
        Pfd[:, :, k] = (
            residual(th, wl, wr, dwl, dwr, PARAMS + dp, geo)
            - residual(th, wl, wr, dwl, dwr, PARAMS - dp, geo)
        ) / (2 * dp[k])
    np.testing.assert_allclose(J, Jfd, atol=1e-7)
    np.testing.assert_allclose(P, Pfd, atol=1e-7)
    # the mu_x column is non-zero only where a side sits on the plateau of eq. (6)
    sat = np.abs(PARAMS[3] * th[:, :2]).max(axis=1) >= PARAMS[1]
    assert sat.any() and not sat.all()
    assert np.all(P[~sat, :, 1] == 0) and np.any(P[sat, :, 1] != 0)


def test_a_side_commanded_to_zero_has_no_jacobian_column(jackal):
    geo = FrictionGeometry.from_robot(jackal)
    wl, wr = np.array([0.0, 5.0]), np.array([5.0, 0.0])
    _, J, _ = balance_jacobians(np.full((2, 3), 0.1), wl, wr, np.zeros(2), np.zeros(2), PARAMS, geo)
    assert np.all(J[0, :, 0] == 0) and np.all(J[1, :, 1] == 0)
    assert np.any(J[0, :, 1] != 0) and np.any(J[1, :, 0] != 0)


def test_velocity_sensitivity_matches_finite_differences_of_the_solve(jackal):
    """The implicit-function derivative of the solved motion equals re-solving at perturbed parameters."""
    geo = FrictionGeometry.from_robot(jackal)
    inp = random_steps(jackal, 300, 2)
    sol = solve(*inp, PARAMS, geo)
    assert np.all(sol.status == 1)
    S = velocity_sensitivity(sol.theta, sol.status, *inp, PARAMS, geo)
    h = 1e-5
    for k in range(5):
        dp = np.zeros(5)
        dp[k] = h * PARAMS[k]
        vp = body_velocity(
            solve(*inp, PARAMS + dp, geo, theta0=sol.theta).theta, inp[0], inp[1], geo.r, geo.B
        )
        vm = body_velocity(
            solve(*inp, PARAMS - dp, geo, theta0=sol.theta).theta, inp[0], inp[1], geo.r, geo.B
        )
        np.testing.assert_allclose(S[:, :, k], (vp - vm) / (2 * dp[k]), atol=2e-6, err_msg=f"parameter {k}")
    assert np.abs(S).max() > 0.1


def test_sensitivity_of_steps_without_a_root_is_the_least_squares_one(jackal):
    """Where no root exists (an acceleration friction cannot deliver) the derivative is that of the
    Gauss-Newton minimiser: finite, and equal to -pinv(J) dF/dp."""
    geo = FrictionGeometry.from_robot(jackal)
    wl, wr = np.array([6.0, -4.0]), np.array([6.0, 8.0])
    dwl, dwr = np.array([300.0, -300.0]), np.array([300.0, 300.0])
    sol = solve(wl, wr, dwl, dwr, PARAMS, geo)
    assert np.all(sol.status == 2)
    S = velocity_sensitivity(sol.theta, sol.status, wl, wr, dwl, dwr, PARAMS, geo)
    _, J, P = balance_jacobians(sol.theta, wl, wr, dwl, dwr, PARAMS, geo)
    dth = -np.linalg.pinv(J, rcond=1e-12) @ P
    assert np.all(np.isfinite(S))
    np.testing.assert_allclose(
        S[:, 2], (geo.r * wl[:, None] * dth[:, 0] - geo.r * wr[:, None] * dth[:, 1]) / geo.B
    )
    assert free_mask(wl, wr).all()


def test_the_cost_a_solve_reports_is_the_balance_at_the_slips_it_returns(jackal, offset_geometry):
    """The LM evaluates F at each step's start itself (no separate residual pass): every step's reported
    cost, warm-started or not, restarted or not, standing still or not, is 0.5 |F|^2 of ``residual`` at the
    returned theta, to the bit where the LM produced it."""
    geo = offset_geometry
    # random steps, two accelerations friction cannot deliver (restarted) and a standstill
    extra = ([6.0, -4.0, 0.0], [6.0, 8.0, 0.0], [300.0, -300.0, 0.0], [300.0, 300.0, 0.0])
    wl, wr, dwl, dwr = (
        np.concatenate([a, b]) for a, b in zip(random_steps(jackal, 60, 7), extra, strict=True)
    )
    for theta0 in (None, np.full((wl.size, 3), 0.01)):
        sol = solve(wl, wr, dwl, dwr, PARAMS, geo, theta0=theta0)
        F = residual(sol.theta, wl, wr, dwl, dwr, PARAMS, geo)
        np.testing.assert_allclose(sol.cost, 0.5 * np.sum(F * F, axis=1), rtol=1e-14, atol=0)
        assert sol.info["restarted"] >= 2 and np.all(sol.status[-3:] > 0) and sol.cost[-1] == 0.0
        first = solve(wl, wr, dwl, dwr, PARAMS, geo, theta0=theta0, restarts=False)
        F = residual(first.theta, wl, wr, dwl, dwr, PARAMS, geo)
        np.testing.assert_array_equal(first.cost, 0.5 * np.sum(F * F, axis=1))


def test_a_world_of_other_gravity_is_the_same_model_with_its_force_coefficients_scaled(jackal):
    """The models' g is standard gravity; a world of another g (the simulator's 9.81) costs nothing: every
    ground force of eqs. (5)-(7) is a coefficient times N, N proportional to g, so the balance under g' with
    mu_r, mu_x, mu_y, lambda scaled by g / g' (C unchanged) has the same roots
    (pipeline/core/constants.py)."""
    assert STANDARD_GRAVITY == scipy.constants.g
    std = FrictionGeometry.from_robot(jackal)
    assert std.g == STANDARD_GRAVITY
    world = FrictionGeometry.from_robot(jackal, g=9.81)
    inp = random_steps(jackal, 200, seed=5)
    scaled = PARAMS.copy()
    scaled[:4] *= 9.81 / STANDARD_GRAVITY  # mu_r, mu_x, mu_y, lambda; not C
    a = solve(*inp, scaled, std)
    b = solve(*inp, PARAMS, world)
    both = (a.status == 1) & (b.status == 1) & ~a.saturated(inp[0], inp[1], scaled)
    assert both.sum() >= 180
    np.testing.assert_allclose(a.theta[both], b.theta[both], rtol=0, atol=1e-9)


def test_compiled_solve_agrees_with_the_per_step_reference_on_an_offset_cg(jackal, offset_geometry):
    geo = offset_geometry
    inp = random_steps(jackal, 150, seed=11)
    fast = solve(*inp, PARAMS, geo)
    ref = solve_reference(*inp, PARAMS, geo)
    both = (fast.status == 1) & (ref.status == 1)
    assert both.sum() >= 140
    unique = both & ~ref.saturated(inp[0], inp[1], PARAMS)
    vf = body_velocity(fast.theta, inp[0], inp[1], geo.r, geo.B)
    vr = body_velocity(ref.theta, inp[0], inp[1], geo.r, geo.B)
    assert np.max(np.abs(vf - vr)[unique]) < 1e-9
    assert fast.n_not_converged == ref.n_not_converged == 0


def test_fit_on_data_from_the_model_recovers_its_parameters_to_solver_precision(jackal):
    """With exact parameter derivatives the fit on noise-free data generated by the model lands on the
    generating parameters (not merely near them); mu_x, which nothing here saturates, keeps its start
    raised to the lowest value the data allow."""
    truth_p = {"mu_r": 0.05, "mu_x": 0.9, "mu_y": 0.6, "lambda": 6.0, "C": 0.3}
    table = command_table(jackal, 600, seed=3)
    data = label_with(table, FrictionBased(jackal, truth_p).predict(table))
    start = {"mu_r": 0.035, "mu_x": 0.8, "mu_y": 0.75, "lambda": 8.0, "C": 0.4}
    fitted = FrictionBased(jackal, start).fit(data)
    for k in ("mu_r", "mu_y", "lambda", "C"):
        assert fitted.params[k] == pytest.approx(truth_p[k], rel=1e-8), k
    assert fitted.fit_loss_ < 1e-20
    assert fitted.fit_info_["mu_x_identified"] is False
