"""Friction-based kinematic model (the paper's section III, eqs. 5-12).

Per time step, theta = (s_l, s_r, x_ICR) solves the force/torque balance F(theta) = 0 (eqs. 9-11) built from
the commanded wheel rates and their derivatives; eq. (8) then gives (vx, vy, wz). The inner solve is
batched over all steps (``friction_solver.solve``). The five parameters {mu_r, mu_x, mu_y, lambda, C} are
fitted by nonlinear least squares (scipy ``least_squares``, in log space so they stay positive) on the
velocity prediction error, each evaluation warm-started from the previous evaluation's slips. The fit's
Jacobian is analytic: the solved slips' derivative with respect to the parameters by the implicit function
theorem at the converged balance (``velocity_sensitivity``), one 3x3 solve per step instead of five more
solves of every step for finite differences.

Identifiability (what the data can and cannot pin down):
- mu_x only matters where a tractive force saturates (lambda |s| >= mu_x in eq. 6); on data where the min()
  never saturates it has no effect and is not identifiable (kept at its initial value).
- C and mu_y enter eq. (7) as mu_y (1 - exp(-|alpha|/C)); at small slip angles this is mu_y |alpha| / C, so
  only mu_y / C is identifiable unless slip angles reach a sizeable fraction of C.
- mu_r and lambda: straight driving fixes the slip mu_r / lambda; their scale relative to the inertial
  terms M a needs accelerations and turns. All friction coefficients scale together with M a otherwise.
- Zero slip: mu_r = 0 and no accelerations (steady straight driving) give s = 0, i.e. the ideal model;
  lambda -> infinity with mu_r = 0 gives zero slip ratios for any motion (eq. 8 with s = 0).
"""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd
from scipy.optimize import least_squares

from ._util import col, mse, targets, training_rows
from .base import KinematicModel, ModelError
from .friction_solver import (
    PARAM_NAMES,
    FrictionGeometry,
    SolveResult,
    body_velocity,
    free_mask,
    solve,
    velocity_sensitivity,
)

log = logging.getLogger(__name__)

#: (low, high) of each parameter during a fit; `options.param_ranges` overrides
PARAM_RANGES = {
    "mu_r": (1e-4, 0.5),
    "mu_x": (0.05, 3.0),
    "mu_y": (0.05, 3.0),
    "lambda": (0.5, 200.0),
    "C": (0.01, 5.0),
}

DEFAULT_PARAMS = {"mu_r": 0.03, "mu_x": 0.8, "mu_y": 0.6, "lambda": 8.0, "C": 0.3}

#: fractions of the commanded accelerations tried, in order, for a step whose solve is not physical
ACCEL_SCALES = (0.5, 0.25, 0.125, 0.0)
#: LM iterations of those solves (a root converges in far fewer; a step still descending after them
#: counts as not balanced at that fraction)
FALLBACK_ITER = 30


