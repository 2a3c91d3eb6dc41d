"""Discrepancy discovery: find where a model and the measured data disagree and name the missing
physical effect (SPEC.md "Discrepancy discovery").

Workflow, per terrain, on the Train split only (the test splits are never read):

0. The pool: the Train sequences, each a held-out unit (time blocks of them when there are fewer than
   ``min_units``; a terrain too small for the test is refused), the commands aligned with the grid
   (:func:`align_commands`: the split's hold of 45 Hz commands on its 30 Hz grid is up to a quarter
   command period older or younger than what the velocities see).
1. Fit the base model (default: extended differential drive, ``edd``) and take its residuals: body
   velocities (vx, vy, wz) against ground truth, and 6 s horizon pose errors (RMSRE).
2. For every effect of the catalogue (:mod:`skidbench.models.effects`) not yet in the model, fit the
   augmented model (base model refitted together with the effect's parameters, by alternation) on the
   training folds and predict the held-out fold; likewise the library terms (:mod:`skidbench.models.terms`)
   that a majority of the folds' own screens select, each fold with its own knots.
3. Score each candidate against the current model on the held-out predictions, and every candidate of the
   step together by the search-wide test (the best of them against what a dataset with nothing missing
   gives).
4. Add the best candidate that passes (a catalogue name unless a term is significantly better), refit,
   and repeat; stop when none passes ("no missing effect found").

The held-out evaluation and the significance rule are in :mod:`skidbench.benchmark.discover_stats`; the
figure data in :mod:`skidbench.benchmark.discover_panels`.

Effects keep their physical direction (parameter bounds in the catalogue: slips are shortfalls, the
side slip is outward, chi grows in tight turns, the turn deficit grows with speed).
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
    folds_of,
    search_test,
    sign_flip_pvalue,
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


def align_commands(pool: Pool, robot: Robot) -> Pool:
    """The pool with each sequence's commands shifted by the timing error of their association with the
    grid (``cmd_association.offset_s`` of its split metadata, :mod:`skidbench.pipeline.splits.build`):
    the wheel commands read at ``t + offset`` (linear interpolation between grid samples, the ends held),
    ``cmd_v``/``cmd_w`` recomputed from them with the robot's ideal kinematics (as the split does) and
    their derivatives taken as the split takes them. Without it a commensurate command rate (45 Hz on the
    30 Hz grid) shows as a lag or a lead of up to a quarter command period, which the search would name
    (``lin.dw*|v|.wz`` for a lead: the catalogue's slips only take a lag). Sequences without the record
    are left as they are, and ``pool.note`` names them; ``pool.alignment`` lists what was applied."""
    table = pool.table.copy()
    applied, unrecorded = {}, []
    for g, meta in enumerate(pool.metas):
        rec = (meta or {}).get("cmd_association")
        if not rec:
            unrecorded.append(pool.sequences[g])
        off = float((rec or {}).get("offset_s") or 0.0)
        if off == 0.0:
            continue
        rows = np.flatnonzero(pool.groups == g)
        t = pool.t[rows]
        wl = np.interp(t + off, t, table["cmd_wl"].to_numpy(float)[rows])
        wr = np.interp(t + off, t, table["cmd_wr"].to_numpy(float)[rows])
        v, w = robot.twist_from_wheel_rates(wl, wr)  # (linear: the same as shifting cmd_v, cmd_w)
        cols = {"cmd_v": v, "cmd_w": w, "cmd_wl": wl, "cmd_wr": wr}
        if len(t) >= 2:
            cols |= {"cmd_dwl": np.gradient(wl, t), "cmd_dwr": np.gradient(wr, t)}
        for c, x in cols.items():
            table.loc[rows, c] = x
        applied[pool.sequences[g]] = off
    note = pool.note
    if unrecorded:  # split files written before the split recorded it
        note += (
            f"; commands not aligned with the grid in {len(unrecorded)} sequence(s) whose split file has "
            f"no cmd_association record (e.g. {unrecorded[0]}; `skidbench split` writes it)"
        )
    return dataclasses.replace(pool, table=table, alignment=applied, note=note)


def apply_protocol(pool: Pool, protocol: str, robot: Robot, response: Any = None) -> Pool:
    """The pool with its inputs replaced by those of the input protocol (pipeline/protocol.py), computed
    per original sequence (``pool.groups``), targets and held-out units kept: discovery then searches
    what the base model misses given the protocol's inputs (under ``response`` the wheel response is
    given, so ``actuator_lag`` has nothing left to explain)."""
    table = fit_table(pool.table.assign(sequence=pool.groups), protocol, robot, response)
    table["sequence"] = pool.units
    return dataclasses.replace(pool, table=table)


def prepare_pool(pool: Pool, inputs: str, robot: Robot, response: Any = None) -> Pool:
    """The pool as the search sees it under the input protocol ``inputs``: the commands aligned with
    the grid (:func:`align_commands`) under ``commanded``; the protocol's inputs otherwise
    (:func:`apply_protocol`: the calibrated wheel response already holds the association's timing, the
    encoders have none)."""
    if inputs == "commanded":
        return align_commands(pool, robot)
    return apply_protocol(pool, inputs, robot, response)


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


def _naming(
    kind: str, ev: dict, scored_t: ScoredTerms, scored_c: Scored, n_params: int, equivalents: list[dict]
) -> dict[str, Any]:
    """The check behind a name: a catalogue effect against the best open-ended term of no more
    parameters (and the terms listed as its equivalents); a term against the best catalogue effect."""
    if kind == "catalogue":
        rivals = {k: v[0] for k, v in scored_t.items() if v[2].n_params_with_knots <= n_params}
    else:
        rivals = {k: v[0] for k, v in scored_c.items()}
    out: dict[str, Any] = {"rival": None, "rival_heldout_gain": None, "heldout_gain": ev["heldout_gain"]}
    if rivals:
        best = max(rivals, key=lambda k: rivals[k]["heldout_gain"])
        out |= {"rival": best, "rival_heldout_gain": rivals[best]["heldout_gain"]}
    if kind == "catalogue":
        out["equivalent_terms"] = equivalents
    return out


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
#: library form -> (evidence, held-out evaluation, the form (no knots), each fold's term with its knots)
ScoredTerms = dict[str, tuple[dict[str, Any], HeldOut, termlib.Term, list[termlib.Term]]]


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
    """One progress line: a candidate's held-out gains, its own and its search-wide p-value, and whether
    it passes the rule."""
    run.say(
        f"[{run.terrain}]   {name:28s} gain {ev['heldout_gain']:+.4f} (penalised "
        f"{ev['penalised_gain']:+.4f}) p={ev['paired_p_value']:.3g} p_search={ev.get('p_search', 1.0):.3g} "
        f"velocity gain {ev['velocity_gain']:+.4f}{'' if ev['stable_across_folds'] else ' unstable'}"
        f"{'  PASS' if ev['passes'] else ''}"
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
        "command_alignment_s": dict(pool.alignment),  # align_commands: each sequence's command shift
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
        scored[eid] = (compare(run.cur, ho, CATALOGUE[eid].n_params, run.settings), ho)
    return scored


def _excluded_forms(run: _Search) -> tuple[str, ...]:
    """Library forms not searched: the terms already added, the equivalents of the catalogue effects
    already added (the same residual under another name) and, when the held-out units are time blocks
    of a few sequences, the forms that are functions of sequence time (:func:`terms.time_forms`: blocks
    of one sequence share its ground truth's slow drift, so they cannot test a change over time)."""
    eq = [f for e in run.effects for f in termlib.equivalent_forms(e)]
    timed = termlib.time_forms() if run.pool.blocks else []
    return tuple(t.form for t in run.terms) + tuple(eq) + tuple(timed)


def _fold_screens(run: _Search) -> termlib.FoldScreens:
    """The library screened once per fold, each on its training units only: the current model fitted on
    them (as :func:`cross_validate` fits it) and the sparse regression on what it leaves there. A form
    is a candidate when a majority of the folds select it, and each fold's held-out evaluation uses the
    knots its own screen chose, so no held-out unit takes part in choosing what it is scored on."""
    pool, aug = run.pool, run.aug
    screens = []
    for held in folds_of(pool, run.settings.folds):
        train = np.setdiff1d(np.arange(pool.n_units), held)
        st = aug.fit(run.effects, train, run.warm, fixed_tau=True, terms=run.terms)
        rows = np.isin(pool.units, train) & pool.valid
        sig = aug.signals(st.feats, st.base_pred)
        screens.append(
            termlib.screen(
                sig,
                termlib.base_gains(sig, rows),
                run.robot.track_width,
                pool.target - st.pred,
                rows,
                aug.weights,
                exclude=_excluded_forms(run),
                max_candidates=run.settings.max_terms,
            )
        )
    return termlib.FoldScreens(screens, min_folds=len(screens) // 2 + 1)


def _score_form(run: _Search, fs: termlib.FoldScreens, template: termlib.Term, scored_t: ScoredTerms) -> None:
    """One library form added to the current model, each fold with its own screen's knots, scored held
    out against the current model (into ``scored_t``)."""
    fold_terms = fs.fold_terms(template)
    ho = cross_validate(run.aug, run.effects, run.warm, run.terms, fold_terms=fold_terms)
    ev = compare(run.cur, ho, template.n_params_with_knots, run.settings, template.touched, "candidate_term")
    ev["fold_votes"] = fs.votes(template.form)
    ev["fold_knots"] = [list(t.knots) for t in fold_terms]
    scored_t[template.form] = (ev, ho, template, fold_terms)


def _score_terms(run: _Search) -> tuple[ScoredTerms, dict[str, Any], termlib.FoldScreens | None]:
    """The open-ended terms (``discover.open_ended``): the forms a majority of the folds' screens select
    (:func:`_fold_screens`), at most ``max_terms``, each scored held out like a catalogue effect.
    Returns the scores, what the screens selected (for the record) and the screens (none when off)."""
    scored_t: ScoredTerms = {}
    if not run.settings.open_ended:
        return scored_t, {}, None
    fs = _fold_screens(run)
    stable = fs.stable(run.settings.max_terms)
    screen_info = {
        "fold_supports": [sc.selected for sc in fs.screens],
        "candidates": [t.form for t in stable],
        "min_folds": fs.min_folds,
    }
    for template in stable:
        _score_form(run, fs, template, scored_t)
    return scored_t, screen_info, fs


def _score_rival(run: _Search, best_c: str, scored_t: ScoredTerms, fs: termlib.FoldScreens) -> None:
    """The catalogue's best must beat the library's best form of no more parameters on its channels
    (best mean share over the folds' screens): that rival, when not scored yet, is scored too."""
    chans = tuple(CHANNELS.index(c) for c in channels_of(best_c))
    rival = fs.best_rival(chans, CATALOGUE[best_c].n_params, tuple(scored_t) + _excluded_forms(run))
    if rival is not None:
        _score_form(run, fs, rival, scored_t)


def _best_catalogue(scored: Scored, key: str = "rule_ok") -> str | None:
    ok = [e for e, (ev, _) in scored.items() if ev[key]]
    return max(ok, key=lambda e: scored[e][0]["penalised_gain"]) if ok else None


def significantly_better(a: dict[str, Any], ho_a: HeldOut, b: dict[str, Any], ho_b: HeldOut, s) -> bool:
    """Whether candidate a beats candidate b beyond their uncertainty: its per-unit held-out 6 s gains are
    larger (one-sided sign-flip test of the differences at ``alpha``) and its held-out velocity residual
    is smaller unit by unit (:func:`explains_better`). Otherwise the two explain the residual equally."""
    da = np.array([np.nan if x is None else x for x in a["unit_gains"]], float)
    db = np.array([np.nan if x is None else x for x in b["unit_gains"]], float)
    diff = da - db
    pose_ok = bool(np.nanmean(diff) > 0 and sign_flip_pvalue(diff, s.seed) <= s.alpha)
    return pose_ok and explains_better(ho_a, ho_b, s)[0]


def _tie_candidate(run: _Search, scored: Scored) -> str | None:
    """When only library terms pass: the catalogue effect of largest penalised gain that passes every part
    of the rule but its own 6 s sign-flip test (``paired_p_value``), marked ``named_on_tie``. That some
    effect is there is shown by the passing term (the search-wide test bounds the chance of any name on
    data with nothing missing, whichever is given); which name it gets is the naming rule's (a term is
    named instead only when significantly better than this effect, :func:`_choose`)."""
    alpha = run.settings.alpha
    ok = [e for e, (ev, _) in scored.items() if ev["rule_ok"] and ev.get("p_search", 1.0) <= alpha]
    if not ok:
        return None
    best = max(ok, key=lambda e: scored[e][0]["penalised_gain"])
    scored[best][0]["named_on_tie"] = True
    return best


def _same_channels(form: str, eid: str) -> bool:
    """Whether the library form changes only channels the catalogue effect ``eid`` changes."""
    return set(termlib.parse_form(form).touched) <= {CHANNELS.index(c) for c in channels_of(eid)}


def _restates_named(run: _Search, form: str, ev: dict[str, Any]) -> bool:
    """Whether a library form states, on its own channels, a catalogue effect the model already has
    (``terms.catalogue_equivalent``): then what it explains is the residual of that effect's functional
    form, not another effect, and it is not named. It is listed on the step that named the effect
    (``naming.form_residual_terms``, with the step at which it passed, its held-out gain and ``p_search``)."""
    eid = termlib.catalogue_equivalent(form)
    if eid is None or eid not in run.effects or not _same_channels(form, eid):
        return False
    step = next(st for st in run.steps if st["effect"] == eid)
    step["naming"].setdefault("form_residual_terms", []).append(
        {"term": form, "at_step": len(run.steps) + 1, "heldout_gain": ev["heldout_gain"],
         "p_search": ev.get("p_search")}
    )  # fmt: skip
    run.say(f"[{run.terrain}]   {form} states {eid}, already named: the residual of its form, not named")
    return True


def _choose(run: _Search, scored: Scored, scored_t: ScoredTerms) -> tuple[str, str, list[dict]] | None:
    """The candidate to add, as (kind, id, equivalent terms) with kind "catalogue" or "term"; None when
    none passes. The interpretable name wins a tie: the passing catalogue effect of largest penalised gain
    is named unless a passing term is significantly better (:func:`significantly_better`); a term
    that states a passing catalogue effect in other words on the effect's own channels
    (``terms.catalogue_equivalent``) names that effect, and one that states an effect the model already
    has is not named at all (:func:`_restates_named`). The terms that explain the named effect's residual
    as well are listed as its equivalents."""
    best_c = _best_catalogue(scored, "passes")
    passing_t = [k for k, v in scored_t.items() if v[0]["passes"] and not _restates_named(run, k, v[0])]
    if best_c is None and not passing_t:
        return None
    if best_c is None:  # a term passes: a catalogue effect that ties it names what it found
        best_c = _tie_candidate(run, scored)

    def equivalents(eid: str) -> list[dict]:
        ev_c, ho_c = scored[eid]
        out = []
        for k, (ev, ho, _, _) in scored_t.items():
            same = termlib.catalogue_equivalent(k) == eid
            if same or (ev["passes"] and not significantly_better(ev, ho, ev_c, ho_c, run.settings)):
                out.append({"term": k, "heldout_gain": ev["heldout_gain"], "p_search": ev.get("p_search"),
                            "reparametrisation": same})  # fmt: skip
        return out

    better = [
        k
        for k in passing_t
        if best_c is None or significantly_better(*scored_t[k][:2], *scored[best_c], run.settings)
    ]
    if not better:
        if scored[best_c][0].get("named_on_tie"):
            run.say(f"[{run.terrain}]   {best_c} ties the passing terms (none significantly better): named")
        return ("catalogue", best_c, equivalents(best_c))
    if best_c is not None:
        scored[best_c][0].pop("named_on_tie", None)
    name = max(better, key=lambda k: scored_t[k][0]["penalised_gain"])
    eid = termlib.catalogue_equivalent(name)
    if (
        eid is not None
        and _same_channels(name, eid)
        and eid in scored
        and scored[eid][0]["passes"]
        and not significantly_better(*scored_t[name][:2], *scored[eid], run.settings)
    ):
        # the same statement about the same channels, as well explained by the catalogue's own form: the
        # catalogue's name. Significantly better than that form, it is not the effect as the catalogue
        # states it (a wheel dead zone cuts spins' yaw rate, a function of curvature that chi(R) takes
        # only at a bound), and a form that also changes a channel the effect does not (one side's slip,
        # which takes forward speed too) states something more: either is named by itself
        run.say(f"[{run.terrain}]   {name} states {eid} in another form: named {eid}")
        return ("catalogue", eid, equivalents(eid))
    if best_c is not None:
        run.say(f"[{run.terrain}]   {best_c} not named: {name} is significantly better")
    return ("term", name, [])


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
    run: _Search,
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
            "naming": _naming("catalogue", ev, scored_t, scored, e.n_params, equivalents),
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
    run: _Search, name: str, scored: Scored, scored_t: ScoredTerms, evidence: dict[str, Any]
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
            "formula": f"{'vx, wz' if term.channel < 0 else CHANNELS[term.channel]} += theta * g, "
            f"g = {term.key}",
            "evidence": {**ev, **evidence},
            "naming": _naming("term", ev, scored_t, scored, term.n_params, []),
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
        scored_t, screen_info, fs = _score_terms(run)
        best_c = _best_catalogue(scored)
        if best_c is not None and fs is not None:
            _score_rival(run, best_c, scored_t, fs)
        # the search-wide test: every candidate of the step against the best a clean dataset would give
        every = {**{e: v[0] for e, v in scored.items()}, **{k: v[0] for k, v in scored_t.items()}}
        search_test(every, settings)
        for name, v in [*scored.items(), *scored_t.items()]:
            _show(run, name, v[0])
        evidence = {
            "candidates": {e: _evidence_row(v[0]) for e, v in scored.items()},
            "terms": {k: _evidence_row(v[0]) for k, v in scored_t.items()},
            "screen": screen_info,
        }
        choice = _choose(run, scored, scored_t)
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
