"""The horizon's uncertainty scores: a model whose velocity errors are Gaussian with the covariance it
claims covers the true end pose 95 % of the time at the nominal 95 % (white and time-correlated errors),
and one that claims too little covers less."""

from __future__ import annotations

import numpy as np
import pytest

from skidbench.benchmark.scoring.horizon import (
    CHI2_95_1DOF,
    CHI2_95_2DOF,
    correlation_inflation,
    window_errors,
)
from skidbench.pipeline.core.geometry import integrate_body_velocity

N_SEQ = 1500  # independent sequences, one window each: coverage sampling std = sqrt(.95 .05 / 1500) = 0.56 %
STD = np.array([0.08, 0.05, 0.06])  # vx m/s, vy m/s, wz rad/s


def coverage(rho: float = 0.0, claimed_scale: float = 1.0, seed: int = 0) -> tuple[float, float]:
    """(position, yaw) coverage of the 95 % region over N_SEQ independent 2 s windows at 10 Hz, errors
    AR(1) with coefficient ``rho`` and stationary std STD; the model claims STD * claimed_scale. The
    windows are blocks of one long trajectory (nominal velocity and error restart per block); only the
    windows that start on a block boundary are scored, so they share no step."""
    rng = np.random.default_rng(seed)
    n, dt = 20, 0.1
    block = n + 1
    nominal = np.zeros((N_SEQ, block, 3))
    nominal[:, :, 0] = rng.uniform(0.3, 1.5, (N_SEQ, 1))
    nominal[:, :, 2] = rng.uniform(-1, 1, (N_SEQ, 1))
    e = np.empty((N_SEQ, block, 3))
    e[:, 0] = rng.normal(size=(N_SEQ, 3)) * STD
    for k in range(1, block):  # stationary AR(1), every block at once
        e[:, k] = rho * e[:, k - 1] + np.sqrt(1 - rho**2) * rng.normal(size=(N_SEQ, 3)) * STD
    nominal, e = nominal.reshape(-1, 3), e.reshape(-1, 3)
    T = len(nominal)
    t = np.arange(T) * dt
    gt = integrate_body_velocity(np.zeros(3), (nominal + e)[:-1], dt)
    cov = np.broadcast_to(np.diag((STD * claimed_scale) ** 2), (T, 3, 3))
    autocorr = rho ** np.arange(n)[:, None] * np.ones((1, 3)) if rho else None
    w = window_errors(t, gt, nominal, n * dt, velocity_cov=cov, autocorr=autocorr)
    w = w[w["start"] % block == 0]
    assert len(w) == N_SEQ
    return float(np.mean(w["pos_d2"] <= CHI2_95_2DOF)), float(np.mean(w["yaw_z2"] <= CHI2_95_1DOF))


def test_known_white_gaussian_velocity_noise_is_covered_95_percent():
    pos, yaw = coverage()
    tol = 3 * np.sqrt(0.95 * 0.05 / N_SEQ)  # 3 sampling standard deviations
    assert pos == pytest.approx(0.95, abs=tol) and yaw == pytest.approx(0.95, abs=tol)


def test_time_correlated_noise_is_covered_95_percent_with_its_autocorrelation():
    pos, yaw = coverage(rho=0.8, seed=1)
    tol = 3 * np.sqrt(0.95 * 0.05 / N_SEQ)
    assert yaw == pytest.approx(0.95, abs=tol)  # yaw: the inflation is exact (a sum of rates)
    # position: the inflation treats correlated steps as sharing one lever arm; slightly conservative
    assert pos == pytest.approx(0.95, abs=tol + 0.01) and pos >= 0.95 - tol


def test_an_overconfident_model_covers_less():
    pos, yaw = coverage(claimed_scale=0.5, seed=2)
    assert pos < 0.75 and yaw < 0.75


def test_correlation_inflation_closed_forms():
    assert correlation_inflation(None, 10) == pytest.approx(np.ones(3))
    ones = np.ones((50, 3))  # fully correlated: the sum of n steps has n times the white variance
    assert correlation_inflation(ones, 10) == pytest.approx(np.full(3, 10.0))
    rho = 0.5 ** np.arange(50)[:, None] * np.ones((1, 3))
    n = 10
    k = np.arange(1, n)
    expected = 1 + 2 * np.sum((1 - k / n) * 0.5**k)
    assert correlation_inflation(rho, n) == pytest.approx(np.full(3, expected))
