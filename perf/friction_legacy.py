"""The friction model's fit as it was before issue 14 (model version 1.5, commit 9f1e841), frozen for the
``friction_fit`` comparison only: the batched Levenberg-Marquardt with forward-difference Jacobians
(3 extra residual evaluations per iteration) and the outer ``least_squares`` with finite-difference
parameter Jacobians (``diff_step`` 1e-3 in log space: 5 more solves of every step per Jacobian).

Only the algorithms are frozen. The physics (``residual``, ``low_slip_start``, ``body_velocity``,
``free_mask``, the geometry) and the model's constants are imported from ``skidbench.models``, so the
comparison stays between two ways of solving the same model. Not used by the pipeline.
"""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd
from scipy.optimize import least_squares

from skidbench.models.base import ModelError
from skidbench.models.columns import mse, targets, training_rows
from skidbench.models.friction.balance import (
    PARAM_NAMES,
    FrictionGeometry,
    body_velocity,
    free_mask,
    param_vector,
    residual,
)
from skidbench.models.friction.fit import PARAM_RANGES
from skidbench.models.friction.model import ACCEL_SCALES, FALLBACK_ITER, FrictionBased
from skidbench.models.friction.solver import SolveResult, low_slip_start

log = logging.getLogger(__name__)


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


def solve_v15(
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
    p = param_vector(params)
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


class LegacyFrictionFit(FrictionBased):
    """``FrictionBased`` with the version-1.5 solve and fit (for the benchmark only)."""

    def velocities(self, inputs, params=None, theta0=None) -> tuple[np.ndarray, SolveResult]:
        """(T, 3) body velocities and the per-step solve (eq. 12 then eq. 8).

        A step whose solve is not physical (no root, not converged, or a slip ratio outside [-1, 1], i.e.
        a wheel's ground speed outside 0..2 r omega; these are steps that command an acceleration
        friction cannot deliver, such as a step change of the command) is solved again with its
        commanded accelerations scaled by ``ACCEL_SCALES`` in turn, and predicted from the first
        physical solution: the motion at the largest tried fraction of the commanded acceleration
        that the forces can balance (``sol.accel_scale``; 0 is the steady state). Without it such a
        step predicted body speeds of hundreds of m/s on DRIVE's command steps. ``sol.status`` stays
        the status of the commanded problem. ``options.accel_fallback=false`` turns it off.
        """
        p = self.params if params is None else params
        geo = self.geometry
        sol = solve_v15(*inputs, p, geo, theta0=theta0)
        wl, wr, dwl, dwr = (np.asarray(a, dtype=float).ravel() for a in inputs)
        scale = np.ones(wl.size)
        bad = ~self._physical(sol.theta, sol.status, wl, wr)
        if bad.any() and self.options.get("accel_fallback", True):
            # every fraction of every such step in one batched solve (they are independent problems)
            idx = np.flatnonzero(bad)
            ks = np.repeat(np.asarray(ACCEL_SCALES, dtype=float), idx.size)
            rep = np.tile(idx, len(ACCEL_SCALES))
            sub = solve_v15(
                wl[rep], wr[rep], ks * dwl[rep], ks * dwr[rep], p, geo, restarts=False, max_iter=FALLBACK_ITER
            )
            ok = self._physical(sub.theta, sub.status, wl[rep], wr[rep]).reshape(len(ACCEL_SCALES), idx.size)
            found = ok.any(axis=0)
            first = np.argmax(ok, axis=0)  # the largest fraction with a physical solution
            pick = first * idx.size + np.arange(idx.size)
            theta = sol.theta.copy()
            theta[idx[found]] = sub.theta[pick[found]]
            scale[idx[found]] = np.asarray(ACCEL_SCALES)[first[found]]
            info = {**sol.info, "commanded_theta": sol.theta}  # the commanded problem's (a warm start)
            sol = SolveResult(theta, sol.status, sol.cost, sol.n_iter, info, scale)
        else:
            sol.accel_scale = scale
        return body_velocity(sol.theta, wl, wr, geo.r, geo.B), sol

    def fit(self, table: pd.DataFrame) -> LegacyFrictionFit:
        self.check_columns(table, fitting=True)
        train = training_rows(table)
        inp = self.inputs(train)
        y = targets(train)
        names = list(self.options.get("fit_params") or PARAM_NAMES)
        unknown = [n for n in names if n not in PARAM_NAMES]
        if unknown:
            raise ModelError(f"model {self.name}: unknown fit_params {unknown} (known: {PARAM_NAMES})")
        base = dict(self.params)
        warm = {"theta": None}
        loss = str(self.options.get("loss", "soft_l1"))
        f_scale = float(self.options.get("f_scale", 0.1))  # m/s, rad/s: where soft_l1 turns linear
        track: dict = {"excluded": 0, "scored": None}

        def unpack(z):
            p = dict(base)
            p.update({n: float(np.exp(v)) for n, v in zip(names, z, strict=True)})
            return p

        def resid(z):
            v, sol = self.velocities(inp, unpack(z), theta0=warm["theta"])
            if warm["theta"] is None or np.all(sol.status > 0):
                # warm start for the next evaluation: the commanded problem's solution, not the fallback's
                warm["theta"] = sol.info.get("commanded_theta", sol.theta)
            # The scored steps are fixed at the start: those with a root under the initial parameters.
            # A step without one there (an acceleration friction cannot deliver) has only a least-squares
            # slip, a poor, jumpy function of the parameters, and stays out; a scored step that loses its
            # root later keeps its least-squares residual (what `predict` returns for it), so the
            # optimizer cannot buy a lower loss by pushing steps into "no root".
            # A scored step the solver has not finished (status 0) keeps its best iterate's residual too:
            # dropping it would let the optimizer escape into parameters the solver cannot handle.
            if track.get("scored") is None:
                track["scored"] = sol.status == 1
            bad = ~track["scored"]
            track["excluded"] = int(bad.sum())
            r = v - y
            r[bad] = 0.0
            return r.ravel()

        z0 = np.log([float(base[n]) for n in names])
        # physically plausible ranges (friction and rolling coefficients, slip stiffness, the lateral
        # law's angle scale), so the fit cannot wander where the force balance means nothing
        ranges = {**PARAM_RANGES, **(self.options.get("param_ranges") or {})}
        lo = np.log([float(ranges[n][0]) for n in names])
        hi = np.log([float(ranges[n][1]) for n in names])
        z0 = np.clip(z0, lo + 1e-9, hi - 1e-9)
        res = least_squares(
            resid,
            z0,
            bounds=(lo, hi),
            method="trf",
            loss=loss,
            f_scale=f_scale,
            # log-space step: large enough that the finite differences see the parameters, not the
            # inner solver's tolerance (1e-6 left the fit at its start on real data)
            diff_step=float(self.options.get("diff_step", 1e-3)),
            xtol=float(self.options.get("xtol", 1e-10)),
            ftol=float(self.options.get("ftol", 1e-12)),
            gtol=float(self.options.get("gtol", 1e-12)),
            max_nfev=int(self.options.get("max_nfev", 200)),
        )
        self.params = unpack(res.x)
        pred, sol = self.velocities(inp)
        rooted = sol.status == 1
        scored = track["scored"]
        # mu_x matters only where eq. (6) saturates; if nothing saturates, any mu_x above the largest
        # lambda |s| fits equally well: keep the initial value (raised to that bound) and say so. The bound
        # is taken over the scored steps that have a root (a no-root step's theta is a least-squares
        # minimiser, often at full slip, and says nothing about mu_x)
        used = rooted & track["scored"]
        lam_s = float(self.params["lambda"] * np.abs(sol.theta[used, :2]).max(initial=0.0))
        mu_x_identified = bool(np.any(sol.saturated(inp[0], inp[1], self.params) & used))
        if "mu_x" in names and not mu_x_identified:
            self.params["mu_x"] = max(float(base["mu_x"]), lam_s)
            pred, sol = self.velocities(inp)
            rooted = sol.status == 1
        self.last_solve_ = sol
        self.fit_loss_ = mse(pred[scored], y[scored]) if scored.any() else float("nan")
        moved = bool(np.any(np.abs(res.x - z0) > 1e-6))
        self.fit_info_ = {
            "nfev": int(res.nfev),
            "optimizer_status": int(res.status),
            "optimizer_message": str(res.message),
            "moved_from_start": moved,
            "loss": loss,
            "f_scale": f_scale,
            "fitted": names,
            "steps": int(len(rooted)),
            "steps_not_converged": sol.n_not_converged,
            "steps_without_root": int(np.sum(sol.status == 2)),
            "steps_excluded_from_loss": int(np.sum(~scored)),
            "fit_loss_all_steps": mse(pred, y),
            "mu_x_identified": mu_x_identified,
            "mu_x_lower_bound": lam_s,
        }
        if not moved:
            log.warning("model %s: the fit did not move from its start (%s)", self.name, res.message)
        return self
