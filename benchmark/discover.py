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

The held-out evaluation and the significance rule (a penalised held-out 6 s gain, a paired sign-flip
test over held-out units, velocity residuals that agree) are in :mod:`skidbench.benchmark.discover_stats`;
the figure data in :mod:`skidbench.benchmark.discover_panels`.

Effects keep their physical direction (parameter bounds in the catalogue: slips are shortfalls, the
side slip is outward, chi grows in tight turns, the turn deficit grows with speed).

Among the candidates that pass, the one with the largest penalised gain is added.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy.optimize import minimize_scalar

from skidbench.benchmark.discover_panels import (
    residual_panel,
    term_panel,
    unexplained_panels,
)
from skidbench.benchmark.discover_stats import (
    HeldOut,
    channels_of,
    compare,
    cross_validate,
    explains_better,
)
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
from skidbench.models.effects import CATALOGUE, EFFECT_IDS
from skidbench.pipeline.protocol import fit_table
from skidbench.pipeline.robot import Robot
from skidbench.pipeline.schema import load_split_tables as _load_split_tables
from skidbench.pipeline.schema import read_split

log = logging.getLogger("skidbench.discover")

NO_EFFECT_MESSAGE = "no missing effect found"


# -- the pool ---------------------------------------------------------------------------------------


def load_pool(
    splits_root: Path,
    terrain: str,
    settings: DiscoverSettings,
    files_of: Callable[[str, str], list[Path]] | None = None,
) -> Pool:
    """The held-out pool of a terrain: its ``settings.splits`` sequences (default Train) and nothing else;
    when they are fewer than ``min_units``, cut into time blocks (:func:`build_pool`). Discovery selects
    and fits on these only: the test splits (CV, LD) are never read, so that the ``discovered`` model's
    score there is a held-out one. ``files_of(terrain, split)``: the split files to read (the current
    manifest's); default every file under ``splits_root``."""

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
    pool.note = f"selected on {'/'.join(settings.splits)} only: " + pool.describe()
    return pool


def too_small(pool: Pool, settings: DiscoverSettings) -> str | None:
    """Why the pool cannot support a discovery (None when it can): fewer held-out units than the
    sign-flip test needs to reject at ``alpha`` (2^-n > alpha), or no unit with a full horizon window."""
    need = max(2, int(np.ceil(np.log2(1.0 / settings.alpha))))
    if pool.n_units < need:
        return (
            f"{pool.describe()}: {pool.n_units} held-out unit(s) of at least {settings.horizon_s:g} s, and "
            f"a sign-flip test over n units cannot reach alpha = {settings.alpha:g} with n < {need}; "
            f"record at least {need * settings.horizon_s:g} s of {'/'.join(settings.splits)} driving"
        )
    return None


def apply_protocol(pool: Pool, protocol: str, robot: Robot, response: Any = None) -> Pool:
    """The pool with its inputs replaced by those of the input protocol (pipeline/protocol.py), computed
    per original sequence (``pool.groups``), targets and held-out units kept: discovery then searches
    what the base model misses given the protocol's inputs (under ``response`` the wheel response is
    given, so ``actuator_lag`` has nothing left to explain)."""
    table = fit_table(pool.table.assign(sequence=pool.groups), protocol, robot, response)
    table["sequence"] = pool.units
    return dataclasses.replace(pool, table=table)


# -- the result, and the parts of a step -----------------------------------------------------------


@dataclass
class TerrainDiscovery:
    """What discovery found on one terrain (written to ``discovery.json`` by ``discover_app``): the effects
    and terms added in order, one step each with its evidence, the base and final models' held-out
    errors, the figure data, the candidates rejected last and the residual left unexplained."""

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
    selected_on: dict[str, Any] = field(default_factory=dict)  # the splits, sequences and units searched
    refused: str | None = None  # why no search was run (a pool too small for the test)


def selected_on(pool: Pool, settings: DiscoverSettings) -> dict[str, Any]:
    """What a discovery selected and fitted on: the splits, their sequences, the held-out units."""
    return {
        "splits": list(settings.splits),
        "sequences": list(pool.sequences),
        "n_units": pool.n_units,
        "units": "time blocks" if pool.blocks else "sequences",
        "text": f"{'/'.join(settings.splits)} only: {pool.describe()}",
    }


