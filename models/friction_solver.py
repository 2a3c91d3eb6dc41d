"""The friction-based kinematic model's inner problem (paper eqs. 5-12), batched over time steps.

At each time step t the unknowns are theta_t = (s_l, s_r, x_ICR) (left/right slip ratio, ICR offset, m);
the inputs are the commanded wheel rates (wl, wr, rad/s) and their derivatives (dwl, dwr, rad/s^2).
``residual`` evaluates the force/torque balance F(theta) (eqs. 9-11) for all steps at once; ``solve``
finds F(theta) = 0 for all steps by Levenberg-Marquardt (eq. 12), and ``solve_reference`` does the paper's
per-step scipy trust-region solve, used to check it. ``balance_jacobians`` gives the analytic dF/dtheta and
dF/dp, and ``velocity_sensitivity`` the derivative of the solved motion with respect to the parameters by
the implicit function theorem (what the fit's Jacobian is made of).

The physics lives once, in the compiled ``_step_balance`` (numba): every step is a 3-unknown problem with
its own iteration count, which compiled per-step loops do without the per-iteration Python overhead a
vectorised batch paid while a few stragglers iterated (issue 14; ``make bench BENCH=friction_fit``).

Conventions (SPEC.md "Models", notes on the friction model):
- F is normalised: F1, F2 by M g and F3 by M g b (b = half track) so that one tolerance fits all three;
  the roots are the paper's.
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

from dataclasses import dataclass, field

import numpy as np
from numba import njit

G = 9.80665  # m/s^2
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
    g: float = G

    @classmethod
    def from_robot(cls, robot, g: float = G) -> FrictionGeometry:
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
# geometry vector layout (``_geo_vector``): r, B, M, I_z, x_CG, y_CG, X[4], Y[4], N[4], scale[3]
_GX, _GY, _GN, _GS = 6, 10, 14, 18


def _geo_vector(geo: FrictionGeometry) -> np.ndarray:
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
def _step_balance(th, rw, sg, dvx_c, dw_c, free, p, gv, F, J, P, want_j, want_p):
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
def _balance_all(theta, rw, sg, dvx_c, dw_c, free, p, gv, want_j, want_p):
    """``_step_balance`` for every step: theta (T, 3), rw/sg/free (T, 2)/(T, 2)/(T, 3) -> F (T, 3),
    J (T, 3, 3), P (T, 3, 5) (zeros where not asked for)."""
    T = theta.shape[0]
    F = np.zeros((T, 3))
    J = np.zeros((T, 3, 3) if want_j else (1, 3, 3))
    P = np.zeros((T, 3, 5) if want_p else (1, 3, 5))
    for t in range(T):
        jt = t if want_j else 0
        pt = t if want_p else 0
        _step_balance(
            theta[t], rw[t], sg[t], dvx_c[t], dw_c[t], free[t], p, gv, F[t], J[jt], P[pt], want_j, want_p
        )
    return F, J, P


@njit(cache=True)
def _solve_spd3(A, b, x):
    """x = A^-1 b for a symmetric positive definite 3x3 A (Cholesky); False where A is not numerically
    positive definite (x untouched)."""
    a00 = A[0, 0]
    if not a00 > 0.0:
        return False
    l00 = np.sqrt(a00)
    l10, l20 = A[0, 1] / l00, A[0, 2] / l00
    a11 = A[1, 1] - l10 * l10
    if not a11 > 0.0:
        return False
    l11 = np.sqrt(a11)
    l21 = (A[1, 2] - l20 * l10) / l11
    a22 = A[2, 2] - l20 * l20 - l21 * l21
    if not a22 > 0.0:
        return False
    l22 = np.sqrt(a22)
    y0 = b[0] / l00
    y1 = (b[1] - l10 * y0) / l11
    y2 = (b[2] - l20 * y0 - l21 * y1) / l22
    x[2] = y2 / l22
    x[1] = (y1 - l21 * x[2]) / l11
    x[0] = (y0 - l10 * x[1] - l20 * x[2]) / l00
    return True


@njit(cache=True)
def _lm_steps(
    theta, F, cost, idx, rw, sg, dvx_c, dw_c, free, p, gv, ftol, gtol, max_iter, stall_rtol, stall_iter
):
    """Levenberg-Marquardt, one step at a time, on the steps ``idx`` (in place on theta/F/cost rows):
    (status (n,), iterations of the longest) with status 1 root, 2 stationary point of F^T F, 0 not
    converged. Steps are independent problems; each iterates exactly as the batched form would."""
    n = idx.size
    status = np.zeros(n, dtype=np.int8)
    hist = np.empty(stall_iter)
    J = np.zeros((3, 3))
    Jn = np.zeros((3, 3))
    Fn = np.zeros(3)
    tn = np.zeros(3)
    g = np.zeros(3)
    A = np.zeros((3, 3))
    d = np.zeros(3)
    delta = np.zeros(3)
    dummy = np.zeros((3, 5))
    longest = 0
    for q in range(n):
        t = idx[q]
        th, f = theta[t], F[t]
        if max(abs(f[0]), abs(f[1]), abs(f[2])) < ftol:
            status[q] = 1
            continue
        c = cost[t]
        mu = 1e-3
        hist[:] = c
        _step_balance(th, rw[t], sg[t], dvx_c[t], dw_c[t], free[t], p, gv, Fn, J, dummy, True, False)
        it = 0
        st = 0
        while it < max_iter:
            it += 1
            stat_v = 0.0
            for a in range(3):
                g[a] = J[0, a] * f[0] + J[1, a] * f[1] + J[2, a] * f[2]
                for b in range(3):
                    A[a, b] = J[0, a] * J[0, b] + J[1, a] * J[1, b] + J[2, a] * J[2, b]
                d[a] = max(A[a, a], 1e-12)
                stat_v = max(stat_v, abs(g[a]) / np.sqrt(d[a]))
            stat = stat_v < gtol  # smooth stationary point, not a root
            for a in range(3):
                A[a, a] += mu * d[a]
            if not _solve_spd3(A, g, delta):
                delta[:] = 0.0
            for a in range(3):
                tn[a] = th[a] - delta[a] * free[t, a]
            _step_balance(tn, rw[t], sg[t], dvx_c[t], dw_c[t], free[t], p, gv, Fn, Jn, dummy, True, False)
            cn = 0.5 * (Fn[0] * Fn[0] + Fn[1] * Fn[1] + Fn[2] * Fn[2])
            mua = mu
            if cn < c:
                th[:] = tn
                f[:] = Fn
                c = cn
                J[:, :] = Jn
                mu = max(mua / 3.0, 1e-12)
            else:
                mu = mua * 4.0
            # stalled: over the last stall_iter iterations the cost fell by less than stall_rtol of itself.
            # Where no root exists the infimum of F^T F often sits on a kink or jump of F (sgn(V_wy) at zero
            # yaw rate, the mu_x plateau of eq. 6): no smooth stationary point, the gradient test never
            # fires and LM creeps along the kink; stalling is the non-smooth stationarity test.
            oldest = hist[it % stall_iter]
            stalled = (it >= stall_iter) and (oldest - c <= stall_rtol * oldest)
            hist[it % stall_iter] = c
            if max(abs(f[0]), abs(f[1]), abs(f[2])) < ftol:
                st = 1
                break
            if stat or stalled or mua > 1e10:
                st = 2
                break
        cost[t] = c
        status[q] = st
        longest = max(longest, it)
    return status, longest


def _step_inputs(wl, wr, dwl, dwr, geo: FrictionGeometry, mask: np.ndarray | None = None):
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
        _step_balance(theta[t], rw[t], sg[t], dvx_c[t], dw_c[t], free[t], p, gv, F, J, P, True, True)
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
    args = _step_inputs(wl, wr, dwl, dwr, geo)
    return _balance_all(th, *args, _param_vector(params), _geo_vector(geo), False, False)[0]


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
    args = _step_inputs(wl, wr, dwl, dwr, geo)
    return _balance_all(th, *args, _param_vector(params), _geo_vector(geo), True, True)


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
    args = _step_inputs(wl, wr, dwl, dwr, geo, mask)
    p = _param_vector(params)
    status = np.ascontiguousarray(status, dtype=np.int8)
    # a regular root: one 3x3 solve per step at the root's Jacobian (compiled)
    dth, regular = _root_sensitivity(np.ascontiguousarray(theta), status, *args, p, _geo_vector(geo))
    rest = ~regular & mask.any(axis=1)
    if rest.any():
        _, J, P = _balance_all(
            np.ascontiguousarray(theta[rest]), *(a[rest] for a in args), p, _geo_vector(geo), True, True
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


def _param_vector(params: dict | np.ndarray) -> np.ndarray:
    if isinstance(params, dict):
        return np.array([float(params[k]) for k in PARAM_NAMES])
    return np.asarray(params, dtype=float)


def free_mask(wl: np.ndarray, wr: np.ndarray) -> np.ndarray:
    """(T, 3) bool: which of (s_l, s_r, x_ICR) are unknowns at each step (a zero-rate side has no slip
    ratio; x_ICR is meaningless only when both sides stand still)."""
    zl = np.abs(wl) <= ZERO_RATE
    zr = np.abs(wr) <= ZERO_RATE
    return np.stack([~zl, ~zr, ~(zl & zr)], axis=-1)


@dataclass
class SolveResult:
    """Per-step solution of F(theta) = 0. ``status``: 1 root found, 2 stationary point of F^T F that is not
    a root (no theta balances the forces; theta is the least-squares minimiser, eq. 12), 0 not converged."""

    theta: np.ndarray  # (T, 3)
    status: np.ndarray  # (T,) int8
    cost: np.ndarray  # (T,) 0.5 |F|^2 (normalised)
    n_iter: int
    info: dict = field(default_factory=dict)
    #: (T,) the fraction of the commanded accelerations ``theta`` balances: 1 everywhere for ``solve``;
    #: below 1 where the model fell back to a reduced acceleration (``FrictionBased.velocities``)
    accel_scale: np.ndarray | None = None

    @property
    def converged(self) -> np.ndarray:
        return self.status > 0

    @property
    def n_not_converged(self) -> int:
        return int(np.sum(self.status == 0))

    def saturated(self, wl: np.ndarray, wr: np.ndarray, params: dict | np.ndarray) -> np.ndarray:
        """(T,) bool: a side's tractive force sits on the mu_x plateau of eq. (6). There F is flat in that
        side's slip ratio, so the root need not be unique (two solvers may return different roots)."""
        mu_r, mu_x, mu_y, lam, C = _param_vector(params)
        m = free_mask(np.asarray(wl).ravel(), np.asarray(wr).ravel())[:, :2]
        return np.any(m & (lam * np.abs(self.theta[:, :2]) >= mu_x), axis=1)


