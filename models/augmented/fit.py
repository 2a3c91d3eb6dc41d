"""The augmented fit: a base model plus effects of the catalogue (:mod:`skidbench.models.augmented.effects`)
and
open-ended terms (:mod:`skidbench.models.augmented.terms`) fitted together by alternation on whole sequences.

What discovery (:mod:`skidbench.benchmark.discovery.discover`) searches with and what an augmented model
(:mod:`skidbench.models.augmented.model`) is fitted by: the settings, the pool of sequences, the
:class:`Augmenter` and :func:`fit_effects`.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.optimize import least_squares, minimize_scalar

from skidbench.models.augmented import terms as termlib
from skidbench.models.augmented.effects import (
    CATALOGUE,
    INPUT_BOUNDS,
    SPEED_SCALE,
    apply_effects,
    base_targets,
    command_features,
    input_effect,
    input_response,
    sqrt_radius,
)
from skidbench.models.base import KinematicModel
from skidbench.pipeline.core.errors import SkidbenchError
from skidbench.pipeline.core.protocol import INPUT_COLUMNS
from skidbench.pipeline.core.robot import Robot

log = logging.getLogger("skidbench.discover")

CHANNELS = ("vx", "vy", "wz")
#: the lag's time constant is searched to this relative precision (in log tau)
TAU_XTOL = 0.01


class DiscoverError(SkidbenchError):
    pass


@dataclass(frozen=True)
class DiscoverSettings:
    horizon_s: float = 6.0
    folds: int = 5
    min_units: int = 8  # cut sequences into time blocks when there are fewer sequences than this
    chunk_s: float = 30.0  # longest block when cutting (s); never shorter than one horizon
    alpha: float = 0.05
    penalty_per_param: float = 0.02
    min_gain: float = 0.02
    max_effects: int = 4  # catalogue effects and open-ended terms together
    max_terms: int = 4  # open-ended candidates validated per step (the sparse regression's best)
    open_ended: bool = True  # search the term library (models/augmented/terms.py) next to the catalogue
    channel_tolerance: float = 0.01  # held-out log-MSE loss allowed on a velocity channel the effect changes
    min_share: float = 0.10  # a name cuts the 6 s error that remains by this share of it (one metric) ...
    min_points: float = 0.001  # ... and by this much (RMSRE as a fraction: 0.1 percentage point)
    scale_spread: float = 0.5  # a speed scale's slow and fast halves differ by less than this share of it
    alternations: int = 6  # base/effect refit alternations
    tau_bounds: tuple[float, float] = (0.02, 1.5)
    splits: tuple[str, ...] = ("train",)
    seed: int = 0

    def rule(self) -> str:
        return (
            f"add the best candidate whose held-out {self.horizon_s:g} s gain G = sum over (translational, "
            f"rotational) of log(RMSRE_before^2 / RMSRE_after^2) satisfies G - {self.penalty_per_param:g} * "
            f"n_params >= {self.min_gain:g}, whose per-held-out-unit gains pass the search-wide test (a "
            f"max-statistic sign-flip test over every candidate of the step, catalogue effects and library "
            f"terms together: p_search <= alpha = {self.alpha:g}), whose fitted parameter has one sign in "
            f"every fold, and whose held-out velocity residual (sum over vx, vy, wz of log "
            f"MSE_before/MSE_after) also improves with no changed channel worse by more than "
            f"{self.channel_tolerance:g}; library terms are the forms a majority of the folds' screens "
            f"(each on its training units only) select; a catalogue name wins unless a term is "
            f"significantly better; held out by {self.folds}-fold over whole {'/'.join(self.splits)} "
            f"sequences (contiguous time blocks of {self.horizon_s:g} to {self.chunk_s:g} s when there are "
            f"fewer than {self.min_units}); the test splits are never read; commands aligned with the grid"
        )


# -- data ---------------------------------------------------------------------------------------


@dataclass
class Pool:
    """The training sequences of one terrain, concatenated, with held-out units assigned."""

    table: pd.DataFrame  # split columns + "sequence" (= unit code, contiguous)
    groups: np.ndarray  # (T,) original sequence code (lag filters restart here)
    units: np.ndarray  # (T,) unit code (held-out granularity)
    unit_names: list[str]
    target: np.ndarray  # (T, 3) ground-truth vx, vy, wz
    valid: np.ndarray  # (T,) bool
    pose: np.ndarray  # (T, 3)
    t: np.ndarray  # (T,)
    sequences: list[str]
    note: str = ""
    metas: list[dict] = field(default_factory=list)  # each sequence's split metadata, in ``groups`` order
    alignment: dict[str, float] = field(default_factory=dict)  # sequence -> command shift applied (s)

    @property
    def blocks(self) -> bool:
        """Whether the held-out units are time blocks of sequences (fewer sequences than ``min_units``)."""
        return self.n_units > len(self.sequences)

    def describe(self) -> str:
        """What the units are, in words (what discovery selected on)."""
        seconds = float(sum(self.t[self.groups == g][-1] - self.t[self.groups == g][0]
                            for g in range(len(self.sequences))))  # fmt: skip
        what = f"{len(self.sequences)} sequence{'s' if len(self.sequences) != 1 else ''} ({seconds:.0f} s)"
        if self.blocks:
            return f"{what} cut into {self.n_units} time blocks of {seconds / self.n_units:.1f} s"
        return f"{what}, each a held-out unit"

    @property
    def n_units(self) -> int:
        return len(self.unit_names)


def build_pool(tables: list[tuple[pd.DataFrame, dict]], settings: DiscoverSettings) -> Pool:
    """Concatenate split tables; the held-out units are whole sequences, or, when there are fewer sequences
    than ``min_units``, contiguous time blocks of them: each sequence cut into blocks of equal length, at
    least one horizon long (the horizon windows run across block boundaries: :func:`horizon_metrics` of
    :mod:`skidbench.benchmark.discovery.stats`), about ``total / min_units`` (at most ``chunk_s``) long."""
    tables = [(df, m) for df, m in tables if len(df) > 2]
    if not tables:
        raise DiscoverError("no training sequences with data")
    cut = len(tables) < settings.min_units
    total = sum(float(df["t"].iloc[-1] - df["t"].iloc[0]) for df, _ in tables)
    # blocks long enough for a horizon, short enough to give min_units held-out units
    chunk = max(settings.horizon_s, min(settings.chunk_s, total / max(settings.min_units, 1)))
    frames, groups, units, unit_names, names = [], [], [], [], []
    for g, (df, meta) in enumerate(tables):
        name = str(meta.get("sequence", f"seq{g}"))
        names.append(name)
        df = df.reset_index(drop=True)
        t = df["t"].to_numpy(float)
        n = len(df)
        bounds = [0, n]
        if cut:
            dur = t[-1] - t[0]
            k = max(1, min(int(round(dur / chunk)), int(dur // settings.horizon_s)))
            bounds = [int(round(i * n / k)) for i in range(k + 1)]
        for j, (a, b) in enumerate(itertools.pairwise(bounds)):
            unit_names.append(name if len(bounds) == 2 else f"{name}#{j}")
            units.append(np.full(b - a, len(unit_names) - 1))
        groups.append(np.full(n, g))
        frames.append(df)
    table = pd.concat(frames, ignore_index=True)
    units_a = np.concatenate(units)
    table["sequence"] = units_a
    valid = table["valid"].to_numpy(bool) & np.all(np.isfinite(table[list(CHANNELS)].to_numpy(float)), axis=1)
    return Pool(
        table=table,
        groups=np.concatenate(groups),
        units=units_a,
        unit_names=unit_names,
        target=np.nan_to_num(table[list(CHANNELS)].to_numpy(float)),
        valid=valid,
        pose=table[["x", "y", "yaw"]].to_numpy(float),
        t=table["t"].to_numpy(float),
        sequences=names,
        metas=[dict(m) for _, m in tables],
    )


# -- the augmented model --------------------------------------------------------------------------


ModelFactory = Callable[[], KinematicModel]


@dataclass
class FitState:
    effects: list[str]
    params: dict[str, np.ndarray]
    tau: float | None
    base: KinematicModel
    pred: np.ndarray  # (T, 3) augmented prediction on every row of the pool
    base_pred: np.ndarray  # (T, 3) base prediction (on lagged inputs) on every row
    feats: dict[str, np.ndarray]
    loss: float
    terms: list[termlib.Term] = field(default_factory=list)  # open-ended terms (models/augmented/terms.py)
    term_params: dict[str, dict[str, float]] = field(default_factory=dict)  # key -> theta, c_v, c_w


class Augmenter:
    """Fits base model + effects on a subset of a pool's rows and predicts every row."""

    def __init__(self, pool: Pool, factory: ModelFactory, robot: Robot, settings: DiscoverSettings):
        self.pool = pool
        self.factory = factory
        self.robot = robot
        self.s = settings
        self._lag_cache: dict[float, tuple[pd.DataFrame, dict]] = {}
        self._sub_cache: dict[tuple, pd.DataFrame] = {}
        self._feats0 = command_features(pool.table, robot.wheel_radius, robot.track_width)
        self.weights = np.ones(3)

    def inputs(
        self, tau: float | None, eid: str = "actuator_lag"
    ) -> tuple[pd.DataFrame, dict[str, np.ndarray]]:
        """The pool's inputs through the input transform ``eid`` at ``tau`` (cached), with their features."""
        if tau is None:
            return self.pool.table, self._feats0
        key = (eid, round(float(tau), 6))
        if key not in self._lag_cache:
            if len(self._lag_cache) > 64:
                self._lag_cache.clear()
            tab = input_response(eid, self.pool.table, key[1], self.pool.groups)
            self._lag_cache[key] = (
                tab,
                command_features(tab, self.robot.wheel_radius, self.robot.track_width),
            )
        return self._lag_cache[key]

    def _fit_base(
        self, table: pd.DataFrame, rows: np.ndarray, target: np.ndarray | None, key: tuple
    ) -> KinematicModel:
        if key not in self._sub_cache:
            if len(self._sub_cache) > 64:
                self._sub_cache.clear()
            cols = [c for c in table.columns if c not in ("x", "y", "yaw", "stamp_ns")]
            self._sub_cache[key] = table.loc[rows, cols]
        sub = self._sub_cache[key]
        if target is not None:
            sub = sub.copy()
            for j, c in enumerate(CHANNELS):
                sub[c] = target[rows, j]
        return self.factory().fit(sub)

    def _loss(self, pred: np.ndarray, rows: np.ndarray) -> float:
        r = (pred[rows] - self.pool.target[rows]) ** 2
        return float(np.sum(r.mean(axis=0) * self.weights))

    def fit(
        self,
        effects: list[str],
        train_units: np.ndarray,
        warm: dict[str, np.ndarray] | None = None,
        fixed_tau: bool = False,
        terms: tuple[termlib.Term, ...] | list[termlib.Term] = (),
        rows: np.ndarray | None = None,
    ) -> FitState:
        """The model fitted on the valid rows of ``train_units`` (or on ``rows``, a (T,) mask: a held-out
        fold's training rows less the buffer around its blocks) and predicted on every row."""
        if rows is None:
            rows = np.isin(self.pool.units, train_units) & self.pool.valid
        terms = list(terms)
        inp = input_effect(effects)
        if inp is not None:
            if fixed_tau and warm and inp in warm:  # scoring another candidate: keep tau
                return self._fit_at(effects, rows, float(warm[inp][0]), warm, quick=False, terms=terms)
            # a fixed log grid (lag-filtered inputs are cached and shared by folds and candidates), then
            # Brent's bounded search between the best grid point's neighbours (in log tau): the loss is far
            # from a parabola over the grid's spacing (x1.6), and a parabola through three grid points put
            # an 80 ms lag at 74 ms, a misfit a second effect then took (an acceleration slip after the lag)
            lo, hi = INPUT_BOUNDS[inp] or self.s.tau_bounds
            grid = np.exp(np.linspace(math.log(lo), math.log(hi), 10))
            losses = np.array(
                [self._fit_at(effects, rows, g, warm, quick=True, terms=terms).loss for g in grid]
            )
            i = int(np.clip(np.argmin(losses), 1, len(grid) - 2))
            res = minimize_scalar(
                lambda x: self._fit_at(effects, rows, float(np.exp(x)), warm, quick=True, terms=terms).loss,
                bounds=(math.log(grid[i - 1]), math.log(grid[i + 1])),
                method="bounded",
                options={"xatol": TAU_XTOL},
            )
            best = float(np.exp(res.x)) if res.fun <= losses.min() else float(grid[int(np.argmin(losses))])
            return self._fit_at(effects, rows, best, warm, quick=False, terms=terms)
        return self._fit_at(effects, rows, None, warm, quick=False, terms=terms)

    def _fit_at(
        self,
        effects: list[str],
        rows: np.ndarray,
        tau: float | None,
        warm: dict[str, np.ndarray] | None,
        quick: bool,
        terms: list[termlib.Term] | None = None,
    ) -> FitState:
        terms = list(terms or [])
        inp = input_effect(effects)
        table, feats = self.inputs(tau, inp or "actuator_lag")
        key = (inp, None if tau is None else round(float(tau), 6), rows.tobytes().__hash__())
        corr = [e for e in effects if CATALOGUE[e].kind != "input"]
        base = self._fit_base(table, rows, None, key)
        base_pred = base.predict(table[list(INPUT_COLUMNS)])  # a model sees only its inputs
        params = {e: np.array((warm or {}).get(e, CATALOGUE[e].init), dtype=float) for e in corr}
        theta = np.zeros(len(terms))
        n_alt = (2 if quick else self.s.alternations) if (corr or terms) else 0
        prev = np.inf
        for _ in range(n_alt):
            if corr:
                params = self._fit_params(
                    corr,
                    params,
                    base_pred,
                    feats,
                    rows,
                    self._term_sum(terms, theta, feats, base_pred),
                    base_gain=True,
                )
            theta = self._fit_terms(terms, params, base_pred, feats, rows)
            shift = self._term_sum(terms, theta, feats, base_pred)
            bt = base_targets(self.pool.target - shift, base_pred, feats, params)
            if terms:  # beyond a limit / inside a dead zone the base model keeps its own output
                sig = self.signals(feats, base_pred)
                for t in terms:
                    m = t.passive(sig)
                    for c in t.touched:
                        bt[m, c] = base_pred[m, c]
            base = self._fit_base(table, rows, bt, key)
            base_pred = base.predict(table[list(INPUT_COLUMNS)])  # a model sees only its inputs
            loss = self._loss(
                apply_effects(base_pred, feats, params) + self._term_sum(terms, theta, feats, base_pred), rows
            )
            if prev - loss < 1e-6 * max(prev, 1e-12):
                break
            prev = loss
        if corr:
            params = self._fit_params(
                corr, params, base_pred, feats, rows, self._term_sum(terms, theta, feats, base_pred)
            )
        theta = self._fit_terms(terms, params, base_pred, feats, rows)
        pred = apply_effects(base_pred, feats, params) + self._term_sum(terms, theta, feats, base_pred)
        all_params = dict(params)
        if tau is not None:
            all_params = {inp or "actuator_lag": np.array([tau]), **all_params}
        gains = self._gains(feats, base_pred)
        tp = {
            t.key: {"theta": float(th), "c_v": gains[0], "c_w": gains[1]}
            for t, th in zip(terms, theta, strict=True)
        }
        return FitState(
            effects, all_params, tau, base, pred, base_pred, feats, self._loss(pred, rows), terms, tp
        )

    def signals(self, feats: dict[str, np.ndarray], base_pred: np.ndarray) -> dict[str, np.ndarray]:
        return termlib.signals(feats, base_pred, self.pool.t, self.robot.track_width)

    def _gains(self, feats, base_pred) -> tuple[float, float]:
        # the base model's gains on every valid row (the same for every fold: a property of the base
        # model's form, not of the held-out rows' targets)
        return termlib.base_gains(self.signals(feats, base_pred), self.pool.valid)

    def _term_sum(self, terms, theta, feats, base_pred) -> np.ndarray:
        out = np.zeros_like(base_pred, dtype=float)
        if not terms:
            return out
        sig = self.signals(feats, base_pred)
        gains = self._gains(feats, base_pred)
        for t, th in zip(terms, theta, strict=True):
            out += t.correction(sig, gains, self.robot.track_width, th)
        return out

    def _fit_terms(self, terms, params, base_pred, feats, rows) -> np.ndarray:
        """The terms' coefficients: weighted least squares on what the base model and the effects leave."""
        if not terms:
            return np.zeros(0)
        sig = self.signals(feats, base_pred)
        gains = self._gains(feats, base_pred)
        designs = [t.design(sig, gains, self.robot.track_width) for t in terms]
        resid = self.pool.target - apply_effects(base_pred, feats, params)
        return termlib.fit_thetas(terms, designs, resid, rows, self.weights)

    def _fit_params(
        self, corr, params, base_pred, feats, rows, offset=None, base_gain: bool = False
    ) -> dict[str, np.ndarray]:
        """Effect parameters with the base prediction fixed: box-bounded weighted least squares
        (:func:`_bounded_least_squares`); the curvature law, the one clearly nonlinear effect, from a few
        starting values of b2.

        ``base_gain`` (inside the alternation): a multiplicative yaw-rate effect is fitted together with a
        free gain on the base model's yaw rate, which is then dropped (the base model's refit on the
        effect-corrected targets takes it: for ``edd`` its chi). The effect's factor and the base model's
        own yaw-rate gain trade off (chi_base and ``curvature_dependent_icr``'s b1 both scale the yaw rate
        of a turn); with the base held at its fit without the effect, a chi that has absorbed the effect's
        mean, alternation stalls far from the joint optimum (b1 = 0.58, b2 = 17, chi 1.30 on data made
        with b1 = 0.6, b2 = 1, chi 1: a chi that only spins see, and a residual in wz proportional to
        |v| sign(w) that the term library then names)."""
        sizes = [CATALOGUE[e].n_params for e in corr]
        x0 = np.concatenate([params[e] for e in corr]).astype(float)
        bp = base_pred[rows]
        # (the speed scale's yaw part, too, trades off with the base model's own yaw-rate gain)
        gain = base_gain and any(CATALOGUE[e].kind == "mult" or e == SPEED_SCALE for e in corr)
        fr = {k: v[rows] for k, v in feats.items()}
        fr["sqrt_R"] = sqrt_radius(fr["R"])  # computed once, not at every residual evaluation
        chans = sorted({c for e in corr for c in CATALOGUE[e].channels})  # what the parameters change
        tg = self.pool.target[rows][:, chans]
        if offset is not None:  # the open-ended terms' correction, held fixed while the effects are fitted
            tg = tg - offset[rows][:, chans]
        sw = np.sqrt(self.weights[chans] / max(rows.sum(), 1))

        def unpack(x):
            out, i = {}, 0
            for e, n in zip(corr, sizes, strict=True):
                out[e] = x[i : i + n]
                i += n
            return out

        def resid(x):
            b = bp
            if gain:  # the base model's yaw rate times the free gain x[-1]
                b = bp.copy()
                b[:, 2] *= x[-1]
            return ((apply_effects(b, fr, unpack(x))[:, chans] - tg) * sw).ravel()

        lo = np.concatenate([[b[0] for b in CATALOGUE[e].bounds] for e in corr])
        hi = np.concatenate([[b[1] for b in CATALOGUE[e].bounds] for e in corr])
        if gain:
            x0, lo, hi = np.append(x0, 1.0), np.append(lo, 0.2), np.append(hi, 5.0)
        starts = [x0]
        cold = "curvature_dependent_icr" in corr and np.allclose(
            params["curvature_dependent_icr"], CATALOGUE["curvature_dependent_icr"].init
        )
        if cold:  # a few starting values for b2 (a warm start is already near its optimum)
            i = sum(sizes[: corr.index("curvature_dependent_icr")])
            for b2 in (0.3, 1.0, 4.0):
                xs = x0.copy()
                xs[i + 1] = b2
                starts.append(xs)
        best, best_cost = x0, np.inf
        for xs in starts:
            x = _bounded_least_squares(resid, xs, lo, hi, 60 if "curvature_dependent_icr" in corr else 20)
            c = float(np.sum(resid(x) ** 2))
            if c < best_cost:
                best, best_cost = x, c
        return unpack(best)


