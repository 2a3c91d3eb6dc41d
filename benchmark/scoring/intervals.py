"""Every score with its uncertainty: block-bootstrap confidence intervals, paired comparisons and the
ranking rule (docs/intervals.md says why each choice, with the coverage it was measured to have).

Not the predictive covariance of a learned model (docs/uncertainty.md): this is the sampling uncertainty
of a score, what another drive of the same robot on the same terrain would have given.

**Independent units.** Overlapping windows of one drive share their data, so windows are not independent;
the units resampled are *blocks*: the windows of one sequence whose start time falls in one interval of
``block_s`` seconds (two horizons unless set, never under one; :func:`assign_blocks`). Windows of two
sequences are never in one block. A *stratum* is a set of blocks scored together (a terrain's test split
at one horizon); strata are resampled separately (a stratified bootstrap), every model with the same
draws, so differences between two models on the same windows are paired.

**Scores.** A score is a ratio of block sums, ``m = sum(S_b) / sum(N_b)``, through ``g``: ``rms`` (RMSRE:
``S`` sums the squared relative errors, ``g = sqrt``) or ``mean``; a :class:`Stat` is any linear
combination of scores of several strata and columns (a cell, a mean of the four metrics, a mean over
terrains, the difference of two models).

**The interval** (studentized block bootstrap, "bootstrap-t"): the standard error of a statistic comes
from its linearisation over blocks (the delta method on the block influence values ``u_b``) with the
covariance of adjacent blocks of one sequence added (the last windows of a block overlap the next
block's, and a drive's errors persist for seconds); each resample's statistic is studentized by its own
standard error (adjacency is lost in a resample, so without that term), and the interval is
``theta - t*_(1-a/2) se, theta - t*_(a/2) se``. Percentile and BCa intervals were measured to cover
0.56-0.93 at the block counts of a benchmark, this one 0.89-0.96 with blocks of two horizons
(docs/intervals.md, ``tests/intervals_study.py``).

**Rankable.** A statistic on at least ``min_blocks`` blocks (and 2 in each of its strata) is rankable;
below that it is shown with its reason and never ranked (:func:`rank_board`).

Pure: numpy and pandas, no MLflow, no files. Deterministic: the resampling of a stratum depends only on
``(seed, stratum key, number of blocks)``, so evaluate (one model) and compare (every model) draw the same
weights for the same stratum.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
import scipy.stats

from skidbench.benchmark.errors import EvaluationError

LEVEL = 0.95
#: bootstrap resamples per stratum (quantiles of 2.5 % and 97.5 % from 50 resamples each side)
RESAMPLES = 2000
#: fewest independent blocks behind a statistic for it to be ranked (and at least 2 in each of its strata;
#: docs/intervals.md: why 8)
MIN_BLOCKS = 8
#: the default block length in horizons (docs/intervals.md: one horizon covered 0.82-0.90 where the errors
#: are correlated beyond a window, two 0.89-0.96)
HORIZONS_PER_BLOCK = 2
AGGREGATIONS = ("rms", "mean")
#: the columns of :func:`estimate`'s frame
RESULT_COLUMNS = ("stat", "estimate", "lo", "hi", "se", "n_windows", "n_blocks", "min_blocks", "rankable",
                  "reason")  # fmt: skip


class IntervalError(EvaluationError):
    pass


@dataclass(frozen=True)
class IntervalConfig:
    """``level`` of the intervals, bootstrap ``resamples``, ``min_blocks`` for a statistic to be ranked,
    ``block_s`` (s; None: :data:`HORIZONS_PER_BLOCK` horizons; never shorter than one horizon) and the
    ``seed`` of the draws."""

    level: float = LEVEL
    resamples: int = RESAMPLES
    min_blocks: int = MIN_BLOCKS
    block_s: float | None = None
    seed: int = 0

    @classmethod
    def from_cfg(cls, cfg: Any) -> IntervalConfig:
        """From a stage config's ``intervals`` group (conf/intervals/default.yaml); defaults without one."""
        got = (cfg.get("intervals") if hasattr(cfg, "get") else None) or {}
        d = cls()
        block = got.get("block_s", d.block_s)
        return cls(
            level=float(got.get("level", d.level)),
            resamples=int(got.get("resamples", d.resamples)),
            min_blocks=int(got.get("min_blocks", d.min_blocks)),
            block_s=None if block is None else float(block),
            seed=int(got.get("seed", d.seed)),
        )

    def block_length(self, horizon_s: float) -> float:
        """The block length (s) at a horizon: ``block_s``, or :data:`HORIZONS_PER_BLOCK` horizons when it is
        None. IntervalError when ``block_s`` is shorter than the horizon (a block's windows would overlap
        more than the next block's)."""
        if self.block_s is None:
            return float(HORIZONS_PER_BLOCK * horizon_s)
        if self.block_s < horizon_s - 1e-9:
            raise IntervalError(
                f"intervals.block_s={self.block_s:g} s is shorter than the {horizon_s:g} s horizon: blocks "
                "must be at least one horizon long (overlapping windows of one drive are not independent)"
            )
        return float(self.block_s)


