"""The leaderboard's tables (``skidbench compare``): the ranked summary over terrains, the standings under
the ranking rule with their intervals, the per-terrain detail, the protocols side by side, and their
Markdown; pure functions of a board (:func:`selection.board_from_runs`) and its standings
(:mod:`skidbench.benchmark.scoring.standings`), no MLflow and no files. benchmark/board/compare.py writes
them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd

from skidbench.benchmark.board import boards as brd
from skidbench.benchmark.board.installed import NOT_INSTALLED
from skidbench.benchmark.errors import EvaluationError
from skidbench.benchmark.scoring import intervals as iv
from skidbench.benchmark.scoring import metrics as mt
from skidbench.benchmark.scoring import ranks as rk
from skidbench.benchmark.scoring import standings as st
from skidbench.benchmark.scoring.floor import FLOOR
from skidbench.pipeline.core.layout import PROTOCOLS

SPLITS = ("cv", "ld")


class CompareError(EvaluationError):
    pass


# -- the leaderboard --------------------------------------------------------------------------------
def _windows(counts: pd.Series) -> str:
    """The windows behind an RMSRE, summed over terrains, as text ("?" when the runs did not log it)."""
    vals = pd.to_numeric(counts, errors="coerce").to_numpy(float)
    return str(int(np.nansum(vals))) if np.isfinite(vals).any() else "?"


def check_one_protocol(board: pd.DataFrame) -> str:
    """The one input protocol of a board's runs; CompareError when it holds runs of several (runs driven
    by different inputs are never ranked together) or of none recorded."""
    found = sorted({str(x) for x in board["inputs"]}) if "inputs" in board else ["unknown"]
    if len(found) > 1:
        raise CompareError(
            f"the selected runs were driven by different input protocols {found}; runs of different "
            "protocols are never ranked together: choose one with inputs=<protocol> (the report sets the "
            "protocols side by side per model instead)"
        )
    return found[0] if found else "unknown"


def _optional_cells(values: pd.Series, metric: mt.Metric) -> pd.Series:
    """The cells of an optional metric (uncertainty): empty for a model without it (a deterministic
    model), else the number as shown (``metric.scale``), to 0.1."""
    return values.map(lambda v: "" if not np.isfinite(v) else f"{v * metric.scale:.1f}")


def _metric_cells(row: dict[str, Any], ok: pd.DataFrame, horizon_s: float) -> None:
    """Per metric and split: the mean over terrains of the finished runs (``over_terrains``) and, for a
    metric with a window count, the windows behind it summed over terrains."""
    for metric in mt.METRICS:
        for split in SPLITS:
            key = metric.metric_key(split, horizon_s)
            vals = ok[key].to_numpy(float) if key in ok else np.array([])
            row[metric.column_label(split)] = metric.over_terrains(vals)
            n_key = metric.windows_key(split, horizon_s)
            if n_key is not None:
                row[metric.count_label(split)] = _windows(ok[n_key] if n_key in ok else pd.Series([]))


def summary_table(
    board: pd.DataFrame, horizon_s: float, rank_by: str, standings: st.Standings | None = None
) -> pd.DataFrame:
    """Per model: the mean over terrains of each RMSRE (%), terrains scored, failures; ranked by
    ``rank_by`` (``<split>_<trans|rot>``, e.g. ``ld_trans``: :func:`tracking.rank_key`). CompareError when
    the board mixes input protocols (:func:`check_one_protocol`). With ``standings``
    (:mod:`skidbench.benchmark.scoring.standings`): ranked by its statistic with the ranking rule
    (:func:`standings_table`), every paper metric with its 95 % interval, and the floor."""
    check_one_protocol(board)
    if standings is not None:
        return standings_table(board, horizon_s, standings)
    rank_keys = (  # the aggregate: the mean of the paper's metrics on CV and LD (standings.AGGREGATE)
        [m.metric_key(s, horizon_s) for m in mt.PAPER for s in SPLITS]
        if rank_by == st.AGGREGATE
        else [mt.rank_key(rank_by, horizon_s)]
    )
    rows = []
    for model, g in board.groupby("model", sort=False):
        ok = g[g["status"] == "FINISHED"]
        row: dict[str, Any] = {"model": marked(model, g)}
        _metric_cells(row, ok, horizon_s)
        row["terrains"] = f"{len(ok)}/{len(g)}"
        bad = g[g["status"] != "FINISHED"]
        row["failed"] = (
            ", ".join(f"{t} ({s})" for t, s in zip(bad["terrain"], bad["status"], strict=True)) or ""
        )
        ranked = [ok[k].to_numpy(float) for k in rank_keys if len(ok) and k in ok]
        means = [np.nanmean(v) if np.isfinite(v).any() else np.nan for v in ranked]
        row["_key"] = float(np.mean(means)) if means and np.isfinite(means).all() else np.nan
        row["_unranked"] = bool(unranked_why(g))  # shown, never ranked
        row["_key"] = np.inf if row["_unranked"] else row["_key"]
        rows.append(row)
    out = pd.DataFrame(rows).sort_values("_key", na_position="last", kind="stable")
    out.insert(0, "rank", [str(k) for k in range(1, len(out) + 1)])
    out.loc[out["_unranked"].to_numpy(bool), "rank"] = ""
    out = out.drop(columns="_unranked")
    for metric in (m for m in mt.METRICS if m.optional):
        for split in SPLITS:
            lab = metric.column_label(split)
            out[lab] = _optional_cells(out[lab].astype(float), metric)
    return out.drop(columns="_key").reset_index(drop=True)


def ci_text(v: float, lo: float, hi: float, digits: int = 2) -> str:
    """``6.91 [6.20, 7.62]``: a value and its interval as the boards show them (``n/a`` for no value)."""
    if not np.isfinite(v):
        return "n/a"
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return f"{v:.{digits}f} [n/a]"
    return f"{v:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def scope_line(standings: st.Standings) -> str:
    """What the board's intervals cover (their ``scope``, docs/intervals.md "What an interval covers"): the
    means over terrains' and each terrain's cells', in one line; "" when no interval was computed."""

    def kinds(frame: pd.DataFrame) -> list[str]:
        got = set(frame["scope"].dropna().astype(str)) if "scope" in frame else set()
        return [k for k in iv.SCOPES if k in got]

    means, cells = kinds(standings.overall), kinds(standings.cells)
    if not means and not cells:
        return ""
    parts = [f"the means over terrains {' / '.join(means)}"] if means else []
    parts += [f"each terrain's cells {' / '.join(cells)}"] if cells else []
    if any(k != iv.OVER_DRIVES for k in means + cells):
        covers = "they cover other stretches of the recorded drives, not how another drive would differ"
    else:
        covers = "they cover other drives like the recorded ones"
    return f'Intervals: {"; ".join(parts)}: {covers} (docs/intervals.md, "What an interval covers").'


