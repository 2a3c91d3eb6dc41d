"""Fitting the friction-based model's five parameters {mu_r, mu_x, mu_y, lambda, C}: a bounded nonlinear
least-squares problem in log space, and the steps around it.

``FrictionBased.fit`` runs :class:`FrictionFit`, whose steps are, in order:

1. ``prepare``: the valid Train rows' inputs (wl, wr, dwl, dwr) and target velocities, the names fitted
   (``options.fit_params``, default all five), and the start: the configured params, or
   (``options.start: steady_state``, the default) the steady-state closed forms
   (``FrictionBased.steady_state_start``);
2. ``free_fit``: scipy ``least_squares`` (trf; ``options.loss`` soft_l1 with ``f_scale`` 0.1 m/s, rad/s;
   bounds ``PARAM_RANGES``) of the velocity prediction error over z = log p (:class:`FitProblem`);
3. ``identify_lateral``: whether the data identify eq. (7)'s saturation level mu_y
   (:func:`lateral_identifiability`); where they do not, mu_y is held and the rest refitted from the same
   lateral stiffness mu_y / C (``refit_mu_y_held``);
4. ``lateral_stiffness``: the identified k_y = mu_y / C and its standard error at the final fit;
5. ``identify_mu_x``: whether eq. (6) saturates on any scored step; if not, mu_x is raised to the lowest
   value consistent with the data (it has no effect below) and the prediction solved again;
6. ``report``: ``fit_info_`` (optimizer, steps, identification, bound margins, standard errors).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
from scipy.optimize import OptimizeResult, least_squares

from skidbench.models.base import ModelError
from skidbench.models.columns import mse, targets, training_rows
from skidbench.models.friction.balance import PARAM_NAMES, FrictionGeometry, free_mask, velocity_sensitivity
from skidbench.models.friction.solver import SolveResult

#: (low, high) of each parameter during a fit; `options.param_ranges` overrides
PARAM_RANGES = {
    "mu_r": (1e-4, 0.5),
    "mu_x": (0.05, 3.0),
    "mu_y": (0.05, 3.0),
    "lambda": (0.5, 200.0),
    "C": (0.01, 5.0),
}
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
#: after the first evaluation, a point where more than this fraction of the steps has no root is solved
#: without the acceleration fallback (``FrictionBased.velocities``): it changes neither the statuses nor
#: the warm start, only the residuals of a trial point trf rejects
FAR_TRIAL_ROOTLESS = 0.5


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


@dataclass
class Solution:
    """One bounded least-squares run: the names it fitted, its start z0 (log p), scipy's result, and every
    parameter's value at the solution (the fitted ones from ``res.x``, the others as held)."""

    names: list[str]
    z0: np.ndarray
    res: OptimizeResult
    params: dict

    @property
    def moved(self) -> bool:
        """Whether the optimizer moved any fitted log p from its start by more than 1e-6."""
        return bool(np.any(np.abs(self.res.x - self.z0) > 1e-6))


