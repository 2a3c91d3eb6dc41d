"""SE(2)/SE(3) helpers: closed forms and round trips."""

import numpy as np
import pytest

from skidbench.pipeline.core import geometry as g


def test_compose_with_inverse_is_identity():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(50, 3))
    np.testing.assert_allclose(g.wrap_angle(g.se2_compose(a, g.se2_inverse(a))), 0.0, atol=1e-12)


def test_relative_then_compose_round_trips():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(2, 50, 3))
    np.testing.assert_allclose(g.se2_compose(a, g.se2_relative(a, b)), b, atol=1e-12)


def test_constant_twist_integrates_to_exact_circle():
    v, w, dt, n = 1.0, 0.5, 0.01, 628
    poses = g.integrate_body_velocity(np.zeros(3), np.tile([v, 0.0, w], (n, 1)), dt)
    t = dt * n
    expected = [v / w * np.sin(w * t), v / w * (1 - np.cos(w * t)), w * t]
    np.testing.assert_allclose(poses[-1], expected, atol=1e-12)


def test_straight_line_has_no_lateral_motion():
    poses = g.integrate_body_velocity(np.array([1.0, 2.0, np.pi / 2]), np.tile([2.0, 0, 0], (10, 1)), 0.1)
    np.testing.assert_allclose(poses[-1], [1.0, 4.0, np.pi / 2], atol=1e-12)


@pytest.mark.parametrize("yaw", [-3.0, -1.0, 0.0, 0.7, 3.1])
def test_quaternion_yaw_round_trip(yaw):
    assert g.yaw_from_quaternion(g.quaternion_from_yaw(yaw)) == pytest.approx(yaw)


def test_matrix_quaternion_round_trip():
    rng = np.random.default_rng(2)
    q = rng.normal(size=(20, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.sign(q[:, 3:4])
    np.testing.assert_allclose(g.matrix_to_quaternion(g.quaternion_to_matrix(q)), q, atol=1e-12)


def test_se3_inverse_and_projection():
    T = g.se3_from_xyz_rpy(np.array([1.0, 2.0, 0.3]), np.array([0.0, 0.0, 0.4]))
    np.testing.assert_allclose(T @ g.se3_inverse(T), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(g.se3_to_se2(T), [1.0, 2.0, 0.4], atol=1e-12)