def standings_table(board: pd.DataFrame, horizon_s: float, standings: st.Standings) -> pd.DataFrame:
    """The leaderboard under the ranking rule (docs/intervals.md): per model, in order of its rank and
    point estimate, ``rank`` (1 + the models resolved better), ``standing`` (best / tied for best / not
    ranked: why), the ranking statistic (:data:`standings.AGGREGATE`: the mean of the four RMSREs) and each
    paper metric's mean over terrains with their 95 % intervals, the other headline metrics, the windows and
    blocks behind them, terrains and failures; the floor last (never ranked)."""
    ov = standings.overall.set_index("model")
    floor = standings.cells[standings.cells["model"] == FLOOR]
    agg_label = st.AGGREGATE_LABEL if standings.ranked_by == st.AGGREGATE else f"{standings.ranked_by} %"
    rows = []
    missing = [m for m in board["model"].dropna().unique() if m not in ov.index]  # failed everywhere
    for model in [*ov.index, *missing]:
        g = board[board["model"] == model]
        ok = g[g["status"] == "FINISHED"]
        why = unranked_why(g) or "no finished run to score"
        r = ov.loc[model] if model in ov.index else _no_standing(ov.columns, why)
        row: dict[str, Any] = {"rank": r["rank"], "model": marked(model, g) if len(g) else model}
        row[agg_label] = ci_text(float(r["estimate"]), float(r["lo"]), float(r["hi"]))
        for metric in mt.HEADLINE:
            for split in SPLITS:
                lab = metric.column_label(split)
                if metric.paper:  # with its interval (the mean over terrains, resampled)
                    c = f"{metric.name}|{split}|"
                    row[lab] = ci_text(float(r[c + "estimate"]), float(r[c + "lo"]), float(r[c + "hi"]))
                else:
                    key = metric.metric_key(split, horizon_s)
                    vals = ok[key].to_numpy(float) if key in ok else np.array([])
                    if model == FLOOR:
                        vals = floor[(floor["metric"] == metric.name) & (floor["split"] == split)]["estimate"]
                        vals = vals.to_numpy(float)
                    v = metric.over_terrains(vals) if len(vals) else np.nan
                    row[lab] = "n/a" if not np.isfinite(v) else f"{v:.{3 if v < 1 else 2}f}"
                n_key = metric.windows_key(split, horizon_s)
                if n_key is not None:
                    counts = ok[n_key] if n_key in ok else pd.Series([])
                    if model == FLOOR:
                        counts = floor[(floor["metric"] == metric.name) & (floor["split"] == split)][
                            "n_windows"
                        ]
                    row[metric.count_label(split)] = _windows(counts)
        row["blocks"] = int(r["n_blocks"]) if pd.notna(r["n_blocks"]) else 0
        row["standing"] = r["standing"]
        row["terrains"] = f"{len(ok)}/{len(g)}" if len(g) else str(board["terrain"].nunique())
        bad = g[g["status"] != "FINISHED"]
        row["failed"] = ", ".join(f"{t} ({s})" for t, s in zip(bad["terrain"], bad["status"], strict=True))
        row["_key"] = (0 if r["rank"] else 1 if model != FLOOR else 2, _rank_number(r["rank"]),
                       float(r["estimate"]) if pd.notna(r["estimate"]) else np.inf)  # fmt: skip
        rows.append(row)
    out = pd.DataFrame(rows)
    out = out.iloc[sorted(range(len(out)), key=lambda i: out["_key"].iloc[i])]
    return out.drop(columns="_key").reset_index(drop=True)


