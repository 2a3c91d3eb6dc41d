"""Discrepancy discovery: find where a model and the measured data disagree and name the missing
physical effect (SPEC.md "Discrepancy discovery").

Workflow, per terrain, on the Train split:

1. Fit the base model (default: extended differential drive, ``edd``) and take its residuals: body
   velocities (vx, vy, wz) against ground truth, and 6 s horizon pose errors (RMSRE).
2. For every effect of the catalogue (:mod:`skidbench.models.effects`) not yet in the model, fit the
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
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy.optimize import minimize_scalar

from skidbench.benchmark.horizon import rmsre, window_errors
from skidbench.models import terms as termlib
from skidbench.models.effect_fit import (
    CHANNELS,
    Augmenter,
    DiscoverError,
    DiscoverSettings,
    FitState,
    ModelFactory,
    Pool,
    build_pool,
    channel_weights,
    jsonable_params,
)
from skidbench.models.effects import (
    CATALOGUE,
    EFFECT_IDS,
    revealing_feature,
)
from skidbench.pipeline.protocol import fit_table
from skidbench.pipeline.robot import Robot
from skidbench.pipeline.schema import load_split_tables as _load_split_tables
from skidbench.pipeline.schema import read_split

log = logging.getLogger("skidbench.discover")

NO_EFFECT_MESSAGE = "no missing effect found"


# -- data ---------------------------------------------------------------------------------------


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
    terms: list[str] = field(default_factory=list)  # open-ended terms added (keys of models/terms.py)
    unexplained: dict[str, Any] | None = None  # what is left when nothing more passes


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
    """Catalogue effects and open-ended terms (:mod:`skidbench.models.terms`) scored side by side on
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
    aug.weights = channel_weights(pool, base_fit)
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
                    "params": jsonable_params(state.params),
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
        # the channel weights are the inverse residual variances of the model as it now is (the base model's
        # overstated the channels the added correction fixed): re-estimated, with the model refitted and held
        # out under them, so the next candidates are fitted and compared as a Gaussian likelihood with
        # per-channel noise would weigh them (with the base model's weights, a wheel-level term's constant
        # absorbs the base model's own vx misfit and leaves the yaw rate a residual a catalogue effect names)
        weights = channel_weights(pool, state)
        if not np.allclose(weights, aug.weights, rtol=0.05):
            aug.weights = weights
            state = aug.fit(effects, all_units, warm, terms=terms)
            warm = {k: v for k, v in state.params.items()}
            cur = cross_validate(aug, effects, warm, terms)
            # the step reports the constants of the model as refitted under the new weights
            if kind == "catalogue":
                steps[-1]["params"] = jsonable_params(state.params)
            else:
                theta = state.term_params[term.key]["theta"]
                steps[-1]["params"] = {term.key: _term_step_params(state, term)}
                steps[-1]["explanation"] = term.describe(theta, robot.wheel_radius)
        steps[-1]["channel_weights_after"] = dict(zip(CHANNELS, map(float, aug.weights), strict=True))
    found = effects + [t.key for t in terms]
    named = [st["effect"] + ("" if st["kind"] == "catalogue" else f" [{st['explanation']}]") for st in steps]
    message = NO_EFFECT_MESSAGE if not found else "missing effect(s) found: " + ", ".join(named)
    if found and len(found) < settings.max_effects:
        message += "; no further effect earns its place"
    say(f"[{terrain}] {message}")
    final = {
        "effects": list(effects),
        "terms": [t.key for t in terms],
        "params": jsonable_params(state.params),
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
