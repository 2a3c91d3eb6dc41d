"""Which candidate a step names (:mod:`skidbench.benchmark.discovery.discover`): the interpretable name wins
a tie.
The passing catalogue effect of largest penalised gain is named unless a passing library term is
significantly better; a term that restates a catalogue effect names it when the effect's own form explains
the residual as well; a term that restates an effect already named is the residual of its form, not a new
name (docs/discovery.md, "Naming rule")."""

from __future__ import annotations

from typing import Any

import numpy as np

from skidbench.benchmark.discovery.search import Scored, ScoredTerms, Search
from skidbench.benchmark.discovery.stats import HeldOut, channels_of, explains_better, sign_flip_pvalue
from skidbench.models.augmented import terms as termlib
from skidbench.models.augmented.effects import FAMILIES, family_of
from skidbench.models.augmented.fit import CHANNELS


def keep_best_members(scored: Scored) -> Scored:
    """A catalogue effect is a family of forms (``effects.FAMILIES``): its best-fitting member (largest
    penalised gain among those that pass, else among all) stays in ``scored`` and carries the catalogue's
    name; the others are removed from it and returned (a term must beat every member to be named instead).
    Each kept member's evidence lists its family's members and their gains (``family``)."""
    rivals: Scored = {}
    for ms in FAMILIES.values():
        present = [m for m in ms if m in scored]
        if len(present) < 2:
            continue
        ok = [m for m in present if scored[m][0]["passes"]] or present
        best = max(ok, key=lambda m: scored[m][0]["penalised_gain"])
        scored[best][0]["family"] = {m: scored[m][0]["penalised_gain"] for m in present}
        for m in present:
            if m != best:
                rivals[m] = scored.pop(m)
    return rivals


def member_of(scored: Scored, eid: str) -> str | None:
    """The member of catalogue effect ``eid``'s family that ``scored`` holds (None: none)."""
    return next((m for m in scored if family_of(m) == eid), None)


def best_catalogue(scored: Scored, key: str = "rule_ok") -> str | None:
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


def tie_candidate(run: Search, scored: Scored) -> str | None:
    """When only library terms pass: the catalogue effect of largest penalised gain that passes every part
    of the rule but its own 6 s sign-flip test (``paired_p_value``), marked ``named_on_tie``. That some
    effect is there is shown by the passing term (the search-wide test bounds the chance of any name on
    data with nothing missing, whichever is given); which name it gets is the naming rule's (a term is
    named instead only when significantly better than this effect, :func:`choose`). The effect must matter
    to a lab by itself (``practical``, :func:`search.practical_check`): a name is a name, and on the DRIVE
    Warthog an angular-acceleration slip that cut 1.8 % of the 6 s rotational error was named on a tie
    with a yaw-rate saturation that cut far more."""
    alpha = run.settings.alpha
    ok = [
        e
        for e, (ev, _) in scored.items()
        if ev["rule_ok"] and ev.get("p_search", 1.0) <= alpha and ev.get("practical", {}).get("ok", True)
    ]
    if not ok:
        return None
    best = max(ok, key=lambda e: scored[e][0]["penalised_gain"])
    scored[best][0]["named_on_tie"] = True
    return best


def same_channels(form: str, eid: str) -> bool:
    """Whether the library form changes only channels the catalogue effect ``eid`` changes."""
    return set(termlib.parse_form(form).touched) <= {CHANNELS.index(c) for c in channels_of(eid)}


def restates_named(run: Search, form: str, ev: dict[str, Any]) -> bool:
    """Whether a library form states, on its own channels, a catalogue effect the model already has
    (``terms.catalogue_equivalent``): then what it explains is the residual of that effect's functional
    form, not another effect, and it is not named. It is listed on the step that named the effect
    (``naming.form_residual_terms``, with the step at which it passed, its held-out gain and ``p_search``)."""
    eid = termlib.catalogue_equivalent(form)
    if eid is None or eid not in {family_of(e) for e in run.effects} or not same_channels(form, eid):
        return False
    step = next(st for st in run.steps if st["effect"] == eid)
    step["naming"].setdefault("form_residual_terms", []).append(
        {"term": form, "at_step": len(run.steps) + 1, "heldout_gain": ev["heldout_gain"],
         "p_search": ev.get("p_search")}
    )  # fmt: skip
    run.say(f"[{run.terrain}]   {form} states {eid}, already named: the residual of its form, not named")
    return True


def choose(
    run: Search, scored: Scored, scored_t: ScoredTerms, rivals: Scored | None = None
) -> tuple[str, str, list[dict]] | None:
    """The candidate to add, as (kind, id, equivalent terms) with kind "catalogue" or "term"; None when
    none passes. The interpretable name wins a tie: the passing catalogue effect of largest penalised gain
    is named unless a passing term is significantly better (:func:`significantly_better`); a term
    that states a passing catalogue effect in other words on the effect's own channels
    (``terms.catalogue_equivalent``) names that effect, and one that states an effect the model already
    has is not named at all (:func:`restates_named`). The terms that explain the named effect's residual
    as well are listed as its equivalents."""
    best_c = best_catalogue(scored, "passes")
    passing_t = [k for k, v in scored_t.items() if v[0]["passes"] and not restates_named(run, k, v[0])]
    if best_c is None and not passing_t:
        return None
    if best_c is None:  # a term passes: a catalogue effect that ties it names what it found
        best_c = tie_candidate(run, scored)

    def equivalents(eid: str) -> list[dict]:
        ev_c, ho_c = scored[eid]
        out = []
        for k, (ev, ho, _, _) in scored_t.items():
            same = termlib.catalogue_equivalent(k) == family_of(eid)
            if same or (ev["passes"] and not significantly_better(ev, ho, ev_c, ho_c, run.settings)):
                out.append({"term": k, "heldout_gain": ev["heldout_gain"], "p_search": ev.get("p_search"),
                            "reparametrisation": same})  # fmt: skip
        return out

    def beats(k: str, eid: str) -> bool:  # better than the effect and every other member of its family
        fam = [scored[eid], *(v for m, v in (rivals or {}).items() if family_of(m) == family_of(eid))]
        return all(significantly_better(*scored_t[k][:2], *v, run.settings) for v in fam)

    better = [k for k in passing_t if best_c is None or beats(k, best_c)]
    if not better:
        if scored[best_c][0].get("named_on_tie"):
            run.say(f"[{run.terrain}]   {best_c} ties the passing terms (none significantly better): named")
        return ("catalogue", best_c, equivalents(best_c))
    if best_c is not None:
        scored[best_c][0].pop("named_on_tie", None)
    name = max(better, key=lambda k: scored_t[k][0]["penalised_gain"])
    fam = termlib.catalogue_equivalent(name)
    eid = member_of(scored, fam) if fam is not None else None
    if eid is not None and same_channels(name, fam) and scored[eid][0]["passes"] and not beats(name, eid):
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


def naming_record(
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