def refused_terrain(pool: Pool, settings: DiscoverSettings, terrain: str, base_name: str, reason: str):
    """The record of a terrain whose pool is too small to search (:func:`too_small`)."""
    nan = {"translational": float("nan"), "rotational": float("nan")}
    base = {"heldout_rmsre": nan, "n_sequences": len(pool.sequences), "n_heldout_units": pool.n_units}
    return TerrainDiscovery(
        terrain, base_name, [], [], base, {"effects": [], "terms": [], "heldout_rmsre": nan},
        f"refused: {reason}", [], None, 0.0, selected_on=selected_on(pool, settings), refused=reason,
    )  # fmt: skip


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


# -- the search, step by step -----------------------------------------------------------------------

Scored = dict[str, tuple[dict[str, Any], HeldOut]]  # catalogue effect -> (evidence, held-out evaluation)
ScoredTerms = dict[str, tuple[dict[str, Any], HeldOut, termlib.Term]]  # term key -> (..., the term)


@dataclass
class _Search:
    """One terrain's search as it stands: the model (catalogue effects and terms added so far, fitted on
    every training unit, its parameters as the warm start of the next fits, its held-out evaluation
    ``cur``) and what has been recorded (steps, figure data, the rejected candidates, the unexplained
    residual)."""

    pool: Pool
    aug: Augmenter
    robot: Robot
    settings: DiscoverSettings
    terrain: str
    say: Callable[[str], None]
    all_units: np.ndarray
    state: FitState
    cur: HeldOut
    base_info: dict[str, Any]
    effects: list[str] = field(default_factory=list)
    terms: list[termlib.Term] = field(default_factory=list)
    warm: dict[str, np.ndarray] = field(default_factory=dict)
    steps: list[dict[str, Any]] = field(default_factory=list)
    figure_data: list[dict[str, Any]] = field(default_factory=list)
    rejected: dict[str, Any] | None = None
    unexplained: dict[str, Any] | None = None


def _show(run: _Search, name: str, ev: dict[str, Any]) -> None:
    """One progress line: a candidate's held-out gains and whether it passes the rule."""
    run.say(
        f"[{run.terrain}]   {name:28s} gain {ev['heldout_gain']:+.4f} (penalised "
        f"{ev['penalised_gain']:+.4f}) p={ev['paired_p_value']:.3g} "
        f"velocity gain {ev['velocity_gain']:+.4f}{'  PASS' if ev['passes'] else ''}"
    )


def _evidence_row(ev: dict[str, Any]) -> dict[str, Any]:
    """A candidate's evidence as the step's table of candidates records it."""
    return {k: v for k, v in ev.items() if k != "heldout_mse_before"}


def _fit_base(
    pool: Pool,
    factory: ModelFactory,
    robot: Robot,
    settings: DiscoverSettings,
    terrain: str,
    base_name: str,
    say: Callable[[str], None],
) -> _Search:
    """Fit the base model on every training unit and score it held out: the search's starting point. The
    channel weights of the fits are set from this fit's residuals (:func:`channel_weights`)."""
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
        "selected_on": pool.describe(),
    }
    if pool.note:
        say(f"[{terrain}] note: {pool.note}")
    say(
        f"[{terrain}] base {base_name}: held-out {settings.horizon_s:g} s RMSRE "
        f"trans {cur.rmsre['translational']:.4f} rot {cur.rmsre['rotational']:.4f} "
        f"({pool.n_units} held-out units from {len(pool.sequences)} sequences)"
    )
    return _Search(pool, aug, robot, settings, terrain, say, all_units, base_fit, cur, base_info)


def _score_catalogue(run: _Search, candidates: tuple[str, ...]) -> Scored:
    """Every catalogue effect of ``candidates`` not yet in the model, added to it, fitted fold by fold and
    scored held out against the current model."""
    scored: Scored = {}
    for eid in candidates:
        if eid in run.effects:
            continue
        ho = cross_validate(run.aug, run.effects + [eid], run.warm, run.terms)
        ev = compare(run.cur, ho, CATALOGUE[eid].n_params, run.settings)
        scored[eid] = (ev, ho)
        _show(run, eid, ev)
    return scored


