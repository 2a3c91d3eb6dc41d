"""The ranking rule and the tests behind a board's words (docs/intervals.md, "The ranking rule" and "The
paper's claim"), on the estimates of :mod:`skidbench.benchmark.scoring.intervals`.

**Ranks.** ``rank`` = 1 + the number of rankable entries *resolved* better than it (their paired
difference's interval excludes 0 and the two estimates differ by more than :data:`TOLERANCE`), then made
monotone in the estimate: no entry ranks above one whose estimate is lower (a wide interval is not resolved
from anything, and would otherwise rank 1 while a better entry ranks 2). Entries whose estimates are equal
within the tolerance share one rank.

**Words.** ``best``: resolved better than every other entry. ``tied for best``: of rank 1 and *shown
equivalent* to the leader, its paired difference's interval inside +-``margin`` points (a resolved
equivalence, two one-sided tests at the interval's level: :func:`equivalent`) or equal within the
tolerance; a rank-1 entry only not resolved from the leader is neither, and the leader then ``leads, not
resolved``. So no entry is "tied for best" only because its interval is wide.

**Tests.** :func:`p_greater` (one-sided, from an estimate, its standard error and effective degrees of
freedom: Student's t) and :func:`holm` (Holm's step-down correction over a family of such tests). Pure.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd
import scipy.stats

NOT_RANKED = "not ranked"
BEST = "best"
TIED = "tied for best"
LEADS = "leads, not resolved"
#: the standing's reason of the one entry of a board: there is nothing to rank it against
ALONE = "the only entry; a board of one ranks nothing"
#: points: estimates closer than this are equal (the boards show two decimals)
TOLERANCE = 0.005
#: points: the equivalence margin (two entries within it of each other are "comparable")
MARGIN = 1.0


def resolved(lo: float, hi: float) -> bool:
    """A difference is resolved when its interval excludes 0."""
    return bool(np.isfinite(lo) and np.isfinite(hi) and (lo > 0.0 or hi < 0.0))


def equivalent(lo: float, hi: float, margin: float = MARGIN) -> bool:
    """A difference is shown equivalent to 0 when its interval lies inside ``[-margin, margin]`` (two
    one-sided tests, each at half the interval's complement)."""
    return bool(np.isfinite(lo) and np.isfinite(hi) and -margin < lo and hi < margin)


def p_greater(estimate: float, se: float, df: float, bound: float = 0.0) -> float:
    """One-sided p-value of "the true value is above ``bound``" against "at most ``bound``": Student's t
    on ``df`` effective degrees of freedom (1.0 when nothing is known)."""
    if not (np.isfinite(estimate) and np.isfinite(se) and np.isfinite(df) and df > 0):
        return 1.0
    if se <= 0.0:
        return 0.0 if estimate > bound else 1.0
    return float(scipy.stats.t.sf((estimate - bound) / se, df))


def holm(p: Sequence[float], alpha: float) -> list[bool]:
    """Holm's step-down procedure: which of the tests with p-values ``p`` reject at family-wise error
    rate ``alpha`` (the k-th smallest against ``alpha / (m - k)``, stopping at the first that does not)."""
    order = np.argsort(np.asarray(p, dtype=float), kind="stable")
    out = [False] * len(order)
    for k, i in enumerate(order):
        if p[i] > alpha / (len(order) - k):
            break
        out[i] = True
    return out


def rank_board(
    scores: pd.DataFrame, differences: pd.DataFrame, margin: float = MARGIN, tolerance: float = TOLERANCE
) -> pd.DataFrame:
    """Ranks rows by one score with their paired differences (module docstring).

    ``scores``: one row per entry (index: its name), columns ``estimate``, ``rankable``, ``reason``;
    ``differences``: index ``(a, b)`` with ``lo``, ``hi`` of ``a - b`` (either order given suffices).
    Returns, per entry, ``rank`` ("" when not rankable) and ``standing`` (:data:`BEST`, :data:`TIED`,
    :data:`LEADS`, "" or ``not ranked: <reason>``). A board with no rankable entry ranks nothing, nor a
    board of one entry (``not ranked:`` :data:`ALONE`, whatever its interval)."""
    out = pd.DataFrame(index=scores.index, data={"rank": "", "standing": ""})
    if len(scores.index) == 1:
        out["standing"] = f"{NOT_RANKED}: {ALONE}"
        return out
    est = {i: float(scores.loc[i, "estimate"]) for i in scores.index}
    ok = sorted((i for i in scores.index if bool(scores.loc[i, "rankable"]) and np.isfinite(est[i])),
                key=lambda i: est[i])  # fmt: skip
    for i in scores.index:
        if i not in ok:
            out.loc[i, "standing"] = f"{NOT_RANKED}: {scores.loc[i, 'reason'] or 'no score'}"
    if not ok:
        return out

    def diff(a, b) -> tuple[float, float]:
        if (a, b) in differences.index:
            r = differences.loc[(a, b)]
            return float(r["lo"]), float(r["hi"])
        r = differences.loc[(b, a)]
        return -float(r["hi"]), -float(r["lo"])

    def same(a, b) -> bool:
        return abs(est[a] - est[b]) <= tolerance

    better = {i: sum(1 for j in ok if j != i and not same(i, j) and diff(i, j)[0] > 0.0) for i in ok}
    rank, last = {}, 0
    for k, i in enumerate(ok):  # in order of the estimate: shared within the tolerance, never decreasing
        equal = [j for j in ok[:k] if same(i, j)]
        rank[i] = rank[equal[0]] if equal else max(1 + better[i], last)
        last = rank[i]
    leader = ok[0]
    for i in ok:
        out.loc[i, "rank"] = str(rank[i])
    others = [j for j in ok if j != leader]
    if all(resolved(*diff(leader, j)) and diff(leader, j)[1] < 0.0 and not same(leader, j) for j in others):
        out.loc[leader, "standing"] = BEST
        return out
    tied = [j for j in others if rank[j] == 1 and (same(leader, j) or equivalent(*diff(leader, j), margin))]
    out.loc[leader, "standing"] = TIED if tied else LEADS
    for j in tied:
        out.loc[j, "standing"] = TIED
    return out


def board_verdict(standing: pd.Series, margin: float = MARGIN) -> str:
    """One line for a board: who is best, who is tied, who leads unresolved, or that no entry is ranked."""
    best = [str(i) for i, s in standing.items() if s == BEST]
    tied = [str(i) for i, s in standing.items() if s == TIED]
    leads = [str(i) for i, s in standing.items() if s == LEADS]
    if best:
        return f"best: {best[0]} (its paired difference from every other is resolved)"
    if tied:
        return f"tied for best: {', '.join(tied)} (shown equivalent within {margin:g} point)"
    if leads:
        return f"leads, not resolved: {leads[0]} (not resolved from every other, nor shown equivalent)"
    why = sorted({str(s).removeprefix(f"{NOT_RANKED}: ") for s in standing if str(s).startswith(NOT_RANKED)})
    return "no entry ranked: " + ("; ".join(why) or "no entry")