# -- blocks -------------------------------------------------------------------------------------------------
def assign_blocks(sequence: Sequence, t0: np.ndarray, block_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Block of every window: the windows of one sequence whose start ``t0`` (s) falls in the same
    ``block_s`` interval from the sequence's first window. Returns ``(block (W,) int in 0..K-1, adjacent
    (K-1,) bool)``: blocks are numbered by sequence (in order of first appearance) then time, and
    ``adjacent[b]`` says blocks ``b`` and ``b + 1`` are consecutive intervals of one sequence (their windows
    overlap; the standard error counts their covariance)."""
    if not block_s > 0:
        raise IntervalError(f"block length {block_s} s is not positive")
    seq = pd.Series(np.asarray(sequence, dtype=object)).astype(str)
    t0 = np.asarray(t0, dtype=float)
    if len(seq) != len(t0):
        raise IntervalError(f"{len(seq)} sequence labels for {len(t0)} window start times")
    if len(t0) == 0:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=bool)
    seq_code, _ = pd.factorize(seq)
    first = np.full(int(seq_code.max()) + 1, np.inf)
    np.minimum.at(first, seq_code, t0)
    pos = np.floor((t0 - first[seq_code]) / block_s + 1e-9).astype(np.int64)
    key = seq_code.astype(np.int64) * (int(pos.max()) + 1) + pos  # ordered by (sequence, time)
    uniq, block = np.unique(key, return_inverse=True)
    stride = int(pos.max()) + 1
    s_of, p_of = uniq // stride, uniq % stride
    adjacent = (s_of[1:] == s_of[:-1]) & (np.diff(p_of) == 1)
    return block.astype(int), adjacent


def stratum_key(split: str, horizon_s: float, sequences: Iterable[str]) -> str:
    """The key of a stratum: a test split's sequences at one horizon (``ld@6s:grass_ld_00``). It seeds the
    stratum's draws, so evaluate and compare, which name the terrain differently, draw the same ones."""
    return f"{split}@{horizon_s:g}s:" + ",".join(sorted({str(s) for s in sequences}))


# -- strata and their block sums --------------------------------------------------------------------------
@dataclass
class Stratum:
    """The blocks of one stratum and, per column, the block sums of its values: ``sums[column] = (S, N)``
    ((K,) each: the sum of the values, squared for ``rms``, and the number of finite values per block)."""

    key: str
    n_blocks: int
    adjacent: np.ndarray
    n_windows: int
    sums: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    aggregation: dict[str, str] = field(default_factory=dict)