def _score_terms(run: _Search) -> tuple[ScoredTerms, dict[str, Any], termlib.Screen | None]:
    """The open-ended terms (``discover.open_ended``): the sparse regression on the current model's
    held-out residual picks up to ``max_terms`` candidates, each scored held out like a catalogue effect.
    Returns the scores, what the screen selected (for the record) and the screen (none when off)."""
    scored_t: ScoredTerms = {}
    if not run.settings.open_ended:
        return scored_t, {}, None
    sig = run.aug.signals(run.state.feats, run.state.base_pred)
    gains = termlib.base_gains(sig, run.pool.valid)
    scr = termlib.screen(
        sig,
        gains,
        run.robot.track_width,
        run.pool.target - run.cur.pred,
        run.pool.valid,
        run.aug.weights,
        exclude=tuple(t.key for t in run.terms),
        max_candidates=run.settings.max_terms,
    )
    screen_info = {"stlsq_support": scr.selected, "candidates": [t.key for t in scr.candidates]}
    for term in scr.candidates:
        ho = cross_validate(run.aug, run.effects, run.warm, run.terms + [term])
        ev = compare(run.cur, ho, term.n_params, run.settings, term.touched)
        scored_t[term.key] = (ev, ho, term)
        _show(run, term.key, ev)
    return scored_t, screen_info, scr


def _score_rival(
    run: _Search, best_c: str, scored_t: ScoredTerms, table_t: dict[str, Any], scr: termlib.Screen
) -> str | None:
    """The catalogue's best must beat the library's best term of no more parameters on its channels:
    that rival, when the screen has one not yet scored, is scored and recorded (``scored_t``,
    ``table_t``). Returns its key when it passes."""
    chans = tuple(CHANNELS.index(c) for c in channels_of(best_c))
    rival = scr.rival(chans, CATALOGUE[best_c].n_params, tuple(scored_t))
    if rival is None:
        return None
    ho = cross_validate(run.aug, run.effects, run.warm, run.terms + [rival])
    ev = compare(run.cur, ho, rival.n_params, run.settings, rival.touched)
    scored_t[rival.key] = (ev, ho, rival)
    table_t[rival.key] = _evidence_row(ev)
    _show(run, rival.key, ev)
    return rival.key if ev["passes"] else None


def _choose(
    run: _Search, scored: Scored, scored_t: ScoredTerms, table_t: dict[str, Any], scr: termlib.Screen | None
) -> tuple[str, str] | None:
    """The candidate to add, as (kind, id) with kind "catalogue" or "term"; None when none passes. The
    passing catalogue effect of largest penalised gain is named unless a passing term explains the
    held-out velocity residual significantly better, unit by unit (the same sign-flip test), and is no
    more complex or has the larger penalised gain too; with no passing effect, the best passing term."""
    passing = [e for e, (ev, _) in scored.items() if ev["passes"]]
    passing_t = [k for k, (ev, _, _) in scored_t.items() if ev["passes"]]
    if not passing:
        return ("term", max(passing_t, key=lambda k: scored_t[k][0]["penalised_gain"])) if passing_t else None
    best_c = max(passing, key=lambda e: scored[e][0]["penalised_gain"])
    if run.settings.open_ended and scr is not None:
        rival = _score_rival(run, best_c, scored_t, table_t, scr)
        if rival is not None:
            passing_t.append(rival)
    cat_ev, cat_ho = scored[best_c]
    better = {
        k: explains_better(scored_t[k][1], cat_ho, run.settings)
        for k in passing_t
        if scored_t[k][2].n_params <= CATALOGUE[best_c].n_params
        or scored_t[k][0]["penalised_gain"] > cat_ev["penalised_gain"]
    }
    winners = [k for k, (ok, _) in better.items() if ok]
    if not winners:
        return ("catalogue", best_c)
    name = max(winners, key=lambda k: scored_t[k][0]["penalised_gain"])
    run.say(
        f"[{run.terrain}]   {best_c} not named: {name} explains the held-out residual better "
        f"(p = {better[name][1]:.3g})"
    )
    return ("term", name)


