"""Discrepancy discovery: find where a model and the measured data disagree and name the missing
physical effect (SPEC.md "Discrepancy discovery").

Workflow, per terrain, on the Train split only (the test splits are never read):

0. The pool: the Train sequences, each a held-out unit (time blocks of them when there are fewer than
   ``min_units``; a terrain too small for the test is refused), the commands aligned with the grid
   (``discover_pool.align_commands``: the split's hold of 45 Hz commands on its 30 Hz grid is up to a quarter
   command period older or younger than what the velocities see).
1. Fit the base model (default: extended differential drive, ``edd``) and take its residuals: body
   velocities (vx, vy, wz) against ground truth, and 6 s horizon pose errors (RMSRE).
2. For every effect of the catalogue (:mod:`skidbench.models.augmented.effects`) not yet in the model, fit the
   augmented model (base model refitted together with the effect's parameters, by alternation) on the
   training folds and predict the held-out fold; likewise the library terms
   (:mod:`skidbench.models.augmented.terms`)
   that a majority of the folds' own screens select, each fold with its own knots.
3. Score each candidate against the current model on the held-out predictions, and every candidate of the
   step together by the search-wide test (the best of them against what a dataset with nothing missing
   gives).
4. Add the best candidate that passes (a catalogue name unless a term is significantly better), refit,
   and repeat; stop when none passes ("no missing effect found").

This module runs the steps and records them; the pool (step 0) is :mod:`skidbench.benchmark.discovery.pool`,
the scoring of a step's candidates :mod:`skidbench.benchmark.discovery.search`, the choice of the name
:mod:`skidbench.benchmark.discovery.naming`, the held-out evaluation and the significance rule
:mod:`skidbench.benchmark.discovery.stats`, the figure data :mod:`skidbench.benchmark.discovery.panels`.

Effects keep their physical direction (parameter bounds in the catalogue: slips are shortfalls, the
side slip is outward, chi grows in tight turns, the turn deficit grows with speed).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import minimize, minimize_scalar

from skidbench.benchmark.discovery.naming import best_catalogue, choose, naming_record
from skidbench.benchmark.discovery.panels import residual_panel, term_panel, unexplained_panels
from skidbench.benchmark.discovery.pool import selected_on
from skidbench.benchmark.discovery.search import (
    Scored,
    ScoredTerms,
    Search,
    evidence_row,
    fit_base,
    score_catalogue,
    score_rival,
    score_terms,
    show,
)
from skidbench.benchmark.discovery.stats import HeldOut, cross_validate, search_test
from skidbench.models.augmented import terms as termlib
from skidbench.models.augmented.effects import CATALOGUE, EFFECT_IDS
from skidbench.models.augmented.fit import (
    CHANNELS,
    Augmenter,
    DiscoverSettings,
    FitState,
    ModelFactory,
    Pool,
    channel_weights,
    jsonable_params,
)
from skidbench.pipeline.core.robot import Robot

log = logging.getLogger("skidbench.discover")

NO_EFFECT_MESSAGE = "no missing effect found"


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
    terms: list[str] = field(
        default_factory=list
    )  # open-ended terms added (keys of models/augmented/terms.py)
    unexplained: dict[str, Any] | None = None  # what is left when nothing more passes
    selected_on: dict[str, Any] = field(default_factory=dict)  # the splits, sequences and units searched
    refused: str | None = None  # why no search was run (a pool too small for the test)


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
    them against the base model fitted without the term, which has absorbed part of the effect), on the
    fit loss over ``units`` (the training rows), within +-``rel`` of the screened values: one knot by a
    bounded scalar search; two together by a bounded Nelder-Mead search in knot / screened knot. Two
    knots trade off (a load limit ``k0 - k1 |w|`` is pinned where its rows are, at |w| near 2 rad/s), and a
    scalar search per knot in turn stopped on that valley short of its floor: 12.6 and 1.8 rad/s for the
    injected 13 and 2, at a loss the joint optimum (13.0 and 1.97) beat (docs/discovery.md)."""
    if not term.knots:
        return term
    k0 = np.asarray(term.knots, float)

    def loss(x) -> float:
        kn = [float(v) for v in k0 * np.asarray(x, float)]
        return aug.fit(effects, units, warm, fixed_tau=True, terms=[*terms, term.with_knots(kn)]).loss

    start = loss(np.ones(len(k0)))
    if len(k0) == 1:
        res = minimize_scalar(
            lambda x: loss([x]), bounds=(1 - rel, 1 + rel), method="bounded", options={"maxiter": maxiter}
        )
        x, fun = np.array([res.x]), float(res.fun)
    else:
        res = minimize(
            loss,
            np.ones(len(k0)),
            method="Nelder-Mead",
            bounds=[(1 - rel, 1 + rel)] * len(k0),
            options={"xatol": 1e-3, "fatol": 1e-7 * abs(start), "maxfev": 2 * maxiter * len(k0) + 20,
                     "initial_simplex": np.vstack([np.ones(len(k0)), 1 + 0.05 * np.eye(len(k0))])},
        )  # fmt: skip
        x, fun = np.asarray(res.x, float), float(res.fun)
    if fun < start:
        return term.with_knots([float(v) for v in k0 * x])
    return term


