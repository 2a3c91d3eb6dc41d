"""Friction-based kinematic model (the paper's section III, eqs. 5-12).

Per time step, theta = (s_l, s_r, x_ICR) solves the force/torque balance F(theta) = 0 (eqs. 9-11) built from
the commanded wheel rates and their derivatives; eq. (8) then gives (vx, vy, wz). The inner solve is
batched over all steps (``friction_solver.solve``). The five parameters {mu_r, mu_x, mu_y, lambda, C} are
fitted by nonlinear least squares (scipy ``least_squares``, in log space so they stay positive) on the
velocity prediction error, each evaluation warm-started from the previous evaluation's slips; the fit's
steps are ``friction_fit``'s. The fit's Jacobian is analytic: the solved slips' derivative with respect to
the parameters by the implicit function theorem at the converged balance (``velocity_sensitivity``), one
3x3 solve per step instead of five more solves of every step for finite differences.

Identifiability (what the data can and cannot pin down):
- mu_x only matters where a tractive force saturates (lambda |s| >= mu_x in eq. 6); on data where the min()
  never saturates it has no effect and is not identifiable (kept at its initial value).
- C and mu_y enter eq. (7) as mu_y (1 - exp(-|alpha|/C)): an initial lateral stiffness k_y = mu_y / C and a
  saturation level mu_y. Where the data's lateral resistance grows in proportion to the slip angle over all
  the slip angles they reach, only k_y is identifiable: the fit runs along mu_y / C towards the linear law
  until a bound stops it. Then mu_y is held (not identified, bounded below; ``lateral_identifiability``)
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

from skidbench.models.base import KinematicModel, ModelError
from skidbench.models.columns import col
from skidbench.models.friction.balance import FrictionGeometry, body_velocity, free_mask
from skidbench.models.friction.fit import PARAM_RANGES, START_MARGIN, FrictionFit
from skidbench.models.friction.solver import SolveResult, solve

log = logging.getLogger(__name__)

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


class FrictionBased(KinematicModel):
    name = "friction"
    version = "1.9"  # the versions and what changed: CHANGELOG.md
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
        ``cmd_dwl``, ``cmd_dwr``, i.e. the inputs of the run's protocol (pipeline/core/protocol.py)."""
        return tuple(col(table, c) for c in ("cmd_wl", "cmd_wr", "cmd_dwl", "cmd_dwr"))

    def velocities(
        self, inputs, params=None, theta0=None, fallback_below: float | None = None
    ) -> tuple[np.ndarray, SolveResult]:
        """(T, 3) body velocities and the per-step solve (eq. 12 then eq. 8).

        A step whose solve is not physical (no root, not converged, or a slip ratio outside [-1, 1], i.e.
        a wheel's ground speed outside 0..2 r omega; these are steps that command an acceleration
        friction cannot deliver, such as a step change of the command) is solved again with its
        commanded accelerations scaled by ``ACCEL_SCALES`` in turn, and predicted from the first
        physical solution: the motion at the largest tried fraction of the commanded acceleration
        that the forces can balance (``sol.accel_scale``; 0 is the steady state). Without it such a
        step predicted body speeds of hundreds of m/s on DRIVE's command steps. ``sol.status`` stays
        the status of the commanded problem. ``options.accel_fallback=false`` turns it off;
        ``fallback_below`` (a fraction) skips it where more than that fraction of the steps has no root
        (``FitProblem.evaluate``: a trial point far from any fit).
        """
        p = self.params if params is None else params
        geo = self.geometry
        sol = solve(*inputs, p, geo, theta0=theta0)
        wl, wr, dwl, dwr = (np.asarray(a, dtype=float).ravel() for a in inputs)
        scale = np.ones(wl.size)
        bad = ~self._physical(sol.theta, sol.status, wl, wr)
        fallback = self.options.get("accel_fallback", True)
        if fallback_below is not None and np.mean(sol.status != 1) > fallback_below:
            fallback = False
        if bad.any() and fallback:
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
        """Fit the parameters on the table's valid rows: the steps of ``friction_fit.FrictionFit`` (the
        start, the free fit, mu_y's and mu_x's identifiability, the report in ``fit_info_``)."""
        fit = FrictionFit.prepare(self, table).run()
        if not fit.free.moved:
            log.warning(
                "model %s: the fit did not move from its start (%s)", self.name, fit.final.res.message
            )
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
                m = START_MARGIN * np.log(hi / lo)
                self.params[n] = float(np.exp(np.clip(np.log(v), np.log(lo) + m, np.log(hi) - m)))
        info.update(source="steady_state", **{n: self.params[n] for n in start})
        return info

    def predict(self, table: pd.DataFrame) -> np.ndarray:
        self.check_columns(table)
        pred, sol = self.velocities(self.inputs(table))
        self.last_solve_ = sol
        return pred
