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


def _lm(theta, F, cost, idx, inp, p, geo, mask, *, ftol, gtol, max_iter, fd_step, stall_rtol, stall_iter):
    """Levenberg-Marquardt on the steps ``idx`` (in place on theta/F/cost rows); returns (status, n_iter)
    for those steps: 1 root, 2 stationary point of F^T F (not a root), 0 not converged."""
    wl, wr, dwl, dwr = inp
    n = idx.size
    status = np.zeros(n, dtype=np.int8)
    status[np.max(np.abs(F[idx]), axis=1) < ftol] = 1
    mu = np.full(n, 1e-3)
    hist = np.tile(cost[idx][:, None], (1, stall_iter))  # cost over the last stall_iter iterations
    loc = np.flatnonzero(status == 0)  # positions in idx still iterating
    eye = np.eye(3)
    it = 0
    while loc.size and it < max_iter:
        it += 1
        active = idx[loc]
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
        mua = mu[loc]
        stat = np.max(np.abs(g) / np.sqrt(d), axis=1) < gtol  # smooth stationary point, not a root
        A = JTJ + mua[:, None, None] * (d[:, :, None] * eye)
        delta = -np.linalg.solve(A, g[..., None])[..., 0] * m
        tn = th + delta
        Fn = residual(tn, *a, p, geo)
        cn = 0.5 * np.sum(Fn * Fn, axis=1)
        ok = cn < cost[active]
        acc = active[ok]
        theta[acc], F[acc], cost[acc] = tn[ok], Fn[ok], cn[ok]
        mu[loc] = np.where(ok, np.maximum(mua / 3.0, 1e-12), mua * 4.0)
        # stalled: over the last stall_iter iterations the cost fell by less than stall_rtol of itself.
        # Where no root exists the infimum of F^T F often sits on a kink or jump of F (sgn(V_wy) at zero
        # yaw rate, the mu_x plateau of eq. 6): no smooth stationary point, the gradient test never fires
        # and LM creeps along the kink; stalling is the non-smooth stationarity test.
        oldest = hist[loc, it % stall_iter]
        stalled = (it >= stall_iter) & (oldest - cost[active] <= stall_rtol * oldest)
        hist[loc, it % stall_iter] = cost[active]
        done_root = np.max(np.abs(F[active]), axis=1) < ftol
        st = np.where(done_root, 1, np.where(stat | stalled | (mua > 1e10), 2, 0)).astype(np.int8)
        status[loc] = st
        loc = loc[st == 0]
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
    fd_step: float = 1e-7,
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
    opts = dict(ftol=ftol, gtol=gtol, fd_step=fd_step, stall_rtol=stall_rtol, stall_iter=stall_iter)
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
