"""Every score with its uncertainty: confidence intervals of scores and of paired differences
(docs/intervals.md says why each choice, with the coverage it was measured to have; the ranking rule on
them is :mod:`skidbench.benchmark.scoring.ranks`).

Not the predictive covariance of a learned model (docs/uncertainty.md): this is the sampling uncertainty
of a score, what another drive of the same robot on the same terrain would have given, as far as the
drives at hand show it.

**Units and blocks.** Overlapping windows of one drive share their data and a drive's errors persist, so
windows are not independent. A stratum's windows (a terrain's test split at one horizon) are summed into
*units* of :data:`UNIT_S` s of window starts within a sequence. A statistic's dependence is measured from
its own influence values over those units (:func:`dependence`: the integrated autocorrelation time
``tau``, corrected for the centring on a short drive's mean and widened by :data:`WIDEN`); the *blocks*
resampled are then pieces of about ``tau`` of each sequence, or whole sequences where a stratum has at
least ``min_sequences`` of them (:func:`_blocks`). Strata are resampled separately (stratified), every
model with the same draws, so differences of two models on the same windows are paired.

**Scores.** A score is a ratio of unit sums, ``m = sum(S_k) / sum(N_k)``, through ``g``: ``rms`` (RMSRE:
``S`` sums the squared relative errors, ``g = sqrt``) or ``mean``; a :class:`Stat` is any linear
combination of scores of several strata and columns (a cell, a mean of the four metrics, a mean over
terrains, the difference of two models).

**The interval.** The variance of a stratum's part is ``sum(u^2) tau / (1 - tau / n)`` over its ``n``
units (whole sequences: their spread; several sequences: the larger of that and the spread between
them), its effective degrees of freedom ``n / tau - 1``, combined over strata by Satterthwaite's rule.
The interval is Student's t on those degrees of freedom, on the log of a positive score (centred for the
log's bias), and where the statistic is rankable its union with the studentized block bootstrap's (which
shows a skew the blocks hold). The coverage bench (perf/coverage.py) measured it on the boards' designs.

**Rankable.** A statistic with at least ``min_blocks`` effective independent blocks (degrees of freedom +
1) and 2 blocks in each of its strata; below that it is shown with its reason and never ranked.

Pure: numpy, scipy and pandas, no MLflow, no files. Deterministic: the resampling of a stratum depends only
on ``(seed, stratum key, number of blocks)``, and a cell's blocks only on its own column, so evaluate (one
model) and compare (every model) give a cell the same interval.
"""

from __future__ import annotations

import threading
import zlib
from collections import OrderedDict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import scipy.stats

from skidbench.benchmark.errors import EvaluationError
from skidbench.benchmark.scoring.settings import IntervalConfig

#: s, the resolution at which window errors are summed before their autocorrelation is measured
UNIT_S = 1.0
#: the correlated part of the measured integrated autocorrelation time (``tau - 1``) is multiplied by this
#: before it is used: measured on one drive of 40-60 s it runs low (a 30 s error component is barely
#: visible in it); the coverage bench (perf/coverage.py, docs/intervals.md) needs 2 to reach 0.93
WIDEN = 2.0
AGGREGATIONS = ("rms", "mean")
#: the columns of :func:`estimate`'s frame (``df``: effective degrees of freedom; ``block_s``: the block
#: length the dependence of the errors gave, NaN where whole sequences are the units; ``scope``: what the
#: interval speaks for, :data:`SCOPES`)
RESULT_COLUMNS = ("stat", "estimate", "lo", "hi", "se", "n_windows", "n_blocks", "min_blocks", "rankable",
                  "reason", "df", "block_s", "scope")  # fmt: skip
#: what an interval speaks for: resampled within one drive, within each of several, or over drives
WITHIN_DRIVE, WITHIN_DRIVES, OVER_DRIVES = "within this drive", "within these drives", "over drives"
SCOPES = (WITHIN_DRIVE, WITHIN_DRIVES, OVER_DRIVES)