@dataclass
class FitProblem:
    """The least squares the fit solves: the body-velocity residuals of the scored steps as a function of
    z = log p of the parameters ``names`` (inside ``ranges``), the others at ``base``.

    Each evaluation solves the force balance of every step (``model.velocities``), warm-started from the
    previous evaluation's slips of the commanded problem (``theta``). The scored steps are fixed at the
    first evaluation: those with a root under the start. A step without one there (an acceleration
    friction cannot deliver) has only a least-squares slip, a poor, jumpy function of the parameters, and
    stays out; a scored step that loses its root later keeps its least-squares residual (what ``predict``
    returns for it), so the optimizer cannot buy a lower loss by pushing steps into "no root"; a scored
    step the solver has not finished (status 0) keeps its best iterate's residual too: dropping it would
    let the optimizer escape into parameters the solver cannot handle. The Jacobian is analytic
    (``jacobian``: the implicit-function derivative of the solved slips, one 3x3 solve per step at the
    converged balance, not five more solves of every step) unless ``analytic`` is False (scipy's
    finite differences, ``options.jacobian: fd``)."""

    model: Any  # the FrictionBased being fitted (its velocities and geometry)
    inp: tuple[np.ndarray, ...]  # (wl, wr, dwl, dwr) of the valid Train rows
    y: np.ndarray  # (T, 3) their target body velocities
    names: list[str]  # fitted now
    base: dict  # every parameter's value where not fitted
    ranges: dict  # (low, high) per parameter
    lsq_options: dict  # least_squares keywords (method, loss, f_scale, tolerances, ...)
    analytic: bool = True
    theta: np.ndarray | None = None  # warm start of the next evaluation
    scored: np.ndarray | None = None  # (T,) bool, fixed at the first evaluation
    last: dict = field(default_factory=dict)  # the last evaluation: z, p, sol, r

    @classmethod
    def for_model(cls, model, inp, y: np.ndarray, names: list[str], start: dict) -> FitProblem:
        """The problem of ``model``'s options: ranges (``param_ranges``), loss and tolerances."""
        o = model.options
        lsq = dict(
            diff_step=float(o.get("diff_step", 1e-3)),
            method="trf",
            loss=str(o.get("loss", "soft_l1")),
            f_scale=float(o.get("f_scale", 0.1)),  # m/s, rad/s: where soft_l1 turns linear
            xtol=float(o.get("xtol", 1e-10)),
            ftol=float(o.get("ftol", 1e-12)),
            gtol=float(o.get("gtol", 1e-12)),
            max_nfev=int(o.get("max_nfev", 200)),
            x_scale=o.get("x_scale", 1.0),
        )
        # physically plausible ranges (friction and rolling coefficients, slip stiffness, the lateral
        # law's angle scale), so the fit cannot wander where the force balance means nothing
        ranges = {**PARAM_RANGES, **(o.get("param_ranges") or {})}
        analytic = o.get("jacobian", "analytic") == "analytic"
        return cls(model, inp, y, list(names), dict(start), ranges, lsq, analytic)

    def params(self, z: np.ndarray) -> dict:
        """Every parameter at z: ``base`` with the fitted ones set to exp(z)."""
        p = dict(self.base)
        p.update({n: float(np.exp(v)) for n, v in zip(self.names, z, strict=True)})
        return p

    def evaluate(self, z: np.ndarray) -> dict:
        """The solve at z (cached: scipy asks for the residual and then the Jacobian at the same z)."""
        last = self.last
        if last.get("z") is not None and np.array_equal(last["z"], z):
            return last
        p = self.params(z)
        far = None if self.scored is None else FAR_TRIAL_ROOTLESS
        v, sol = self.model.velocities(self.inp, p, theta0=self.theta, fallback_below=far)
        if self.theta is None or np.all(sol.status > 0):
            # warm start for the next evaluation: the commanded problem's solution, not the fallback's
            self.theta = sol.info.get("commanded_theta", sol.theta)
        if self.scored is None:
            self.scored = sol.status == 1
        r = v - self.y
        r[~self.scored] = 0.0
        last.clear()
        last.update(z=np.array(z, copy=True), p=p, sol=sol, r=r.ravel())
        return last

    def residuals(self, z: np.ndarray) -> np.ndarray:
        return self.evaluate(z)["r"]

    def jacobian(self, z: np.ndarray) -> np.ndarray:
        """d residual / d log p: the implicit-function derivative of the solved slips (one 3x3 solve per
        step at the converged Jacobian), not 5 more solves of every step."""
        e = self.evaluate(z)
        sol, p = e["sol"], e["p"]
        wl, wr, dwl, dwr = self.inp
        k = np.ones(len(self.y)) if sol.accel_scale is None else sol.accel_scale
        S = velocity_sensitivity(sol.theta, sol.status, wl, wr, k * dwl, k * dwr, p, self.model.geometry)
        cols = [PARAM_NAMES.index(n) for n in self.names]
        Jz = S[:, :, cols] * np.array([p[n] for n in self.names])
        Jz[~self.scored] = 0.0
        return Jz.reshape(-1, len(self.names))

    def solve(self, start: dict) -> Solution:
        """least_squares over ``names`` (log p, inside the ranges) from ``start``."""
        lo = np.log([float(self.ranges[n][0]) for n in self.names])
        hi = np.log([float(self.ranges[n][1]) for n in self.names])
        z0 = np.clip(np.log([float(start[n]) for n in self.names]), lo + 1e-9, hi - 1e-9)
        self.last.clear()
        jac = self.jacobian if self.analytic else "2-point"
        res = least_squares(self.residuals, z0, bounds=(lo, hi), jac=jac, **self.lsq_options)
        return Solution(list(self.names), z0, res, self.params(res.x))

    def hold(self, name: str, value: float, at: dict) -> None:
        """Fit the rest from now on: ``name`` held at ``value``, the others' base ``at``."""
        self.names = [n for n in self.names if n != name]
        self.base = {**at, name: value}


