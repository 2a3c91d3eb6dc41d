"""A board's intervals, its ranking and the paper's claim, from the windows evaluate wrote (compare's side
of :mod:`skidbench.benchmark.scoring.intervals`; docs/intervals.md).

Every (model, terrain) of a board has its per-window table (``<ds>/eval/<model>/<terrain>[.<inputs>]
.windows.parquet``), and so has the floor (benchmark/scoring/floor.py). The windows of one terrain's test
split
are paired across models (the same windows, the same resampled blocks) and every statistic is computed
from them at once: each cell (model, terrain, split, metric) with its interval, equal to what evaluate
logged; the means over terrains; the ranking aggregate (:data:`AGGREGATE`: the mean of the paper's four
RMSREs, translational and rotational on CV and LD); the paired differences the ranking rule and the
paper's claim are decided on. Pure: the windows come in as
tables (:func:`skidbench.benchmark.board.boards.read_windows` reads them).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from skidbench.benchmark.scoring import intervals as iv
from skidbench.benchmark.scoring import metrics as mt
from skidbench.benchmark.scoring import ranks as rk
from skidbench.benchmark.scoring.floor import FLOOR
from skidbench.benchmark.scoring.settings import IntervalConfig

SPLITS = ("cv", "ld")
#: the ranking aggregate: the mean of the paper's metrics (translational and rotational RMSRE) on CV and LD
AGGREGATE = "mean4"
AGGREGATE_LABEL = "mean of 4 %"
#: the models of the paper (Rabiee & Biswas 2019), among which its claim is checked
PAPER_MODELS = ("ideal", "edd", "full_linear", "roc", "enhanced", "friction")
CLAIM_MODEL = "friction"
#: the columns of a per-window table :func:`build` reads (the metrics' where a table has them)
WINDOW_COLUMNS = ("split", "sequence", "start", "t0", *(m.column for m in mt.METRICS if m.bootstrap))
HOLDS, FAILS, UNRESOLVED = "holds", "does not hold", "not resolved by these data"


@dataclass
class Standings:
    """What compare shows of a board beyond the logged values (every frame indexed by position):

    - ``cells``: model, terrain, split, metric (name), estimate, lo, hi, n_windows, n_blocks, rankable,
      reason;
    - ``overall``: per model (the floor last), per paper metric and split the mean over terrains
      (``<metric>|<split>`` estimate/lo/hi columns), the aggregate (``estimate lo hi n_blocks rankable
      reason``), ``rank`` and ``standing``;
    - ``per_terrain``: model, terrain, the aggregate on that terrain, rank, standing;
    - ``verdicts``: ``overall`` and each terrain -> one line (best, tied, or nothing ranked);
    - ``claim``: ``overall`` and each terrain -> (verdict, lines) on the paper's claim;
    - ``ranked_by``: what the board ranks by (:data:`AGGREGATE` or a metric's ``<split>_<short>``);
    - ``differences``: the paired difference ``a - b`` of the ranking statistic over terrains of every two
      ranked models (a, b, estimate, lo, hi, rankable, reason, resolved), what the ranking rule decided on."""

    cells: pd.DataFrame
    overall: pd.DataFrame
    per_terrain: pd.DataFrame
    verdicts: dict[str, str] = field(default_factory=dict)
    claim: dict[str, tuple[str, list[str]]] = field(default_factory=dict)
    ranked_by: str = AGGREGATE
    differences: pd.DataFrame = field(default_factory=pd.DataFrame)

    def cell(self, model: str, terrain: str, split: str, metric: str) -> pd.Series | None:
        c = self.cells
        hit = c[
            (c["model"] == model)
            & (c["terrain"] == terrain)
            & (c["split"] == split)
            & (c["metric"] == metric)
        ]
        return hit.iloc[0] if len(hit) else None


def order_models(models: Sequence[str]) -> list[str]:
    """The paper's models in its order, then every other model by name (the order of every board)."""
    known = [m for m in PAPER_MODELS if m in models]
    return known + sorted(m for m in set(models) if m not in PAPER_MODELS)


def _metrics_of(w: pd.DataFrame) -> list[mt.Metric]:
    return [m for m in mt.METRICS if m.bootstrap is not None and m.column in w]


def build(
    windows: Mapping[tuple[str, str], pd.DataFrame],
    horizon_s: float,
    settings: IntervalConfig | None = None,
    rank_by: str = AGGREGATE,
    detail: bool = True,
) -> Standings:
    """Every statistic of a board from its windows (:func:`read_windows`), ranked by ``rank_by``
    (:data:`AGGREGATE`, or ``<split>_<short>`` of a headline metric: its mean over terrains).
    ``detail=False``: the overall ranking (its rows without the paper metrics' means over terrains) and the
    overall verdict and claim only, the same values as with detail; ``cells`` and ``per_terrain`` are left
    empty and no terrain gets a verdict or claim (what the error-against-horizon report shows of each
    horizon and stratum, at a fraction of the intervals to compute)."""
    terrains = sorted({t for _, t in windows})
    models = _order([m for m, _ in windows if m != FLOOR])
    has_floor = any(m == FLOOR for m, _ in windows)
    everyone = models + ([FLOOR] if has_floor else [])
    sample, cell_stats = _paired_sample(windows, horizon_s, settings, terrains, everyone)
    cells = _cells(sample, cell_stats if detail else {})
    paper = [m.name for m in mt.PAPER]

    def agg_stat(model: str, terrain_list: Sequence[str], name: str) -> tuple[iv.Stat | None, str]:
        """The aggregate over ``terrain_list`` (or one metric when ranking by it), or why there is none."""
        wanted = _ranked_cells(rank_by, paper)
        parts = []
        for t in terrain_list:
            for split, metric in wanted:
                s = cell_stats.get((model, t, split, metric))
                if s is None:
                    return None, f"no {metric} score on {t} {split.upper()}"
                parts.append(s)
        return (iv.mean_of(name, parts), "") if parts else (None, "no score")

    overall, differences = _rank_rows(sample, models, has_floor, terrains, agg_stat, "overall")
    margin = sample.cfg.margin
    verdicts = {"overall": rk.board_verdict(overall.set_index("model")["standing"], margin)}
    claim = {"overall": _claim(sample, cell_stats, models, terrains)}
    if not detail:
        return Standings(cells, overall, pd.DataFrame(), verdicts, claim, rank_by, differences)
    _terrain_means(sample, cell_stats, everyone, terrains, paper, overall)
    per_terrain = pd.concat(
        [_rank_rows(sample, models, has_floor, [t], agg_stat, t)[0].assign(terrain=t) for t in terrains],
        ignore_index=True,
    ) if terrains else pd.DataFrame()  # fmt: skip
    for t in terrains:
        pt = per_terrain[per_terrain["terrain"] == t]
        verdicts[t] = rk.board_verdict(pt.set_index("model")["standing"], margin)
    for t in terrains:
        claim[t] = _claim(sample, cell_stats, models, [t])
    return Standings(cells, overall, per_terrain, verdicts, claim, rank_by, differences)


def _paired_sample(
    windows: Mapping[tuple[str, str], pd.DataFrame], horizon_s: float, settings: IntervalConfig | None,
    terrains: Sequence[str], everyone: Sequence[str],
) -> tuple[iv.Sample, dict[tuple[str, str, str, str], iv.Stat]]:  # fmt: skip
    """The board's paired sample (each terrain's test split: the same windows and blocks for every model)
    and every cell's statistic in it, keyed (model, terrain, split, metric)."""
    sample = iv.Sample(settings or IntervalConfig())
    cell_stats: dict[tuple[str, str, str, str], iv.Stat] = {}
    columns = {k: _columns(w) for k, w in windows.items() if "split" in w}
    for terrain in terrains:
        for split in SPLITS:
            frames = {}
            for model in everyone:
                c = columns.get((model, terrain))
                rows = c["split"] == split if c is not None else None
                if rows is not None and rows.any():
                    frames[model] = {k: v[rows] for k, v in c.items() if k != "split"}
            if not frames:
                continue
            paired = _pair_columns(frames)
            key = iv.stratum_key(split, horizon_s, paired["sequence"])  # as evaluate's: the same draws
            if key in sample.strata:  # two terrains with the same sequence names: strata of their own
                key = f"{key}|{terrain}"
            cols, aggs = {}, {}
            for model, f in frames.items():
                for m in mt.METRICS:
                    if m.name in f:
                        cols[f"{model}|{m.name}"] = paired[f"{m.name}.{model}"]
                        aggs[f"{model}|{m.name}"] = m.bootstrap.aggregation
                        cell_stats[(model, terrain, split, m.name)] = iv.cell(
                            f"{model}|{terrain}|{split}|{m.name}", key, f"{model}|{m.name}"
                        )
            sample.add(key, paired["sequence"], paired["t0"], cols, horizon_s, aggs)
    return sample, cell_stats


def _columns(w: pd.DataFrame) -> dict[str, np.ndarray]:
    """The columns of a windows table a paired sample is made of, as arrays: split, sequence (text),
    start, t0 and each resampled metric's values in its logged unit (``<metric name>``)."""
    return {"split": w["split"].to_numpy(), "sequence": w["sequence"].astype(str).to_numpy(),
            "start": w["start"].to_numpy(), "t0": w["t0"].to_numpy(float),
            **{m.name: m.bootstrap.scale * m.window_values(w) for m in _metrics_of(w)}}  # fmt: skip


def _pair_columns(frames: Mapping[str, Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """:func:`pair_windows` of columns (``frames[model]``: sequence, start, t0 and its values) as arrays:
    ``sequence``, ``t0`` and ``<column>.<model>`` (floats). When every model has the same windows in the
    same order, without a repeated one, they are the first model's sorted by (sequence, start), stably,
    as the join's table; else the join's."""
    first = next(iter(frames.values()))
    seq, start = first["sequence"], first["start"]
    keys = ("sequence", "start", "t0")
    same = all(len(f["start"]) == len(start) and all(np.array_equal(f[k], first[k]) for k in keys)
               for f in frames.values())  # fmt: skip
    if same:
        _, code = np.unique(seq, return_inverse=True)
        order = np.lexsort((start, code))  # stable: pandas' sort_values on (sequence, start)
        a, b = code[order], start[order]
        same = not bool(np.any((a[1:] == a[:-1]) & (b[1:] == b[:-1])))  # no repeated window
    if not same:
        paired = pair_windows({m: pd.DataFrame(f) for m, f in frames.items()})
        return {c: paired[c].to_numpy(object if c == "sequence" else float) for c in paired.columns}
    out = {"sequence": seq[order], "t0": first["t0"][order]}
    for model, f in frames.items():
        out.update({f"{c}.{model}": np.asarray(v, dtype=float)[order] for c, v in f.items()
                    if c not in ("sequence", "start", "t0")})  # fmt: skip
    return out


def pair_windows(
    frames: Mapping[str, pd.DataFrame], on: Sequence[str] = ("sequence", "start")
) -> pd.DataFrame:
    """The windows of several models (``frames[model]``, each with the columns ``on`` and ``t0``) on one
    table: one row per window any model has, the other columns suffixed ``.<model>`` (NaN where a model
    lacks the window), sorted by ``on``. Windows come from the ground truth alone, so models scored on the
    same split have the same ones; the outer join keeps a model that lacks one from dropping it for the
    others. (:func:`_pair_columns` sets models that share every window side by side without the join.)"""
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


def _terrain_means(sample, cell_stats, everyone, terrains, paper, overall: pd.DataFrame) -> None:
    """Adds to ``overall`` the means over terrains of the paper's metrics with their intervals
    (``<metric>|<split>|estimate``, ``|lo``, ``|hi``), shown beside the aggregate."""
    for m_name in paper:
        for split in SPLITS:
            stats = {}
            for model in everyone:
                parts = [cell_stats.get((model, t, split, m_name)) for t in terrains]
                if all(p is not None for p in parts) and parts:
                    stats[model] = iv.mean_of(f"{model}|{m_name}|{split}", parts)
            res = iv.estimate(sample, list(stats.values())).set_index("stat") if stats else None
            for col in ("estimate", "lo", "hi"):
                overall[f"{m_name}|{split}|{col}"] = [
                    float(res.loc[stats[m].name, col]) if m in stats else np.nan for m in overall["model"]
                ]


def _order(models: Sequence[str]) -> list[str]:
    uniq = list(dict.fromkeys(models))
    return [m for m in PAPER_MODELS if m in uniq] + sorted(m for m in uniq if m not in PAPER_MODELS)


def _ranked_cells(rank_by: str, paper: Sequence[str]) -> list[tuple[str, str]]:
    """The (split, metric) cells the ranking statistic averages."""
    if rank_by == AGGREGATE:
        return [(split, m) for m in paper for split in SPLITS]
    split, _, short = str(rank_by).partition("_")
    return [(split, mt.get(short).name)]


def _cells(sample: iv.Sample, cell_stats: dict) -> pd.DataFrame:
    if not cell_stats:
        return pd.DataFrame(columns=["model", "terrain", "split", "metric", *iv.RESULT_COLUMNS])
    res = iv.estimate(sample, list(cell_stats.values()))
    keys = pd.DataFrame(list(cell_stats), columns=["model", "terrain", "split", "metric"])
    return pd.concat([keys, res], axis=1)


def _rank_rows(
    sample, models, has_floor, terrains, agg_stat, scope: str
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """One row per model (and the floor, last): the ranking statistic over ``terrains`` with its interval,
    rank and standing by :func:`ranks.rank_board` on the paired differences; and those differences
    (a, b, estimate, lo, hi, ..., resolved)."""
    stats, why = {}, {}
    for model in models + ([FLOOR] if has_floor else []):
        s, reason = agg_stat(model, terrains, f"{model}|{scope}")
        if s is None:
            why[model] = reason
        else:
            stats[model] = s
    res = iv.estimate(sample, list(stats.values())) if stats else pd.DataFrame(columns=iv.RESULT_COLUMNS)
    res.index = list(stats)
    rows = pd.DataFrame(index=models + ([FLOOR] if has_floor else []), columns=iv.RESULT_COLUMNS)
    for m in rows.index:
        if m in stats:
            rows.loc[m] = res.loc[m]
        else:
            rows.loc[m, ["estimate", "lo", "hi", "rankable", "reason"]] = [
                np.nan,
                np.nan,
                np.nan,
                False,
                why[m],
            ]
    entries = [m for m in models if m in stats and bool(rows.loc[m, "rankable"])]
    diffs = [
        iv.difference(f"{a}-{b}", stats[a], stats[b]) for i, a in enumerate(entries) for b in entries[i + 1 :]
    ]
    pairs = [(a, b) for i, a in enumerate(entries) for b in entries[i + 1 :]]
    d = iv.estimate(sample, diffs) if diffs else pd.DataFrame(columns=iv.RESULT_COLUMNS)
    d.index = pd.MultiIndex.from_tuples(pairs) if pairs else pd.MultiIndex.from_tuples([], names=["a", "b"])
    scores = rows.loc[models].assign(rankable=lambda x: x["rankable"].astype(bool))
    ranks = (
        rk.rank_board(scores, d, sample.cfg.margin) if models else pd.DataFrame(columns=["rank", "standing"])
    )
    rows["rank"] = ""
    rows["standing"] = ""
    for m in models:
        rows.loc[m, "rank"] = ranks.loc[m, "rank"]
        rows.loc[m, "standing"] = ranks.loc[m, "standing"]
    if has_floor:
        rows.loc[FLOOR, "standing"] = "reference (a perfect model against this ground truth; never ranked)"
    out = rows.reset_index(names="model").drop(columns=["stat"])
    d = d.drop(columns=["stat"], errors="ignore").reset_index(names=["a", "b"])
    d["resolved"] = [bool(r and rk.resolved(lo, hi)) for r, lo, hi in zip(d["rankable"], d["lo"], d["hi"],
                                                                           strict=True)]  # fmt: skip
    return out, d


def _claim(sample, cell_stats, models, terrains) -> tuple[str, list[str]]:
    """The paper's claim ("friction-based best on LD, comparable on CV") on ``terrains`` (their mean), among
    the paper's models that have every cell there (docs/intervals.md, "The paper's claim"). ``holds``: on
    each LD metric friction's paired difference from every other model is resolved below 0, and on each CV
    metric it is shown equivalent to every other within the margin (two one-sided tests, each at 5 %);
    ``does not hold``: Holm's correction over the tests against it (another model better on an LD metric,
    friction outside the margin of another on a CV metric) rejects one at a family-wise 5 %; else ``not
    resolved by these data``."""
    paper = [m.name for m in mt.PAPER]
    where = "mean over terrains" if len(terrains) > 1 else terrains[0]

    def stat(model, split, metric):
        parts = [cell_stats.get((model, t, split, metric)) for t in terrains]
        return iv.mean_of(f"{model}|{split}|{metric}", parts) if all(p is not None for p in parts) else None

    if CLAIM_MODEL not in models or any(stat(CLAIM_MODEL, s, m) is None for s in SPLITS for m in paper):
        return UNRESOLVED, [f"- {where}: the friction-based model has no score on every CV/LD metric here"]
    scored = [m for m in models if all(stat(m, s, p) is not None for s in SPLITS for p in paper)]
    others = [m for m in scored if m in PAPER_MODELS and m != CLAIM_MODEL]
    if not others:
        return UNRESOLVED, [f"- {where}: no other model of the paper was scored here"]
    names = [(split, m, o) for m in paper for split in ("ld", "cv") for o in others]
    diffs = [iv.difference(f"{sp}|{m}|{o}", stat(CLAIM_MODEL, sp, m), stat(o, sp, m)) for sp, m, o in names]
    res = iv.estimate(sample, diffs)
    margin, alpha = sample.cfg.margin, 1.0 - sample.cfg.level
    holds, against, lines, unrankable = True, [], [], []
    for (split, m, other), r in zip(names, res.itertuples(index=False), strict=True):
        ok = bool(r.rankable)
        if not ok:
            unrankable.append(f"{split.upper()} {m} vs {other}: {r.reason}")
        rng = (
            f"{r.estimate:+.2f} [{r.lo:+.2f}, {r.hi:+.2f}]"
            if np.isfinite(r.lo)
            else f"{r.estimate:+.2f} [n/a]"
        )
        if split == "ld":
            good = ok and r.hi < 0
            against.append(rk.p_greater(r.estimate, r.se, r.df) if ok else 1.0)  # another model better
            state = "resolved" if ok and rk.resolved(r.lo, r.hi) else "not resolved"
        else:
            p_tost = max(
                rk.p_greater(r.estimate, r.se, r.df, -margin), rk.p_greater(-r.estimate, r.se, r.df, -margin)
            )
            good = ok and p_tost < alpha
            p_out = min(1.0, 2.0 * rk.p_greater(abs(r.estimate), r.se, r.df, margin))  # outside the margin
            against.append(p_out if ok else 1.0)
            state = f"equivalent within +-{margin:g}" if good else f"not shown equivalent within +-{margin:g}"
        holds &= bool(good)
        lines.append(f"  - {split.upper()} {m}: friction - {other} = {rng} points ({state})")
    rejected = rk.holm(against, alpha)
    verdict = FAILS if any(rejected) else HOLDS if holds else UNRESOLVED
    for i, bad in enumerate(rejected):
        if bad:
            lines[i] += " (against the claim, Holm-corrected)"
    head = (
        f"- {where}: **{verdict}** (among {', '.join([CLAIM_MODEL, *others])}; LD: friction resolved better "
        f"than every other on both metrics; CV: equivalent to every other within +-{margin:g} point; "
        f"against it: Holm over {len(against)} tests at {alpha:.0%})"
    )
    if unrankable and verdict == UNRESOLVED:
        head += f"; too few blocks: {unrankable[0]}"
    return verdict, [head, *lines]