def _no_standing(columns: pd.Index, why: str) -> pd.Series:
    """A standings row for a model with nothing to score: no value, not ranked, why."""
    r = pd.Series(np.nan, index=columns, dtype=object)
    r["rank"], r["standing"], r["n_blocks"] = "", f"{rk.NOT_RANKED}: {why}", 0
    return r


def _rank_number(rank: Any) -> int:
    try:
        return int(rank)
    except (TypeError, ValueError):
        return 10**6


def marked(model: str, rows: pd.DataFrame) -> str:
    """A model's name on the leaderboard: ``<name> (external)`` for a row scored from a predictions file,
    ``<name> (code not installed here)`` for rows whose code is not installed here (board/installed.py)."""
    if _code_not_here(rows):
        return f"{model} ({NOT_INSTALLED})"
    return f"{model} (external)" if "external" in rows and rows["external"].any() else str(model)


def unranked_why(rows: pd.DataFrame) -> str:
    """Why a model's rows are not ranked though they finished ("" when nothing stops them): their code is
    not installed here (board/installed.py)."""
    why = _code_not_here(rows)
    return why[0] if why else ""


def _code_not_here(rows: pd.DataFrame) -> list[str]:
    """The "code not installed here" notes of ``rows`` (empty, missing or NaN: none; the floor's rows and
    rows added after the check carry NaN)."""
    if "code_here" not in rows:
        return []
    return [str(x) for x in rows["code_here"] if isinstance(x, str) and x]