class Sample:
    """Everything a set of statistics is computed from: strata of windows, each with its blocks and the
    block sums of its columns (``add``), and the bootstrap weights of each stratum (``weights``)."""

    def __init__(self, settings: IntervalConfig | None = None) -> None:
        self.cfg = settings or IntervalConfig()
        self.strata: dict[str, Stratum] = {}
        self._weights: dict[str, np.ndarray] = {}

    def add(
        self,
        key: str,
        sequence: Sequence,
        t0: np.ndarray,
        values: Mapping[str, np.ndarray],
        horizon_s: float,
        aggregation: str | Mapping[str, str] = "rms",
    ) -> Stratum:
        """A stratum ``key`` of windows (their ``sequence`` and start ``t0``) and its columns
        (``values[column]``: (W,) per window, NaN where the window is left out of that column). Every
        column of a stratum is on the same windows, so that the columns of two models are paired. Adding to
        a stratum again adds columns, which must come with the same windows."""
        block, adjacent = assign_blocks(sequence, t0, self.cfg.block_length(horizon_s))
        n_blocks = int(block.max()) + 1 if len(block) else 0
        st = self.strata.get(key)
        if st is None:
            st = self.strata[key] = Stratum(key, n_blocks, adjacent, len(block))
        elif st.n_blocks != n_blocks or st.n_windows != len(block):
            raise IntervalError(
                f"stratum {key}: {len(block)} windows in {n_blocks} blocks, but its columns so far are on "
                f"{st.n_windows} windows in {st.n_blocks} blocks; pair the windows first (pair_windows)"
            )
        for col, v in values.items():
            agg = aggregation if isinstance(aggregation, str) else aggregation[col]
            if agg not in AGGREGATIONS:
                raise IntervalError(f"column {col}: aggregation {agg!r} is not one of {AGGREGATIONS}")
            v = np.asarray(v, dtype=float)
            if v.shape != (len(block),):
                raise IntervalError(
                    f"stratum {key}, column {col}: {v.shape[0]} values for {len(block)} windows"
                )
            ok = np.isfinite(v)
            x = np.where(ok, v**2 if agg == "rms" else v, 0.0)
            S = np.bincount(block, weights=x, minlength=n_blocks)
            N = np.bincount(block, weights=ok.astype(float), minlength=n_blocks)
            st.sums[col] = (S, N)
            st.aggregation[col] = agg
        return st

    def weights(self, key: str) -> np.ndarray:
        """(B, K) bootstrap counts of stratum ``key``'s blocks (each row: K blocks drawn with replacement),
        from ``(seed, key, K)`` alone."""
        if key not in self._weights:
            K = self.strata[key].n_blocks
            rng = np.random.default_rng([int(self.cfg.seed), zlib.crc32(key.encode()), K])
            self._weights[key] = rng.multinomial(K, np.full(K, 1.0 / K), size=int(self.cfg.resamples)).astype(
                float
            )
        return self._weights[key]


def pair_windows(
    frames: Mapping[str, pd.DataFrame], on: Sequence[str] = ("sequence", "start")
) -> pd.DataFrame:
    """The windows of several models (``frames[model]``, each with the columns ``on`` and ``t0``) on one
    table: one row per window any model has, the other columns suffixed ``.<model>`` (NaN where a model
    lacks the window). Windows come from the ground truth alone, so models scored on the same split have
    the same ones; the outer join keeps a model that lacks one from dropping it for the others."""
    out = None
    for model, df in frames.items():
        keep = df.rename(columns={c: f"{c}.{model}" for c in df.columns if c not in (*on, "t0")})
        if out is None:
            out = keep
        else:
            out = out.merge(keep, on=[*on, "t0"], how="outer")
    if out is None:
        return pd.DataFrame(columns=[*on, "t0"])
    return out.sort_values(list(on), kind="stable").reset_index(drop=True)


# -- statistics -------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Stat:
    """A linear combination of scores: ``terms`` = ((stratum, column, coefficient), ...). ``nonnegative``:
    the lower bound is clipped at 0 (a score, not a difference)."""

    name: str
    terms: tuple[tuple[str, str, float], ...]
    nonnegative: bool = True


def cell(name: str, stratum: str, column: str) -> Stat:
    """One score: a column of one stratum (an RMSRE of a model on a terrain's split)."""
    return Stat(name, ((stratum, column, 1.0),))