def lateral_identifiability(model, inp, names: list[str], ranges: dict, res, scored: np.ndarray) -> dict:
    """Whether the data identify the lateral law's saturation level mu_y, after the free fit (the model's
    params are the free fit's).

    Eq. (7), mu_y (1 - exp(-|alpha|/C)), has an initial stiffness k_y = mu_y / C (per rad) and a
    saturation level mu_y. If the data's lateral resistance grows in proportion to the slip angle over
    every slip angle they reach, the fit runs along mu_y / C = k_y towards the linear law (mu_y and C
    both growing) until mu_y or C meets its upper bound (``RIDGE_EDGE``), the data's slip angles still
    in the law's initial part (``LINEAR_REACH``): then k_y is identified and mu_y only bounded below.
    mu_y is then held at the free fit's one-sided 95 % lower confidence limit (Gauss-Newton,
    ``LATERAL_CL_Z``), but never below the largest lateral coefficient the fitted law
    exerts at the data's slip angles (``SLIP_ANGLE_QUANTILE``) nor nearer its upper bound than
    ``START_MARGIN``; the fit then refits the other parameters with it held. Returns what was found,
    for ``fit_info_["lateral"]``."""
    if not {"mu_y", "C"} <= set(names):
        return {"mu_y_identified": "mu_y" in names, "reason": "mu_y and C are not both fitted"}
    p = model.params
    mu_y, C = float(p["mu_y"]), float(p["C"])
    v, sol = model.velocities(inp)
    used = scored & (sol.status == 1) & free_mask(inp[0], inp[1])[:, :2].any(axis=1)
    alpha = wheel_slip_angles(v[used], model.geometry)
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


