"""Discrepancy discovery: find where a model and the measured data disagree and name the missing
physical effect (SPEC.md "Discrepancy discovery").

Workflow, per terrain, on the Train split:

1. Fit the base model (default: extended differential drive, ``edd``) and take its residuals: body
   velocities (vx, vy, wz) against ground truth, and 6 s horizon pose errors (RMSRE).
2. For every effect of the catalogue (:mod:`skidbench.benchmark.effects`) not yet in the model, fit the
   augmented model (base model refitted together with the effect's parameters, by alternation) on the
   training folds and predict the held-out fold. Folds are whole sequences (k-fold over sequences;
   long sequences are cut into contiguous chunks when there are too few of them), never random rows.
3. Score each candidate against the current model on the held-out predictions.
4. Add the best candidate that passes the significance rule, refit, and repeat; stop when none passes
   ("no missing effect found").

Significance rule (every part must hold; the constants are ``discover.*`` settings):

* the held-out 6 s horizon gain ``G = sum_m log(RMSRE_m,before^2 / RMSRE_m,after^2)`` over the metrics
  m in (translational, rotational) (the Gaussian log-likelihood gain of the benchmark's own pose errors)
  pays for the effect's parameters: ``G - penalty_per_param * n_params >= min_gain`` (defaults 0.02
  and 0.02: an information-criterion-like charge, AIC's 2/n_eff for ~100 independent windows, so a
  one-parameter effect must cut one held-out RMSRE by at least 2 %, or both by 1 %);
* a paired one-sided sign-flip (permutation) test over the held-out units (whole sequences, or
  contiguous chunks) of the per-unit gains ``d_s`` (the same log ratio, per unit) rejects "no
  improvement" at ``alpha`` (default 0.05; exact for up to 16 units);
* the held-out velocity residuals agree: ``sum_c log(MSE_c,before / MSE_c,after)`` over (vx, vy, wz)
  is positive, and no channel the effect changes gets worse by more than ``channel_tolerance`` (0.01)
  (an effect that fixes poses while making a velocity worse is compensating for another, not real).

Effects keep their physical direction (parameter bounds in the catalogue: slips are shortfalls, the
side slip is outward, chi grows in tight turns, the turn deficit grows with speed).

The held-out prediction of each unit comes from the model fitted without it (k-fold over sequences,
never random rows). Velocity-based fitting, pose-based scoring: the 6 s windows integrate the velocity
noise of differentiated visual-odometry poses away, and are what the benchmark ranks models by.
Among the candidates that pass, the one with the largest penalised gain is added.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy.optimize import least_squares, minimize_scalar

from skidbench.benchmark import terms as termlib
from skidbench.benchmark.effects import (
    CATALOGUE,
    EFFECT_IDS,
    apply_effects,
    base_targets,
    command_features,
    lag_filter,
    revealing_feature,
)
from skidbench.benchmark.horizon import rmsre, window_errors
from skidbench.models.base import KinematicModel
from skidbench.pipeline.errors import SkidbenchError
from skidbench.pipeline.protocol import INPUT_COLUMNS, fit_table
from skidbench.pipeline.robot import Robot
from skidbench.pipeline.schema import load_split_tables as _load_split_tables
from skidbench.pipeline.schema import read_split

log = logging.getLogger("skidbench.discover")

CHANNELS = ("vx", "vy", "wz")
NO_EFFECT_MESSAGE = "no missing effect found"


class DiscoverError(SkidbenchError):
    pass


@dataclass(frozen=True)
class DiscoverSettings:
    horizon_s: float = 6.0
    folds: int = 5
    min_units: int = 8  # cut sequences into chunks when there are fewer sequences than this
    chunk_s: float = 30.0  # chunk length when cutting (s); never shorter than 2 horizons
    alpha: float = 0.05
    penalty_per_param: float = 0.02
    min_gain: float = 0.02
    max_effects: int = 4  # catalogue effects and open-ended terms together
    max_terms: int = 4  # open-ended candidates validated per step (the sparse regression's best)
    open_ended: bool = True  # search the term library (benchmark/terms.py) next to the catalogue
    channel_tolerance: float = 0.01  # held-out log-MSE loss allowed on a velocity channel the effect changes
    alternations: int = 6  # base/effect refit alternations
    tau_bounds: tuple[float, float] = (0.02, 1.5)
    splits: tuple[str, ...] = ("train",)
    seed: int = 0

    def rule(self) -> str:
        return (
            f"add the best effect whose held-out {self.horizon_s:g} s gain G = sum over (translational, "
            f"rotational) of log(RMSRE_before^2 / RMSRE_after^2) satisfies G - {self.penalty_per_param:g} * "
            f"n_params >= {self.min_gain:g}, whose per-held-out-unit gains pass a one-sided paired sign-flip "
            f"test at alpha = {self.alpha:g}, and whose held-out velocity residual (sum over vx, vy, wz of "
            f"log MSE_before/MSE_after) also improves with no changed channel worse by more than "
            f"{self.channel_tolerance:g}; held out by {self.folds}-fold over whole sequences "
            f"(contiguous chunks of >= {self.chunk_s:g} s when there are fewer than {self.min_units} "
            "sequences)"
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

    @property
    def n_units(self) -> int:
        return len(self.unit_names)


def build_pool(tables: list[tuple[pd.DataFrame, dict]], settings: DiscoverSettings) -> Pool:
    """Concatenate split tables; cut them into contiguous chunks if there are too few sequences."""
    tables = [(df, m) for df, m in tables if len(df) > 2]
    if not tables:
        raise DiscoverError("no training sequences with data")
    cut = len(tables) < settings.min_units
    total = sum(float(df["t"].iloc[-1] - df["t"].iloc[0]) for df, _ in tables)
    # chunks long enough for several 6 s windows, short enough to give min_units held-out units
    chunk = max(2.0 * settings.horizon_s + 1.0, min(settings.chunk_s, total / max(settings.min_units, 1)))
    frames, groups, units, unit_names, names = [], [], [], [], []
    for g, (df, meta) in enumerate(tables):
        name = str(meta.get("sequence", f"seq{g}"))
        names.append(name)
        df = df.reset_index(drop=True)
        t = df["t"].to_numpy(float)
        n = len(df)
        bounds = [0, n]
        if cut:
            k = max(1, int((t[-1] - t[0]) // chunk))
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
    )


def load_pool(
    splits_root: Path,
    terrain: str,
    settings: DiscoverSettings,
    files_of: Callable[[str, str], list[Path]] | None = None,
) -> Pool:
    """The held-out pool of a terrain: the ``settings.splits`` sequences (default Train). When they give
    fewer than ``min_units`` held-out units (a significance test over fewer units cannot reject at
    alpha), the terrain's other splits (CV, LD) are added, and ``pool.note`` says so. ``files_of(terrain,
    split)``: the split files to read (the current manifest's); default every file under ``splits_root``."""

    def load_split_tables(root: Path, terrain: str, split: str) -> list[tuple[pd.DataFrame, dict]]:
        if files_of is None:
            return _load_split_tables(root, terrain, split)
        return [read_split(p) for p in files_of(terrain, split)]

    tables = []
    for s in settings.splits:
        tables += load_split_tables(Path(splits_root), terrain, s)
    if not tables:
        raise DiscoverError(f"{splits_root}/{terrain}: no split files for {'/'.join(settings.splits)}")
    pool = build_pool(tables, settings)
    extra = [s for s in ("train", "cv", "ld") if s not in settings.splits]
    if pool.n_units < settings.min_units and extra:
        more = [t for s in extra for t in load_split_tables(Path(splits_root), terrain, s)]
        if more:
            pool = build_pool(tables + more, settings)
            pool.note = (
                f"{'/'.join(settings.splits)} gave fewer than {settings.min_units} held-out units; "
                f"{'/'.join(extra)} sequences added to the pool"
            )
    return pool


def apply_protocol(pool: Pool, protocol: str, robot: Robot, response: Any = None) -> Pool:
    """The pool with its inputs replaced by those of the input protocol (pipeline/protocol.py), computed
    per original sequence (``pool.groups``), targets and held-out units kept: discovery then searches
    what the base model misses given the protocol's inputs (under ``response`` the wheel response is
    given, so ``actuator_lag`` has nothing left to explain)."""
    table = fit_table(pool.table.assign(sequence=pool.groups), protocol, robot, response)
    table["sequence"] = pool.units
    return dataclasses.replace(pool, table=table)


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
    terms: list[termlib.Term] = field(default_factory=list)  # open-ended terms (benchmark/terms.py)
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

    def inputs(self, tau: float | None) -> tuple[pd.DataFrame, dict[str, np.ndarray]]:
        if tau is None:
            return self.pool.table, self._feats0
        key = round(float(tau), 6)
        if key not in self._lag_cache:
            if len(self._lag_cache) > 64:
                self._lag_cache.clear()
            tab = lag_filter(self.pool.table, key, self.pool.groups)
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
    ) -> FitState:
        rows = np.isin(self.pool.units, train_units) & self.pool.valid
        terms = list(terms)
        if "actuator_lag" in effects:
            if fixed_tau and warm and "actuator_lag" in warm:  # scoring another candidate: keep tau
                return self._fit_at(
                    effects, rows, float(warm["actuator_lag"][0]), warm, quick=False, terms=terms
                )
            # a fixed log grid (lag-filtered inputs are cached and shared by folds and candidates), then
            # a parabola through the best grid point and its neighbours (in log tau)
            lo, hi = self.s.tau_bounds
            grid = np.exp(np.linspace(math.log(lo), math.log(hi), 10))
            losses = np.array(
                [self._fit_at(effects, rows, g, warm, quick=True, terms=terms).loss for g in grid]
            )
            i = int(np.clip(np.argmin(losses), 1, len(grid) - 2))
            x = np.log(grid[i - 1 : i + 2])
            y = losses[i - 1 : i + 2]
            den = (x[0] - x[1]) * (x[0] - x[2]) * (x[1] - x[2])
            A = (x[2] * (y[1] - y[0]) + x[1] * (y[0] - y[2]) + x[0] * (y[2] - y[1])) / den
            B = (x[2] ** 2 * (y[0] - y[1]) + x[1] ** 2 * (y[2] - y[0]) + x[0] ** 2 * (y[1] - y[2])) / den
            best = float(grid[int(np.argmin(losses))])
            if A > 0:
                best = float(np.exp(np.clip(-B / (2 * A), x[0], x[2])))
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
        table, feats = self.inputs(tau)
        key = (None if tau is None else round(float(tau), 6), rows.tobytes().__hash__())
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
                    corr, params, base_pred, feats, rows, self._term_sum(terms, theta, feats, base_pred)
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
            all_params = {"actuator_lag": np.array([tau]), **all_params}
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
            out += th * t.columns(sig, gains, self.robot.track_width)
        return out

    def _fit_terms(self, terms, params, base_pred, feats, rows) -> np.ndarray:
        """The terms' coefficients: weighted least squares on what the base model and the effects leave."""
        if not terms:
            return np.zeros(0)
        sig = self.signals(feats, base_pred)
        gains = self._gains(feats, base_pred)
        cols = [t.columns(sig, gains, self.robot.track_width) for t in terms]
        resid = self.pool.target - apply_effects(base_pred, feats, params)
        return termlib.fit_thetas(terms, cols, resid, rows, self.weights)

    def _fit_params(self, corr, params, base_pred, feats, rows, offset=None) -> dict[str, np.ndarray]:
        """Effect parameters with the base prediction fixed: box-bounded weighted least squares
        (:func:`_bounded_least_squares`); the curvature law, the one clearly nonlinear effect, from a few
        starting values of b2."""
        sizes = [CATALOGUE[e].n_params for e in corr]
        x0 = np.concatenate([params[e] for e in corr]).astype(float)
        bp = base_pred[rows]
        fr = {k: v[rows] for k, v in feats.items()}
        chans = sorted({CATALOGUE[e].channel for e in corr})  # only these depend on the parameters
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
            return ((apply_effects(bp, fr, unpack(x))[:, chans] - tg) * sw).ravel()

        lo = np.concatenate([[b[0] for b in CATALOGUE[e].bounds] for e in corr])
        hi = np.concatenate([[b[1] for b in CATALOGUE[e].bounds] for e in corr])
        starts = [x0]
        if "curvature_dependent_icr" in corr:  # a few starting values for b2
            i = sum(sizes[: corr.index("curvature_dependent_icr")])
            for b2 in (0.3, 1.0, 4.0):
                xs = x0.copy()
                xs[i + 1] = b2
                starts.append(xs)
        best, best_cost = x0, np.inf
        for xs in starts:
            x = _bounded_least_squares(resid, xs, lo, hi, 60 if len(starts) > 1 else 20)
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
    warm-started from the last. What an augmented model (``skidbench.models.augmented``) calls on Train."""
    unknown = [e for e in effects if e not in CATALOGUE]
    if unknown:
        raise DiscoverError(f"unknown effect(s) {unknown} (catalogue: {list(EFFECT_IDS)})")
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
    res = (state.pred - pool.target)[pool.valid]
    aug.weights = 1.0 / np.maximum(res.var(axis=0) + (res.mean(axis=0) ** 2), 1e-12)
    warm: dict[str, np.ndarray] = {}
    for i in range(len(effects)):
        state = aug.fit(list(effects[: i + 1]), units, warm)
        warm = dict(state.params)
    if terms:
        state = aug.fit(list(effects), units, warm, terms=list(terms))
    return state


# -- held-out evaluation ------------------------------------------------------------------------


@dataclass
class HeldOut:
    effects: list[str]
    pred: np.ndarray  # (T, 3) held-out prediction of every row
    mse: np.ndarray  # (3,) pooled held-out MSE per channel
    unit_mse: np.ndarray  # (U, 3)
    rmsre: dict[str, float]
    windows: pd.DataFrame
    fold_params: list[dict[str, list[float]]] = field(default_factory=list)


def folds_of(pool: Pool, k: int) -> list[np.ndarray]:
    k = max(2, min(k, pool.n_units))
    ids = np.arange(pool.n_units)
    return [ids[ids % k == j] for j in range(k)]


def horizon_metrics(pool: Pool, pred: np.ndarray, horizon_s: float) -> tuple[dict[str, float], pd.DataFrame]:
    frames = []
    for u in range(pool.n_units):
        m = pool.units == u
        w = window_errors(pool.t[m], pool.pose[m], pred[m], horizon_s, valid=pool.valid[m])
        w["unit"] = u
        frames.append(w)
    win = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    if win.empty:
        return {"translational": float("nan"), "rotational": float("nan")}, win
    return {"translational": rmsre(win["rel_trans"]), "rotational": rmsre(win["rel_rot"])}, win


def cross_validate(
    aug: Augmenter, effects: list[str], warm: dict | None = None, terms: list[termlib.Term] | None = None
) -> HeldOut:
    """Held-out predictions by k-fold over units. The lag time constant of a model that already has
    ``actuator_lag`` stays at its fitted value while other candidates are scored (it is re-searched
    when the model is refitted after an effect is added)."""
    pool = aug.pool
    pred = np.zeros_like(pool.target)
    fold_params = []
    for held in folds_of(pool, aug.s.folds):
        train = np.setdiff1d(np.arange(pool.n_units), held)
        st = aug.fit(effects, train, warm, fixed_tau=True, terms=terms or [])
        rows = np.isin(pool.units, held)
        pred[rows] = st.pred[rows]
        fold_params.append(
            {
                **{e: [float(v) for v in p] for e, p in st.params.items()},
                **{k: [v["theta"]] for k, v in st.term_params.items()},
            }
        )
    err2 = (pred - pool.target) ** 2
    v = pool.valid
    mse = err2[v].mean(axis=0)
    unit_mse = np.array(
        [
            err2[v & (pool.units == u)].mean(axis=0) if np.any(v & (pool.units == u)) else [np.nan] * 3
            for u in range(pool.n_units)
        ]
    )
    rm, win = horizon_metrics(pool, pred, aug.s.horizon_s)
    return HeldOut(list(effects), pred, mse, unit_mse, rm, win, fold_params)


def sign_flip_pvalue(d: np.ndarray, seed: int = 0, n_random: int = 20000) -> float:
    """One-sided p-value of mean(d) > 0 under random sign flips (exact for up to 16 units)."""
    d = np.asarray(d, dtype=float)
    d = d[np.isfinite(d)]
    n = len(d)
    if n == 0:
        return 1.0
    obs = d.mean()
    if n <= 16:
        signs = np.array(list(itertools.product((-1.0, 1.0), repeat=n)))
    else:
        signs = np.random.default_rng(seed).choice((-1.0, 1.0), size=(n_random, n))
    null = (signs * d).mean(axis=1)
    return float(np.mean(null >= obs - 1e-15))


def unit_rmsre(ho: HeldOut, n_units: int) -> np.ndarray:
    """(U, 2) held-out translational and rotational RMSRE of every unit."""
    out = np.full((n_units, 2), np.nan)
    if ho.windows.empty:
        return out
    for u, w in ho.windows.groupby("unit"):
        out[int(u)] = [rmsre(w["rel_trans"]), rmsre(w["rel_rot"])]
    return out


def _log_ratio2(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        g = 2.0 * np.log(np.asarray(before, float) / np.asarray(after, float))
    return np.where(np.isfinite(g), g, np.nan)


def _channels_of(eid: str) -> tuple[str, ...]:
    ch = CATALOGUE[eid].channel
    return CHANNELS if ch < 0 else (CHANNELS[ch],)


def compare(
    before: HeldOut,
    after: HeldOut,
    n_params: int,
    s: DiscoverSettings,
    touched_channels: tuple[int, ...] | None = None,
) -> dict[str, Any]:
    """The evidence for one candidate: held-out gains and the significance rule's verdict
    (``touched_channels``: the velocity channels the candidate changes; default: its effect's)."""
    keys = ("translational", "rotational")
    pose_gain = _log_ratio2([before.rmsre[k] for k in keys], [after.rmsre[k] for k in keys])
    G = float(np.nansum(pose_gain))
    n_units = len(before.unit_mse)
    d = np.nansum(_log_ratio2(unit_rmsre(before, n_units), unit_rmsre(after, n_units)), axis=1)
    p = sign_flip_pvalue(d, s.seed)
    eps = 1e-18
    vel_gain = np.log((before.mse + eps) / (after.mse + eps))
    Gv = float(np.sum(vel_gain))
    penalised = G - s.penalty_per_param * n_params
    if touched_channels is not None:
        touched = list(touched_channels)
    else:
        touched = [CHANNELS.index(c) for c in _channels_of(after.effects[-1])] if after.effects else []
    worse = [CHANNELS[c] for c in touched if vel_gain[c] < -s.channel_tolerance]
    passes = bool(penalised >= s.min_gain and p <= s.alpha and Gv > 0.0 and not worse)
    return {
        "n_params": n_params,
        "heldout_gain": G,
        "heldout_gain_per_metric": dict(zip(keys, map(float, pose_gain), strict=True)),
        "penalised_gain": float(penalised),
        "velocity_gain": Gv,
        "velocity_gain_per_channel": dict(zip(CHANNELS, map(float, vel_gain), strict=True)),
        "heldout_mse_before": dict(zip(CHANNELS, map(float, before.mse), strict=True)),
        "heldout_mse_after": dict(zip(CHANNELS, map(float, after.mse), strict=True)),
        "velocity_channels_worse": worse,
        "paired_p_value": p,
        "n_heldout_units": int(np.sum(np.isfinite(d))),
        "units_improved": int(np.sum(d > 0)),
        "heldout_rmsre_before": before.rmsre,
        "heldout_rmsre_after": after.rmsre,
        "passes": passes,
    }


# -- the discovery loop -------------------------------------------------------------------------


@dataclass
class TerrainDiscovery:
    terrain: str
    base_model: str
    effects: list[str]
    steps: list[dict[str, Any]]
    base: dict[str, Any]
    final: dict[str, Any]
    message: str
    figure_data: list[dict[str, Any]]
    rejected: dict[str, Any] | None
    seconds: float
    terms: list[str] = field(default_factory=list)  # open-ended terms added (keys of benchmark/terms.py)
    unexplained: dict[str, Any] | None = None  # what is left when nothing more passes


def _jsonable_params(params: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    return {e: dict(zip(CATALOGUE[e].param_names, map(float, p), strict=True)) for e, p in params.items()}


def refine_knots(
    aug: Augmenter,
    effects: list[str],
    warm: dict[str, np.ndarray],
    terms: list[termlib.Term],
    term: termlib.Term,
    units: np.ndarray,
    rel: float = 0.4,
    maxiter: int = 16,
) -> termlib.Term:
    """The knots of an accepted term, fitted with the base model and its coefficient (the screen chose
    them against the base model fitted without the term, which has absorbed part of the effect): a
    bounded scalar search per knot within +-``rel`` of the screened value, on the fit loss over
    ``units`` (the training rows)."""
    if not term.knots:
        return term
    knots = list(term.knots)
    for j, k0 in enumerate(term.knots):
        lo, hi = sorted((k0 * (1 - rel), k0 * (1 + rel)))

        def loss(x, j=j):
            kn = list(knots)
            kn[j] = float(x)
            return aug.fit(effects, units, warm, fixed_tau=True, terms=[*terms, term.with_knots(kn)]).loss

        res = minimize_scalar(loss, bounds=(lo, hi), method="bounded", options={"maxiter": maxiter})
        if res.fun < loss(k0 if j == 0 else knots[j]):
            knots[j] = float(res.x)
    return term.with_knots(knots)


def _term_step_params(state: FitState, term: termlib.Term) -> dict[str, float]:
    p = dict(state.term_params[term.key])
    for i, k in enumerate(term.knots):
        p[f"knot{i}"] = float(k)
    return p


def _explains_better(ho_a: HeldOut, ho_b: HeldOut, s: DiscoverSettings) -> tuple[bool, float]:
    """Whether model a's held-out velocity residual is smaller than model b's, unit by unit: the per-unit
    sum over channels of log(MSE_b / MSE_a), one-sided sign-flip test at ``alpha``."""
    eps = 1e-18
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.nansum(np.log((ho_b.unit_mse + eps) / (ho_a.unit_mse + eps)), axis=1)
    p = sign_flip_pvalue(d, s.seed)
    return bool(np.nanmean(d) > 0 and p <= s.alpha), p


def _naming(kind: str, ev: dict, scored_t: dict, scored_c: dict, n_params: int) -> dict[str, Any]:
    """The check behind a name: a catalogue effect against the best open-ended term of no more
    parameters; a term against the best catalogue effect."""
    if kind == "catalogue":
        rivals = {k: e for k, (e, _, t) in scored_t.items() if t.n_params <= n_params}
    else:
        rivals = {k: e for k, (e, _) in scored_c.items()}
    if not rivals:
        return {"rival": None, "rival_heldout_gain": None, "heldout_gain": ev["heldout_gain"]}
    best = max(rivals, key=lambda k: rivals[k]["heldout_gain"])
    return {
        "rival": best,
        "rival_heldout_gain": rivals[best]["heldout_gain"],
        "heldout_gain": ev["heldout_gain"],
    }


def unexplained_report(pool: Pool, aug: Augmenter, state: FitState, ho: HeldOut) -> dict[str, Any]:
    """What the model leaves on held-out units, per channel: its RMS, the share of the target's RMS, and
    the library signals it follows most (Pearson r)."""
    resid = pool.target - ho.pred
    v = pool.valid
    rms = np.sqrt(np.mean(resid[v] ** 2, axis=0))
    scale = np.sqrt(np.mean(pool.target[v] ** 2, axis=0))
    corr = termlib.correlates(aug.signals(state.feats, state.base_pred), resid, v)
    parts = []
    for c, ch in enumerate(CHANNELS):
        top = ", ".join(f"{d['signal']} (r = {d['r']:+.2f})" for d in corr[ch])
        unit = "rad/s" if ch == "wz" else "m/s"
        parts.append(
            f"{ch} {rms[c]:.4g} {unit} ({rms[c] / max(scale[c], 1e-12):.0%} of its RMS; follows {top})"
        )
    return {
        "heldout_residual_rms": dict(zip(CHANNELS, map(float, rms), strict=True)),
        "relative_to_target_rms": dict(
            zip(CHANNELS, map(float, rms / np.maximum(scale, 1e-12)), strict=True)
        ),
        "correlates": corr,
        "heldout_rmsre": ho.rmsre,
        "text": "unexplained held-out residual: " + "; ".join(parts),
    }


def discover_terrain(
    pool: Pool,
    factory: ModelFactory,
    robot: Robot,
    settings: DiscoverSettings,
    terrain: str,
    base_name: str,
    candidates: tuple[str, ...] = EFFECT_IDS,
    progress: Callable[[str], None] | None = None,
) -> TerrainDiscovery:
    """Catalogue effects and open-ended terms (:mod:`skidbench.benchmark.terms`) scored side by side on
    the same held-out units by the same rule; the best passing one is added, except that a catalogue
    effect is named only when no open-ended term of no more parameters explains more of the held-out
    gap (then the term is added under its own formula). When nothing passes, the residual is reported
    as unexplained with its size and its strongest correlates."""
    t_start = time.perf_counter()
    say = progress or (lambda msg: log.info(msg))
    aug = Augmenter(pool, factory, robot, settings)
    all_units = np.arange(pool.n_units)
    base_fit = aug.fit([], all_units)
    res = (base_fit.pred - pool.target)[pool.valid]
    aug.weights = 1.0 / np.maximum(res.var(axis=0) + (res.mean(axis=0) ** 2), 1e-12)
    cur = cross_validate(aug, [])
    base_info = {
        "train_residual_rmse": dict(zip(CHANNELS, map(float, np.sqrt((res**2).mean(axis=0))), strict=True)),
        "train_residual_mean": dict(zip(CHANNELS, map(float, res.mean(axis=0)), strict=True)),
        "heldout_rmsre": cur.rmsre,
        "heldout_mse": dict(zip(CHANNELS, map(float, cur.mse), strict=True)),
        "params": base_fit.base.get_params(),
        "n_sequences": len(pool.sequences),
        "n_heldout_units": pool.n_units,
        "n_samples": int(pool.valid.sum()),
        "pool_note": pool.note,
    }
    if pool.note:
        say(f"[{terrain}] note: {pool.note}")
    say(
        f"[{terrain}] base {base_name}: held-out {settings.horizon_s:g} s RMSRE "
        f"trans {cur.rmsre['translational']:.4f} rot {cur.rmsre['rotational']:.4f} "
        f"({pool.n_units} held-out units from {len(pool.sequences)} sequences)"
    )
    effects: list[str] = []
    terms: list[termlib.Term] = []
    warm: dict[str, np.ndarray] = {}
    steps: list[dict[str, Any]] = []
    figure_data: list[dict[str, Any]] = []
    rejected = None
    unexplained = None
    state = base_fit
    B = robot.track_width

    def show(name: str, ev: dict) -> None:
        say(
            f"[{terrain}]   {name:28s} gain {ev['heldout_gain']:+.4f} (penalised "
            f"{ev['penalised_gain']:+.4f}) p={ev['paired_p_value']:.3g} "
            f"velocity gain {ev['velocity_gain']:+.4f}{'  PASS' if ev['passes'] else ''}"
        )

    while len(effects) + len(terms) < settings.max_effects:
        scored: dict[str, tuple[dict, HeldOut]] = {}
        for eid in candidates:
            if eid in effects:
                continue
            ho = cross_validate(aug, effects + [eid], warm, terms)
            ev = compare(cur, ho, CATALOGUE[eid].n_params, settings)
            scored[eid] = (ev, ho)
            show(eid, ev)
        scored_t: dict[str, tuple[dict, HeldOut, termlib.Term]] = {}
        screen_info: dict[str, Any] = {}
        scr = None
        if settings.open_ended:
            # the sparse regression on the current model's held-out residual picks the candidates
            sig = aug.signals(state.feats, state.base_pred)
            gains = termlib.base_gains(sig, pool.valid)
            scr = termlib.screen(
                sig,
                gains,
                B,
                pool.target - cur.pred,
                pool.valid,
                aug.weights,
                exclude=tuple(t.key for t in terms),
                max_candidates=settings.max_terms,
            )
            screen_info = {"stlsq_support": scr.selected, "candidates": [t.key for t in scr.candidates]}
            for term in scr.candidates:
                ho = cross_validate(aug, effects, warm, terms + [term])
                ev = compare(cur, ho, term.n_params, settings, term.touched)
                scored_t[term.key] = (ev, ho, term)
                show(term.key, ev)
        table = {
            e: {k: v for k, v in ev.items() if k != "heldout_mse_before"} for e, (ev, _) in scored.items()
        }
        table_t = {
            k: {kk: v for kk, v in ev.items() if kk != "heldout_mse_before"}
            for k, (ev, _, _) in scored_t.items()
        }
        passing = [e for e, (ev, _) in scored.items() if ev["passes"]]
        passing_t = [k for k, (ev, _, _) in scored_t.items() if ev["passes"]]
        choice: tuple[str, str] | None = None  # (kind, id)
        best_c = max(passing, key=lambda e: scored[e][0]["penalised_gain"]) if passing else None
        best_t = max(passing_t, key=lambda k: scored_t[k][0]["penalised_gain"]) if passing_t else None
        if best_c is not None and settings.open_ended and scr is not None:
            # the catalogue's best must beat the library's best term of no more parameters on its channels
            chans = tuple(CHANNELS.index(c) for c in _channels_of(best_c))
            rival = scr.rival(chans, CATALOGUE[best_c].n_params, tuple(scored_t))
            if rival is not None:
                ho = cross_validate(aug, effects, warm, terms + [rival])
                ev = compare(cur, ho, rival.n_params, settings, rival.touched)
                scored_t[rival.key] = (ev, ho, rival)
                table_t[rival.key] = {k: v for k, v in ev.items() if k != "heldout_mse_before"}
                show(rival.key, ev)
                if ev["passes"]:
                    passing_t.append(rival.key)
                    best_t = max(passing_t, key=lambda k: scored_t[k][0]["penalised_gain"])
        if best_c is not None:
            # a term takes a passing catalogue effect's place only when it explains the held-out velocity
            # residual significantly better, unit by unit (the same sign-flip test): a term no more
            # complex than the effect, or one whose penalised gain is also larger
            cat_ev, cat_ho = scored[best_c]
            better = {
                k: _explains_better(scored_t[k][1], cat_ho, settings)
                for k in passing_t
                if scored_t[k][2].n_params <= CATALOGUE[best_c].n_params
                or scored_t[k][0]["penalised_gain"] > cat_ev["penalised_gain"]
            }
            winners = [k for k, (ok, _) in better.items() if ok]
            if winners:
                choice = ("term", max(winners, key=lambda k: scored_t[k][0]["penalised_gain"]))
                say(
                    f"[{terrain}]   {best_c} not named: {choice[1]} explains the held-out residual better "
                    f"(p = {better[choice[1]][1]:.3g})"
                )
            else:
                choice = ("catalogue", best_c)
        elif best_t is not None:
            choice = ("term", best_t)
        if choice is None:
            pool_best = [(e, scored[e][0]["penalised_gain"]) for e in scored] + [
                (k, scored_t[k][0]["penalised_gain"]) for k in scored_t
            ]
            best = max(pool_best, key=lambda p: p[1])[0] if pool_best else None
            rejected = {"best_candidate": best, "candidates": table, "terms": table_t, "screen": screen_info}
            best_cat = max(scored, key=lambda e: scored[e][0]["penalised_gain"]) if scored else None
            figure_data.append(_residual_panel(pool, state, best_cat, cur, None))
            unexplained = unexplained_report(pool, aug, state, cur)
            figure_data += _unexplained_panels(pool, aug, state, cur, unexplained)
            say(f"[{terrain}] {unexplained['text']}")
            break
        kind, name = choice
        prev_state = state
        if kind == "catalogue":
            ev, ho = scored[name]
            state = aug.fit(effects + [name], all_units, warm, terms=terms)  # refit on all training sequences
            warm = {k: v for k, v in state.params.items()}
            effects.append(name)
            e = CATALOGUE[name]
            steps.append(
                {
                    "effect": name,
                    "kind": "catalogue",
                    "explanation": e.explanation,
                    "formula": e.formula,
                    "evidence": {**ev, "candidates": table, "terms": table_t, "screen": screen_info},
                    "naming": _naming("catalogue", ev, scored_t, scored, e.n_params),
                    "params": _jsonable_params(state.params),
                    "heldout_rmsre_before": cur.rmsre,
                    "heldout_rmsre_after": ho.rmsre,
                }
            )
            figure_data.append(_residual_panel(pool, prev_state, name, cur, state))
        else:
            ev, ho, term = scored_t[name]
            refined = refine_knots(aug, effects, warm, terms, term, all_units)
            if refined != term:  # the held-out evidence of the model as it is added
                ho = cross_validate(aug, effects, warm, terms + [refined])
                ev = compare(cur, ho, refined.n_params, settings, refined.touched)
                term = refined
            state = aug.fit(effects, all_units, warm, terms=terms + [term])
            warm = {k: v for k, v in state.params.items()}
            terms.append(term)
            theta = state.term_params[term.key]["theta"]
            steps.append(
                {
                    "effect": term.key,
                    "kind": "term",
                    "explanation": term.describe(theta, robot.wheel_radius),
                    "formula": f"{'vx, wz' if term.channel < 0 else CHANNELS[term.channel]} += theta * g, "
                    f"g = {term.key}",
                    "evidence": {**ev, "candidates": table, "terms": table_t, "screen": screen_info},
                    "naming": _naming("term", ev, scored_t, scored, term.n_params),
                    "params": {term.key: _term_step_params(state, term)},
                    "heldout_rmsre_before": cur.rmsre,
                    "heldout_rmsre_after": ho.rmsre,
                }
            )
            figure_data.append(_term_panel(pool, prev_state, term, cur, state, aug))
        say(
            f"[{terrain}] + {name}: held-out RMSRE trans {cur.rmsre['translational']:.4f} -> "
            f"{ho.rmsre['translational']:.4f}, rot {cur.rmsre['rotational']:.4f} -> "
            f"{ho.rmsre['rotational']:.4f}" + (f" ({steps[-1]['explanation']})" if kind == "term" else "")
        )
        cur = ho
    found = effects + [t.key for t in terms]
    named = [st["effect"] + ("" if st["kind"] == "catalogue" else f" [{st['explanation']}]") for st in steps]
    message = NO_EFFECT_MESSAGE if not found else "missing effect(s) found: " + ", ".join(named)
    if found and len(found) < settings.max_effects:
        message += "; no further effect earns its place"
    say(f"[{terrain}] {message}")
    final = {
        "effects": list(effects),
        "terms": [t.key for t in terms],
        "params": _jsonable_params(state.params),
        "term_params": {t.key: _term_step_params(state, t) for t in terms},
        "base_params": state.base.get_params(),
        "heldout_rmsre": cur.rmsre,
        "heldout_mse": dict(zip(CHANNELS, map(float, cur.mse), strict=True)),
    }
    return TerrainDiscovery(
        terrain,
        base_name,
        effects,
        steps,
        base_info,
        final,
        message,
        figure_data,
        rejected,
        time.perf_counter() - t_start,
        [t.key for t in terms],
        unexplained,
    )


def _binned(x: np.ndarray, r: np.ndarray, extra: np.ndarray | None = None) -> dict[str, list[float]]:
    """Quantile-binned means (and standard errors) of ``r`` against ``x`` (20 bins)."""
    if len(x) < 10:
        return {}
    qs = np.unique(np.quantile(x, np.linspace(0, 1, 21)))
    if len(qs) < 2:
        return {}
    idx = np.clip(np.searchsorted(qs, x, side="right") - 1, 0, len(qs) - 2)
    nb = len(qs) - 1
    cnt = np.bincount(idx, minlength=nb).astype(float)
    ok = cnt > 0
    c = np.maximum(cnt, 1)

    def mean(y):
        return np.where(ok, np.bincount(idx, y, minlength=nb) / c, np.nan)

    by = mean(r)
    sd = np.sqrt(np.maximum(mean(r * r) - by**2, 0.0))
    out = {"bin_x": mean(x).tolist(), "bin_y": by.tolist(), "bin_se": (sd / np.sqrt(c)).tolist()}
    if extra is not None:
        out["bin_fit"] = mean(extra).tolist()
    return out


def _term_panel(pool: Pool, state: FitState, term: termlib.Term, ho: HeldOut, after: FitState, aug) -> dict:
    """Held-out residual of the term's (first) channel against its signal, and the correction added."""
    ch = 0 if term.channel < 0 else term.channel
    sig = aug.signals(state.feats, state.base_pred)
    x = sig["rim_l"] if term.family == "slip" and term.signal == "l" else None
    if x is None:
        x = sig["rim_r"] if term.family == "slip" else None
    if x is None:
        x = sig["t"] if term.family == "after" else None
    if x is None:
        x = np.maximum(np.abs(sig["rim_l"]), np.abs(sig["rim_r"])) if term.channel < 0 else None
    if x is None:
        x = termlib._signal(term.signal, sig)
    r = (pool.target - ho.pred)[:, ch]
    m = pool.valid & np.isfinite(x)
    out = {"effect": term.key, "channel": CHANNELS[ch], "feature": term.signal, "accepted": True}
    out.update(_binned(x[m], r[m], (after.pred - state.pred)[:, ch][m]))
    return out


def _unexplained_panels(pool: Pool, aug, state: FitState, ho: HeldOut, rep: dict) -> list[dict]:
    """One panel per velocity channel: the held-out residual against its strongest correlate."""
    sig = aug.signals(state.feats, state.base_pred)
    out = []
    for c, ch in enumerate(CHANNELS):
        if not rep["correlates"][ch]:
            continue
        name = rep["correlates"][ch][0]["signal"]
        x = termlib._signal(name, sig)
        r = (pool.target - ho.pred)[:, c]
        m = pool.valid & np.isfinite(x)
        d = {
            "effect": "unexplained",
            "channel": ch,
            "feature": f"{name} (r = {rep['correlates'][ch][0]['r']:+.2f})",
        }
        d.update(_binned(x[m], r[m]))
        d["accepted"] = False
        d["unexplained"] = True
        out.append(d)
    return out


def _residual_panel(
    pool: Pool, state: FitState, eid: str | None, ho: HeldOut, after: FitState | None
) -> dict:
    """Binned held-out residual of the effect's channel against the feature that revealed it."""
    if eid is None:
        return {}
    e = CATALOGUE[eid]
    ch = 2 if e.channel < 0 else e.channel
    x = revealing_feature(eid, state.feats, state.base_pred)
    r = (pool.target - ho.pred)[:, ch]
    m = pool.valid & np.isfinite(x)
    x, r = x[m], r[m]
    out = {"effect": eid, "channel": CHANNELS[ch], "feature": e.feature_label, "accepted": after is not None}
    if len(x) < 10:
        return out
    qs = np.unique(np.quantile(x, np.linspace(0, 1, 21)))
    idx = np.clip(np.searchsorted(qs, x, side="right") - 1, 0, len(qs) - 2)
    bx = np.array([x[idx == i].mean() if np.any(idx == i) else np.nan for i in range(len(qs) - 1)])
    by = np.array([r[idx == i].mean() if np.any(idx == i) else np.nan for i in range(len(qs) - 1)])
    be = np.array(
        [
            r[idx == i].std() / max(1, np.sum(idx == i)) ** 0.5 if np.any(idx == i) else np.nan
            for i in range(len(qs) - 1)
        ]
    )
    out.update({"bin_x": bx.tolist(), "bin_y": by.tolist(), "bin_se": be.tolist()})
    if after is not None:  # the correction the effect adds (relative to the previous model), binned
        delta = (after.pred - state.pred)[:, ch][m]
        out["bin_fit"] = [
            float(delta[idx == i].mean()) if np.any(idx == i) else float("nan") for i in range(len(qs) - 1)
        ]
    return out
