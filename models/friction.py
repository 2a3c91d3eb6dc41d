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

from . import actuator
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

#: the steady-state start needs a straight-driving slip of at least this: below it s_0 (and mu_r = lambda s_0)
#: is within the ground truth's speed noise (on mini's asphalt Train, s_0 = 0.0018 and that start led the
#: fit to mu_r on its lower bound; DRIVE's Husky and Warthog: s_0 = 0.048 and 0.051)
MIN_STRAIGHT_SLIP = 0.01
#: fractions of the commanded accelerations tried, in order, for a step whose solve is not physical
ACCEL_SCALES = (0.5, 0.25, 0.125, 0.0)
#: LM iterations of those solves (a root converges in far fewer; a step still descending after them
#: counts as not balanced at that fraction)
FALLBACK_ITER = 30


def bound_report(params: dict, names: list[str], ranges: dict, res) -> dict:
    """Each fitted parameter's distance from its bounds and its standard error, for the fit JSON and MLflow.

    ``param_bound_margin``: min(distance to the lower, to the upper bound) / range width, in the space the
    fit works in (log p; 0 = on a bound, 0.5 = the middle); ``param_bound_margin_linear``: the same in p.
    ``param_stderr``: the Gauss-Newton standard error from the optimizer's Jacobian at the solution,
    sqrt(diag((J^T J)^-1) * 2 cost / (m - n)) in log p, turned into p by the delta method (p * se_log);
    NaN where J^T J is singular in that direction (a parameter the data do not pin)."""
    margin, margin_lin, stderr = {}, {}, {}
    z = np.log([float(params[n]) for n in names])
    J = np.asarray(res.jac, dtype=float)
    m, n = J.shape
    dof = max(m - n, 1)
    s2 = 2.0 * float(res.cost) / dof
    try:
        cov = np.linalg.pinv(J.T @ J, rcond=1e-12) * s2
        se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        se[np.diag(J.T @ J) <= 0] = np.nan
    except np.linalg.LinAlgError:
        se = np.full(n, np.nan)
    for i, name in enumerate(names):
        lo, hi = (float(v) for v in ranges[name])
        llo, lhi = np.log(lo), np.log(hi)
        margin[name] = float(min(z[i] - llo, lhi - z[i]) / (lhi - llo))
        p = float(params[name])
        margin_lin[name] = float(min(p - lo, hi - p) / (hi - lo))
        stderr[name] = float(p * se[i])
    return {"param_bound_margin": margin, "param_bound_margin_linear": margin_lin, "param_stderr": stderr}