def _term_step_params(state: FitState, term: termlib.Term) -> dict[str, float]:
    p = dict(state.term_params[term.key])
    for i, k in enumerate(term.knots):
        p[f"knot{i}"] = float(k)
    return p


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


def _report_unexplained(run: Search, scored: Scored, scored_t: ScoredTerms, evidence: dict[str, Any]) -> None:
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
    run: Search,
    name: str,
    scored: Scored,
    scored_t: ScoredTerms,
    evidence: dict[str, Any],
    equivalents: list[dict],
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
            "naming": naming_record("catalogue", ev, scored_t, scored, e.n_params, equivalents),
            "params": jsonable_params(run.state.params),
            "heldout_rmsre_before": run.cur.rmsre,
            "heldout_rmsre_after": ho.rmsre,
        }
    )
    if equivalents:
        run.say(f"[{run.terrain}]   {name}: equivalent terms " + ", ".join(q["term"] for q in equivalents))
    run.figure_data.append(residual_panel(run.pool, prev_state, name, run.cur, run.state))
    return ho


def _add_term(
    run: Search, name: str, scored: Scored, scored_t: ScoredTerms, evidence: dict[str, Any]
) -> tuple[HeldOut, termlib.Term]:
    """Add the library form ``name``: its knots (the median of the folds' screens) refined with the model
    on every training unit, refit, record the step (the term described with its constants; the evidence
    is the one the choice was made on, each fold with its own knots) and its panel. Returns the held-out
    evaluation of the model as added (the knots fixed) and the term."""
    ev, ho, template, fold_terms = scored_t[name]
    term = template
    if fold_terms and fold_terms[0].knots:
        term = template.with_knots(np.median([t.knots for t in fold_terms], axis=0))
        term = refine_knots(run.aug, run.effects, run.warm, run.terms, term, run.all_units)
        ho = cross_validate(run.aug, run.effects, run.warm, run.terms + [term])
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
            "formula": f"{'vx, wz' if term.channel < 0 else CHANNELS[term.channel]} += "
            + ("g at the wheel radius theta r, " if term.family in termlib.RADIUS_HINGES else "theta * g, ")
            + f"g = {term.key}",
            "evidence": {**ev, **evidence},
            "naming": naming_record("term", ev, scored_t, scored, term.n_params, []),
            "params": {term.key: _term_step_params(run.state, term)},
            "heldout_rmsre_before": run.cur.rmsre,
            "heldout_rmsre_after": ho.rmsre,
        }
    )
    run.figure_data.append(term_panel(run.pool, prev_state, term, run.cur, run.state, run.aug))
    return ho, term


def _accept(run: Search, name: str, kind: str, ho: HeldOut) -> None:
    """The added candidate's held-out evaluation becomes the current model's; the gap it closed is
    reported."""
    cur = run.cur
    run.say(
        f"[{run.terrain}] + {name}: held-out RMSRE trans {cur.rmsre['translational']:.4f} -> "
        f"{ho.rmsre['translational']:.4f}, rot {cur.rmsre['rotational']:.4f} -> "
        f"{ho.rmsre['rotational']:.4f}" + (f" ({run.steps[-1]['explanation']})" if kind == "term" else "")
    )
    run.cur = ho


def _reweight(run: Search, kind: str, term: termlib.Term | None) -> None:
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


def _result(run: Search, base_name: str, t_start: float) -> TerrainDiscovery:
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
    """Catalogue effects and open-ended terms (:mod:`skidbench.models.augmented.terms`) scored side by side on
    the same held-out units by the same rule; the best passing one is added, except that a catalogue
    effect is named only when no open-ended term of no more parameters explains more of the held-out
    gap (then the term is added under its own formula). When nothing passes, the residual is reported
    as unexplained with its size and its strongest correlates. ``factory()``: a fresh base model;
    ``progress``: where the progress lines go (default: the ``skidbench.discover`` logger)."""
    t_start = time.perf_counter()
    say = progress or (lambda msg: log.info(msg))
    run = fit_base(pool, factory, robot, settings, terrain, base_name, say)
    while len(run.effects) + len(run.terms) < settings.max_effects:
        scored = score_catalogue(run, candidates)
        scored_t, screen_info, fs = score_terms(run)
        best_c = best_catalogue(scored)
        if best_c is not None and fs is not None:
            score_rival(run, best_c, scored_t, fs)
        # the search-wide test: every candidate of the step against the best a clean dataset would give
        every = {**{e: v[0] for e, v in scored.items()}, **{k: v[0] for k, v in scored_t.items()}}
        search_test(every, settings)
        for name, v in [*scored.items(), *scored_t.items()]:
            show(run, name, v[0])
        evidence = {
            "candidates": {e: evidence_row(v[0]) for e, v in scored.items()},
            "terms": {k: evidence_row(v[0]) for k, v in scored_t.items()},
            "screen": screen_info,
        }
        choice = choose(run, scored, scored_t)
        if choice is None:
            _report_unexplained(run, scored, scored_t, evidence)
            break
        kind, name, equivalents = choice
        if kind == "catalogue":
            ho, term = _add_effect(run, name, scored, scored_t, evidence, equivalents), None
        else:
            ho, term = _add_term(run, name, scored, scored_t, evidence)
        _accept(run, name if kind == "catalogue" else term.key, kind, ho)
        _reweight(run, kind, term)
    return _result(run, base_name, t_start)