def mean_of(name: str, stats: Iterable[Stat]) -> Stat:
    """The mean of several statistics (e.g. the four metrics of a model, a metric over terrains)."""
    stats = list(stats)
    terms: dict[tuple[str, str], float] = {}
    for s in stats:
        for st, col, c in s.terms:
            terms[(st, col)] = terms.get((st, col), 0.0) + c / len(stats)
    return Stat(
        name, tuple((st, col, c) for (st, col), c in terms.items()), all(s.nonnegative for s in stats)
    )


def difference(name: str, a: Stat, b: Stat) -> Stat:
    """``a - b`` (paired when ``a`` and ``b`` are on the same strata: the same resampled blocks)."""
    terms: dict[tuple[str, str], float] = {}
    for sign, s in ((1.0, a), (-1.0, b)):
        for st, col, c in s.terms:
            terms[(st, col)] = terms.get((st, col), 0.0) + sign * c
    return Stat(name, tuple((st, col, c) for (st, col), c in terms.items()), nonnegative=False)


def _score(S, N, agg):
    with np.errstate(divide="ignore", invalid="ignore"):
        m = S / N
    return np.sqrt(m) if agg == "rms" else m


def _slope(m, agg):
    """dg/dm at m: the delta method's factor (g = sqrt for rms, identity for mean)."""
    if agg == "mean":
        return np.ones_like(m)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(m > 0, 0.5 / np.sqrt(m), 0.0)


def estimate(sample: Sample, stats: Sequence[Stat]) -> pd.DataFrame:
    """Every statistic with its interval: one row each, columns :data:`RESULT_COLUMNS` (``n_windows``: the
    largest number of windows behind one of its scores, summed over strata; ``n_blocks``: the blocks of
    its strata; ``min_blocks``: the fewest of one stratum; ``reason``: why it is not rankable)."""
    cfg = sample.cfg
    rows = []
    a2 = (1.0 - cfg.level) / 2.0
    for stat in stats:
        rows.append(_one(sample, stat, a2))
    return pd.DataFrame(rows, columns=list(RESULT_COLUMNS))