def _lm(theta, F, cost, idx, inp, p, geo, mask, *, ftol, gtol, max_iter, stall_rtol, stall_iter):
    """Levenberg-Marquardt on the steps ``idx`` (in place on theta/F/cost rows); returns (status, n_iter)
    for those steps: 1 root, 2 stationary point of F^T F (not a root), 0 not converged. Each step iterates
    in compiled code (``_lm_steps``) with the analytic Jacobian: one balance evaluation per iteration."""
    args = _step_inputs(*inp, geo, mask)
    idx = np.ascontiguousarray(idx, dtype=np.int64)
    p = np.asarray(p, dtype=float)
    return _lm_steps(
        theta,
        F,
        cost,
        idx,
        *args,
        p,
        _geo_vector(geo),
        ftol,
        gtol,
        int(max_iter),
        stall_rtol,
        int(stall_iter),
    )


def low_slip_start(wl, wr, dwl, dwr, params, geo: FrictionGeometry) -> np.ndarray:
    """(T, 3) analytic start from the low-slip linearisation of eqs. (6), (7), (9)-(11) about the zero-slip
    motion: lateral forces and rolling resistance from the ideal velocities, longitudinal forces linear in
    s (lambda s N, clipped at the mu_x plateau), small slip angles for x_ICR."""
    mu_r, mu_x, mu_y, lam, C = _param_vector(params)
    r, B = geo.r, geo.B
    th0 = np.zeros((wl.size, 3))
    v = body_velocity(th0, wl, wr, r, B)
    vx, wz = v[:, 0], v[:, 2]
    x_i, y_i = geo.wheel_xy[:, 0], geo.wheel_xy[:, 1]
    N = geo.normal
    vwx = vx[:, None] - wz[:, None] * y_i
    vwy = wz[:, None] * x_i
    alpha = np.arctan2(np.abs(vwy), np.abs(vwx))
    fy = -np.sign(vwy) * mu_y * (1.0 - np.exp(-alpha / C)) * N
    Rr = mu_r * N * np.sign(vwx)
    x_cg, y_cg = geo.cg
    tau_y = ((x_i - x_cg) * fy).sum(-1) + ((y_i - y_cg) * Rr).sum(-1)
    dvx = r * (dwr + dwl) / 2.0
    dw = r * (dwr - dwl) / B
    b = B / 2.0
    NL, NR = N[:2].sum(), N[2:].sum()
    sum_fx = geo.mass * dvx + Rr.sum(-1)  # F1 = 0 with a_x ~ dv_x
    diff_fx = (tau_y - geo.I_z * dw) / b  # F3 = 0: b (fx_L - fx_R) = tau_y - I_z dw (y_CG ~ 0)
    fl, fr = (sum_fx + diff_fx) / 2.0, (sum_fx - diff_fx) / 2.0
    cap = 1.05 * mu_x / lam  # just onto the plateau where the force asks for more than mu_x N
    sl = np.clip(np.sign(wl) * fl / (lam * NL), -cap, cap)
    sr = np.clip(np.sign(wr) * fr / (lam * NR), -cap, cap)
    # F2 = 0 with small slip angles: sum_i -(mu_y / C) N_i wz (x_i - x_ICR) / |V_wx,i| = M wz v_x
    vabs = np.maximum(np.abs(vwx), 1e-3)
    k = N / vabs
    x_icr = ((k * x_i).sum(-1) + geo.mass * vx * C / mu_y) / k.sum(-1)
    x_icr = np.clip(x_icr, -np.abs(x_i).max(), np.abs(x_i).max())
    out = np.stack([sl, sr, np.where(np.abs(wz) > 0, x_icr, 0.0)], axis=-1)
    return np.where(free_mask(wl, wr), out, 0.0)


