"""Solving the friction-based kinematic model's force balance F(theta) = 0 (paper eq. 12) for every time step.

``solve`` finds the roots for all steps at once: a Levenberg-Marquardt compiled per step (numba,
``_lm_steps``) on the analytic Jacobian of the balance (``friction_balance.step_balance``), with warm
starts, restarts for the few steps it leaves without a root, a stationarity test that works on the
sgn/min kinks, and a per-step trust-region fallback for stragglers. ``solve_reference`` does the paper's
per-step scipy trust-region solve, used to check it. ``low_slip_start`` is the analytic start of the
restarts; ``SolveResult`` what a solve returns (per step: theta, status, cost).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit
from scipy.optimize import least_squares

from skidbench.models.friction.balance import (
    FrictionGeometry,
    balance_all,
    body_velocity,
    free_mask,
    geo_vector,
    param_vector,
    residual,
    step_balance,
    step_inputs,
)


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
    """Levenberg-Marquardt, one step at a time, on the steps ``idx`` (in place on theta/F/cost rows; F and
    cost are computed here from theta, their rows need no values on entry): (status (n,), iterations of
    the longest) with status 1 root, 2 stationary point of F^T F, 0 not converged. Steps are independent
    problems; each iterates exactly as the batched form would."""
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
        # F and J at the start in one balance evaluation (the cost summed in numpy's order)
        step_balance(th, rw[t], sg[t], dvx_c[t], dw_c[t], free[t], p, gv, f, J, dummy, True, False)
        c = 0.5 * (f[0] * f[0] + f[1] * f[1] + f[2] * f[2])
        cost[t] = c
        if max(abs(f[0]), abs(f[1]), abs(f[2])) < ftol:
            status[q] = 1
            continue
        mu = 1e-3
        hist[:] = c
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
            step_balance(tn, rw[t], sg[t], dvx_c[t], dw_c[t], free[t], p, gv, Fn, Jn, dummy, True, False)
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
        mu_r, mu_x, mu_y, lam, C = param_vector(params)
        m = free_mask(np.asarray(wl).ravel(), np.asarray(wr).ravel())[:, :2]
        return np.any(m & (lam * np.abs(self.theta[:, :2]) >= mu_x), axis=1)


def _lm(theta, F, cost, idx, inp, p, geo, mask, *, ftol, gtol, max_iter, stall_rtol, stall_iter):
    """Levenberg-Marquardt on the steps ``idx`` (in place on theta/F/cost rows); returns (status, n_iter)
    for those steps: 1 root, 2 stationary point of F^T F (not a root), 0 not converged. Each step iterates
    in compiled code (``_lm_steps``) with the analytic Jacobian: one balance evaluation per iteration."""
    args = step_inputs(*inp, geo, mask)
    idx = np.ascontiguousarray(idx, dtype=np.int64)
    p = np.asarray(p, dtype=float)
    return _lm_steps(
        theta,
        F,
        cost,
        idx,
        *args,
        p,
        geo_vector(geo),
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
    mu_r, mu_x, mu_y, lam, C = param_vector(params)
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
    p = param_vector(params)
    T = wl.size
    mask = free_mask(wl, wr)
    zero_start = theta0 is None
    theta = np.zeros((T, 3)) if zero_start else np.array(theta0, dtype=float).reshape(T, 3)
    theta = np.where(mask, theta, 0.0)
    theta[~np.isfinite(theta)] = 0.0
    status = np.zeros(T, dtype=np.int8)
    # standstill (both sides zero): eq. (8) gives zero velocity whatever theta; nothing to solve
    still = ~mask.any(axis=1)
    status[still] = 1
    # F and cost of the other steps are the LM's first evaluation
    F, cost = np.zeros((T, 3)), np.zeros(T)
    if still.any():
        F[still] = residual(theta[still], *(a[still] for a in inp), p, geo)
        cost[still] = 0.5 * np.sum(F[still] * F[still], axis=1)
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
        n_iter += _restart(theta, F, cost, status, todo, inp, p, geo, mask, zero_start, max_iter, opts)
    left = np.flatnonzero(status == 0)
    info["fallback"] = 0
    if restarts and 0 < left.size <= fallback_max:
        # the last few stragglers: the per-step trust-region solve from their best point
        info["fallback"] = int(left.size)
        _fallback_trf(theta, F, cost, status, left, inp, p, geo, mask, ftol)
    return SolveResult(theta, status, cost, n_iter, info)


def _restart(
    theta, F, cost, status, todo, inp, p, geo, mask, zero_start: bool, max_iter: int, opts: dict
) -> int:
    """``solve``'s restarts of the steps ``todo`` (those without a root after the first pass; in place on the
    theta/F/cost/status rows): from the low-slip linearisation, from full slip and (if the first pass was
    warm-started) from zero slip, and by continuation over the acceleration; each step keeps the first root
    found, else the lowest F^T F; steps still descending then get 4 x ``max_iter`` iterations. Returns the
    iterations those passes added (of their longest step each)."""
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
    st_inp = tuple(np.concatenate([a] * k + [b]) for a, b in zip(sub, (sub[0], sub[1], z, z), strict=True))
    st_mask = np.concatenate([m_sub] * (k + 1))
    th_s = np.where(st_mask, np.concatenate(starts + [np.zeros((nt, 3))]), 0.0)
    F_s, c_s = np.zeros_like(th_s), np.zeros(th_s.shape[0])
    st_s, it_s = _lm(
        th_s, F_s, c_s, np.arange(th_s.shape[0]), st_inp, p, geo, st_mask, max_iter=max_iter, **opts
    )
    n_iter = it_s
    # continuation over the acceleration: the zero-acceleration solution as the start
    th_c = th_s[k * nt :].copy()
    F_c, c_c = np.zeros_like(th_c), np.zeros(nt)
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
    return n_iter


def _fallback_trf(theta, F, cost, status, idx, inp, p, geo, mask, ftol, max_nfev: int = 200) -> None:
    """``solve``'s last resort for the few steps ``idx`` still descending: scipy's trf per step from its best
    point (in place on the theta/F/cost/status rows). The balance of the step is evaluated by the compiled
    kernel directly, its inputs prepared once per step (what ``residual`` would redo at every evaluation)."""
    pv, gv = param_vector(p), geo_vector(geo)
    for t in idx:
        free = np.flatnonzero(mask[t])
        args = step_inputs(*(a[t : t + 1] for a in inp), geo)

        def fun(x, free=free, args=args):
            th = np.zeros((1, 3))
            th[0, free] = x
            return balance_all(th, *args, pv, gv, False, False)[0][0]

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
    wl, wr, dwl, dwr = (np.asarray(a, dtype=float).ravel() for a in (wl, wr, dwl, dwr))
    p = param_vector(params)
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