def _one(sample: Sample, stat: Stat, a2: float) -> dict:
    cfg = sample.cfg
    by_stratum: dict[str, list[tuple[str, float]]] = {}
    for st, col, c in stat.terms:
        if st not in sample.strata or col not in sample.strata[st].sums:
            raise IntervalError(f"statistic {stat.name}: no column {col!r} in stratum {st!r}")
        if c != 0.0:
            by_stratum.setdefault(st, []).append((col, c))
    row = {"stat": stat.name, "estimate": np.nan, "lo": np.nan, "hi": np.nan, "se": np.nan, "n_windows": 0,
           "n_blocks": 0, "min_blocks": 0, "rankable": False, "reason": ""}  # fmt: skip
    if not by_stratum:  # e.g. a model minus itself: every coefficient cancels
        row.update(estimate=0.0, lo=0.0, hi=0.0, se=0.0, rankable=True)
        strata = {st for st, _, _ in stat.terms}
        row["n_blocks"] = sum(sample.strata[s].n_blocks for s in strata)
        row["min_blocks"] = min((sample.strata[s].n_blocks for s in strata), default=0)
        row["n_windows"] = sum(sample.strata[s].n_windows for s in strata)
        return row
    theta = 0.0
    theta_b = np.zeros(int(sample.cfg.resamples))
    var_iid = var_hac = var_boot = 0.0
    var_b = np.zeros(int(sample.cfg.resamples))
    n_windows = 0
    blocks = []
    for st_key, cols in by_stratum.items():
        st = sample.strata[st_key]
        K = st.n_blocks
        # the blocks that hold a value of every score of the stratum: a block whose windows all fall under
        # the minimum distance (or rotation) adds nothing to that score
        blocks.append((st_key, int(min(np.count_nonzero(st.sums[col][1]) for col, _ in cols))))
        n_windows += int(max(st.sums[col][1].sum() for col, _ in cols))
        if any(st.sums[col][1].sum() == 0 for col, _ in cols):
            row.update(n_windows=n_windows, reason=f"{st_key}: no window counts for this score")
            return _finish(row, blocks, cfg.min_blocks)
        W = sample.weights(st_key)  # (B, K)
        u = np.zeros(K)  # the statistic's influence values over the stratum's blocks (delta method)
        u_b = np.zeros((W.shape[0], K))  # ... in each resample
        for col, c in cols:
            S, N = st.sums[col]
            agg = st.aggregation[col]
            m = S.sum() / N.sum()
            theta += c * float(_score(S.sum(), N.sum(), agg))
            u += c * _slope(m, agg) * (S - m * N) / N.sum()
            Sb, Nb = W @ S, W @ N
            with np.errstate(divide="ignore", invalid="ignore"):
                mb = Sb / Nb
                u_b += (c * _slope(mb, agg) / Nb)[:, None] * (S[None, :] - mb[:, None] * N[None, :])
            theta_b += c * _score(Sb, Nb, agg)
        if K >= 2:
            f = K / (K - 1.0)
            cross = max(0.0, float(np.sum(u[:-1] * u[1:] * st.adjacent)))  # overlapping neighbours
            var_boot += float(np.sum(u**2))  # what resampling K blocks from K gives: (K - 1) / K of it
            var_iid += f * float(np.sum(u**2))
            var_hac += f * (float(np.sum(u**2)) + 2.0 * cross)
            var_b += f * np.sum(W * u_b**2, axis=1)
    row["estimate"] = theta
    row["n_windows"] = n_windows
    row = _finish(row, blocks, cfg.min_blocks)
    if min(k for _, k in blocks) < 2:
        row["reason"] = row["reason"] or "one block: no interval"
        return row
    ok = np.isfinite(theta_b)
    if var_hac == 0.0:  # no spread at all (a model minus an identical one)
        row.update(lo=theta, hi=theta, se=0.0)
        return row
    if row["rankable"]:
        lo, hi, row["se"] = _bootstrap_t(theta, theta_b[ok], var_b[ok], var_hac, a2)
    else:
        lo, hi, row["se"] = _bootstrap_se_t(theta, theta_b[ok], stat, blocks, var_boot, var_iid, var_hac, a2)
    if not (np.isfinite(lo) and np.isfinite(hi)):
        row["reason"] = row["reason"] or "too few blocks for a finite interval"
        return row
    if stat.nonnegative:
        lo = max(lo, 0.0)
    row.update(lo=float(lo), hi=float(hi))
    return row


def _bootstrap_t(theta, theta_b, var_b, var_hac, a2) -> tuple[float, float, float]:
    """The studentized interval: each resample's statistic studentized by its own standard error
    (``var_b``: resampled blocks are independent), the estimate by the standard error with the adjacent
    blocks' covariance (``var_hac``)."""
    se = float(np.sqrt(var_hac))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (theta_b - theta) / np.sqrt(var_b)
    t = np.where(np.isnan(t), 0.0, t)  # a resample equal to the estimate with no spread
    q_hi, q_lo = np.quantile(t, [1.0 - a2, a2], method="inverted_cdf")
    return theta - q_hi * se, theta - q_lo * se, se


def _bootstrap_se_t(
    theta, theta_b, stat, blocks, var_boot, var_iid, var_hac, a2
) -> tuple[float, float, float]:
    """The interval under the minimum of blocks, where the studentized one is unstable (one block can
    dominate: a resample without it has almost no spread): the bootstrap standard error (of the log of a
    positive score), made unbiased (``var_iid / var_boot``: K / (K - 1)) and widened by the adjacent blocks'
    covariance, with a Student-t quantile on the blocks' degrees of freedom."""
    widen = float(np.sqrt(var_hac / var_boot)) if var_boot > 0.0 else 1.0
    df = max(1.0, sum(k - 1 for _, k in blocks) * (var_iid / var_hac if var_hac > 0.0 else 1.0))
    tq = float(scipy.stats.t.ppf(1.0 - a2, df))
    if stat.nonnegative and theta > 0.0 and bool(np.all(theta_b > 0.0)):
        sd = float(np.std(np.log(theta_b), ddof=1)) * widen
        return theta * np.exp(-tq * sd), theta * np.exp(tq * sd), theta * sd
    sd = float(np.std(theta_b, ddof=1)) * widen
    return theta - tq * sd, theta + tq * sd, sd


