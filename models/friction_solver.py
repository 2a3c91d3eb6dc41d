"""The friction-based kinematic model's inner problem (paper eqs. 5-12), batched over time steps.

At each time step t the unknowns are theta_t = (s_l, s_r, x_ICR) (left/right slip ratio, ICR offset, m);
the inputs are the commanded wheel rates (wl, wr, rad/s) and their derivatives (dwl, dwr, rad/s^2).
``residual`` evaluates the force/torque balance F(theta) (eqs. 9-11) for all steps at once; ``solve``
finds F(theta) = 0 for all steps by a vectorised Levenberg-Marquardt iteration (eq. 12), and
``solve_reference`` does the paper's per-step scipy trust-region solve, used to check it.

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
    mu_r, mu_x, mu_y, lam, C = _param_vector(params)
    r, B = geo.r, geo.B
    v = body_velocity(theta, wl, wr, r, B)
    vx, vy, wz = v[..., 0], v[..., 1], v[..., 2]
    x_i, y_i = geo.wheel_xy[:, 0], geo.wheel_xy[:, 1]
    N = geo.normal
    # per-wheel quantities, shape (T, 4): FL, RL, FR, RR
    s = np.stack([theta[..., 0], theta[..., 0], theta[..., 1], theta[..., 1]], axis=-1)
    omega = np.stack([wl, wl, wr, wr], axis=-1)
    vwx = vx[..., None] - wz[..., None] * y_i
    vwy = vy[..., None] + wz[..., None] * x_i
    fx = np.sign(omega) * np.clip(lam * s, -mu_x, mu_x) * N  # eq. (6)
    alpha = np.arctan2(np.abs(vwy), np.abs(vwx))  # |alpha|, eq. (4)
    fy = -np.sign(vwy) * mu_y * (1.0 - np.exp(-alpha / C)) * N  # eq. (7)
    R = mu_r * N * np.sign(vwx)  # eq. (5), against the wheel's own longitudinal velocity
    Fx = fx - R
    # commanded accelerations (the paper's zero-order approximation)
    dvx = r * (dwr + dwl) / 2.0
    dw = r * (dwr - dwl) / B
    x_cg, y_cg = geo.cg
    vcgx = vx - y_cg * wz
    vcgy = vy + x_cg * wz
    ax = dvx - wz * vcgy  # rigid-body transport: a = dv/dt + w x v
    ay = wz * vcgx
    F1 = Fx.sum(-1) - geo.mass * ax  # eq. (9)
    F2 = fy.sum(-1) - geo.mass * ay  # eq. (10)
    F3 = ((x_i - x_cg) * fy - (y_i - y_cg) * Fx).sum(-1) - geo.I_z * dw  # eq. (11)
    return np.stack([F1, F2, F3], axis=-1) / geo.force_scale


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
    fd_step: float = 1e-7,
) -> SolveResult:
    """Batched Levenberg-Marquardt on all steps at once (eq. 12).

    Each iteration forms a forward-difference Jacobian (3 extra batched residual evaluations), solves the
    damped normal equations (J^T J + mu D) delta = -J^T F for every still-active step, and accepts a step
    only where it lowers |F| (per-step damping mu up/down): a trust-region-like globalisation that
    tolerates the kinks of sgn/clip. ``theta0`` warm-starts (default: zero slip, x_ICR = 0).
    Converged: |F|_inf < ftol (root) or the scaled gradient |J^T F|_inf < gtol (stationary, not a root).
    """
    wl, wr, dwl, dwr = (np.asarray(a, dtype=float).ravel() for a in (wl, wr, dwl, dwr))
    p = _param_vector(params)
    T = wl.size
    mask = free_mask(wl, wr)
    theta = np.zeros((T, 3)) if theta0 is None else np.array(theta0, dtype=float).reshape(T, 3)
    theta = np.where(mask, theta, 0.0)
    status = np.zeros(T, dtype=np.int8)
    F = residual(theta, wl, wr, dwl, dwr, p, geo)
    cost = 0.5 * np.sum(F * F, axis=1)
    mu = np.full(T, 1e-3)
    # standstill (both sides zero): eq. (8) gives zero velocity whatever theta; nothing to solve
    still = ~mask.any(axis=1)
    status[still] = 1
    root = np.max(np.abs(F), axis=1) < ftol
    status[root] = 1
    active = np.flatnonzero(status == 0)
    it = 0
    eye = np.eye(3)
    while active.size and it < max_iter:
        it += 1
        th, Fa, m = theta[active], F[active], mask[active]
        a = (wl[active], wr[active], dwl[active], dwr[active])
        J = np.empty((active.size, 3, 3))
        for k in range(3):
            h = fd_step * np.maximum(1.0, np.abs(th[:, k]))
            tk = th.copy()
            tk[:, k] += h
            J[:, :, k] = (residual(tk, *a, p, geo) - Fa) / h[:, None]
        J *= m[:, None, :]  # pinned variables have no column
        g = np.einsum("tij,ti->tj", J, Fa)
        JTJ = np.einsum("tij,tik->tjk", J, J)
        d = np.maximum(np.diagonal(JTJ, axis1=1, axis2=2), 1e-12)
        mua = mu[active]
        # stationary point (gradient vanishes) but not a root
        stat = np.max(np.abs(g) / np.sqrt(d), axis=1) < gtol
        A = JTJ + mua[:, None, None] * (d[:, :, None] * eye)
        delta = -np.linalg.solve(A, g[..., None])[..., 0] * m
        tn = th + delta
        Fn = residual(tn, *a, p, geo)
        cn = 0.5 * np.sum(Fn * Fn, axis=1)
        ok = cn < cost[active]
        acc = active[ok]
        theta[acc], F[acc], cost[acc] = tn[ok], Fn[ok], cn[ok]
        mu[active] = np.where(ok, np.maximum(mua / 3.0, 1e-12), mua * 4.0)
        done_root = np.max(np.abs(F[active]), axis=1) < ftol
        # a rejected step with a tiny relative change, or damping grown so large that steps vanish, means LM
        # has stalled at a (non-smooth) stationary point, e.g. a locked side whose lateral force has a kink
        tiny = ~ok & (np.max(np.abs(delta), axis=1) < 1e-15 * (1.0 + np.max(np.abs(th), axis=1)))
        status[active[done_root]] = 1
        status[active[~done_root & (stat | tiny | (mua > 1e8))]] = 2
        active = active[status[active] == 0]
    return SolveResult(theta, status, cost, it, {"ftol": ftol, "gtol": gtol})


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