def solve(
    wl: np.ndarray,
    wr: np.ndarray,
    dwl: np.ndarray,
    dwr: np.ndarray,
    params: dict | np.ndarray,
    geo: FrictionGeometry,
    theta0: np.ndarray | None = None,
    *,
    ftol: float = 1e-12,
    gtol: float = 1e-13,
    max_iter: int = 100,
    stall_rtol: float = 1e-10,
    stall_iter: int = 8,
    restarts: bool = True,
    fallback_max: int = 10,
) -> SolveResult:
    """Batched Levenberg-Marquardt on all steps at once (eq. 12), with restarts for the steps it leaves
    without a root.

    Each LM iteration (per step, compiled: ``_lm_steps``) evaluates F and its analytic Jacobian J at the
    trial point (one balance evaluation), solves the damped normal equations (J^T J + mu D) delta = -J^T F
    by a 3x3 Cholesky factorisation, and accepts a step
    only where it lowers F^T F (per-step damping mu up/down): a trust-region-like globalisation with F^T F as
    merit function, which tolerates the kinks of sgn/clip. ``theta0`` warm-starts (default: zero slip,
    x_ICR = 0, the reference's start).

    Status per step: 1 root (|F|_inf < ftol); 2 stationary point of F^T F that is not a root (scaled gradient
    |J^T F| < gtol, or F^T F stalled: it fell by less than ``stall_rtol`` of itself over ``stall_iter``
    iterations, which is how a minimum on a kink of F shows; no theta balances the forces there, e.g. a
    commanded acceleration that friction cannot deliver, and theta is the least-squares minimiser); 0 not
    converged (still descending after ``max_iter`` iterations).

    Restarts (``restarts``, only for the steps without a root after the first pass, usually a few percent):
    from the zero-slip start (if ``theta0`` was given), from the analytic low-slip linearisation
    (``low_slip_start``), and by continuation over the acceleration (solve at zero commanded acceleration,
    then warm-start the real one) and from full slip; each step keeps the first root found, else the lowest
    F^T F. Steps still descending get a last pass with 4 x max_iter iterations, and if at most
    ``fallback_max`` remain, a per-step scipy trf solve from their best point. Where the first pass
    finds a root it is kept, so roots are the ones a zero-slip (or warm) start leads to, like the reference's.
    """
    wl, wr, dwl, dwr = (np.asarray(a, dtype=float).ravel() for a in (wl, wr, dwl, dwr))
    inp = (wl, wr, dwl, dwr)
    p = _param_vector(params)
    T = wl.size
    mask = free_mask(wl, wr)
    zero_start = theta0 is None
    theta = np.zeros((T, 3)) if zero_start else np.array(theta0, dtype=float).reshape(T, 3)
    theta = np.where(mask, theta, 0.0)
    theta[~np.isfinite(theta)] = 0.0
    status = np.zeros(T, dtype=np.int8)
    F = residual(theta, *inp, p, geo)
    cost = 0.5 * np.sum(F * F, axis=1)
    # standstill (both sides zero): eq. (8) gives zero velocity whatever theta; nothing to solve
    still = ~mask.any(axis=1)
    status[still] = 1
    opts = dict(ftol=ftol, gtol=gtol, stall_rtol=stall_rtol, stall_iter=stall_iter)
    idx = np.flatnonzero(~still)
    status[idx], n_iter = _lm(theta, F, cost, idx, inp, p, geo, mask, max_iter=max_iter, **opts)
    info = {
        "ftol": ftol,
        "gtol": gtol,
        "first_pass_not_converged": int(np.sum(status == 0)),
        "first_pass_no_root": int(np.sum(status == 2)),
        "restarted": 0,
    }
    todo = np.flatnonzero(status != 1)
    if restarts and todo.size:
        info["restarted"] = int(todo.size)
        sub = tuple(a[todo] for a in inp)
        m_sub = mask[todo]
        nt = todo.size
        z = np.zeros(nt)
        # full slip (the wheels spin, the robot barely moves): where no root exists the least-squares
        # minimum often lies there, beyond the mu_x plateau a zero-slip start gets stuck on (F flat in s)
        starts = [low_slip_start(*sub, p, geo), np.tile([0.999, 0.999, 0.0], (nt, 1))]
        if not zero_start:
            starts.append(np.zeros((nt, 3)))
        # all starts in one batched LM call (the per-iteration cost is mostly fixed overhead), plus the
        # zero-acceleration problem from zero slip for the continuation below
        k = len(starts)
        st_inp = tuple(
            np.concatenate([a] * k + [b]) for a, b in zip(sub, (sub[0], sub[1], z, z), strict=True)
        )
        st_mask = np.concatenate([m_sub] * (k + 1))
        th_s = np.where(st_mask, np.concatenate(starts + [np.zeros((nt, 3))]), 0.0)
        F_s = residual(th_s, *st_inp, p, geo)
        c_s = 0.5 * np.sum(F_s * F_s, axis=1)
        st_s, it_s = _lm(
            th_s, F_s, c_s, np.arange(th_s.shape[0]), st_inp, p, geo, st_mask, max_iter=max_iter, **opts
        )
        n_iter += it_s
        # continuation over the acceleration: the zero-acceleration solution as the start
        th_c = th_s[k * nt :].copy()
        F_c = residual(th_c, *sub, p, geo)
        c_c = 0.5 * np.sum(F_c * F_c, axis=1)
        st_c, it_c = _lm(th_c, F_c, c_c, np.arange(nt), sub, p, geo, m_sub, max_iter=max_iter, **opts)
        n_iter += it_c
        cands = [
            (
                th_s[j * nt : (j + 1) * nt],
                F_s[j * nt : (j + 1) * nt],
                c_s[j * nt : (j + 1) * nt],
                st_s[j * nt : (j + 1) * nt],
            )
            for j in range(k)
        ] + [(th_c, F_c, c_c, st_c)]
        for th_j, F_j, c_j, st_j in cands:
            better = (status[todo] != 1) & ((st_j == 1) | (c_j < cost[todo]))
            kk = todo[better]
            theta[kk], F[kk], cost[kk], status[kk] = th_j[better], F_j[better], c_j[better], st_j[better]
        # still descending: more iterations for these few only
        left = np.flatnonzero(status == 0)
        if left.size:
            status[left], it_s = _lm(theta, F, cost, left, inp, p, geo, mask, max_iter=4 * max_iter, **opts)
            n_iter += it_s
    left = np.flatnonzero(status == 0)
    info["fallback"] = 0
    if restarts and 0 < left.size <= fallback_max:
        # the last few stragglers: the per-step trust-region solve from their best point
        info["fallback"] = int(left.size)
        _fallback_trf(theta, F, cost, status, left, inp, p, geo, mask, ftol)
    return SolveResult(theta, status, cost, n_iter, info)