def detail_table(
    board: pd.DataFrame, horizon_s: float, standings: st.Standings | None = None
) -> pd.DataFrame:
    """One row per (model, terrain): every metric, the windows behind it, and for a metric with an interval
    its bounds and independent blocks (``<label> lo``, ``<label> hi``, ``<label> blocks``, as evaluate
    logged them); fit and predict numbers, the run, the reason of a failure. With ``standings``: the
    ranking aggregate on the terrain with its interval, rank and standing, and the floor of the row's
    terrain (``floor <label>``: added columns; the report shows the floor's own rows: report_detail)."""
    models = [marked(m, board.loc[[i]]) for i, m in zip(board.index, board["model"], strict=True)]
    out = pd.DataFrame({"model": models, "inputs": board["inputs"], "terrain": board["terrain"],
                        "status": board["status"]})  # fmt: skip
    for metric in mt.METRICS:
        for split in SPLITS:
            values = board[metric.metric_key(split, horizon_s)]
            lab = metric.column_label(split)
            out[lab] = _optional_cells(values.astype(float), metric) if metric.optional else values
            n_key = metric.windows_key(split, horizon_s)
            if n_key is not None:
                out[metric.count_label(split)] = [_windows(pd.Series([v])) for v in board[n_key]]
            if metric.bootstrap is not None and not metric.optional:
                lo, hi, blocks = metric.interval_keys(split, horizon_s)
                out[f"{lab} lo"] = board[lo] if lo in board else np.nan
                out[f"{lab} hi"] = board[hi] if hi in board else np.nan
                out[f"{lab} blocks"] = board[blocks] if blocks in board else np.nan
                seed_sd = f"{metric.metric_key(split, horizon_s)}_seed_sd"
                if seed_sd in board and board[seed_sd].notna().any():  # a model fitted over several seeds
                    out[f"{lab} seed sd"] = board[seed_sd]
    if standings is not None and len(standings.per_terrain):
        pt = standings.per_terrain.set_index(["model", "terrain"])
        keys = list(zip(board["model"], board["terrain"], strict=True))
        label = st.AGGREGATE_LABEL if standings.ranked_by == st.AGGREGATE else f"{standings.ranked_by} %"
        for col, name in (("estimate", label), ("lo", f"{label} lo"), ("hi", f"{label} hi")):
            out[name] = [float(pt.loc[k, col]) if k in pt.index else np.nan for k in keys]
        out["rank on terrain"] = [str(pt.loc[k, "rank"]) if k in pt.index else "" for k in keys]
        out["standing on terrain"] = [str(pt.loc[k, "standing"]) if k in pt.index else "" for k in keys]
        floor = standings.cells[standings.cells["model"] == FLOOR].set_index(["terrain", "split", "metric"])
        for metric in mt.PAPER:  # the floor of the row's terrain, beside the model's value
            for split in SPLITS:
                at = [(t, split, metric.name) for t in board["terrain"]]
                out[f"floor {metric.column_label(split)}"] = [
                    float(floor.loc[k, "estimate"]) if k in floor.index else np.nan for k in at
                ]
    out["fit_loss"] = board["fit_loss"]
    out["fit s"] = board["fit_time_s"]
    out["predict s"] = board["predict_time_s"]
    out["run"] = board["run_id"].str[:8]
    out["reason"] = board["reason"]
    return out


def report_detail(board: pd.DataFrame, horizon_s: float, standings: st.Standings | None) -> pd.DataFrame:
    """The report's per-terrain table: :func:`detail_table` with the floor's own rows (status
    ``reference``) after the models'."""
    if standings is None:
        return detail_table(board, horizon_s)
    detail = detail_table(_with_floor_rows(board, horizon_s, standings), horizon_s, standings)
    return detail.drop(columns=[c for c in detail.columns if c.startswith("floor ")])


def _with_floor_rows(board: pd.DataFrame, horizon_s: float, standings: st.Standings) -> pd.DataFrame:
    """``board`` with a row per terrain for the floor (status ``reference``), its cells from the windows."""
    cells = standings.cells[standings.cells["model"] == FLOOR]
    if not len(cells):
        return board
    rows = []
    for terrain, g in cells.groupby("terrain", sort=True):
        row: dict[str, Any] = {"model": FLOOR, "inputs": board["inputs"].iloc[0] if len(board) else "",
                               "terrain": terrain, "status": "reference", "reason": "never ranked",
                               "run_id": "", "external": False}  # fmt: skip
        for r in g.itertuples(index=False):
            metric = mt.get(r.metric)
            lo, hi, blocks = metric.interval_keys(r.split, horizon_s)
            row[metric.metric_key(r.split, horizon_s)] = r.estimate
            row[lo], row[hi], row[blocks] = r.lo, r.hi, r.n_blocks
            n_key = metric.windows_key(r.split, horizon_s)
            if n_key is not None:
                row[n_key] = r.n_windows
        rows.append(row)
    return pd.concat([board, pd.DataFrame(rows)], ignore_index=True)


def display_detail(detail: pd.DataFrame) -> pd.DataFrame:
    """The per-terrain table as the report shows it: each value with its interval in one cell
    (``6.91 [6.20, 7.62]``), the windows and blocks behind it in one (``1171 w / 4 b``)."""
    out = detail.copy()
    for col in list(out.columns):
        if f"{col} lo" in out and f"{col} hi" in out:
            triples = zip(out[col], out[f"{col} lo"], out[f"{col} hi"], strict=True)
            out[col] = [
                ci_text(float(v), float(a), float(b)) if pd.notna(v) else "n/a" for v, a, b in triples
            ]
            if f"{col} seed sd" in out:  # the seed spread beside the data interval
                out[col] = [c + (f" ±{sd:.2f}s" if pd.notna(sd) else "")
                            for c, sd in zip(out[col], out[f"{col} seed sd"], strict=True)]  # fmt: skip
                out = out.drop(columns=[f"{col} seed sd"])
            out = out.drop(columns=[f"{col} lo", f"{col} hi"])
            n_col = col.removesuffix(" %").removesuffix(" m") + " n"
            if f"{col} blocks" in out and n_col in out:
                out[n_col] = [f"{n} w / {int(b)} b" if pd.notna(b) else str(n)
                              for n, b in zip(out[n_col], out[f"{col} blocks"], strict=True)]  # fmt: skip
            out = out.drop(columns=[f"{col} blocks"], errors="ignore")
    return out