def _bounded_least_squares(resid, x, lo, hi, max_nfev: int) -> np.ndarray:
    """``scipy.optimize.least_squares`` with box bounds: ``dogbox``, because an effect's parameters start
    at their no-effect value, often a bound, where ``trf``'s scaling shrinks the first steps to nothing
    (it stopped at 2e-10 from the start on mini). The effects have one or two parameters each and are
    (nearly) linear in them: a few steps suffice."""
    lo = np.asarray(lo, float)
    hi = np.maximum(np.asarray(hi, float), lo + 1e-12)  # least_squares needs lo < hi
    # a relative finite-difference step of 1e-4: the effects' features are smoothed derivatives, and the
    # default (1.5e-8) sees only their round-off
    res = least_squares(
        resid, np.clip(x, lo, hi), bounds=(lo, hi), method="dogbox", diff_step=1e-4, max_nfev=max_nfev
    )
    log.debug("effect fit: %s (nfev %d)", res.message, res.nfev)
    return res.x


def channel_weights(pool: Pool, state: FitState) -> np.ndarray:
    """(3,) the fit's channel weights: the inverse mean squared residual of ``state`` per velocity channel
    on the valid rows (1/(m/s)^2, 1/(rad/s)^2)."""
    res = (state.pred - pool.target)[pool.valid]
    return 1.0 / np.maximum(res.var(axis=0) + (res.mean(axis=0) ** 2), 1e-12)


