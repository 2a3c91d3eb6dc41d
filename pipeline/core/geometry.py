"""SE(2)/SE(3) geometry: the one home for pose composition, angle wrapping and quaternion conversion.

Planar poses are arrays ``(..., 3)`` of ``(x, y, yaw)`` in metres and radians. Quaternions are
``(..., 4)`` in ``(qx, qy, qz, qw)`` order (ROS and TUM order).
"""

from __future__ import annotations

import numpy as np


def wrap_angle(a: np.ndarray | float) -> np.ndarray:
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def se2_compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a (+) b: pose ``b`` expressed in frame ``a``, mapped to a's parent frame. Broadcasts."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, a[..., 2] + b[..., 2]], axis=-1)


def se2_inverse(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -c * a[..., 0] - s * a[..., 1]
    y = s * a[..., 0] - c * a[..., 1]
    return np.stack([x, y, -a[..., 2]], axis=-1)


def se2_relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(-a) (+) b: pose of ``b`` in the frame of ``a``. Yaw is not wrapped (keeps unwrapped differences)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx = b[..., 0] - a[..., 0]
    dy = b[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, b[..., 2] - a[..., 2]], axis=-1)


def integrate_body_velocity(pose0: np.ndarray, vel: np.ndarray, dt: np.ndarray | float) -> np.ndarray:
    """Dead-reckon body-frame velocities ``vel`` (T, 3) = (vx, vy, wz) from ``pose0`` (3,).

    Exact SE(2) exponential per step (constant body twist over each interval). ``dt`` is a scalar or
    (T,) array of step lengths; returns poses (T+1, 3) with yaw unwrapped (cumulative).
    """
    vel = np.asarray(vel, dtype=float)
    dt = np.broadcast_to(np.asarray(dt, dtype=float), vel.shape[:1])
    steps = se2_exp(vel * dt[:, None])
    # yaw is cumulative; positions need the running heading, so accumulate in two passes
    yaw = pose0[2] + np.concatenate([[0.0], np.cumsum(steps[:, 2])])
    c, s = np.cos(yaw[:-1]), np.sin(yaw[:-1])
    dx = c * steps[:, 0] - s * steps[:, 1]
    dy = s * steps[:, 0] + c * steps[:, 1]
    x = pose0[0] + np.concatenate([[0.0], np.cumsum(dx)])
    y = pose0[1] + np.concatenate([[0.0], np.cumsum(dy)])
    return np.stack([x, y, yaw], axis=-1)


def step_velocities(velocity: np.ndarray) -> np.ndarray:
    """(T-1, 3) the body twist of each step between T samples of (vx, vy, wz): the mean of the velocities
    at the step's two ends (the trapezoidal rule, exact for a velocity linear in time), for
    :func:`integrate_body_velocity`. The rule of the horizon evaluation: holding the left sample's velocity
    over the step instead costs 0.4-0.8 % RMSRE at 30 Hz on the simulator's exact truth."""
    velocity = np.asarray(velocity, dtype=float)
    return 0.5 * (velocity[:-1] + velocity[1:])


def se2_exp(xi: np.ndarray) -> np.ndarray:
    """SE(2) exponential of twists ``xi`` (..., 3) = (dx, dy, dtheta) in the body frame."""
    xi = np.asarray(xi, dtype=float)
    th = xi[..., 2]
    small = np.abs(th) < 1e-9
    th_safe = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(th_safe) / th_safe)  # sin(th)/th
    b = np.where(small, th / 2.0, (1.0 - np.cos(th_safe)) / th_safe)  # (1-cos th)/th
    x = a * xi[..., 0] - b * xi[..., 1]
    y = b * xi[..., 0] + a * xi[..., 1]
    return np.stack([x, y, th], axis=-1)


