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
- C and mu_y enter eq. (7) as mu_y (1 - exp(-|alpha|/C)): an initial lateral stiffness k_y = mu_y / C and a
  saturation level mu_y. Where the data's lateral resistance grows in proportion to the slip angle over all
  the slip angles they reach, only k_y is identifiable: the fit runs along mu_y / C towards the linear law
  until a bound stops it. Then mu_y is held (not identified, bounded below; ``_lateral_identifiability``)
  and the rest refitted, as mu_x is when eq. (6) never saturates.
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

from .base import KinematicModel, ModelError
from .columns import col, mse, targets, training_rows
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


#: a fitted mu_y or C closer than this (fraction of its log range) to its upper bound has run along the
#: lateral law's ridge (mu_y / C fixed, both growing: the law ever more linear) to the end of the range
RIDGE_EDGE = 0.01
#: where the slip angles the data reach are read: this quantile of the scored steps' wheel slip angles
SLIP_ANGLE_QUANTILE = 0.95
#: eq. (7) counts as in its linear part over the data while that slip angle is under this many C (at 1 C
#: the law is at 63 % of mu_y; a fit at a bound with the data beyond it is a saturated law, not a ridge)
LINEAR_REACH = 1.0
#: z of the one-sided lower confidence limit (95 %) a not-identified mu_y is held at
LATERAL_CL_Z = 1.645
#: a start, or a held value, stays inside its bounds by this fraction of the log range (on a bound it has
#: no room to move)
START_MARGIN = 0.05


def log_covariance(res) -> np.ndarray:
    """Gauss-Newton covariance of the fitted log p: (J^T J)^-1 * 2 cost / (m - n) from the optimizer's
    Jacobian at the solution (pseudo-inverse; NaN on the diagonal where J^T J has a zero column)."""
    J = np.asarray(res.jac, dtype=float)
    m, n = J.shape
    s2 = 2.0 * float(res.cost) / max(m - n, 1)
    try:
        cov = np.linalg.pinv(J.T @ J, rcond=1e-12) * s2
    except np.linalg.LinAlgError:
        return np.full((n, n), np.nan)
    dead = np.diag(J.T @ J) <= 0
    cov[dead, :] = np.nan
    cov[:, dead] = np.nan
    return cov


def bound_report(params: dict, names: list[str], ranges: dict, res, held: list[str] = ()) -> dict:
    """Each fitted parameter's distance from its bounds and its standard error, for the fit JSON and MLflow.

    ``param_bound_margin``: min(distance to the lower, to the upper bound) / range width, in the space the
    fit works in (log p; 0 = on a bound, 0.5 = the middle); ``param_bound_margin_linear``: the same in p.
    ``param_stderr``: the Gauss-Newton standard error from the optimizer's Jacobian at the solution,
    sqrt(diag((J^T J)^-1) * 2 cost / (m - n)) in log p, turned into p by the delta method (p * se_log);
    NaN where J^T J is singular in that direction (a parameter the data do not pin). ``held`` (not
    fitted, held at a value the fit derived, e.g. a not-identified mu_y): margins reported, standard
    error NaN (``res.jac`` has columns for ``names`` only)."""
    margin, margin_lin, stderr = {}, {}, {}
    cov = log_covariance(res)
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    se[~np.isfinite(np.diag(cov))] = np.nan
    for i, name in enumerate(list(names) + list(held)):
        lo, hi = (float(v) for v in ranges[name])
        llo, lhi = np.log(lo), np.log(hi)
        p = float(params[name])
        z = np.log(p)
        margin[name] = float(min(z - llo, lhi - z) / (lhi - llo))
        margin_lin[name] = float(min(p - lo, hi - p) / (hi - lo))
        stderr[name] = float(p * se[i]) if i < len(names) else float("nan")
    return {"param_bound_margin": margin, "param_bound_margin_linear": margin_lin, "param_stderr": stderr}


def lateral_var_k(cov: np.ndarray, names: list[str]) -> float:
    """Variance of log(mu_y / C) = log mu_y - log C from the covariance of the fitted log p (both fitted)."""
    i, j = names.index("mu_y"), names.index("C")
    v = float(cov[i, i] + cov[j, j] - 2.0 * cov[i, j])
    return v if np.isfinite(v) else float("nan")