@dataclass
class FrictionFit:
    """One fit of a friction model on a Train table: the state its steps share, one method per step
    (module docstring); ``run`` orders them and leaves the model fitted (``params``, ``last_solve_``,
    ``fit_loss_``, ``fit_info_``)."""

    model: Any  # the FrictionBased being fitted
    problem: FitProblem
    names: list[str]  # the parameters fitted (options.fit_params)
    start: dict  # every parameter's start
    start_info: dict  # where the start came from (``fit_info_["start"]``)
    free: Solution | None = None  # the fit of every name in ``names``
    final: Solution | None = None  # the free fit, or the refit with mu_y held
    lateral: dict = field(default_factory=dict)  # ``fit_info_["lateral"]``
    mu_x_identified: bool = True
    mu_x_lower_bound: float = float("nan")
    pred: np.ndarray | None = None  # (T, 3) the fitted model's velocities on the fit rows
    sol: SolveResult | None = None  # and its solve

    @classmethod
    def prepare(cls, model, table: pd.DataFrame) -> FrictionFit:
        """Step 1: the fit rows' inputs and targets, the names fitted, the start (``model.params`` set to
        it) and the problem."""
        model.check_columns(table, fitting=True)
        rows = table["valid"].to_numpy(bool)
        inp = tuple(a[rows] for a in model.inputs(table))
        y = targets(training_rows(table))
        names = list(model.options.get("fit_params") or PARAM_NAMES)
        unknown = [n for n in names if n not in PARAM_NAMES]
        if unknown:
            raise ModelError(f"model {model.name}: unknown fit_params {unknown} (known: {PARAM_NAMES})")
        start_info = {"source": "config"}
        if model.options.get("start", "steady_state") == "steady_state":
            start_info = model.steady_state_start(inp, y, names)
        start = dict(model.params)
        problem = FitProblem.for_model(model, inp, y, names, start)
        return cls(model, problem, names, start, start_info)

    def run(self) -> FrictionFit:
        self.free_fit()
        self.identify_lateral()
        self.lateral_stiffness()
        self.identify_mu_x()
        m = self.model
        m.last_solve_ = self.sol
        scored = self.problem.scored
        m.fit_loss_ = mse(self.pred[scored], self.problem.y[scored]) if scored.any() else float("nan")
        m.fit_info_ = self.report()
        return self

    def free_fit(self) -> None:
        """Step 2: every name in ``names`` fitted from the start."""
        self.free = self.final = self.problem.solve(self.start)
        self.model.params = dict(self.free.params)

    def identify_lateral(self) -> None:
        """Step 3: mu_y's identifiability after the free fit; where only mu_y / C is identified, mu_y held
        (``lateral_identifiability``) and the rest refitted from the end point with the same mu_y / C."""
        p = self.problem
        self.lateral = lateral_identifiability(
            self.model, p.inp, self.names, p.ranges, self.free.res, p.scored
        )
        if not self.lateral["mu_y_identified"]:
            fp = self.free.params
            k_y = fp["mu_y"] / fp["C"]
            held = self.lateral["mu_y_held"]
            start = {**fp, "mu_y": held, "C": held / k_y}
            p.hold("mu_y", held, fp)
            self.final = p.solve(start)
            self.model.params = dict(self.final.params)
            self.lateral["robust_cost_free"] = float(self.free.res.cost)
            self.lateral["robust_cost_held"] = float(self.final.res.cost)
            self.lateral["nfev_held"] = int(self.final.res.nfev)

    def lateral_stiffness(self) -> None:
        """Step 4: the identified lateral quantity, k_y = mu_y / C, and its standard error at the final
        fit."""
        if not ("C" in self.names and "mu_y" in self.names):
            return
        fitted = self.final.names
        i_c = fitted.index("C")
        cov = log_covariance(self.final.res)
        var_k = cov[i_c, i_c] if "mu_y" not in fitted else lateral_var_k(cov, fitted)
        k_y = self.model.params["mu_y"] / self.model.params["C"]
        self.lateral["lateral_stiffness"] = k_y
        self.lateral["lateral_stiffness_stderr"] = float(k_y * np.sqrt(var_k)) if var_k >= 0 else None

    def identify_mu_x(self) -> None:
        """Step 5: mu_x matters only where eq. (6) saturates; if nothing saturates, any mu_x above the
        largest lambda |s| fits equally well: keep the start (raised to that bound) and say so. The bound
        is taken over the scored steps that have a root (a no-root step's theta is a least-squares
        minimiser, often at full slip, and says nothing about mu_x). Leaves the fitted prediction."""
        m, inp = self.model, self.problem.inp
        self.pred, self.sol = m.velocities(inp)
        used = (self.sol.status == 1) & self.problem.scored
        self.mu_x_lower_bound = float(m.params["lambda"] * np.abs(self.sol.theta[used, :2]).max(initial=0.0))
        self.mu_x_identified = bool(np.any(self.sol.saturated(inp[0], inp[1], m.params) & used))
        if "mu_x" in self.names and not self.mu_x_identified:
            m.params["mu_x"] = max(float(self.start["mu_x"]), self.mu_x_lower_bound)
            self.pred, self.sol = m.velocities(inp)

    def report(self) -> dict:
        """Step 6: ``fit_info_``."""
        names, final, free, sol, p = self.names, self.final, self.free, self.sol, self.problem
        scored = p.scored
        identified = {n: True for n in names}
        if "mu_x" in names:
            identified["mu_x"] = self.mu_x_identified
        if "mu_y" in names:
            identified["mu_y"] = self.lateral["mu_y_identified"]
        held = [n for n in names if n not in final.names]
        report = bound_report(self.model.params, final.names, p.ranges, final.res, held=held)
        report["param_identified"] = {n: float(v) for n, v in identified.items()}
        if final is not free:
            # the free fit's standard errors, for the record (mu_y's there is along the flat ridge)
            report["param_stderr_free_fit"] = bound_report(free.params, names, p.ranges, free.res)[
                "param_stderr"
            ]
        return {
            "nfev": int(free.res.nfev),
            "optimizer_status": int(final.res.status),
            "optimizer_message": str(final.res.message),
            "moved_from_start": free.moved,
            "loss": p.lsq_options["loss"],
            "f_scale": p.lsq_options["f_scale"],
            "fitted": names,
            "steps": int(len(sol.status)),
            "steps_not_converged": sol.n_not_converged,
            "steps_without_root": int(np.sum(sol.status == 2)),
            "steps_excluded_from_loss": int(np.sum(~scored)),
            "fit_loss_all_steps": mse(self.pred, p.y),
            "mu_x_identified": self.mu_x_identified,
            "mu_x_lower_bound": self.mu_x_lower_bound,
            "lateral": self.lateral,
            "start": self.start_info,
            **report,
        }