def markdown_table(df: pd.DataFrame, digits: int = 2) -> str:
    def fmt(v: Any) -> str:
        if isinstance(v, float | np.floating):
            if not np.isfinite(v):
                return "n/a"
            return f"{v:.{digits}f}" if abs(v) >= 10 ** (-digits) or v == 0 else f"<{10 ** (-digits):g}"
        return str(v).replace("|", "\\|")

    head = "| " + " | ".join(map(str, df.columns)) + " |"
    sep = "|" + "|".join("---:" if pd.api.types.is_numeric_dtype(df[c]) else "---" for c in df.columns) + "|"
    body = ["| " + " | ".join(fmt(v) for v in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join([head, sep, *body])


# -- the three protocols side by side ----------------------------------------------------------------
def decomposition_table(boards: dict[str, pd.DataFrame], horizon_s: float) -> pd.DataFrame:
    """Per model (mean over the terrains scored under every protocol shown): each headline metric under
    each protocol, ``commanded / response / measured``; a comparison of one model's inputs, not a ranking.
    The numbers are also in the hidden columns ``_<metric>_<split>_<protocol>`` (for the figure)."""
    shown = [p for p in PROTOCOLS if p in boards]
    if not shown:
        return pd.DataFrame()
    ok = {p: b[b["status"] == "FINISHED"] for p, b in boards.items()}
    models = st.order_models(sorted({m for b in ok.values() for m in b["model"]}))
    rows = []
    for m in models:
        terrains = set.intersection(*[set(ok[p][ok[p]["model"] == m]["terrain"]) for p in shown])
        row: dict[str, Any] = {"model": m, "terrains": len(terrains)}
        for metric in mt.HEADLINE:
            for split in SPLITS:
                key = metric.metric_key(split, horizon_s)
                vals = []
                for p in shown:
                    b = ok[p][(ok[p]["model"] == m) & ok[p]["terrain"].isin(terrains)]
                    v = b[key].to_numpy(float)
                    vals.append(metric.over_terrains(v))
                row[metric.column_label(split)] = " / ".join(
                    "n/a" if not np.isfinite(v) else f"{v:.2f}" for v in vals
                )
                for p, v in zip(shown, vals, strict=True):
                    row[f"_{metric.name}_{split}_{p}"] = v
        rows.append(row)
    df = pd.DataFrame(rows)
    df.attrs["protocols"] = shown
    return df


def leaderboard_texts(
    board: pd.DataFrame,
    runs: pd.DataFrame,
    horizon_s: float,
    rank_by: str,
    header: Sequence[str],
    standings: st.Standings | None = None,
) -> tuple[str, str, str]:
    """One protocol's leaderboard as ``(csv, md, the ranked table's md)``: the CSV holds one row per
    (model, terrain) with every metric and the provenance of its run (:func:`boards.provenance`: run id,
    options digest, versions, ...); the Markdown ``header`` lines, the ranked means over terrains, then
    the rows with their run, options digest, model code and skidbench commit. With ``standings``: ranked
    by the ranking rule, every cell with its interval and the terrain's floor (added CSV columns)."""
    summary = summary_table(board, horizon_s, rank_by, standings)
    detail = detail_table(board, horizon_s, standings).drop(columns=["run"])
    prov = brd.provenance(runs).drop(columns=["reproduce"])
    rows = pd.concat([detail, board[["run_id"]]], axis=1).merge(prov, on="run_id", how="left")
    short = lambda col, n=8: rows[col].fillna("").astype(str).str[:n]  # noqa: E731
    shown = detail.assign(
        run=short("run_id"),
        options=short("options_digest"),
        code=(rows["model_version"].fillna("").astype(str) + " " + short("code_digest")).str.strip(),
        commit=short("git_commit", 12),
    )
    lb_md = markdown_table(summary)
    if standings is not None:
        lb_md += "\n\n" + standings.verdicts["overall"]
        if scope_line(standings):
            lb_md += "\n\n" + scope_line(standings)
    md = "\n".join([*header, "", lb_md, "", markdown_table(display_detail(shown)), ""])
    return rows.to_csv(index=False), md, lb_md