def wheel_slip_angles(v: np.ndarray, geo: FrictionGeometry) -> np.ndarray:
    """(T, 4) |alpha| of each wheel (eq. 4: atan2(|V_wy|, |V_wx|)) from body velocities v (T, 3)."""
    X, Y = geo.wheel_xy[:, 0], geo.wheel_xy[:, 1]
    vwx = v[:, :1] - v[:, 2:3] * Y
    vwy = v[:, 1:2] + v[:, 2:3] * X
    return np.arctan2(np.abs(vwy), np.abs(vwx))


class FrictionBased(KinematicModel):
    name = "friction"
    # 1.1: solver restarts and no-root/stationary status; 1.2: robust fit (soft_l1, log-space diff_step);
    # 1.3: the scored steps are those with a root at the start (no escape into "no root");
    # 1.4: unfinished steps stay scored; parameters bounded to physically plausible ranges
    # 1.5: a step without a physical solution is predicted at a reduced acceleration (velocities)
    # 1.6: driven by the actuator output (dead time + lag from Train encoders, models/actuator.py); the fit
    # uses analytic (implicit-function) parameter Jacobians (issue 14: how it is computed, not the model)
    # 1.7: mu_y held (not identified) when the fit runs along mu_y / C to the end of the range (eq. 7 linear
    # over the data's slip angles); fit_info reports every parameter's identification
    # 1.8: driven by the general wheel response (models/actuator.py: per sum/difference mode lag, slew limit,
    # gain and saturation, and the wheels' rate limit, its structure chosen on held-out Train blocks)
    # 1.9: the paper's model again: five parameters, driven by the inputs of the run's protocol (commanded
    # rates and their derivatives by default); the wheel response is a calibration of the robot shared by
    # every model (pipeline/wheel_response.py, ``inputs=response``), no longer an option of this model
    version = "1.9"
    required_columns = ("cmd_wl", "cmd_wr", "cmd_dwl", "cmd_dwr")
    # the spec sheet's radius and track: the slip ratios (eq. 4) are what the radius an effective-radius
    # calibration measures absorbs, and the wheel positions are physical; taking the calibrated radius
    # counts the slip twice (DRIVE Husky Train: fit loss 0.149 with it, 0.0845 without; README)
    calibrated_constants = ()
    calibration_usage = (
        "neither: its slip ratios absorb the effective radius, its wheel positions are physical"
    )

    def __init__(self, robot, params=None, **options):
        if "actuator" in options:
            raise ModelError(
                f"model {self.name}: options.actuator was removed in 1.9: the wheel response is a calibration"
                " of the robot shared by every model now (`skidbench calibrate`, then inputs=response)"
            )
        # a fit of <= 1.8 also held its wheel response (actuator_* entries): not this model's parameters
        params = {k: v for k, v in (params or {}).items() if not str(k).startswith("actuator_")}
        super().__init__(robot, params, **options)
        self.params = {**DEFAULT_PARAMS, **self.params}
        self.geometry = FrictionGeometry.from_robot(robot)
        self.last_solve_: SolveResult | None = None
        self.fit_info_: dict = {}

    def inputs(self, table: pd.DataFrame) -> tuple[np.ndarray, ...]:
        """(wl, wr, dwl, dwr) (each (T,)): the wheel rates (rad/s) and their derivatives (rad/s^2) the force
        balance is driven by, as the paper does (section III): the table's ``cmd_wl``, ``cmd_wr``,
        ``cmd_dwl``, ``cmd_dwr``, i.e. the inputs of the run's protocol (pipeline/protocol.py)."""
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
        # what is fitted and from what: a refit with mu_y held (below) changes both
        cur = {"names": names, "base": base}

        def unpack(z):
            p = dict(cur["base"])
            p.update({n: float(np.exp(v)) for n, v in zip(cur["names"], z, strict=True)})
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
            cols = [PARAM_NAMES.index(n) for n in cur["names"]]
            Jz = S[:, :, cols] * np.array([p[n] for n in cur["names"]])
            Jz[~track["scored"]] = 0.0
            return Jz.reshape(-1, len(cur["names"]))

        # physically plausible ranges (friction and rolling coefficients, slip stiffness, the lateral
        # law's angle scale), so the fit cannot wander where the force balance means nothing
        ranges = {**PARAM_RANGES, **(self.options.get("param_ranges") or {})}
        opts = dict(
            jac=jac if self.options.get("jacobian", "analytic") == "analytic" else "2-point",
            diff_step=float(self.options.get("diff_step", 1e-3)),
            method="trf",
            loss=loss,
            f_scale=f_scale,
            xtol=float(self.options.get("xtol", 1e-10)),
            ftol=float(self.options.get("ftol", 1e-12)),
            gtol=float(self.options.get("gtol", 1e-12)),
            max_nfev=int(self.options.get("max_nfev", 200)),
            x_scale=self.options.get("x_scale", 1.0),
        )

        def run(start: dict):
            """least_squares over ``cur["names"]`` (log p, inside the ranges) from ``start``."""
            lo = np.log([float(ranges[n][0]) for n in cur["names"]])
            hi = np.log([float(ranges[n][1]) for n in cur["names"]])
            z0 = np.clip(np.log([float(start[n]) for n in cur["names"]]), lo + 1e-9, hi - 1e-9)
            last.clear()
            return z0, least_squares(resid, z0, bounds=(lo, hi), **opts)

        z0, res = run(base)
        self.params = unpack(res.x)
        moved = bool(np.any(np.abs(res.x - z0) > 1e-6))
        free_res, free_params = res, dict(self.params)
        lateral = self._lateral_identifiability(inp, names, ranges, res, track["scored"])
        if not lateral["mu_y_identified"]:
            # the saturation level is only bounded below: hold it (``_lateral_identifiability``) and refit
            # the rest from the end point with the same lateral stiffness mu_y / C
            k_y = self.params["mu_y"] / self.params["C"]
            held = lateral["mu_y_held"]
            start = {**self.params, "mu_y": held, "C": held / k_y}
            cur["names"] = [n for n in names if n != "mu_y"]
            cur["base"] = {**self.params, "mu_y": held}
            _, res = run(start)
            self.params = unpack(res.x)
            lateral["robust_cost_free"] = float(free_res.cost)
            lateral["robust_cost_held"] = float(res.cost)
            lateral["nfev_held"] = int(res.nfev)
        if "C" in names and "mu_y" in names:
            # the identified lateral quantity, k_y = mu_y / C, and its standard error at the final fit
            i_c = cur["names"].index("C")
            cov = log_covariance(res)
            var_k = cov[i_c, i_c] if "mu_y" not in cur["names"] else lateral_var_k(cov, cur["names"])
            k_y = self.params["mu_y"] / self.params["C"]
            lateral["lateral_stiffness"] = k_y
            lateral["lateral_stiffness_stderr"] = float(k_y * np.sqrt(var_k)) if var_k >= 0 else None
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
        identified = {n: True for n in names}
        if "mu_x" in names:
            identified["mu_x"] = mu_x_identified
        if "mu_y" in names:
            identified["mu_y"] = lateral["mu_y_identified"]
        report = bound_report(
            self.params, cur["names"], ranges, res, held=[n for n in names if n not in cur["names"]]
        )
        report["param_identified"] = {n: float(v) for n, v in identified.items()}
        if res is not free_res:
            # the free fit's standard errors, for the record (mu_y's there is along the flat ridge)
            report["param_stderr_free_fit"] = bound_report(free_params, names, ranges, free_res)[
                "param_stderr"
            ]
        self.fit_info_ = {
            "nfev": int(free_res.nfev),
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
            "lateral": lateral,
            "start": start_info,
            **report,
        }
        if not moved:
            log.warning("model %s: the fit did not move from its start (%s)", self.name, res.message)
        return self

    def _lateral_identifiability(self, inp, names: list[str], ranges: dict, res, scored: np.ndarray) -> dict:
        """Whether the data identify the lateral law's saturation level mu_y, after the free fit.

        Eq. (7), mu_y (1 - exp(-|alpha|/C)), has an initial stiffness k_y = mu_y / C (per rad) and a
        saturation level mu_y. If the data's lateral resistance grows in proportion to the slip angle over
        every slip angle they reach, the fit runs along mu_y / C = k_y towards the linear law (mu_y and C
        both growing) until mu_y or C meets its upper bound (``RIDGE_EDGE``), the data's slip angles still
        in the law's initial part (``LINEAR_REACH``): then k_y is identified and mu_y only bounded below.
        mu_y is then held at the free fit's one-sided 95 % lower confidence limit (Gauss-Newton,
        ``LATERAL_CL_Z``), but never below the largest lateral coefficient the fitted law
        exerts at the data's slip angles (``SLIP_ANGLE_QUANTILE``) nor nearer its upper bound than
        ``START_MARGIN``; ``fit`` then refits the other parameters with it held. Returns what was found,
        for ``fit_info_["lateral"]``."""
        if not {"mu_y", "C"} <= set(names):
            return {"mu_y_identified": "mu_y" in names, "reason": "mu_y and C are not both fitted"}
        p = self.params
        mu_y, C = float(p["mu_y"]), float(p["C"])
        v, sol = self.velocities(inp)
        used = scored & (sol.status == 1) & free_mask(inp[0], inp[1])[:, :2].any(axis=1)
        alpha = wheel_slip_angles(v[used], self.geometry)
        a_hi = float(np.quantile(alpha, SLIP_ANGLE_QUANTILE)) if alpha.size else float("nan")
        cov = log_covariance(res)
        i = names.index("mu_y")
        se_mu = float(np.sqrt(cov[i, i])) if np.isfinite(cov[i, i]) and cov[i, i] >= 0 else float("nan")
        var_k = lateral_var_k(cov, names)
        k_y = mu_y / C
        upper = {}
        for n, val in (("mu_y", mu_y), ("C", C)):
            lo, hi = (float(x) for x in ranges[n])
            upper[n] = float((np.log(hi) - np.log(val)) / np.log(hi / lo))
        info = {
            "mu_y_identified": True,
            "mu_y_free_fit": mu_y,
            "C_free_fit": C,
            "upper_bound_margin_free_fit": upper,
            "lateral_stiffness": k_y,
            "lateral_stiffness_stderr": float(k_y * np.sqrt(var_k))
            if np.isfinite(var_k) and var_k >= 0
            else None,
            "slip_angle_p95": a_hi,
            "lateral_reach": a_hi / C,
        }
        if min(upper.values()) >= RIDGE_EDGE or not a_hi / C < LINEAR_REACH:
            return info
        f_hi = mu_y * (1.0 - np.exp(-a_hi / C)) if np.isfinite(a_hi) else 0.0
        cl = mu_y * np.exp(-LATERAL_CL_Z * se_mu) if np.isfinite(se_mu) else 0.0
        lo, hi = (float(x) for x in ranges["mu_y"])
        cap = hi * np.exp(-START_MARGIN * np.log(hi / lo))
        floor = lo * np.exp(START_MARGIN * np.log(hi / lo))
        held, rule = cl, "one-sided 95 % lower confidence limit of the free fit"
        if f_hi > held:
            held, rule = f_hi, "largest lateral coefficient of the fitted law at the p95 slip angle"
        if held > cap:
            held, rule = cap, "upper bound less START_MARGIN of the log range"
        elif held < floor:
            held, rule = floor, "lower bound plus START_MARGIN of the log range"
        info.update(
            mu_y_identified=False,
            reason="the fit ran along mu_y / C to the upper end of the range with the data's slip angles "
            "under C: the lateral law is linear over them; only mu_y / C is identified, mu_y bounded below",
            mu_y_held=float(held),
            mu_y_hold_rule=rule,
            mu_y_lower_bound=float(f_hi),
            mu_y_lower_confidence_limit=float(cl),
        )
        return info

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
                m = START_MARGIN * np.log(hi / lo)
                self.params[n] = float(np.exp(np.clip(np.log(v), np.log(lo) + m, np.log(hi) - m)))
        info.update(source="steady_state", **{n: self.params[n] for n in start})
        return info

    def predict(self, table: pd.DataFrame) -> np.ndarray:
        self.check_columns(table)
        pred, sol = self.velocities(self.inputs(table))
        self.last_solve_ = sol
        return pred