class IntervalError(EvaluationError):
    pass


def block_length(settings: IntervalConfig, horizon_s: float) -> float | None:
    """The fixed block length (s) of ``settings`` at a horizon, or None when it comes from the errors'
    autocorrelation. IntervalError when ``intervals.block_s`` is shorter than the horizon (a block's windows
    would overlap more than the next block's)."""
    if settings.block_s is None:
        return None
    if settings.block_s < horizon_s - 1e-9:
        raise IntervalError(
            f"intervals.block_s={settings.block_s:g} s is shorter than the {horizon_s:g} s horizon: blocks "
            "must be at least one horizon long (overlapping windows of one drive are not independent)"
        )
    return float(settings.block_s)


# -- blocks -------------------------------------------------------------------------------------------------
def _units(sequence: Sequence, t0: np.ndarray, unit_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit of every window (the windows of one sequence whose start falls in one ``unit_s`` interval from
    the sequence's first window), numbered by sequence then time: ``(unit (W,), sequence of each unit (K,),
    position of each unit in its sequence, in units (K,))``."""
    if not unit_s > 0:
        raise IntervalError(f"block length {unit_s} s is not positive")
    seq = pd.Series(np.asarray(sequence, dtype=object)).astype(str)
    t0 = np.asarray(t0, dtype=float)
    if len(seq) != len(t0):
        raise IntervalError(f"{len(seq)} sequence labels for {len(t0)} window start times")
    if len(t0) == 0:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    seq_code, _ = pd.factorize(seq)
    first = np.full(int(seq_code.max()) + 1, np.inf)
    np.minimum.at(first, seq_code, t0)
    pos = np.floor((t0 - first[seq_code]) / unit_s + 1e-9).astype(np.int64)
    stride = int(pos.max()) + 1
    uniq, unit = np.unique(seq_code.astype(np.int64) * stride + pos, return_inverse=True)
    return unit.astype(int), (uniq // stride).astype(int), (uniq % stride).astype(int)


def stratum_key(split: str, horizon_s: float, sequences: Iterable[str]) -> str:
    """The key of a stratum: a test split's sequences at one horizon (``ld@6s:grass_ld_00``). It seeds the
    stratum's draws, so evaluate and compare, which name the terrain differently, draw the same ones."""
    return f"{split}@{horizon_s:g}s:" + ",".join(sorted({str(s) for s in sequences}))


# -- strata and their unit sums ---------------------------------------------------------------------------
@dataclass
class Stratum:
    """The units of one stratum (:data:`UNIT_S` pieces of its sequences, or ``block_s`` ones when that is
    fixed) and, per column, the unit sums of its values: ``sums[column] = (S, N)`` ((K,) each: the sum of
    the values, squared for ``rms``, and the number of finite values per unit). ``seq``/``pos``: each
    unit's sequence (0..) and position in it (units); ``fixed``: the units are the blocks (``block_s``)."""

    key: str
    n_blocks: int
    seq: np.ndarray
    pos: np.ndarray
    n_windows: int
    horizon_s: float
    unit_s: float
    fixed: bool = False
    sums: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    aggregation: dict[str, str] = field(default_factory=dict)

    @property
    def n_sequences(self) -> int:
        return int(self.seq.max()) + 1 if len(self.seq) else 0


class Sample:
    """Everything a set of statistics is computed from: strata of windows, each with its units and the
    unit sums of its columns (``add``), and the bootstrap weights of each stratum's blocks (``weights``)."""

    def __init__(self, settings: IntervalConfig | None = None) -> None:
        self.cfg = settings or IntervalConfig()
        self.strata: dict[str, Stratum] = {}
        self._weights: dict[tuple[str, int], np.ndarray] = {}

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
        fixed = block_length(self.cfg, horizon_s)
        unit_s = fixed if fixed is not None else min(UNIT_S, float(horizon_s))
        unit, seq_of, pos_of = _units(sequence, t0, unit_s)
        n_units = len(seq_of)
        st = self.strata.get(key)
        if st is None:
            st = self.strata[key] = Stratum(key, n_units, seq_of, pos_of, len(unit), float(horizon_s), unit_s,
                                            fixed is not None)  # fmt: skip
        elif st.n_blocks != n_units or st.n_windows != len(unit):
            raise IntervalError(
                f"stratum {key}: {len(unit)} windows in {n_units} units, but its columns so far are on "
                f"{st.n_windows} windows in {st.n_blocks} units; pair them first (standings.pair_windows)"
            )
        for col, v in values.items():
            agg = aggregation if isinstance(aggregation, str) else aggregation[col]
            if agg not in AGGREGATIONS:
                raise IntervalError(f"column {col}: aggregation {agg!r} is not one of {AGGREGATIONS}")
            v = np.asarray(v, dtype=float)
            if v.shape != (len(unit),):
                raise IntervalError(
                    f"stratum {key}, column {col}: {v.shape[0]} values for {len(unit)} windows"
                )
            ok = np.isfinite(v)
            x = np.where(ok, v**2 if agg == "rms" else v, 0.0)
            S = np.bincount(unit, weights=x, minlength=n_units)
            N = np.bincount(unit, weights=ok.astype(float), minlength=n_units)
            st.sums[col] = (S, N)
            st.aggregation[col] = agg
        return st

    def weights(self, key: str, n_blocks: int | None = None) -> np.ndarray:
        """(B, K) bootstrap counts of ``n_blocks`` blocks of stratum ``key`` (each row: K blocks drawn with
        replacement; default: its units), from ``(seed, key, K)`` alone."""
        K = int(self.strata[key].n_blocks if n_blocks is None else n_blocks)
        if (key, K) not in self._weights:
            self._weights[(key, K)] = _draws(int(self.cfg.seed), key, K, int(self.cfg.resamples))
        return self._weights[(key, K)]


#: bytes of bootstrap draws kept per process (least recently used first out): a board's strata at every
#: horizon and protocol reuse the same draws, so the reuse within one horizon's boards stays in memory
#: whatever the dataset's size. The counts are kept in the smallest unsigned integer type that holds K (a
#: count is at most K: one byte each below 256 blocks, an eighth of the floats they are used as)
DRAWS_CACHE_BYTES = 64 * 2**20
_drawn: OrderedDict[tuple[int, str, int, int], np.ndarray] = OrderedDict()
_drawn_lock = threading.Lock()


def _draws(seed: int, key: str, K: int, resamples: int) -> np.ndarray:
    """(resamples, K) bootstrap counts of K blocks (floats), from ``(seed, key, K)`` alone: the same draws
    for every sample that resamples that stratum (compare's paired samples rank many pairs on the same
    strata; drawing them once per process, not once per sample, is the same numbers). Kept while the
    draws of the process stay under :data:`DRAWS_CACHE_BYTES`."""
    k = (seed, key, K, resamples)
    with _drawn_lock:
        counts = _drawn.get(k)
        if counts is not None:
            _drawn.move_to_end(k)
    if counts is None:
        rng = np.random.default_rng([seed, zlib.crc32(key.encode()), K])
        counts = rng.multinomial(K, np.full(K, 1.0 / K), size=resamples)
        counts = counts.astype(np.min_scalar_type(K))  # exact: every count is in 0..K
        with _drawn_lock:
            _drawn[k] = counts
            total = sum(v.nbytes for v in _drawn.values())
            while total > DRAWS_CACHE_BYTES and len(_drawn) > 1:
                total -= _drawn.popitem(last=False)[1].nbytes
    w = counts.astype(float)
    w.setflags(write=False)
    return w


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
    a2 = (1.0 - sample.cfg.level) / 2.0
    return pd.DataFrame([_one(sample, stat, a2) for stat in stats], columns=list(RESULT_COLUMNS))


@dataclass
class _Part:
    """One stratum of a statistic: its influence values over the stratum's units (the delta method) and the
    columns behind it ``(S, N, aggregation, coefficient)``."""

    st: Stratum
    u: np.ndarray
    cols: list[tuple[np.ndarray, np.ndarray, str, float]]
    present: int  # units with a window of the statistic
    min_sequences: int = IntervalConfig.min_sequences

    @property
    def whole_sequences(self) -> bool:
        return False if self.st.fixed else self.st.n_sequences >= self.min_sequences


def _parts(sample: Sample, stat: Stat, row: dict) -> tuple[list[_Part], list[tuple[str, int]], float]:
    """The strata of ``stat`` with its influence values, (stratum, units with a value) and its estimate;
    sets ``row``'s window count and, when a score has no window, its reason (then no parts)."""
    by_stratum: dict[str, list[tuple[str, float]]] = {}
    for st, col, c in stat.terms:
        if st not in sample.strata or col not in sample.strata[st].sums:
            raise IntervalError(f"statistic {stat.name}: no column {col!r} in stratum {st!r}")
        if c != 0.0:
            by_stratum.setdefault(st, []).append((col, c))
    parts, units, theta = [], [], 0.0
    for key, cols in by_stratum.items():
        st = sample.strata[key]
        present = int(min(np.count_nonzero(st.sums[col][1]) for col, _ in cols))
        units.append((key, present))
        row["n_windows"] += int(max(st.sums[col][1].sum() for col, _ in cols))
        if present == 0:
            row["reason"] = f"{key}: no window counts for this score"
            return [], units, np.nan
        u = np.zeros(st.n_blocks)
        got = []
        for col, c in cols:
            S, N = st.sums[col]
            agg = st.aggregation[col]
            m = S.sum() / N.sum()
            theta += c * float(_score(S.sum(), N.sum(), agg))
            u += c * _slope(m, agg) * (S - m * N) / N.sum()
            got.append((S, N, agg, c))
        parts.append(_Part(st, u, got, present, sample.cfg.min_sequences))
    return parts, units, theta


def _grid(part: _Part) -> np.ndarray:
    """(sequences, positions) the part's influence values on a dense grid (0 where a unit has no window)."""
    st = part.st
    g = np.zeros((st.n_sequences, int(st.pos.max()) + 1))
    g[st.seq, st.pos] = part.u
    return g


def dependence(parts: Sequence[_Part]) -> float:
    """The integrated autocorrelation time ``tau`` (in units) of a statistic's influence values, measured
    over the strata resampled within drives (pooled: one dependence, the strata's own spread): the
    autocorrelation summed up to its first non-positive lag, then corrected for the centring on each
    stratum's own mean (which pulls every lag down by about ``tau / n``: ``rho = rho^ (1 - c) + c``,
    ``c = tau / n``, iterated), capped at 0.9 of the stratum's units. ``tau`` units carry as much as one
    independent one: ``n / tau`` is the effective sample size."""
    gam, g0n, g0 = None, 0.0, 0.0
    for p in parts:
        g = _grid(p)
        P = g.shape[1]
        gj = sum(np.correlate(r, r, mode="full")[P - 1 :] for r in g)
        gam = gj if gam is None else _padded_sum(gam, gj)
        g0n += gj[0] * p.present
        g0 += gj[0]
    if gam is None or g0 <= 0.0:
        return 1.0
    n = g0n / g0  # the units of a stratum, weighted by its variance
    rho = gam / gam[0]
    lags = int(max(1, min(len(rho), np.floor(n / 2.0))))
    r = rho[1:lags]
    stop = np.flatnonzero(r <= 0.0)
    r = r[: stop[0]] if len(stop) else r  # the initial positive sequence
    tau = 1.0 + 2.0 * float(np.sum(r))
    c = min(tau / n, 0.5)  # one step of the centring's correction over the same lags
    tau = 1.0 + WIDEN * 2.0 * float(np.sum(r * (1.0 - c) + c))  # the correlated part widened
    return float(min(tau, 0.9 * n))
    return float(tau)


def _padded_sum(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.zeros(max(len(a), len(b)))
    out[: len(a)] += a
    out[: len(b)] += b
    return out


def _blocks(part: _Part, tau: float) -> tuple[np.ndarray, int, float]:
    """Block of each unit of a stratum: whole sequences where it has enough of them, its fixed blocks,
    else each sequence cut into pieces of about ``tau`` units (at least 2 where it is 2 ``tau`` long).
    Returns (block of each unit, number of blocks, block length in s or NaN for whole sequences)."""
    st = part.st
    if part.whole_sequences:
        return st.seq, st.n_sequences, float("nan")
    if st.fixed:
        return np.arange(st.n_blocks), st.n_blocks, st.unit_s
    span = np.zeros(st.n_sequences, dtype=int)
    np.maximum.at(span, st.seq, st.pos + 1)
    pieces = np.minimum(span, np.maximum(2, np.floor(span / max(tau, 1.0) + 1e-9))).astype(int)
    first = np.concatenate([[0], np.cumsum(pieces)[:-1]])
    block = first[st.seq] + np.minimum(st.pos * pieces[st.seq] // span[st.seq], pieces[st.seq] - 1)
    return block, int(pieces.sum()), float(max(tau, 1.0) * st.unit_s)


def _one(sample: Sample, stat: Stat, a2: float) -> dict:
    cfg = sample.cfg
    row = {"stat": stat.name, "estimate": np.nan, "lo": np.nan, "hi": np.nan, "se": np.nan, "n_windows": 0,
           "n_blocks": 0, "min_blocks": 0, "rankable": False, "reason": "", "df": np.nan,
           "block_s": np.nan, "scope": ""}  # fmt: skip
    parts, units, theta = _parts(sample, stat, row)
    strata = {st for st, _, _ in stat.terms}
    if not units:  # e.g. a model minus itself: every coefficient cancels
        row.update(estimate=0.0, lo=0.0, hi=0.0, se=0.0, rankable=True)
        row["n_blocks"] = sum(sample.strata[s].n_blocks for s in strata)
        row["min_blocks"] = min((sample.strata[s].n_blocks for s in strata), default=0)
        row["n_windows"] = sum(sample.strata[s].n_windows for s in strata)
        return row
    if not parts:
        return _finish(row, [(k, n) for k, n in units], cfg.min_blocks, np.nan)
    row["estimate"] = theta
    row["scope"] = _scope(parts)
    within = [p for p in parts if not p.whole_sequences and not p.st.fixed]
    tau = dependence(within) if within else 1.0
    B = int(cfg.resamples)
    theta_b, var_b = np.zeros(B), np.zeros(B)
    var, var_df, blocks, lengths = 0.0, 0.0, [], []
    for p in parts:
        block, K, length = _blocks(p, tau)
        blocks.append((p.st.key, K))
        lengths.append(length)
        U = np.bincount(block, weights=p.u, minlength=K)
        if p.whole_sequences or p.st.fixed:
            v_s = K / (K - 1.0) * float(np.sum(U**2)) if K >= 2 else np.inf
            df_s = K - 1.0
        else:
            n = float(p.present)
            v_s = float(np.sum(p.u**2)) * tau / max(1.0 - tau / n, 0.1)
            df_s = max(n / tau - 1.0, 0.5)  # under 1.5 effective blocks: as wide as half a degree
            v_s, df_s = _between_sequences(p, v_s, df_s)
        var += v_s
        var_df += v_s**2 / df_s if df_s > 0 else np.inf
        if K >= 2:
            tb, vb = _resampled(sample.weights(p.st.key, K), p, block, K)
            theta_b += tb
            var_b += vb
    df = var**2 / var_df if var_df > 0 and np.isfinite(var_df) else (np.inf if var_df == 0 else 0.0)
    row["block_s"] = float(np.nanmax(lengths)) if np.any(np.isfinite(lengths)) else np.nan
    row = _finish(row, blocks, cfg.min_blocks, df)
    if min(k for _, k in blocks) < 2 or not df > 0:
        row["reason"] = row["reason"] or "one unit: no interval"
        return row
    if var == 0.0:  # no spread at all (a model minus an identical one)
        row.update(lo=theta, hi=theta, se=0.0)
        return row
    ok = np.isfinite(theta_b)
    lo, hi, row["se"] = _student_t(theta, stat, var, df, a2, _log_bias(parts))
    if row["rankable"]:  # the union with the studentized bootstrap's: its skew where the blocks show one
        lo_t, hi_t, _ = _bootstrap_t(theta, theta_b[ok], var_b[ok], var, a2)
        lo, hi = min(lo, lo_t), max(hi, hi_t)
    if not (np.isfinite(lo) and np.isfinite(hi)):
        row["reason"] = row["reason"] or "too few blocks for a finite interval"
        return row
    if stat.nonnegative:
        lo = max(lo, 0.0)
    row.update(lo=float(lo), hi=float(hi))
    return row


def _between_sequences(part: _Part, var: float, df: float) -> tuple[float, float]:
    """A stratum of several sequences (fewer than are resampled whole): the spread between its sequences
    (each one's influence sum) where it is larger than the dependence within them gives, with its
    degrees of freedom (sequences - 1). A slow error component shows between drives before it shows in
    any one of them."""
    k = part.st.n_sequences
    if k < 2:
        return var, df
    U = np.bincount(part.st.seq, weights=part.u, minlength=k)
    between = k / (k - 1.0) * float(np.sum(U**2))
    return (between, k - 1.0) if between > var else (var, df)


def _scope(parts: Sequence[_Part]) -> str:
    if all(p.whole_sequences for p in parts):
        return OVER_DRIVES
    if len(parts) == 1 and parts[0].st.n_sequences == 1:
        return WITHIN_DRIVE
    return WITHIN_DRIVES


#: elements of the (resamples, blocks) arrays :func:`_resampled` works on at once (512 kB an array): its
#: passes over them stay in the processor's cache, and its two arrays are allocated once per call
_CHUNK = 65536


def _resampled(W: np.ndarray, part: _Part, block: np.ndarray, K: int) -> tuple[np.ndarray, np.ndarray]:
    """Each resample's statistic over a stratum's blocks and its variance (resampled blocks are taken as
    independent: the sum of the resample's squared block influence values, times K / (K - 1)). Computed
    for a chunk of resamples at a time (each resample's numbers are its own: the same in any chunk)."""
    B = W.shape[0]
    theta_b = np.zeros(B)
    cols = []
    for S, N, agg, c in part.cols:
        Sk, Nk = np.bincount(block, weights=S, minlength=K), np.bincount(block, weights=N, minlength=K)
        Sb, Nb = W @ Sk, W @ Nk
        with np.errstate(divide="ignore", invalid="ignore"):
            mb = Sb / Nb
            cols.append((Sk, Nk, mb, c * _slope(mb, agg) / Nb))
        theta_b += c * _score(Sb, Nb, agg)
    var_b = np.empty(B)
    rows = max(1, _CHUNK // K)
    u, t = np.empty((min(rows, B), K)), np.empty((min(rows, B), K))
    for i in range(0, B, rows):
        j = min(i + rows, B)
        u_b, tmp = u[: j - i], t[: j - i]
        u_b.fill(0.0)
        for Sk, Nk, mb, f in cols:  # u_b += f (Sk - mb Nk), column by column
            with np.errstate(divide="ignore", invalid="ignore"):
                np.multiply.outer(mb[i:j], Nk, out=tmp)
                np.subtract(Sk, tmp, out=tmp)
                np.multiply(f[i:j, None], tmp, out=tmp)
                np.add(u_b, tmp, out=u_b)
        np.square(u_b, out=u_b)
        np.multiply(W[i:j], u_b, out=u_b)
        np.sum(u_b, axis=1, out=var_b[i:j])
    return theta_b, K / (K - 1.0) * var_b


def _bootstrap_t(theta, theta_b, var_b, var, a2) -> tuple[float, float, float]:
    """The studentized interval: each resample's statistic studentized by its own standard error
    (``var_b``: resampled blocks are independent), the estimate by the standard error that counts the
    dependence of the errors (``var``)."""
    se = float(np.sqrt(var))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (theta_b - theta) / np.sqrt(var_b)
    t = np.where(np.isnan(t), 0.0, t)  # a resample equal to the estimate with no spread
    q_hi, q_lo = np.quantile(t, [1.0 - a2, a2], method="inverted_cdf")
    return theta - q_hi * se, theta - q_lo * se, se


def _log_bias(parts: Sequence[_Part]) -> float:
    """How much the log of a score is low on average, per unit of its squared relative standard error.
    The second-order delta method gives 1 for an RMS (the square root of a mean: -Var(m) / 4 m^2) and 1/2
    for a mean; on the coverage bench's skewed errors with 2-5 effective blocks the measured bias of a one
    drive RMSRE was twice that (-0.12 against -0.06 in the log), so twice it is used."""
    return 2.0 if all(agg == "rms" for p in parts for _, _, agg, _ in p.cols) else 1.0


def _student_t(theta, stat, var, df, a2, log_bias=1.0) -> tuple[float, float, float]:
    """The interval under the minimum of blocks, where the studentized one is unstable (one block can
    dominate: a resample without it has almost no spread): the standard error (of the log of a positive
    score, centred where the log's second-order bias puts the true value, so the interval is asymmetric
    as the score's spread is) with a Student-t quantile on the effective degrees of freedom."""
    tq = float(scipy.stats.t.ppf(1.0 - a2, max(df, 0.5)))
    sd = float(np.sqrt(var))
    if stat.nonnegative and theta > 0.0:
        rel = sd / theta
        mid = theta * np.exp(log_bias * rel**2)
        return mid * np.exp(-tq * rel), mid * np.exp(tq * rel), sd
    return theta - tq * sd, theta + tq * sd, sd


def _finish(row: dict, blocks: list[tuple[str, int]], min_blocks: int, df: float) -> dict:
    """Sets the block counts and effective degrees of freedom of a row (``blocks``: (stratum, blocks) per
    stratum) and whether it is rankable: at least ``min_blocks`` effective independent blocks (``df + 1``:
    the blocks' Satterthwaite degrees of freedom, the dependence counted) and 2 blocks in each stratum; the
    reason names the stratum or the count that falls short."""
    row["n_blocks"] = int(sum(k for _, k in blocks))
    row["min_blocks"] = int(min((k for _, k in blocks), default=0))
    row["df"] = float(df)
    if row["reason"]:
        return row
    need = f"(ranking needs {min_blocks})"
    if row["min_blocks"] < 2:
        where = min(blocks, key=lambda b: b[1])[0]
        if len(blocks) == 1:
            row["reason"] = f"1 independent block {need}"
        else:
            row["reason"] = f"1 independent block in {where} (each stratum needs 2)"
    elif not df + 1.0 >= min_blocks - 1e-9:
        row["reason"] = f"{max(df + 1.0, 1.0):.1f} effective independent blocks {need}"
    else:
        row["rankable"] = bool(np.isfinite(row["estimate"]))
    return row