class FrictionBased(KinematicModel):
    name = "friction"
    # 1.1: solver restarts and no-root/stationary status; 1.2: robust fit (soft_l1, log-space diff_step);
    # 1.3: the scored steps are those with a root at the start (no escape into "no root");
    # 1.4: unfinished steps stay scored; parameters bounded to physically plausible ranges
    # 1.5: a step without a physical solution is predicted at a reduced acceleration (velocities)
    # (issue 14 changed how the fit is computed, analytic Jacobians, not the model: the version stays)
    version = "1.5"
    required_columns = ("cmd_wl", "cmd_wr", "cmd_dwl", "cmd_dwr")

    def __init__(self, robot, params=None, **options):
        super().__init__(robot, params, **options)
        self.params = {**DEFAULT_PARAMS, **self.params}
        self.geometry = FrictionGeometry.from_robot(robot)
        self.last_solve_: SolveResult | None = None
        self.fit_info_: dict = {}

    @staticmethod
    def inputs(table: pd.DataFrame) -> tuple[np.ndarray, ...]:
        """(wl, wr, dwl, dwr): commanded wheel rates (rad/s) and their derivatives (rad/s^2), each (T,)."""
        return tuple(col(table, c) for c in ("cmd_wl", "cmd_wr", "cmd_dwl", "cmd_dwr"))

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
        sol = solve(*inputs, p, geo, theta0=theta0)
        wl, wr, dwl, dwr = (np.asarray(a, dtype=float).ravel() for a in inputs)
        scale = np.ones(wl.size)
        bad = ~self._physical(sol.theta, sol.status, wl, wr)
        if bad.any() and self.options.get("accel_fallback", True):
            # every fraction of every such step in one batched solve (they are independent problems)
            idx = np.flatnonzero(bad)
            ks = np.repeat(np.asarray(ACCEL_SCALES, dtype=float), idx.size)
            rep = np.tile(idx, len(ACCEL_SCALES))
            sub = solve(
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

    @staticmethod
    def _physical(theta: np.ndarray, status: np.ndarray, wl: np.ndarray, wr: np.ndarray) -> np.ndarray:
        """(T,) a root with both slip ratios in [-1, 1] (a side with no commanded rate has none)."""
        free = free_mask(wl, wr)[:, :2]
        return (status == 1) & ~np.any(free & (np.abs(theta[:, :2]) > 1.0), axis=1)

    def fit(self, table: pd.DataFrame) -> FrictionBased:
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
        last: dict = {}
        geo = self.geometry

        def unpack(z):
            p = dict(base)
            p.update({n: float(np.exp(v)) for n, v in zip(names, z, strict=True)})
            return p

        def evaluate(z):
            """The solve at z (cached: scipy asks for the residual and then the Jacobian at the same z)."""
            if last.get("z") is not None and np.array_equal(last["z"], z):
                return last
            p = unpack(z)
            v, sol = self.velocities(inp, p, theta0=warm["theta"])
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
            last.clear()
            last.update(z=np.array(z, copy=True), p=p, sol=sol, r=r.ravel())
            return last

        def resid(z):
            return evaluate(z)["r"]

        def jac(z):
            # d residual / d log p: the implicit-function derivative of the solved slips (one 3x3 solve per
            # step at the converged Jacobian), not 5 more solves of every step
            e = evaluate(z)
            sol, p = e["sol"], e["p"]
            k = np.ones(len(y)) if sol.accel_scale is None else sol.accel_scale
            S = velocity_sensitivity(sol.theta, sol.status, inp[0], inp[1], k * inp[2], k * inp[3], p, geo)
            cols = [PARAM_NAMES.index(n) for n in names]
            Jz = S[:, :, cols] * np.array([p[n] for n in names])
            Jz[~track["scored"]] = 0.0
            return Jz.reshape(-1, len(names))

        z0 = np.log([float(base[n]) for n in names])
        # physically plausible ranges (friction and rolling coefficients, slip stiffness, the lateral
        # law's angle scale), so the fit cannot wander where the force balance means nothing
        ranges = {**PARAM_RANGES, **(self.options.get("param_ranges") or {})}
        lo = np.log([float(ranges[n][0]) for n in names])
        hi = np.log([float(ranges[n][1]) for n in names])
        z0 = np.clip(z0, lo + 1e-9, hi - 1e-9)
        opts = dict(
            jac=jac if self.options.get("jacobian", "analytic") == "analytic" else "2-point",
            diff_step=float(self.options.get("diff_step", 1e-3)),
            bounds=(lo, hi),
            method="trf",
            loss=loss,
            f_scale=f_scale,
            xtol=float(self.options.get("xtol", 1e-10)),
            ftol=float(self.options.get("ftol", 1e-12)),
            gtol=float(self.options.get("gtol", 1e-12)),
            max_nfev=int(self.options.get("max_nfev", 200)),
            x_scale=self.options.get("x_scale", 1.0),
        )
        res = least_squares(resid, z0, **opts)
        # the objective has jumps (steps gaining or losing a root): trf's trust region can collapse on one
        # and stop on xtol short of the minimum; a fresh trust region from its end point goes on
        nfev = int(res.nfev)
        for _ in range(int(self.options.get("outer_restarts", 0))):
            again = least_squares(resid, res.x, **opts)
            nfev += int(again.nfev)
            if not again.cost < res.cost * (1.0 - 1e-9):
                break
            res = again
        res.nfev = nfev
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

    def predict(self, table: pd.DataFrame) -> np.ndarray:
        self.check_columns(table)
        pred, sol = self.velocities(self.inputs(table))
        self.last_solve_ = sol
        return pred
