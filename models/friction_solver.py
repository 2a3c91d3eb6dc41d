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


@dataclass(frozen=True)
class _Steps:
    """Per-step inputs of the force balance, component-major (each (n,)): r omega and sgn(omega) of each
    side, the commanded body accelerations (dv_x, dw), and the free-variable mask (3, n) as floats."""

    rwl: np.ndarray
    rwr: np.ndarray
    sgl: np.ndarray
    sgr: np.ndarray
    dvx: np.ndarray
    dw: np.ndarray
    free: np.ndarray

    @classmethod
    def of(cls, wl, wr, dwl, dwr, geo: FrictionGeometry, mask: np.ndarray | None = None) -> _Steps:
        r, B = geo.r, geo.B
        m = free_mask(wl, wr) if mask is None else mask
        # the commanded accelerations (the paper's zero-order approximation)
        return cls(
            r * wl, r * wr, np.sign(wl), np.sign(wr), r * (dwr + dwl) / 2.0, r * (dwr - dwl) / B, m.T * 1.0
        )

    def take(self, k) -> _Steps:
        return _Steps(
            *(a[..., k] for a in (self.rwl, self.rwr, self.sgl, self.sgr, self.dvx, self.dw, self.free))
        )


def _balance(
    th: np.ndarray, st: _Steps, p: np.ndarray, geo: FrictionGeometry, jac: bool = False, pjac: bool = False
):
    """The normalised force balance F (eqs. 9-11) of steps ``st`` at ``th`` (3, n), component-major: F (3, n),
    and on request its Jacobian dF/dtheta (3, 3, n; columns of pinned variables zero) and its derivative with
    respect to the parameters dF/d(mu_r, mu_x, mu_y, lambda, C) (3, 5, n). The derivatives are those of the
    smooth piece the step lies on: sgn() has none, and clip() of eq. (6) has lambda inside the plateau and 0
    on it (so F is flat in a saturated side's slip ratio there)."""
    mu_r, mu_x, mu_y, lam, C = (float(v) for v in p)
    B, M = geo.B, geo.mass
    x_cg, y_cg = (float(v) for v in geo.cg)
    sl, sr, xi = th
    el = (1.0 - sl) * st.rwl  # ground speed of the left wheel centres, V_wx (eq. 8)
    er = (1.0 - sr) * st.rwr
    vx = 0.5 * (el + er)
    wz = (er - el) / B
    vy = -xi * wz
    n = vx.size
    F = np.zeros((3, n))
    J = np.zeros((3, 3, n)) if jac else None
    P = np.zeros((3, 5, n)) if pjac else None
    if jac:
        # d(vx, wz, vy) / d(s_l, s_r); d/dx_ICR: vy only (-wz)
        dvx = (-0.5 * st.rwl, -0.5 * st.rwr)
        dwz = (st.rwl / B, -st.rwr / B)
        dvy = (-xi * dwz[0], -xi * dwz[1])
    for i in range(4):
        X, Y, N = (float(v) for v in (geo.wheel_xy[i, 0], geo.wheel_xy[i, 1], geo.normal[i]))
        side = 0 if i < 2 else 1
        s, sg = (sl, st.sgl) if side == 0 else (sr, st.sgr)
        lx, ly = X - x_cg, Y - y_cg  # lever arms about the CG
        ls = lam * s
        fx = sg * np.clip(ls, -mu_x, mu_x) * N  # eq. (6)
        vwx = vx - wz * Y
        vwy = vy + wz * X
        avx, avy = np.abs(vwx), np.abs(vwy)
        alpha = np.arctan2(avy, avx)  # |alpha|, eq. (4)
        E = np.exp(-alpha / C)
        sy, sx = np.sign(vwy), np.sign(vwx)
        fy = -sy * mu_y * (1.0 - E) * N  # eq. (7)
        Fx = fx - mu_r * N * sx  # eq. (5): rolling resistance against the wheel's own V_wx
        F[0] += Fx
        F[1] += fy
        F[2] += lx * fy - ly * Fx
        inside = np.abs(ls) < mu_x
        if jac:
            q = vwx * vwx + vwy * vwy
            k = np.divide((mu_y * N / C) * E, q, out=np.zeros(n), where=q > 0)
            gx = k * vwy * sx  # d fy / d V_wx  (smooth through V_wy = 0)
            gy = -k * avx  # d fy / d V_wy
            for j in (0, 1):
                dfy = gx * (dvx[j] - Y * dwz[j]) + gy * (dvy[j] + X * dwz[j])
                J[1, j] += dfy
                J[2, j] += lx * dfy
            dfy = -gy * wz  # d/dx_ICR through vy
            J[1, 2] += dfy
            J[2, 2] += lx * dfy
            dfx = np.where(inside, sg * (lam * N), 0.0)  # d fx / d s (own side only)
            J[0, side] += dfx
            J[2, side] -= ly * dfx
        if pjac:
            dR = -N * sx  # d Fx / d mu_r
            dmx = np.where(inside, 0.0, sg * np.sign(ls) * N)  # d fx / d mu_x (on the plateau)
            dlam = np.where(inside, sg * s * N, 0.0)  # d fx / d lambda
            dmy = -sy * (1.0 - E) * N  # d fy / d mu_y
            dC = sy * (mu_y * N / (C * C)) * E * alpha  # d fy / d C
            for j, d in ((0, dR), (1, dmx), (3, dlam)):
                P[0, j] += d
                P[2, j] -= ly * d
            for j, d in ((2, dmy), (4, dC)):
                P[1, j] += d
                P[2, j] += lx * d
    # rigid-body transport: a = dv/dt + w x v at the CG
    vcgx = vx - y_cg * wz
    vcgy = vy + x_cg * wz
    F[0] -= M * (st.dvx - wz * vcgy)  # eq. (9)
    F[1] -= M * (wz * vcgx)  # eq. (10)
    F[2] -= geo.I_z * st.dw  # eq. (11)
    scale = geo.force_scale
    F /= scale[:, None]
    if jac:
        for j in (0, 1):
            J[0, j] += M * (dwz[j] * vcgy + wz * (dvy[j] + x_cg * dwz[j]))
            J[1, j] -= M * (dwz[j] * vcgx + wz * (dvx[j] - y_cg * dwz[j]))
        J[0, 2] += M * wz * (-wz)
        J /= scale[:, None, None]
        J *= st.free[None]
    if pjac:
        P /= scale[:, None, None]
    return F, J, P


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
    th = np.asarray(theta, dtype=float).reshape(-1, 3).T
    return _balance(th, _Steps.of(wl, wr, dwl, dwr, geo), _param_vector(params), geo)[0].T


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
    th = np.asarray(theta, dtype=float).reshape(-1, 3).T
    F, J, P = _balance(th, _Steps.of(wl, wr, dwl, dwr, geo), _param_vector(params), geo, jac=True, pjac=True)
    return F.T, np.moveaxis(J, -1, 0), np.moveaxis(P, -1, 0)


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
    _, J, P = balance_jacobians(theta, wl, wr, dwl, dwr, params, geo)
    mask = free_mask(wl, wr)
    dth = np.zeros_like(P)
    # a regular root (every variable free, J well conditioned): one 3x3 solve per step
    cols = np.linalg.norm(J, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        rel_det = np.abs(np.linalg.det(J)) / np.prod(cols, axis=1)
    regular = (np.asarray(status) == 1) & mask.all(axis=1) & (rel_det > 1e-10)
    if regular.any():
        dth[regular] = -np.linalg.solve(J[regular], P[regular])
    rest = ~regular & mask.any(axis=1)
    if rest.any():
        dth[rest] = -np.linalg.pinv(J[rest], rcond=1e-12) @ P[rest]
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


def _solve_spd3(a00, a01, a02, a11, a12, a22, b):
    """x (3, n) with A x = b for symmetric positive definite 3x3 A given by its upper triangle (each (n,)),
    by an explicit Cholesky factorisation (vectorised; NaN where A is not numerically positive definite)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        l00 = np.sqrt(a00)
        l10, l20 = a01 / l00, a02 / l00
        l11 = np.sqrt(a11 - l10 * l10)
        l21 = (a12 - l20 * l10) / l11
        l22 = np.sqrt(a22 - l20 * l20 - l21 * l21)
        y0 = b[0] / l00
        y1 = (b[1] - l10 * y0) / l11
        y2 = (b[2] - l20 * y0 - l21 * y1) / l22
        x2 = y2 / l22
        x1 = (y1 - l21 * x2) / l11
        x0 = (y0 - l10 * x1 - l20 * x2) / l00
    return np.stack([x0, x1, x2])


def _lm(theta, F, cost, idx, inp, p, geo, mask, *, ftol, gtol, max_iter, stall_rtol, stall_iter):
    """Levenberg-Marquardt on the steps ``idx`` (in place on theta/F/cost rows); returns (status, n_iter)
    for those steps: 1 root, 2 stationary point of F^T F (not a root), 0 not converged.

    Works component-major on the still-active steps only, with the analytic Jacobian of ``_balance``
    (evaluated with F at each trial point, so an iteration costs one balance evaluation), and a
    vectorised Cholesky solve of the damped 3x3 normal equations."""
    wl, wr, dwl, dwr = inp
    n = idx.size
    th = theta[idx].T.copy()
    f = F[idx].T.copy()
    c = cost[idx].copy()
    status = np.zeros(n, dtype=np.int8)
    status[np.max(np.abs(f), axis=0) < ftol] = 1
    mu = np.full(n, 1e-3)
    hist = np.tile(c[:, None], (1, stall_iter))  # cost over the last stall_iter iterations
    loc = np.flatnonzero(status == 0)  # positions in idx still iterating
    steps = _Steps.of(wl[idx[loc]], wr[idx[loc]], dwl[idx[loc]], dwr[idx[loc]], geo, mask[idx[loc]])
    J = _balance(th[:, loc], steps, p, geo, jac=True)[1] if loc.size else None
    it = 0
    while loc.size and it < max_iter:
        it += 1
        t, fa, m = th[:, loc], f[:, loc], steps.free
        g = np.einsum("ijt,it->jt", J, fa)
        a00, a11, a22 = (np.einsum("it,it->t", J[:, j], J[:, j]) for j in range(3))
        a01 = np.einsum("it,it->t", J[:, 0], J[:, 1])
        a02 = np.einsum("it,it->t", J[:, 0], J[:, 2])
        a12 = np.einsum("it,it->t", J[:, 1], J[:, 2])
        d = np.maximum(np.stack([a00, a11, a22]), 1e-12)
        mua = mu[loc]
        stat = np.max(np.abs(g) / np.sqrt(d), axis=0) < gtol  # smooth stationary point, not a root
        delta = -_solve_spd3(a00 + mua * d[0], a01, a02, a11 + mua * d[1], a12, a22 + mua * d[2], g) * m
        tn = t + np.nan_to_num(delta, nan=0.0, posinf=0.0, neginf=0.0)
        Fn, Jn, _ = _balance(tn, steps, p, geo, jac=True)
        cn = 0.5 * np.sum(Fn * Fn, axis=0)
        ok = cn < c[loc]
        acc = loc[ok]
        th[:, acc], f[:, acc], c[acc] = tn[:, ok], Fn[:, ok], cn[ok]
        J[..., ok] = Jn[..., ok]
        mu[loc] = np.where(ok, np.maximum(mua / 3.0, 1e-12), mua * 4.0)
        # stalled: over the last stall_iter iterations the cost fell by less than stall_rtol of itself.
        # Where no root exists the infimum of F^T F often sits on a kink or jump of F (sgn(V_wy) at zero
        # yaw rate, the mu_x plateau of eq. 6): no smooth stationary point, the gradient test never fires
        # and LM creeps along the kink; stalling is the non-smooth stationarity test.
        oldest = hist[loc, it % stall_iter]
        cl = c[loc]
        stalled = (it >= stall_iter) & (oldest - cl <= stall_rtol * oldest)
        hist[loc, it % stall_iter] = cl
        done_root = np.max(np.abs(f[:, loc]), axis=0) < ftol
        st = np.where(done_root, 1, np.where(stat | stalled | (mua > 1e10), 2, 0)).astype(np.int8)
        status[loc] = st
        go = st == 0
        if not go.all():
            loc, J, steps = loc[go], J[..., go], steps.take(go)
    theta[idx], F[idx], cost[idx] = th.T, f.T, c
    return status, it


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

    Each LM iteration forms a forward-difference Jacobian (3 extra batched residual evaluations), solves the
    damped normal equations (J^T J + mu D) delta = -J^T F for every still-active step, and accepts a step
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
