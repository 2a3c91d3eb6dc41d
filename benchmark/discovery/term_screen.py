"""The sparse regression that picks candidate terms from the library of
:mod:`skidbench.models.augmented.terms`
(SPEC.md "Discrepancy discovery"): every hinge's knot chosen on a quantile grid of its signal and refined
by a bounded scalar search, by the weighted residual sum of squares a one-term fit leaves; the best knot of
each (family, signal, channel) then enters a ridge-regularised sequentially thresholded least squares
(STLSQ, as in SINDy, Brunton et al. 2016) over the three channels at once; the surviving terms, ranked by
what each explains alone, are the candidates (:func:`screen`). Discovery screens each fold's training units
apart (:class:`FoldScreens`): a form is a candidate when a majority of the folds select it."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize_scalar

from skidbench.models.augmented.terms import KNOTS, RADIUS_HINGES, Term, _signal, library_groups, parse_form


def _knot_grid(term: Term, sig: dict[str, np.ndarray]) -> list[tuple[float, ...]]:
    q = _quantiles(term.family)
    if term.family == "after":
        return [(float(k),) for k in np.unique(np.quantile(sig["t"], np.linspace(0.1, 0.9, 17)))]
    if term.channel < 0:
        rim = np.abs(np.concatenate([sig["rim_l"], sig["rim_r"]]))
        ks = np.unique(np.quantile(rim, q))
        if term.family == "wload":
            scale = float(np.quantile(rim, 0.9)) / max(float(np.quantile(sig["|w|"], 0.9)), 1e-6)
            k1s = scale * np.array([0.05, 0.1, 0.2, 0.35, 0.5])
            return [(float(a), float(b)) for a in ks for b in k1s]
        return [(float(k),) for k in ks if k > 0]
    x = np.abs(_signal(term.signal, sig))
    return [(float(k),) for k in np.unique(np.quantile(x, q)) if k > 0]


def _quantiles(family: str) -> np.ndarray:
    """Where a knot may sit, as quantiles of its signal's magnitude: a dead zone near rest, a limit in the
    upper part of the range (a knot beyond the data would be a straight line, the ``lin`` family's)."""
    if family in ("dz", "wdz"):
        return np.linspace(0.02, 0.5, 16)
    return np.linspace(0.3, 0.99, 16)


def _one_term_gain(
    g: dict[int, np.ndarray], r: np.ndarray, wts: np.ndarray, free: bool = True
) -> tuple[float, float]:
    """(weighted SSE reduction, theta) of fitting theta * g to the residual r alone (``free``; else theta
    = 1); g: the term's columns by channel (:meth:`Term.channel_columns`), r (n, 3), wts (3,) the
    channel weights."""
    num = sum(float(wts[c] * np.dot(col, r[:, c])) for c, col in g.items())
    den = sum(float(wts[c] * np.dot(col, col)) for c, col in g.items())
    if den <= 1e-18:
        return 0.0, 0.0
    if not free:
        return 2.0 * num - den, 1.0
    return num * num / den, num / den


def _one_radius_hinge_gain(term: Term, sig, gains, B, r: np.ndarray, wts: np.ndarray) -> float:
    """The weighted SSE reduction of a wheel hinge with its radius theta fitted (theta g + g0,
    :meth:`Term.design`): its knots chosen at the calibrated radius would take up the vx residual the
    radius leaves (a dead zone's calibrated radius is 18 % short)."""
    g, g0 = term.design(sig, gains, B)
    y = r - g0
    num = float(np.sum(wts * np.einsum("tc,tc->c", g, y)))
    den = float(np.sum(wts * np.einsum("tc,tc->c", g, g)))
    base = float(np.sum(wts * (np.einsum("tc,tc->c", r, r) - np.einsum("tc,tc->c", y, y))))
    return base + (num * num / den if den > 1e-18 else 0.0)


def _best_knots(term, sig, gains, B, r, wts) -> tuple[Term, float]:
    """The knots of a template that explain most of ``r`` alone (``sig`` and ``r`` on the screened rows)."""
    grid = _knot_grid(term, sig)
    if not grid:
        return term, 0.0
    free = term.free_theta

    def gain(kn) -> float:
        if term.family in RADIUS_HINGES:
            return _one_radius_hinge_gain(term.with_knots(kn), sig, gains, B, r, wts)
        return _one_term_gain(term.with_knots(kn).channel_columns(sig, gains, B), r, wts, free)[0]

    scores = [gain(k) for k in grid]
    i = int(np.argmax(scores))
    best = list(grid[i])
    best_score = scores[i]
    # refine each knot between its grid neighbours (coordinate-wise; two rounds for two knots)
    for _ in range(len(best)):
        for j in range(len(best)):
            vals = sorted({k[j] for k in grid})
            pos = int(np.argmin(np.abs(np.asarray(vals) - best[j])))
            lo, hi = vals[max(pos - 1, 0)], vals[min(pos + 1, len(vals) - 1)]
            if hi - lo <= 1e-12:
                continue

            def f(x, j=j):
                kn = list(best)
                kn[j] = x
                return -gain(kn)

            res = minimize_scalar(f, bounds=(lo, hi), method="bounded", options={"xatol": 1e-4 * (hi - lo)})
            if -res.fun > best_score:
                best[j], best_score = float(res.x), float(-res.fun)
    return term.with_knots(best), best_score


def stlsq(X: np.ndarray, y: np.ndarray, threshold: float, ridge: float = 1e-3, iters: int = 10) -> np.ndarray:
    """Sequentially thresholded least squares (SINDy's STLSQ with a ridge): columns of X standardised to
    unit norm; coefficients whose standardised size is under ``threshold`` (a fraction of |y|) are cut and
    the rest refitted, until the support stops changing. Returns the coefficients of the standardised
    columns (zeros off the support)."""
    return stlsq_gram(X.T @ X, X.T @ y, float(np.dot(y, y)), threshold, ridge, iters)


def stlsq_gram(
    G: np.ndarray, b: np.ndarray, yy: float, threshold: float, ridge: float = 1e-3, iters: int = 10
) -> np.ndarray:
    """:func:`stlsq` from the normal equations (``G = X'X``, ``b = X'y``, ``yy = y'y``)."""
    norms = np.sqrt(np.maximum(np.diag(G), 0.0))
    ok = norms > 1e-12
    scale = np.where(ok, norms, 1.0)
    Gs = G / np.outer(scale, scale)
    bs = b / scale
    yn = float(np.sqrt(yy)) or 1.0
    support = ok.copy()
    coef = np.zeros(len(b))
    for _ in range(iters):
        idx = np.flatnonzero(support)
        c = np.linalg.solve(Gs[np.ix_(idx, idx)] + ridge * np.eye(len(idx)), bs[idx]) if len(idx) else idx
        coef[:] = 0.0
        coef[idx] = c
        new = support & (np.abs(coef) >= threshold * yn)
        if np.array_equal(new, support):
            break
        support = new
    coef[~support] = 0.0
    return coef


@dataclass
class Screen:
    candidates: list[Term]  # in order of what each explains alone, best first
    scores: dict[str, float]  # term key -> fraction of the weighted residual sum of squares it explains alone
    selected: list[str]  # the STLSQ support
    ranked: list[Term] = field(default_factory=list)  # every template at its best knots, best first

    def rival(self, channels: tuple[int, ...], max_params: int, skip: tuple[str, ...] = ()) -> Term | None:
        """The library's best term (alone) that changes one of ``channels`` with at most ``max_params``."""
        for t in self.ranked:
            if t.n_params <= max_params and t.key not in skip and set(t.touched) & set(channels):
                return t
        return None


def screen(
    sig: dict[str, np.ndarray],
    gains: tuple[float, float],
    track_width: float,
    resid: np.ndarray,
    rows: np.ndarray,
    weights: np.ndarray,
    exclude: tuple[str, ...] = (),
    max_candidates: int = 2,
    threshold: float = 0.05,
) -> Screen:
    """Candidate terms for the held-out residual ``resid`` (T, 3) on ``rows``: knots chosen per template,
    then STLSQ over all templates jointly (channels weighted by ``weights``, (3,)); the support ranked by
    what each term explains alone, at most ``max_candidates``."""
    r = np.asarray(resid, float)[rows]
    w3 = np.asarray(weights, float)
    total = float(np.sum(w3 * np.sum(r * r, axis=0))) or 1.0
    sig = {k: np.asarray(v)[rows] for k, v in sig.items()}  # every column below on the screened rows only
    skip = {k.split("@")[0] for k in exclude}  # term keys or forms: the form is what is left out
    best: list[tuple[Term, float]] = []
    for tmpl in library_groups():
        if tmpl.form in skip:
            continue
        if KNOTS[tmpl.family]:
            term, score = _best_knots(tmpl, sig, gains, track_width, r, w3)
        else:
            term = tmpl
            score = _one_term_gain(term.channel_columns(sig, gains, track_width), r, w3)[0]
        if score > 0 and math.isfinite(score):
            best.append((term, score / total))
    if not best:
        return Screen([], {}, [], [])
    # the normal equations channel by channel: a term's column is zero on the channels it does not touch
    sw = np.sqrt(w3)
    P = len(best)
    G, bvec = np.zeros((P, P)), np.zeros(P)
    cols = [t.channel_columns(sig, gains, track_width) for t, _ in best]
    for c in range(3):
        idx = [i for i, (t, _) in enumerate(best) if c in t.touched]
        if not idx:
            continue
        Xc = np.column_stack([cols[i][c] * sw[c] for i in idx])
        # einsum without BLAS: a multi-threaded BLAS product of this size stalls on a loaded machine
        G[np.ix_(idx, idx)] += np.einsum("ti,tj->ij", Xc, Xc, optimize=False)
        bvec[idx] += np.einsum("ti,t->i", Xc, r[:, c] * sw[c], optimize=False)
    coef = stlsq_gram(G, bvec, total, threshold)
    selected = [t for (t, _), c in zip(best, coef, strict=True) if c != 0.0]
    scores = {t.key: s for t, s in best}
    ranked = sorted(selected, key=lambda t: -scores[t.key])
    every = [t for t, _ in sorted(best, key=lambda p: -p[1])]
    return Screen(ranked[:max_candidates], scores, [t.key for t in ranked], every)


@dataclass
class FoldScreens:
    """The screens of the k training sets of a k-fold split (each screen sees its training units only):
    the forms at least ``min_folds`` of them put in their STLSQ support (:meth:`stable`, ranked by their
    mean explained share) and each fold's own knots of a form (:meth:`fold_terms`)."""

    screens: list[Screen]
    min_folds: int

    def votes(self, form: str) -> int:
        """In how many folds' candidates the form is."""
        return sum(any(t.form == form for t in scr.candidates) for scr in self.screens)

    def mean_share(self, form: str) -> float:
        """The mean over folds of the share of the residual the form explains alone (0 where absent)."""
        shares = [sum(v for k, v in scr.scores.items() if k.split("@")[0] == form) for scr in self.screens]
        return float(np.mean(shares)) if shares else 0.0

    def stable(self, max_candidates: int) -> list[Term]:
        """Forms among the candidates of at least ``min_folds`` folds, best mean share first (templates)."""
        forms = {t.form for scr in self.screens for t in scr.candidates}
        forms = [f for f in forms if self.votes(f) >= self.min_folds]
        forms.sort(key=lambda f: (-self.mean_share(f), f))
        return [parse_form(f) for f in forms[:max_candidates]]

    def fold_terms(self, template: Term) -> list[Term]:
        """The form with each fold's knots (a fold whose screen lacks it takes the median of the others')."""
        found = [{t.form: t for t in scr.ranked}.get(template.form) for scr in self.screens]
        known = [t for t in found if t is not None]
        if not known:
            return [template] * len(self.screens)
        fill = (
            template.with_knots(np.median([t.knots for t in known], axis=0)) if known[0].knots else template
        )
        return [t if t is not None else fill for t in found]

    def fold_selected(self, template: Term) -> list[Term | None]:
        """The form as each fold's own screen chose it: its term with that fold's knots where the form is
        among the fold's candidates, None where it is not (that fold's model does not take it)."""
        return [next((t for t in scr.candidates if t.form == template.form), None) for scr in self.screens]

    def best_rival(
        self, channels: tuple[int, ...], max_params: int, skip: tuple[str, ...] = ()
    ) -> Term | None:
        """The form of best mean share that changes one of ``channels`` with at most ``max_params``."""
        forms = sorted({t.form for scr in self.screens for t in scr.ranked} - set(skip))
        ok = [parse_form(f) for f in forms]
        ok = [t for t in ok if set(t.touched) & set(channels) and t.n_params_with_knots <= max_params]
        return max(ok, key=lambda t: self.mean_share(t.form)) if ok else None
