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

from skidbench.benchmark.discovery.checks.ground_truth import ground_truth_findings
from skidbench.benchmark.discovery.checks.scale import ask_speed_scale, restate_scale
from skidbench.benchmark.discovery.naming import best_catalogue, choose, keep_best_members, naming_record
from skidbench.benchmark.discovery.panels import residual_panel, term_panel, unexplained_panels
from skidbench.benchmark.discovery.pool import selected_on
from skidbench.benchmark.discovery.search import (
    Scored,
    ScoredTerms,
    Search,
    evidence_row,
    fit_base,
    practical_check,
    reweight,
    score_catalogue,
    score_rival,
    score_terms,
    show,
    term_step_params,
)
from skidbench.benchmark.discovery.stats import HeldOut, compare, cross_validate, search_test
from skidbench.models.augmented import terms as termlib
from skidbench.models.augmented.effects import (
    CATALOGUE,
    EFFECT_IDS,
    INPUT_BOUNDS,
    SPEED_SCALE,
    family_of,
    members,
)
from skidbench.models.augmented.fit import (
    CHANNELS,
    Augmenter,
    DiscoverSettings,
    FitState,
    ModelFactory,
    Pool,
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
    calibration: dict[str, Any] | None = None  # the speed scale found (the effective wheel radius)
    placebo: dict[str, Any] | None = None  # the placebo check's outcome (discover_app.placebo)


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
    injected 13 and 2, at a loss the joint optimum (13.0 and 1.97) beat (CHANGELOG.md, "Discovery")."""
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
            "effect": family_of(name),
            "member": name,
            "kind": "catalogue",
            "explanation": e.explanation + _delay_note(name, run.state),
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


def _delay_note(name: str, state: FitState) -> str:
    """What a lag found from commands and poses alone may also be: its time constant is the delay of the
    response, and without wheel encoders a motor lag, a dead time in the drive and an offset between the
    commands' and the poses' clocks move the poses alike (a 30 ms clock offset was named as a 20 ms lag)."""
    if name not in INPUT_BOUNDS:
        return ""
    tau = float(state.params[name][0])
    return (
        f" Found from commands and poses: a delay of about {1000 * tau:.0f} ms, which may be a dead time or "
        "a clock offset between the commands and the poses as well as a lag (without wheel encoders "
        "these look the same: check the clocks)."
    )


def _add_term(
    run: Search, name: str, scored: Scored, scored_t: ScoredTerms, evidence: dict[str, Any]
) -> tuple[HeldOut, termlib.Term]:
    """Add the library form ``name``: its knots (the median of the folds' screens) refined with the model
    on every training unit, refit, record the step (the term described with its constants; the evidence
    is the one the choice was made on, each fold with its own knots) and its panel. Returns the held-out
    evaluation of the model as added (the knots fixed) and the term."""
    ev, ho, template, fold_terms = scored_t[name]
    term = template
    chosen = [t for t in fold_terms if t is not None]
    if chosen and chosen[0].knots:
        term = template.with_knots(np.median([t.knots for t in chosen], axis=0))
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
            "params": {term.key: term_step_params(run.state, term)},
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


def _result(run: Search, base_name: str, t_start: float) -> TerrainDiscovery:
    """The search's outcome: the message naming what was found (or that nothing was), the final model
    with its held-out errors, and everything recorded on the way (``t_start``: perf_counter at the start)."""
    effects = [family_of(e) for e in run.effects if e != SPEED_SCALE]
    found = effects + [t.key for t in run.terms]
    named = [
        st["effect"] + ("" if st["kind"] == "catalogue" else f" [{st['explanation']}]")
        for st in run.steps
        if st["kind"] != "calibration"
    ]
    message = NO_EFFECT_MESSAGE if not found else "missing effect(s) found: " + ", ".join(named)
    if found and len(found) < run.settings.max_effects:
        message += "; no further effect earns its place"
    if run.calibration:
        message = f"calibration: {run.calibration['text']}; " + message
    restated = run.base_info.get("speed_scale_check", {}).get("final")
    if restated and not restated["holds"]:
        message = f"calibration: {restated['text']}; " + message
    by_speed = run.base_info.get("speed_scale_check", {}).get("by_speed", {})
    if not by_speed.get("proportional", True):
        message = f"speed deficit: {by_speed['text']}; " + message
    run.say(f"[{run.terrain}] {message}")
    state, cur = run.state, run.cur
    final = {
        "effects": effects,
        "model_effects": list(run.effects),  # the members as fitted (the discovered model's spec)
        "terms": [t.key for t in run.terms],
        "params": jsonable_params(state.params),
        "term_params": {t.key: term_step_params(state, t) for t in run.terms},
        "base_params": state.base.get_params(),
        "heldout_rmsre": cur.rmsre,
        "heldout_mse": dict(zip(CHANNELS, map(float, cur.mse), strict=True)),
    }
    return TerrainDiscovery(
        run.terrain,
        base_name,
        effects,
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
        calibration=run.calibration,
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
    exclude_forms: tuple[str, ...] = (),
) -> TerrainDiscovery:
    """Catalogue effects and open-ended terms (:mod:`skidbench.models.augmented.terms`) scored side by side on
    the same held-out units by the same rule; the best passing one is added, except that a catalogue
    effect is named only when no open-ended term of no more parameters explains more of the held-out
    gap (then the term is added under its own formula). When nothing passes, the residual is reported
    as unexplained with its size and its strongest correlates. ``factory()``: a fresh base model;
    ``progress``: where the progress lines go (default: the ``skidbench.discover`` logger);
    ``exclude_forms``: library forms not searched (the placebo's command-free forms)."""
    t_start = time.perf_counter()
    say = progress or (lambda msg: log.info(msg))
    pool, gt_findings = ground_truth_findings(pool)
    for f in gt_findings:
        say(f"[{terrain}] {f['text']}")
    run = fit_base(pool, factory, robot, settings, terrain, base_name, say)
    run.base_info["ground_truth"] = gt_findings
    run.excluded = tuple(exclude_forms)
    ask_speed_scale(run)
    while len(run.effects) + len(run.terms) < settings.max_effects + (SPEED_SCALE in run.effects):
        if not _step(run, members(candidates)):
            break
        _retest(run)
    restate_scale(run)
    run.base_info["too_small"] = list(run.too_small.values())
    run.base_info["one_metric"] = list(run.one_metric.values())
    run.base_info["dropped"] = run.dropped
    return _result(run, base_name, t_start)


def _step(run: Search, candidates: tuple[str, ...]) -> bool:
    """One step of the search: every candidate scored, tested and checked; the one chosen added (True),
    or, when none passes, the residual reported unexplained (False)."""
    scored = score_catalogue(run, candidates)
    scored_t, screen_info, fs = score_terms(run)
    best_c = best_catalogue(scored)
    if best_c is not None and fs is not None:
        score_rival(run, best_c, scored_t, fs)
    # the search-wide test: every candidate of the step against the best a clean dataset would give
    every = {**{e: v[0] for e, v in scored.items()}, **{k: v[0] for k, v in scored_t.items()}}
    search_test(every, run.settings)
    for name, ev in every.items():
        practical_check(run, ev)
        show(run, name, ev)
        if ev.get("too_small") or ev.get("one_metric"):
            kept = run.one_metric if ev.get("one_metric") else run.too_small
            kept[family_of(name)] = _detected_row(family_of(name), ev)
    evidence = {
        "candidates": {e: evidence_row(v[0]) for e, v in scored.items()},
        "terms": {k: evidence_row(v[0]) for k, v in scored_t.items()},
        "screen": screen_info,
    }
    family_rivals = keep_best_members(scored)
    choice = choose(run, scored, scored_t, family_rivals)
    if choice is None:
        _report_unexplained(run, scored, scored_t, evidence)
        return False
    kind, name, equivalents = choice
    if kind == "catalogue":
        ho, term = _add_effect(run, name, scored, scored_t, evidence, equivalents), None
    else:
        ho, term = _add_term(run, name, scored, scored_t, evidence)
    for kept in (run.too_small, run.one_metric):
        kept.pop(family_of(name) if kind == "catalogue" else term.form, None)
    _accept(run, name if kind == "catalogue" else term.key, kind, ho)
    reweight(run, kind, term)
    return True


def _detected_row(name: str, ev: dict[str, Any]) -> dict[str, Any]:
    """A candidate that passed the statistical rule but not the practical check (:func:`practical_check`):
    too small to act on, or worse on one 6 s metric by as much as a name must gain (``worse``)."""
    pr = ev["practical"]
    what = (
        f"detected, does not help both metrics ({' and '.join(pr['worse'])} worse)"
        if ev.get("one_metric")
        else "detected, too small to act on"
    )
    return {
        "name": name,
        "heldout_gain": ev["heldout_gain"],
        "p_search": ev.get("p_search"),
        "points": {m: pr[m]["points"] for m in ("translational", "rotational")},
        "share": {m: pr[m]["share"] for m in ("translational", "rotational")},
        "worse": list(pr.get("worse", [])),
        "text": f"{name}: {what} (held-out 6 s RMSRE "
        + ", ".join(f"{m} {-pr[m]['points']:+.3f} points ({-100 * pr[m]['share']:+.1f} %)"
                    for m in ("translational", "rotational")) + ")",
    }  # fmt: skip


def _retest(run: Search) -> None:
    """After an addition, every name taken before it is tested again in the refitted model: held out
    without it against the model as it is (its own sign-flip test, the rule's checks and the practical
    minimum); one that no longer earns its place (a parameter refitted to its no-effect value, or a model
    as good without it) is dropped and the model refitted. The calibration finding stays."""
    s = run.settings
    last = run.steps[-1].get("member", run.steps[-1]["effect"])
    names = [e for e in run.effects if e not in (SPEED_SCALE, last)] + [
        t.key for t in run.terms if t.key != last
    ]
    for name in names:
        term = next((t for t in run.terms if t.key == name), None)
        effects = [e for e in run.effects if e != name]
        terms = [t for t in run.terms if t is not term]
        p = run.state.params.get(name)
        at_zero = (
            term is None and name not in INPUT_BOUNDS and p is not None and bool(np.all(np.abs(p) < 1e-9))
        )
        if not at_zero:
            ho = cross_validate(run.aug, effects, run.warm, terms)
            touched = term.touched if term else tuple(CATALOGUE[name].channels)
            n = term.n_params_with_knots if term else CATALOGUE[name].n_params
            ev = compare(ho, run.cur, n, s, touched, name)
            ev["passes"] = bool(ev["rule_ok"] and ev["paired_p_value"] <= s.alpha)
            practical_check(run, ev)
            if ev["passes"]:
                continue
        why = (
            "its parameter refitted to 0" if at_zero else "the model is as good without it on held-out units"
        )
        run.say(f"[{run.terrain}]   {name} re-tested after {run.steps[-1]['effect']}: dropped ({why})")
        run.dropped.append(
            {"name": family_of(name), "member": name, "after_step": len(run.steps), "why": why}
        )
        for st in run.steps:
            if st.get("member", st["effect"]) == name:
                st["dropped"] = why
        run.effects, run.terms = effects, terms
        run.warm.pop(name, None)
        run.state = run.aug.fit(run.effects, run.all_units, run.warm, terms=run.terms)
        run.warm = dict(run.state.params)
        run.cur = cross_validate(run.aug, run.effects, run.warm, run.terms)
