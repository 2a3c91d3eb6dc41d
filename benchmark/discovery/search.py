"""The search's state and how a step scores its candidates (:mod:`skidbench.benchmark.discovery.discover`):
the base
model fitted and held out, every catalogue effect added to the current model and held out, and the library
forms that a majority of the folds' own screens select, each held out with its fold's knots."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from skidbench.benchmark.discovery.stats import (
    HeldOut,
    channels_of,
    compare,
    cross_validate,
    folds_of,
    training_rows,
)
from skidbench.benchmark.discovery.term_screen import FoldScreens, screen
from skidbench.models.augmented import terms as termlib
from skidbench.models.augmented.effects import CATALOGUE, INPUT_BOUNDS, family_of
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

Scored = dict[str, tuple[dict[str, Any], HeldOut]]  # catalogue effect -> (evidence, held-out evaluation)
#: library form -> (evidence, held-out evaluation, the form (no knots), each fold's term with its knots)
ScoredTerms = dict[str, tuple[dict[str, Any], HeldOut, termlib.Term, list[termlib.Term]]]


@dataclass
class Search:
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
    calibration: dict[str, Any] | None = None  # the speed scale found first (discover.ask_speed_scale)
    too_small: dict[str, dict[str, Any]] = field(default_factory=dict)  # detected, too small to act on
    one_metric: dict[str, dict[str, Any]] = field(default_factory=dict)  # detected, worse on the other metric
    dropped: list[dict[str, Any]] = field(default_factory=list)  # names re-tested out of the model
    excluded: tuple[str, ...] = ()  # library forms not searched (a placebo's command-free forms)


def show(run: Search, name: str, ev: dict[str, Any]) -> None:
    """One progress line: a candidate's held-out gains, its own and its search-wide p-value, and whether
    it passes the rule (or passed the statistics but not the practical check)."""
    verdict = "PASS" if ev["passes"] else "detected, one metric worse" if ev.get("one_metric") else ""
    verdict = verdict or ("detected, too small" if ev.get("too_small") else "")
    run.say(
        f"[{run.terrain}]   {name:28s} gain {ev['heldout_gain']:+.4f} (penalised "
        f"{ev['penalised_gain']:+.4f}) p={ev['paired_p_value']:.3g} p_search={ev.get('p_search', 1.0):.3g} "
        f"velocity gain {ev['velocity_gain']:+.4f}{'' if ev['stable_across_folds'] else ' unstable'}"
        f"{'  ' + verdict if verdict else ''}"
    )


def practical_check(run: Search, ev: dict[str, Any]) -> None:
    """A name must matter to a lab, on both 6 s metrics (``discover.min_share``, ``discover.min_points``):
    in one of them it cuts the held-out error that remains by at least ``min_share`` of it and by at least
    ``min_points`` (fractions of RMSRE), and it makes neither worse by as much (a rise of at least
    ``min_share`` of the error and ``min_points``: a change a lab would see). A candidate that passes the
    statistical rule but gains too little is "detected, too small to act on" (``too_small``); one that
    gains on one metric and costs as much on the other is "detected, does not help both metrics"
    (``one_metric``); neither is added. ``passes`` is updated in place."""
    s = run.settings
    b, a = ev["heldout_rmsre_before"], ev["heldout_rmsre_after"]
    drops = {m: (b[m] - a[m], (b[m] - a[m]) / max(b[m], 1e-12)) for m in ("translational", "rotational")}
    gains = any(d >= s.min_points and r >= s.min_share for d, r in drops.values())
    worse = [m for m, (d, r) in drops.items() if -d >= s.min_points and -r >= s.min_share]
    ok = gains and not worse
    ev["practical"] = {m: {"points": 100 * d, "share": r} for m, (d, r) in drops.items()}
    ev["practical"] |= {"ok": ok, "worse": worse}
    ev["detected"] = bool(ev["passes"])
    if ev["passes"] and not ok:
        ev["passes"] = False
        ev["one_metric" if gains else "too_small"] = True
    return None


def evidence_row(ev: dict[str, Any]) -> dict[str, Any]:
    """A candidate's evidence as the step's table of candidates records it."""
    return {k: v for k, v in ev.items() if k != "heldout_mse_before"}


def fit_base(
    pool: Pool,
    factory: ModelFactory,
    robot: Robot,
    settings: DiscoverSettings,
    terrain: str,
    base_name: str,
    say: Callable[[str], None],
) -> Search:
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
        "command_alignment_s": dict(pool.alignment),  # align_commands: each sequence's command shift
    }
    if pool.note:
        say(f"[{terrain}] note: {pool.note}")
    say(
        f"[{terrain}] base {base_name}: held-out {settings.horizon_s:g} s RMSRE "
        f"trans {cur.rmsre['translational']:.4f} rot {cur.rmsre['rotational']:.4f} "
        f"({pool.n_units} held-out units from {len(pool.sequences)} sequences)"
    )
    return Search(pool, aug, robot, settings, terrain, say, all_units, base_fit, cur, base_info)


def score_catalogue(run: Search, candidates: tuple[str, ...]) -> Scored:
    """Every catalogue effect of ``candidates`` not yet in the model, added to it, fitted fold by fold and
    scored held out against the current model."""
    scored: Scored = {}
    for eid in candidates:
        if eid in run.effects or (eid in INPUT_BOUNDS and any(e in INPUT_BOUNDS for e in run.effects)):
            continue  # one input transform at most
        if (
            eid == "actuator_dead_time"
            and not scored.get("actuator_lag", ({"rule_ok": False},))[0]["rule_ok"]
        ):
            continue  # the dead time is scored against the lag only when the lag earns its place
        ho = cross_validate(run.aug, run.effects + [eid], run.warm, run.terms)
        scored[eid] = (compare(run.cur, ho, CATALOGUE[eid].n_params, run.settings), ho)
    return scored


def excluded_forms(run: Search) -> tuple[str, ...]:
    """Library forms not searched: the terms already added, the equivalents of the catalogue effects
    already added (the same residual under another name) and, when the held-out units are time blocks
    of a few sequences, the forms that are functions of sequence time (:func:`terms.time_forms`: blocks
    of one sequence share its ground truth's slow drift, so they cannot test a change over time), and
    the forms of a speed scale (``terms.SCALE_FORMS``: the calibration's question, asked first)."""
    eq = [f for e in run.effects for f in termlib.equivalent_forms(family_of(e))]
    timed = termlib.time_forms() if run.pool.blocks else []
    return tuple(t.form for t in run.terms) + tuple(eq) + tuple(timed) + termlib.SCALE_FORMS + run.excluded


def fold_screens(run: Search) -> FoldScreens:
    """The library screened once per fold, each on its training units only: the current model fitted on
    them (as :func:`cross_validate` fits it) and the sparse regression on what it leaves there. A form
    is a candidate when a majority of the folds select it, and each fold's held-out evaluation uses the
    knots its own screen chose, so no held-out unit takes part in choosing what it is scored on."""
    pool, aug = run.pool, run.aug
    screens = []
    for held in folds_of(pool, run.settings.folds):
        train = np.setdiff1d(np.arange(pool.n_units), held)
        rows = training_rows(pool, held, run.settings.horizon_s)
        st = aug.fit(run.effects, train, run.warm, fixed_tau=True, terms=run.terms, rows=rows)
        sig = aug.signals(st.feats, st.base_pred)
        screens.append(
            screen(
                sig,
                termlib.base_gains(sig, rows),
                run.robot.track_width,
                pool.target - st.pred,
                rows,
                aug.weights,
                exclude=excluded_forms(run),
                max_candidates=run.settings.max_terms,
            )
        )
    return FoldScreens(screens, min_folds=len(screens) // 2 + 1)


def score_form(run: Search, fs: FoldScreens, template: termlib.Term, scored_t: ScoredTerms) -> None:
    """One library form added to the current model in the folds whose own screen chose it (with that
    screen's knots; a fold that did not choose it predicts its held-out units with the current model: the
    candidate set is chosen within each fold from its training units only), scored held out against the
    current model (into ``scored_t``)."""
    fold_terms = fs.fold_selected(template)
    if not any(fold_terms):  # a rival no fold chose: scored with every fold's knots
        fold_terms = fs.fold_terms(template)
    ho = cross_validate(run.aug, run.effects, run.warm, run.terms, fold_terms=fold_terms)
    ev = compare(run.cur, ho, template.n_params_with_knots, run.settings, template.touched, "candidate_term")
    ev["fold_votes"] = fs.votes(template.form)
    ev["fold_knots"] = [None if t is None else list(t.knots) for t in fold_terms]
    scored_t[template.form] = (ev, ho, template, fold_terms)


def score_terms(run: Search) -> tuple[ScoredTerms, dict[str, Any], FoldScreens | None]:
    """The open-ended terms (``discover.open_ended``): the forms a majority of the folds' screens select
    (:func:`fold_screens`), at most ``max_terms``, each scored held out like a catalogue effect.
    Returns the scores, what the screens selected (for the record) and the screens (none when off)."""
    scored_t: ScoredTerms = {}
    if not run.settings.open_ended:
        return scored_t, {}, None
    fs = fold_screens(run)
    stable = fs.stable(run.settings.max_terms)
    screen_info = {
        "fold_supports": [sc.selected for sc in fs.screens],
        "candidates": [t.form for t in stable],
        "min_folds": fs.min_folds,
    }
    for template in stable:
        score_form(run, fs, template, scored_t)
    return scored_t, screen_info, fs


def score_rival(run: Search, best_c: str, scored_t: ScoredTerms, fs: FoldScreens) -> None:
    """The catalogue's best must beat the library's best form of no more parameters on its channels
    (best mean share over the folds' screens): that rival, when not scored yet, is scored too."""
    chans = tuple(CHANNELS.index(c) for c in channels_of(best_c))
    rival = fs.best_rival(chans, CATALOGUE[best_c].n_params, tuple(scored_t) + excluded_forms(run))
    if rival is not None:
        score_form(run, fs, rival, scored_t)


def term_step_params(state: FitState, term: termlib.Term) -> dict[str, float]:
    """A term's fitted constants as its step records them: theta and its knots (``knot0``, ...)."""
    p = dict(state.term_params[term.key])
    for i, k in enumerate(term.knots):
        p[f"knot{i}"] = float(k)
    return p


def reweight(run: Search, kind: str, term: termlib.Term | None) -> None:
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
            run.steps[-1]["params"] = {term.key: term_step_params(run.state, term)}
            run.steps[-1]["explanation"] = term.describe(theta, run.robot.wheel_radius)
    run.steps[-1]["channel_weights_after"] = dict(zip(CHANNELS, map(float, run.aug.weights), strict=True))