def _report_unexplained(
    run: _Search, scored: Scored, scored_t: ScoredTerms, evidence: dict[str, Any]
) -> None:
    """Nothing passes: record the candidates rejected (and the best of them by penalised gain), the
    residual panel of the best catalogue effect, and what the model leaves unexplained on held-out units
    (its size, its strongest correlates, their panels)."""
    pool_best = [(e, scored[e][0]["penalised_gain"]) for e in scored] + [
        (k, scored_t[k][0]["penalised_gain"]) for k in scored_t
    ]
    best = max(pool_best, key=lambda p: p[1])[0] if pool_best else None
    run.rejected = {"best_candidate": best, **evidence}
    best_cat = max(scored, key=lambda e: scored[e][0]["penalised_gain"]) if scored else None
    run.figure_data.append(residual_panel(run.pool, run.state, best_cat, run.cur, None))
    run.unexplained = unexplained_report(run.pool, run.aug, run.state, run.cur)
    run.figure_data += unexplained_panels(run.pool, run.aug, run.state, run.cur, run.unexplained)
    run.say(f"[{run.terrain}] {run.unexplained['text']}")


def _add_effect(
    run: _Search, name: str, scored: Scored, scored_t: ScoredTerms, evidence: dict[str, Any]
) -> HeldOut:
    """Add the catalogue effect ``name``: refit on every training unit, record the step (its explanation,
    evidence, naming check and parameters) and its residual panel. Returns its held-out evaluation."""
    ev, ho = scored[name]
    prev_state = run.state
    run.state = run.aug.fit(run.effects + [name], run.all_units, run.warm, terms=run.terms)
    run.warm = {k: v for k, v in run.state.params.items()}
    run.effects.append(name)
    e = CATALOGUE[name]
    run.steps.append(
        {
            "effect": name,
            "kind": "catalogue",
            "explanation": e.explanation,
            "formula": e.formula,
            "evidence": {**ev, **evidence},
            "naming": _naming("catalogue", ev, scored_t, scored, e.n_params),
            "params": jsonable_params(run.state.params),
            "heldout_rmsre_before": run.cur.rmsre,
            "heldout_rmsre_after": ho.rmsre,
        }
    )
    run.figure_data.append(residual_panel(run.pool, prev_state, name, run.cur, run.state))
    return ho


def _add_term(
    run: _Search, name: str, scored: Scored, scored_t: ScoredTerms, evidence: dict[str, Any]
) -> tuple[HeldOut, termlib.Term]:
    """Add the open-ended term ``name``: its knots refined with the model (and its held-out evidence
    re-taken when they moved), refit on every training unit, record the step (the term described with
    its constants) and its panel. Returns its held-out evaluation and the term as added."""
    ev, ho, term = scored_t[name]
    refined = refine_knots(run.aug, run.effects, run.warm, run.terms, term, run.all_units)
    if refined != term:  # the held-out evidence of the model as it is added
        ho = cross_validate(run.aug, run.effects, run.warm, run.terms + [refined])
        ev = compare(run.cur, ho, refined.n_params, run.settings, refined.touched)
        term = refined
    prev_state = run.state
    run.state = run.aug.fit(run.effects, run.all_units, run.warm, terms=run.terms + [term])
    run.warm = {k: v for k, v in run.state.params.items()}
    run.terms.append(term)
    theta = run.state.term_params[term.key]["theta"]
    run.steps.append(
        {
            "effect": term.key,
            "kind": "term",
            "explanation": term.describe(theta, run.robot.wheel_radius),
            "formula": f"{'vx, wz' if term.channel < 0 else CHANNELS[term.channel]} += theta * g, "
            f"g = {term.key}",
            "evidence": {**ev, **evidence},
            "naming": _naming("term", ev, scored_t, scored, term.n_params),
            "params": {term.key: _term_step_params(run.state, term)},
            "heldout_rmsre_before": run.cur.rmsre,
            "heldout_rmsre_after": ho.rmsre,
        }
    )
    run.figure_data.append(term_panel(run.pool, prev_state, term, run.cur, run.state, run.aug))
    return ho, term


def _accept(run: _Search, name: str, kind: str, ho: HeldOut) -> None:
    """The added candidate's held-out evaluation becomes the current model's; the gap it closed is
    reported."""
    cur = run.cur
    run.say(
        f"[{run.terrain}] + {name}: held-out RMSRE trans {cur.rmsre['translational']:.4f} -> "
        f"{ho.rmsre['translational']:.4f}, rot {cur.rmsre['rotational']:.4f} -> "
        f"{ho.rmsre['rotational']:.4f}" + (f" ({run.steps[-1]['explanation']})" if kind == "term" else "")
    )
    run.cur = ho


