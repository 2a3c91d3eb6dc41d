"""The friction-based kinematic model's force balance (paper eqs. 4-11), batched over time steps.

At each time step t the unknowns are theta_t = (s_l, s_r, x_ICR) (left/right slip ratio, ICR offset, m);
the inputs are the wheel rates (wl, wr, rad/s) and their derivatives (dwl, dwr, rad/s^2) of the run's input
protocol. ``residual`` evaluates the force/torque balance F(theta) (eqs. 9-11) for all steps at once,
``balance_jacobians`` its analytic dF/dtheta and dF/dp, and ``velocity_sensitivity`` the derivative of the
solved motion with respect to the parameters by the implicit function theorem (what the fit's Jacobian is
made of); ``body_velocity`` is eq. (8). Solving F(theta) = 0 is ``friction_solver``'s.

The physics lives once, in the compiled ``step_balance`` (numba): every step is a 3-unknown problem with
its own iteration count, which compiled per-step loops do without the per-iteration Python overhead a
vectorised batch paid while a few stragglers iterated (``make bench BENCH=friction_fit``).

Conventions (SPEC.md "Models", notes on the friction model):
- F is normalised: F1, F2 by M g and F3 by M g b (b = half track) so that one tolerance fits all three;
  the roots are the paper's. g is standard gravity (``STANDARD_GRAVITY``), the model's, whatever world
  the data come from.
- (a_x, a_y) = (dv_x - w v_CGy, dv_y + w v_CGx) (rigid-body transport term), with the commanded
  accelerations in place of dv_x, dv_y, dw (the paper's zero-order approximation).
- |alpha| = atan2(|V_wy|, |V_wx|), defined at V_wx = 0; only |alpha| enters eq. (7).
- The tractive force of eq. (6) is written sgn(omega) * clip(lambda s, -mu_x, mu_x) N: identical to
  sgn(s) sgn(V_wx) min(|s| lambda N, mu_x N) while s < 1 (the only case where V_wx and omega agree in sign),
  and continuous across V_wx = 0, which the solver needs.
- Rolling resistance mu_r N acts against each wheel's own longitudinal velocity V_wx (sgn(0) = 0).
- A side whose commanded rate is zero has no slip ratio (eq. 4 divides by r omega): its s is pinned to 0
  and takes no part in the solve. A robot commanded to stand still is predicted to stand still (eq. 8).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from skidbench.pipeline.core.constants import STANDARD_GRAVITY

PARAM_NAMES = ("mu_r", "mu_x", "mu_y", "lambda", "C")
#: |omega| below this (rad/s) counts as a commanded zero rate: that side has no slip ratio
ZERO_RATE = 1e-9


@dataclass(frozen=True)
class FrictionGeometry:
    """Robot constants the force balance needs. Wheels in the order FL, RL, FR, RR (left = +y)."""

    r: float
    B: float
    mass: float
    I_z: float
    wheel_xy: np.ndarray  # (4, 2) from the geometric centre, m
    cg: np.ndarray  # (2,) (x_CG, y_CG), m
    normal: np.ndarray  # (4,) static normal forces N_i, N
    g: float = STANDARD_GRAVITY

    @classmethod
    def from_robot(cls, robot, g: float = STANDARD_GRAVITY) -> FrictionGeometry:
        xy = np.asarray(robot.wheel_positions, dtype=float)
        cg = np.asarray(robot.cg_offset, dtype=float)
        a, b = np.abs(xy[0])
        # static load distribution: sum N_i = M g, sum N_i (x_i, y_i) = M g (x_CG, y_CG)
        sx, sy = np.sign(xy[:, 0]), np.sign(xy[:, 1])
        normal = robot.mass * g / 4.0 * (1 + sx * cg[0] / a) * (1 + sy * cg[1] / b)
        return cls(
            r=float(robot.wheel_radius),
            B=float(robot.track_width),
            mass=float(robot.mass),
            I_z=float(robot.I_z),
            wheel_xy=xy,
            cg=cg,
            normal=normal,
            g=g,
        )

    @property
    def force_scale(self) -> np.ndarray:
        """Normalisation of (F1, F2, F3): M g, M g, M g B/2."""
        w = self.mass * self.g
        return np.array([w, w, w * self.B / 2.0])


def body_velocity(theta: np.ndarray, wl: np.ndarray, wr: np.ndarray, r: float, B: float) -> np.ndarray:
    """Eq. (8): (T, 3) slip/ICR state and wheel rates -> (T, 3) body velocities (vx, vy, wz)."""
    el = r * (1.0 - theta[..., 0]) * wl  # ground speed of the left wheel centres, V_wx
    er = r * (1.0 - theta[..., 1]) * wr
    wz = (er - el) / B
    return np.stack([(el + er) / 2.0, -theta[..., 2] * wz, wz], axis=-1)


# ---- the force balance of one step, compiled (numba): the one home of eqs. (4)-(11) in code ----
# geometry vector layout (``geo_vector``): r, B, M, I_z, x_CG, y_CG, X[4], Y[4], N[4], scale[3]
_GX, _GY, _GN, _GS = 6, 10, 14, 18


def geo_vector(geo: FrictionGeometry) -> np.ndarray:
    return np.concatenate(
        [
            [geo.r, geo.B, geo.mass, geo.I_z, float(geo.cg[0]), float(geo.cg[1])],
            geo.wheel_xy[:, 0],
            geo.wheel_xy[:, 1],
            geo.normal,
            geo.force_scale,
        ]
    ).astype(float)


@njit(cache=True, fastmath=False)
def step_balance(th, rw, sg, dvx_c, dw_c, free, p, gv, F, J, P, want_j, want_p):
    """F (3,) of one step at th = (s_l, s_r, x_ICR), and on request J = dF/dtheta (3, 3; a pinned variable's
    column zero) and P = dF/d(mu_r, mu_x, mu_y, lambda, C) (3, 5). rw, sg: r omega and sgn(omega) per side;
    dvx_c, dw_c: the commanded body accelerations (the paper's zero-order approximation). Derivatives are
    those of the smooth piece the step is on: sgn() has none; clip() of eq. (6) has lambda off the mu_x
    plateau and 0 on it."""
    mu_r, mu_x, mu_y, lam, C = p[0], p[1], p[2], p[3], p[4]
    B, M, Iz, xcg, ycg = gv[1], gv[2], gv[3], gv[4], gv[5]
    el = (1.0 - th[0]) * rw[0]  # ground speed of the left wheel centres, V_wx (eq. 8)
    er = (1.0 - th[1]) * rw[1]
    vx = 0.5 * (el + er)
    wz = (er - el) / B
    vy = -th[2] * wz
    # d(vx, wz, vy) / d(s_l, s_r); d/dx_ICR: vy only (-wz)
    dvx0, dvx1 = -0.5 * rw[0], -0.5 * rw[1]
    dwz0, dwz1 = rw[0] / B, -rw[1] / B
    dvy0, dvy1 = -th[2] * dwz0, -th[2] * dwz1
    F[0] = F[1] = F[2] = 0.0
    if want_j:
        J[:, :] = 0.0
    if want_p:
        P[:, :] = 0.0
    for i in range(4):
        X, Y, N = gv[_GX + i], gv[_GY + i], gv[_GN + i]
        side = 0 if i < 2 else 1
        s, sgn_w = th[side], sg[side]
        lx, ly = X - xcg, Y - ycg  # lever arms about the CG
        ls = lam * s
        fx = sgn_w * min(max(ls, -mu_x), mu_x) * N  # eq. (6)
        vwx = vx - wz * Y
        vwy = vy + wz * X
        avx, avy = abs(vwx), abs(vwy)
        alpha = np.arctan2(avy, avx)  # |alpha|, eq. (4)
        E = np.exp(-alpha / C)
        sy = np.sign(vwy)
        sx = np.sign(vwx)
        fy = -sy * mu_y * (1.0 - E) * N  # eq. (7)
        Fx = fx - mu_r * N * sx  # eq. (5): rolling resistance against the wheel's own V_wx
        F[0] += Fx
        F[1] += fy
        F[2] += lx * fy - ly * Fx
        inside = abs(ls) < mu_x
        if want_j:
            q = vwx * vwx + vwy * vwy
            k = (mu_y * N / C) * E / q if q > 0.0 else 0.0
            gx = k * vwy * sx  # d fy / d V_wx (smooth through V_wy = 0)
            gy = -k * avx  # d fy / d V_wy
            d0 = gx * (dvx0 - Y * dwz0) + gy * (dvy0 + X * dwz0)
            d1 = gx * (dvx1 - Y * dwz1) + gy * (dvy1 + X * dwz1)
            d2 = -gy * wz
            J[1, 0] += d0
            J[1, 1] += d1
            J[1, 2] += d2
            J[2, 0] += lx * d0
            J[2, 1] += lx * d1
            J[2, 2] += lx * d2
            if inside:
                dfx = sgn_w * lam * N  # d fx / d s (own side only)
                J[0, side] += dfx
                J[2, side] -= ly * dfx
        if want_p:
            dR = -N * sx  # d Fx / d mu_r
            dmx = 0.0 if inside else sgn_w * np.sign(ls) * N  # d fx / d mu_x (on the plateau)
            dlam = sgn_w * s * N if inside else 0.0  # d fx / d lambda
            dmy = -sy * (1.0 - E) * N  # d fy / d mu_y
            dC = sy * (mu_y * N / (C * C)) * E * alpha  # d fy / d C
            P[0, 0] += dR
            P[2, 0] -= ly * dR
            P[0, 1] += dmx
            P[2, 1] -= ly * dmx
            P[0, 3] += dlam
            P[2, 3] -= ly * dlam
            P[1, 2] += dmy
            P[2, 2] += lx * dmy
            P[1, 4] += dC
            P[2, 4] += lx * dC
    # rigid-body transport: a = dv/dt + w x v at the CG
    vcgx = vx - ycg * wz
    vcgy = vy + xcg * wz
    F[0] -= M * (dvx_c - wz * vcgy)  # eq. (9)
    F[1] -= M * (wz * vcgx)  # eq. (10)
    F[2] -= Iz * dw_c  # eq. (11)
    for a in range(3):
        F[a] /= gv[_GS + a]
    if want_j:
        J[0, 0] += M * (dwz0 * vcgy + wz * (dvy0 + xcg * dwz0))
        J[0, 1] += M * (dwz1 * vcgy + wz * (dvy1 + xcg * dwz1))
        J[0, 2] -= M * wz * wz
        J[1, 0] -= M * (dwz0 * vcgx + wz * (dvx0 - ycg * dwz0))
        J[1, 1] -= M * (dwz1 * vcgx + wz * (dvx1 - ycg * dwz1))
        for a in range(3):
            for b in range(3):
                J[a, b] = J[a, b] / gv[_GS + a] * free[b]
    if want_p:
        for a in range(3):
            for b in range(5):
                P[a, b] /= gv[_GS + a]


@njit(cache=True)
def balance_all(theta, rw, sg, dvx_c, dw_c, free, p, gv, want_j, want_p):
    """``step_balance`` for every step: theta (T, 3), rw/sg/free (T, 2)/(T, 2)/(T, 3) -> F (T, 3),
    J (T, 3, 3), P (T, 3, 5) (zeros where not asked for)."""
    T = theta.shape[0]
    F = np.zeros((T, 3))
    J = np.zeros((T, 3, 3) if want_j else (1, 3, 3))
    P = np.zeros((T, 3, 5) if want_p else (1, 3, 5))
    for t in range(T):
        jt = t if want_j else 0
        pt = t if want_p else 0
        step_balance(
            theta[t], rw[t], sg[t], dvx_c[t], dw_c[t], free[t], p, gv, F[t], J[jt], P[pt], want_j, want_p
        )
    return F, J, P


def step_inputs(wl, wr, dwl, dwr, geo: FrictionGeometry, mask: np.ndarray | None = None):
    """Per-step inputs of the compiled balance: r omega and sgn(omega) per side (T, 2), the commanded body
    accelerations dv_x, dw (T,) (the paper's zero-order approximation), the free variables (T, 3) as 0/1."""
    r, B = geo.r, geo.B
    m = free_mask(wl, wr) if mask is None else mask
    rw = np.ascontiguousarray(np.column_stack([r * wl, r * wr]))
    sg = np.ascontiguousarray(np.column_stack([np.sign(wl), np.sign(wr)]))
    return rw, sg, r * (dwr + dwl) / 2.0, r * (dwr - dwl) / B, np.ascontiguousarray(m, dtype=float)


@njit(cache=True)
def _root_sensitivity(theta, status, rw, sg, dvx_c, dw_c, free, p, gv):
    """dtheta/dp = -J^-1 dF/dp (T, 3, 5) at the regular roots (status 1, every variable free, |det J| above
    1e-10 of the product of its column norms), and which steps those are (T,); zeros elsewhere."""
    T = theta.shape[0]
    out = np.zeros((T, 3, 5))
    regular = np.zeros(T, dtype=np.bool_)
    F = np.zeros(3)
    J = np.zeros((3, 3))
    P = np.zeros((3, 5))
    adj = np.zeros((3, 3))
    for t in range(T):
        if status[t] != 1 or free[t, 0] == 0.0 or free[t, 1] == 0.0 or free[t, 2] == 0.0:
            continue
        step_balance(theta[t], rw[t], sg[t], dvx_c[t], dw_c[t], free[t], p, gv, F, J, P, True, True)
        adj[0, 0] = J[1, 1] * J[2, 2] - J[1, 2] * J[2, 1]
        adj[0, 1] = J[0, 2] * J[2, 1] - J[0, 1] * J[2, 2]
        adj[0, 2] = J[0, 1] * J[1, 2] - J[0, 2] * J[1, 1]
        adj[1, 0] = J[1, 2] * J[2, 0] - J[1, 0] * J[2, 2]
        adj[1, 1] = J[0, 0] * J[2, 2] - J[0, 2] * J[2, 0]
        adj[1, 2] = J[0, 2] * J[1, 0] - J[0, 0] * J[1, 2]
        adj[2, 0] = J[1, 0] * J[2, 1] - J[1, 1] * J[2, 0]
        adj[2, 1] = J[0, 1] * J[2, 0] - J[0, 0] * J[2, 1]
        adj[2, 2] = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
        det = J[0, 0] * adj[0, 0] + J[0, 1] * adj[1, 0] + J[0, 2] * adj[2, 0]
        norms = 1.0
        for b in range(3):
            norms *= np.sqrt(J[0, b] * J[0, b] + J[1, b] * J[1, b] + J[2, b] * J[2, b])
        if not abs(det) > 1e-10 * norms:
            continue
        regular[t] = True
        for a in range(3):
            for k in range(5):
                out[t, a, k] = -(adj[a, 0] * P[0, k] + adj[a, 1] * P[1, k] + adj[a, 2] * P[2, k]) / det
    return out, regular


def residual(
    theta: np.ndarray,
    wl: np.ndarray,
    wr: np.ndarray,
    dwl: np.ndarray,
    dwr: np.ndarray,
    params: dict | np.ndarray,
    geo: FrictionGeometry,
) -> np.ndarray:
    """Normalised F(theta) (eqs. 9-11) for every step: theta (T, 3), inputs (T,) -> (T, 3)."""
    wl, wr, dwl, dwr = (np.asarray(a, dtype=float).ravel() for a in (wl, wr, dwl, dwr))
    th = np.ascontiguousarray(np.asarray(theta, dtype=float).reshape(-1, 3))
    args = step_inputs(wl, wr, dwl, dwr, geo)
    return balance_all(th, *args, param_vector(params), geo_vector(geo), False, False)[0]


def balance_jacobians(
    theta: np.ndarray,
    wl: np.ndarray,
    wr: np.ndarray,
    dwl: np.ndarray,
    dwr: np.ndarray,
    params: dict | np.ndarray,
    geo: FrictionGeometry,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """F (T, 3) as ``residual``, its analytic Jacobian dF/dtheta (T, 3, 3; columns of a step's pinned
    variables zero) and dF/dp (T, 3, 5) with respect to (mu_r, mu_x, mu_y, lambda, C)."""
    wl, wr, dwl, dwr = (np.asarray(a, dtype=float).ravel() for a in (wl, wr, dwl, dwr))
    th = np.ascontiguousarray(np.asarray(theta, dtype=float).reshape(-1, 3))
    args = step_inputs(wl, wr, dwl, dwr, geo)
    return balance_all(th, *args, param_vector(params), geo_vector(geo), True, True)


def velocity_sensitivity(
    theta: np.ndarray,
    status: np.ndarray,
    wl: np.ndarray,
    wr: np.ndarray,
    dwl: np.ndarray,
    dwr: np.ndarray,
    params: dict | np.ndarray,
    geo: FrictionGeometry,
) -> np.ndarray:
    """(T, 3, 5) derivative of the body velocities (vx, vy, wz) (eq. 8 at the solved theta) with respect to
    (mu_r, mu_x, mu_y, lambda, C), by the implicit function theorem instead of re-solving.

    At a root F(theta, p) = 0 the slips move with the parameters as J dtheta = -dF/dp dp (J = dF/dtheta,
    the Jacobian the solver converged with); elsewhere (a stationary point of F^T F, an unfinished step, a
    step with a pinned variable, or a singular J such as a saturated side with no other grip on its slip)
    the least-squares solution -pinv(J) dF/dp (the Gauss-Newton sensitivity of the minimiser). These are
    the derivatives of the smooth piece a step is on; a step that changes piece (gains or loses its root,
    enters the mu_x plateau) is a jump no derivative describes."""
    wl, wr, dwl, dwr = (np.asarray(a, dtype=float).ravel() for a in (wl, wr, dwl, dwr))
    theta = np.asarray(theta, dtype=float).reshape(-1, 3)
    mask = free_mask(wl, wr)
    args = step_inputs(wl, wr, dwl, dwr, geo, mask)
    p = param_vector(params)
    status = np.ascontiguousarray(status, dtype=np.int8)
    # a regular root: one 3x3 solve per step at the root's Jacobian (compiled)
    dth, regular = _root_sensitivity(np.ascontiguousarray(theta), status, *args, p, geo_vector(geo))
    rest = ~regular & mask.any(axis=1)
    if rest.any():
        _, J, P = balance_all(
            np.ascontiguousarray(theta[rest]), *(a[rest] for a in args), p, geo_vector(geo), True, True
        )
        dth[rest] = -np.linalg.pinv(J, rcond=1e-12) @ P
    # eq. (8): d(vx, vy, wz) / d(s_l, s_r, x_ICR)
    r, B = geo.r, geo.B
    wz = body_velocity(theta, wl, wr, r, B)[:, 2]
    dv = np.zeros((wl.size, 3, 3))
    dv[:, 0, 0], dv[:, 0, 1] = -r * wl / 2.0, -r * wr / 2.0
    dv[:, 2, 0], dv[:, 2, 1] = r * wl / B, -r * wr / B
    dv[:, 1, 0], dv[:, 1, 1], dv[:, 1, 2] = -theta[:, 2] * dv[:, 2, 0], -theta[:, 2] * dv[:, 2, 1], -wz
    return dv @ dth


def param_vector(params: dict | np.ndarray) -> np.ndarray:
    if isinstance(params, dict):
        return np.array([float(params[k]) for k in PARAM_NAMES])
    return np.asarray(params, dtype=float)


def free_mask(wl: np.ndarray, wr: np.ndarray) -> np.ndarray:
    """(T, 3) bool: which of (s_l, s_r, x_ICR) are unknowns at each step (a zero-rate side has no slip
    ratio; x_ICR is meaningless only when both sides stand still)."""
    zl = np.abs(wl) <= ZERO_RATE
    zr = np.abs(wr) <= ZERO_RATE
    return np.stack([~zl, ~zr, ~(zl & zr)], axis=-1)