class FrictionBased(KinematicModel):
    name = "friction"
    # 1.1: solver restarts and no-root/stationary status; 1.2: robust fit (soft_l1, log-space diff_step);
    # 1.3: the scored steps are those with a root at the start (no escape into "no root");
    # 1.4: unfinished steps stay scored; parameters bounded to physically plausible ranges
    # 1.5: a step without a physical solution is predicted at a reduced acceleration (velocities)
    # 1.6: driven by the actuator output (dead time + lag from Train encoders, models/actuator.py); the fit
    # uses analytic (implicit-function) parameter Jacobians (issue 14: how it is computed, not the model)
    # 1.7: driven by the general wheel response (models/actuator.py: per sum/difference mode lag, slew limit,
    # gain and saturation, and the wheels' rate limit, its structure chosen on held-out Train blocks)
    version = "1.7"
    required_columns = ("cmd_wl", "cmd_wr", "cmd_dwl", "cmd_dwr")
    # the spec sheet's radius and track: the slip ratios (eq. 4) are what the radius an effective-radius
    # calibration measures absorbs, and the wheel positions are physical; taking the calibrated radius
    # counts the slip twice (DRIVE Husky Train: fit loss 0.149 with it, 0.0845 without; README)
    calibrated_constants = ()

    def __init__(self, robot, params=None, **options):
        super().__init__(robot, params, **options)
        self.params = {**DEFAULT_PARAMS, **self.params}
        self.geometry = FrictionGeometry.from_robot(robot)
        self.last_solve_: SolveResult | None = None
        self.fit_info_: dict = {}

    def inputs(self, table: pd.DataFrame) -> tuple[np.ndarray, ...]:
        """(wl, wr, dwl, dwr) (each (T,)): the wheel rates (rad/s) and their derivatives (rad/s^2) the force
        balance is driven by: the commanded ones through the wheel response (the ``actuator_*`` entries of
        ``params``: dead time, lags, slew limits, gains and saturations; ``models/actuator.py``), or the
        commanded ones as they are when the actuator is off or was not identified (no encoders in Train)."""
        table = actuator.respond(table, actuator.WheelResponse.from_params(self.params))
        return tuple(col(table, c) for c in ("cmd_wl", "cmd_wr", "cmd_dwl", "cmd_dwr"))

    def identify_actuator(self, table: pd.DataFrame) -> dict:
        """``options.actuator``: ``auto`` (default) identifies the wheel response from the table's encoders
        (Train), choosing its structure among ``actuator.CANDIDATES`` on held-out Train blocks; a structure
        name (e.g. ``delay+lag``, the 1.6 model) identifies that structure only; ``none`` drives the model
        by the raw commands; a mapping (``{delay_s, tau_s, ...}``, the fields of ``actuator.WheelResponse``)
        sets it. Sets the ``actuator_*`` entries of ``params``; returns what was done (for ``fit_info_``)."""
        opt = self.options.get("actuator", "auto")
        resp = actuator.WheelResponse()
        fields = list(actuator.WheelResponse.__dataclass_fields__)
        if isinstance(opt, dict):
            unknown = sorted(set(opt) - set(fields))
            if unknown:
                raise ModelError(
                    f"model {self.name}: options.actuator: unknown keys {unknown} (known: {fields})"
                )
            resp = actuator.WheelResponse.from_params({f"actuator_{k}": float(v) for k, v in opt.items()})
            info = {"source": "config", **resp.to_params()}
        elif opt in (None, "none", False):
            info = {"source": "none"}
        elif isinstance(opt, str) and (opt == "auto" or opt in actuator.CANDIDATES):
            fit = actuator.identify_response(table, None if opt == "auto" else (opt,))
            if fit is None:
                info = {"source": "none (no encoder readings in Train)"}
            else:
                resp, info = fit.response, {"source": "encoders", **fit.to_dict()}
        else:
            raise ModelError(
                f"model {self.name}: options.actuator={opt!r}: expected auto, none, one of "
                f"{list(actuator.CANDIDATES)} or a mapping of {fields}"
            )
        self.params.update(resp.to_params())
        return info

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
        # the actuator runs on the whole table (a causal filter needs the rows a fit leaves out, too)
        act_info = self.identify_actuator(table)
        all_inp = self.inputs(table)
        rows = table["valid"].to_numpy(bool)
        train = training_rows(table)
        inp = tuple(a[rows] for a in all_inp)
        y = targets(train)
        names = list(self.options.get("fit_params") or PARAM_NAMES)
        unknown = [n for n in names if n not in PARAM_NAMES]
        if unknown:
            raise ModelError(f"model {self.name}: unknown fit_params {unknown} (known: {PARAM_NAMES})")
        start_info = {"source": "config"}
        if self.options.get("start", "steady_state") == "steady_state":
            start_info = self.steady_state_start(inp, targets(train), names)
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
            "actuator": act_info,
            "start": start_info,
            **bound_report(self.params, names, ranges, res),
        }
        if not moved:
            log.warning("model %s: the fit did not move from its start (%s)", self.name, res.message)
        return self

    def steady_state_start(self, inp, y: np.ndarray, names: list[str]) -> dict:
        """Start the fit from the friction parameters that reproduce two steady-state numbers of the Train
        data in closed form (eqs. 5-11 with no acceleration, a centred CG and small rolling terms):
        straight driving balances rolling resistance by slip, lambda s_0 = mu_r, so the speed ratio is
        1 - s_0; a turn about the centre balances the lateral forces' moment by slip, lambda s_t = mu_r +
        (a/b) mu_y (1 - exp(-atan(a/b)/C)), so the yaw-rate ratio is k = 1 - s_t. With mu_y and C at their
        configured values this gives lambda = (a/b) mu_y (1 - exp(-atan(a/b)/C)) / (s_t - s_0), mu_r =
        lambda s_0, and mu_x at least 1.25 lambda s_t (no saturation in the turn). Steady rows: both
        wheels turning, wheel accelerations under 0.2 rad/s^2. Keeps the configured start when the data
        have no such rows, the ratios are not physical (s_t <= s_0) or the straight slip is under
        ``MIN_STRAIGHT_SLIP`` (not resolved by the data)."""
        wl, wr, dwl, dwr = inp
        geo = self.geometry
        r, B = geo.r, geo.B
        steady = (np.abs(dwl) < 0.2) & (np.abs(dwr) < 0.2) & (np.abs(wl) > 0.5) & (np.abs(wr) > 0.5)
        v_w, w_w = r * (wl + wr) / 2.0, r * (wr - wl) / B
        straight = steady & (np.abs(w_w) * B / 2 < 0.05 * np.abs(v_w)) & (np.abs(v_w) > 0.1)
        turning = steady & (np.abs(w_w) > 0.3)
        info: dict = {
            "source": "config",
            "straight_rows": int(straight.sum()),
            "turning_rows": int(turning.sum()),
        }
        if straight.sum() < 10 or turning.sum() < 10:
            return info
        s0 = float(np.median(1.0 - y[straight, 0] / v_w[straight]))
        k = float(np.median(y[turning, 2] / w_w[turning]))
        info.update(speed_ratio=1.0 - s0, yaw_ratio=k)
        st = 1.0 - k
        if not (MIN_STRAIGHT_SLIP <= s0 < st < 1.0):
            return info
        a, b = np.abs(geo.wheel_xy[0])
        ranges = {**PARAM_RANGES, **(self.options.get("param_ranges") or {})}
        mu_y, C = float(self.params["mu_y"]), float(self.params["C"])
        lat = (a / b) * mu_y * (1.0 - np.exp(-np.arctan2(a, b) / C))
        lam = lat / (st - s0)
        start = {"lambda": lam, "mu_r": lam * s0, "mu_x": max(float(self.params["mu_x"]), 1.25 * lam * st)}
        for n, v in start.items():
            if n in names:
                lo, hi = ranges[n]
                # inside the bounds by 5 % of the log range: a start on a bound has no room to move
                m = 0.05 * np.log(hi / lo)
                self.params[n] = float(np.exp(np.clip(np.log(v), np.log(lo) + m, np.log(hi) - m)))
        info.update(source="steady_state", **{n: self.params[n] for n in start})
        return info

    def predict(self, table: pd.DataFrame) -> np.ndarray:
        self.check_columns(table)
        pred, sol = self.velocities(self.inputs(table))
        self.last_solve_ = sol
        return pred