def fit_effects(
    table: pd.DataFrame,
    factory: ModelFactory,
    robot: Robot,
    effects: list[str],
    settings: DiscoverSettings | None = None,
    terms: list[termlib.Term] | tuple[termlib.Term, ...] = (),
) -> FitState:
    """Fit base model + ``effects`` (+ open-ended ``terms``, last) on every valid row of a training table
    (sequences in its ``sequence`` column), the way discovery fits its final model: the base alone first
    (which sets the channel weights), then the effects added one at a time in the given order, each fit
    warm-started from the last, then (as discovery after each step) the channel weights re-estimated from
    the augmented model's residual and the whole refitted once under them. What an augmented model
    (``skidbench.models.augmented.model``) calls on Train."""
    unknown = [e for e in effects if e not in CATALOGUE]
    if unknown:
        raise DiscoverError(f"unknown effect(s) {unknown} (catalogue: {list(CATALOGUE)})")
    s = settings or DiscoverSettings()
    if "sequence" in table.columns:
        tables = [
            (g.drop(columns="sequence").reset_index(drop=True), {"sequence": str(name)})
            for name, g in table.groupby("sequence", sort=False)
        ]
    else:
        tables = [(table.reset_index(drop=True), {"sequence": "0"})]
    pool = build_pool(tables, dataclasses.replace(s, min_units=1))  # whole sequences, never cut
    aug = Augmenter(pool, factory, robot, s)
    units = np.arange(pool.n_units)
    state = aug.fit([], units)
    aug.weights = channel_weights(pool, state)
    warm: dict[str, np.ndarray] = {}
    for i in range(len(effects)):
        state = aug.fit(list(effects[: i + 1]), units, warm)
        warm = dict(state.params)
    if terms:
        state = aug.fit(list(effects), units, warm, terms=list(terms))
    if effects or terms:  # as discovery: the weights re-estimated from the augmented model's residual
        weights = channel_weights(pool, state)
        if not np.allclose(weights, aug.weights, rtol=0.05):
            aug.weights = weights
            state = aug.fit(list(effects), units, dict(state.params), terms=list(terms))
    return state


def jsonable_params(params: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """Effect parameters as JSON: effect id -> {parameter name: value}."""
    return {e: dict(zip(CATALOGUE[e].param_names, map(float, p), strict=True)) for e, p in params.items()}