def _reweight(run: _Search, kind: str, term: termlib.Term | None) -> None:
    """Re-estimate the channel weights after a step and record them with it.

    The channel weights are the inverse residual variances of the model as it now is (the base model's
    overstated the channels the added correction fixed): re-estimated, with the model refitted and held
    out under them, so the next candidates are fitted and compared as a Gaussian likelihood with
    per-channel noise would weigh them (with the base model's weights, a wheel-level term's constant
    absorbs the base model's own vx misfit and leaves the yaw rate a residual a catalogue effect names).
    """
    weights = channel_weights(run.pool, run.state)
    if not np.allclose(weights, run.aug.weights, rtol=0.05):
        run.aug.weights = weights
        run.state = run.aug.fit(run.effects, run.all_units, run.warm, terms=run.terms)
        run.warm = {k: v for k, v in run.state.params.items()}
        run.cur = cross_validate(run.aug, run.effects, run.warm, run.terms)
        # the step reports the constants of the model as refitted under the new weights
        if kind == "catalogue":
            run.steps[-1]["params"] = jsonable_params(run.state.params)
        else:
            theta = run.state.term_params[term.key]["theta"]
            run.steps[-1]["params"] = {term.key: _term_step_params(run.state, term)}
            run.steps[-1]["explanation"] = term.describe(theta, run.robot.wheel_radius)
    run.steps[-1]["channel_weights_after"] = dict(zip(CHANNELS, map(float, run.aug.weights), strict=True))


def _result(run: _Search, base_name: str, t_start: float) -> TerrainDiscovery:
    """The search's outcome: the message naming what was found (or that nothing was), the final model
    with its held-out errors, and everything recorded on the way (``t_start``: perf_counter at the start)."""
    found = run.effects + [t.key for t in run.terms]
    named = [
        st["effect"] + ("" if st["kind"] == "catalogue" else f" [{st['explanation']}]") for st in run.steps
    ]
    message = NO_EFFECT_MESSAGE if not found else "missing effect(s) found: " + ", ".join(named)
    if found and len(found) < run.settings.max_effects:
        message += "; no further effect earns its place"
    run.say(f"[{run.terrain}] {message}")
    state, cur = run.state, run.cur
    final = {
        "effects": list(run.effects),
        "terms": [t.key for t in run.terms],
        "params": jsonable_params(state.params),
        "term_params": {t.key: _term_step_params(state, t) for t in run.terms},
        "base_params": state.base.get_params(),
        "heldout_rmsre": cur.rmsre,
        "heldout_mse": dict(zip(CHANNELS, map(float, cur.mse), strict=True)),
    }
    return TerrainDiscovery(
        run.terrain,
        base_name,
        run.effects,
        run.steps,
        run.base_info,
        final,
        message,
        run.figure_data,
        run.rejected,
        time.perf_counter() - t_start,
        [t.key for t in run.terms],
        run.unexplained,
        selected_on(run.pool, run.settings),
    )


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
    as unexplained with its size and its strongest correlates. ``factory()``: a fresh base model;
    ``progress``: where the progress lines go (default: the ``skidbench.discover`` logger)."""
    t_start = time.perf_counter()
    say = progress or (lambda msg: log.info(msg))
    run = _fit_base(pool, factory, robot, settings, terrain, base_name, say)
    while len(run.effects) + len(run.terms) < settings.max_effects:
        scored = _score_catalogue(run, candidates)
        scored_t, screen_info, scr = _score_terms(run)
        evidence = {
            "candidates": {e: _evidence_row(ev) for e, (ev, _) in scored.items()},
            "terms": {k: _evidence_row(ev) for k, (ev, _, _) in scored_t.items()},
            "screen": screen_info,
        }
        choice = _choose(run, scored, scored_t, evidence["terms"], scr)
        if choice is None:
            _report_unexplained(run, scored, scored_t, evidence)
            break
        kind, name = choice
        if kind == "catalogue":
            ho, term = _add_effect(run, name, scored, scored_t, evidence), None
        else:
            ho, term = _add_term(run, name, scored, scored_t, evidence)
        _accept(run, name, kind, ho)
        _reweight(run, kind, term)
    return _result(run, base_name, t_start)