def yaw_from_quaternion(q: np.ndarray) -> np.ndarray:
    """Yaw (rotation about z, ZYX convention) of quaternions (..., 4) in (qx, qy, qz, qw) order."""
    q = np.asarray(q, dtype=float)
    qx, qy, qz, qw = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def quaternion_from_yaw(yaw: np.ndarray) -> np.ndarray:
    yaw = np.asarray(yaw, dtype=float)
    z = np.zeros_like(yaw)
    return np.stack([z, z, np.sin(yaw / 2.0), np.cos(yaw / 2.0)], axis=-1)


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from unit quaternions (..., 4) in (qx, qy, qz, qw) order."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r = np.empty(q.shape[:-1] + (3, 3))
    r[..., 0, 0] = 1 - 2 * (y * y + z * z)
    r[..., 0, 1] = 2 * (x * y - z * w)
    r[..., 0, 2] = 2 * (x * z + y * w)
    r[..., 1, 0] = 2 * (x * y + z * w)
    r[..., 1, 1] = 1 - 2 * (x * x + z * z)
    r[..., 1, 2] = 2 * (y * z - x * w)
    r[..., 2, 0] = 2 * (x * z - y * w)
    r[..., 2, 1] = 2 * (y * z + x * w)
    r[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def matrix_to_quaternion(r: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) (qx, qy, qz, qw), qw >= 0, from rotation matrices (..., 3, 3).

    Vectorised: each matrix uses the best conditioned of the four standard formulas (the largest of
    4 qw^2, 4 qx^2, 4 qy^2, 4 qz^2)."""
    r = np.asarray(r, dtype=float)
    m = r.reshape(-1, 3, 3)
    m00, m11, m22 = m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]
    # 4 q_i^2 for i = w, x, y, z
    sq = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], 1)
    k = np.argmax(sq, axis=1)
    big = np.sqrt(np.maximum(sq[np.arange(len(m)), k], 1e-300))  # = 2 |q_k|
    d21, d02, d10 = m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]
    s01, s02, s12 = m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1]
    # rows: (qx, qy, qz, qw) * 2|q_k|, for k = w, x, y, z
    cand = np.stack(
        [
            np.stack([d21, d02, d10, big * big], 1),
            np.stack([big * big, s01, s02, d21], 1),
            np.stack([s01, big * big, s12, d02], 1),
            np.stack([s02, s12, big * big, d10], 1),
        ],
        1,
    )
    out = cand[np.arange(len(m)), k] / (2.0 * big)[:, None]
    out *= np.where(out[:, 3:4] < 0, -1.0, 1.0)
    return out.reshape(r.shape[:-2] + (4,))


def se3_matrix(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Homogeneous transforms (..., 4, 4) from translations (..., 3) and quaternions (..., 4)."""
    t = np.asarray(t, dtype=float)
    out = np.zeros(t.shape[:-1] + (4, 4))
    out[..., :3, :3] = quaternion_to_matrix(q)
    out[..., :3, 3] = t
    out[..., 3, 3] = 1.0
    return out


def se3_inverse(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    out = np.zeros_like(T)
    rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def se3_from_xyz_rpy(xyz: np.ndarray, rpy: np.ndarray) -> np.ndarray:
    """A 4x4 transform from a translation and roll-pitch-yaw (ZYX, radians), as URDF writes it."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rot = np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )
    T = np.eye(4)
    T[:3, :3] = rot
    T[:3, 3] = xyz
    return T


def se3_to_se2(T: np.ndarray) -> np.ndarray:
    """Project transforms (..., 4, 4) to planar poses (..., 3): x, y and the yaw of the x axis."""
    T = np.asarray(T, dtype=float)
    return np.stack([T[..., 0, 3], T[..., 1, 3], np.arctan2(T[..., 1, 0], T[..., 0, 0])], axis=-1)


def quaternion_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products ``a b`` of quaternions (..., 4) in (qx, qy, qz, qw) order (rotation ``b`` first,
    then ``a``, as for matrices). Broadcasts."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    ax, ay, az, aw = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bx, by, bz, bw = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def quaternion_slerp(q0: np.ndarray, q1: np.ndarray, frac: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (..., 4) (qx, qy, qz, qw) at fractions (...)
    (0 gives ``q0``, 1 gives ``q1``), along the shorter arc: ``q0 exp(frac log(q0^-1 q1))``.

    The relative rotation's half angle comes from ``atan2``: no precision is lost for the small
    rotations between consecutive samples (``arccos`` of a dot product would lose half the digits)."""
    q0 = np.asarray(q0, dtype=float)
    frac = np.asarray(frac, dtype=float)
    conj = q0 * np.array([-1.0, -1.0, -1.0, 1.0])
    rel = quaternion_multiply(conj, q1)
    rel = np.where(rel[..., 3:4] < 0, -rel, rel)  # the shorter arc
    s = np.linalg.norm(rel[..., :3], axis=-1)
    half = np.arctan2(s, rel[..., 3])
    scale = np.where(s > 0, np.sin(frac * half) / np.where(s > 0, s, 1.0), frac)
    step = np.concatenate([rel[..., :3] * scale[..., None], np.cos(frac * half)[..., None]], axis=-1)
    return quaternion_multiply(q0, step)