def _finish(row: dict, blocks: list[tuple[str, int]], min_blocks: int) -> dict:
    """Sets the block counts of a row (``blocks``: (stratum, blocks with a value) per stratum) and whether
    it is rankable: at least ``min_blocks`` blocks in all and 2 in each stratum (one block has no spread to
    estimate); the reason names the stratum or the count that falls short."""
    row["n_blocks"] = int(sum(k for _, k in blocks))
    row["min_blocks"] = int(min((k for _, k in blocks), default=0))
    if row["reason"]:
        return row
    need = f"(ranking needs {min_blocks})"
    if row["n_blocks"] < min_blocks:
        k = row["n_blocks"]
        row["reason"] = f"{k} independent block{'' if k == 1 else 's'} {need}"
    elif row["min_blocks"] < 2:
        where = min(blocks, key=lambda b: b[1])[0]
        row["reason"] = f"1 independent block in {where} (each stratum needs 2)"
    else:
        row["rankable"] = bool(np.isfinite(row["estimate"]))
    return row


def resolved(lo: float, hi: float) -> bool:
    """A difference is resolved when its interval excludes 0."""
    return bool(np.isfinite(lo) and np.isfinite(hi) and (lo > 0.0 or hi < 0.0))


# -- the ranking rule --------------------------------------------------------------------------------------
NOT_RANKED = "not ranked"
BEST = "best"
TIED = "tied for best"


def rank_board(scores: pd.DataFrame, differences: pd.DataFrame) -> pd.DataFrame:
    """Ranks rows by one score with their paired differences.

    ``scores``: one row per entry (index: its name), columns ``estimate``, ``rankable``, ``reason``;
    ``differences``: index ``(a, b)`` with ``lo``, ``hi`` of ``a - b`` (either order given suffices).
    Returns, per entry, ``rank`` (1 + the number of rankable entries resolved better than it; "" when not
    rankable) and ``standing``: ``best`` (resolved better than every other rankable entry), ``tied for
    best`` (the entries not resolved from the leader by point estimate and with no entry resolved better
    than them, when none is best), ``""`` (behind),
    or ``not ranked: <reason>``. A board with no rankable entry ranks nothing."""
    out = pd.DataFrame(index=scores.index, data={"rank": "", "standing": ""})
    ok = [
        i for i in scores.index if bool(scores.loc[i, "rankable"]) and np.isfinite(scores.loc[i, "estimate"])
    ]
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

    for i in ok:
        better = sum(1 for j in ok if j != i and diff(i, j)[0] > 0.0)  # i - j > 0: j resolved better
        out.loc[i, "rank"] = str(1 + better)
    leader = min(ok, key=lambda i: float(scores.loc[i, "estimate"]))
    others = [j for j in ok if j != leader]
    if all(diff(leader, j)[1] < 0.0 for j in others):
        out.loc[leader, "standing"] = BEST
    else:
        out.loc[leader, "standing"] = TIED
        for j in others:  # tied with the leader, and no other entry resolved better than it
            if not resolved(*diff(leader, j)) and out.loc[j, "rank"] == "1":
                out.loc[j, "standing"] = TIED
    return out


def board_verdict(standing: pd.Series) -> str:
    """One line for a board: who is best, who is tied, or that no entry could be ranked."""
    best = [str(i) for i, s in standing.items() if s == BEST]
    tied = [str(i) for i, s in standing.items() if s == TIED]
    if best:
        return f"best: {best[0]} (its paired difference from every other is resolved)"
    if tied:
        return f"tied for best: {', '.join(tied)} (their paired differences are not resolved)"
    why = sorted({str(s).removeprefix(f"{NOT_RANKED}: ") for s in standing if str(s).startswith(NOT_RANKED)})
    return "no entry ranked: " + ("; ".join(why) or "no entry")