def _fallback_trf(theta, F, cost, status, idx, inp, p, geo, mask, ftol, max_nfev: int = 200) -> None:
    from scipy.optimize import least_squares

    for t in idx:
        free = np.flatnonzero(mask[t])
        one = tuple(a[t : t + 1] for a in inp)

        def fun(x, free=free, one=one):
            th = np.zeros((1, 3))
            th[0, free] = x
            return residual(th, *one, p, geo)[0]

        res = least_squares(
            fun, theta[t, free], method="trf", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=max_nfev
        )
        if res.cost > cost[t]:  # trf never goes uphill; guard anyway
            continue
        theta[t, free], F[t], cost[t] = res.x, res.fun, res.cost
        if np.max(np.abs(res.fun)) < ftol:
            status[t] = 1
        elif res.status > 0:
            status[t] = 2  # trf stopped on its own tolerances: a stationary point of F^T F


def solve_reference(
    wl: np.ndarray,
    wr: np.ndarray,
    dwl: np.ndarray,
    dwr: np.ndarray,
    params: dict | np.ndarray,
    geo: FrictionGeometry,
    *,
    ftol: float = 1e-12,
    tol: float = 1e-15,
) -> SolveResult:
    """The paper's per-step solve: scipy.optimize.least_squares(method="trf") on F(theta) from a zero-slip
    start, one step at a time (slow; for checking ``solve``). Same statuses as ``solve``."""
    from scipy.optimize import least_squares

    wl, wr, dwl, dwr = (np.asarray(a, dtype=float).ravel() for a in (wl, wr, dwl, dwr))
    p = _param_vector(params)
    T = wl.size
    mask = free_mask(wl, wr)
    theta = np.zeros((T, 3))
    status = np.zeros(T, dtype=np.int8)
    cost = np.zeros(T)
    for t in range(T):
        free = np.flatnonzero(mask[t])
        inp = (wl[t : t + 1], wr[t : t + 1], dwl[t : t + 1], dwr[t : t + 1])
        if free.size == 0:
            status[t] = 1
            continue

        def fun(x, free=free, inp=inp):
            th = np.zeros((1, 3))
            th[0, free] = x
            return residual(th, *inp, p, geo)[0]

        res = least_squares(fun, np.zeros(free.size), method="trf", xtol=tol, ftol=tol, gtol=tol)
        theta[t, free] = res.x
        cost[t] = res.cost
        if np.max(np.abs(res.fun)) < ftol:
            status[t] = 1
        elif res.status > 0:
            status[t] = 2
    return SolveResult(theta, status, cost, 0, {"ftol": ftol})
