"""`skidbench compare`: the leaderboard from ``mlflow.search_runs`` and the paper's Figs. 3-7, written to
``<out_root>/<dataset>/reports/`` (report.md, leaderboard-<protocol>.md/.csv and their time-stamped copies,
fig*.png) and logged to MLflow.

The dataset is ``dataset=<name>`` (any dataset of the output root; its ``dataset.json`` gives the identity
its runs carry, so no source arguments are needed), the dataset of ``parent_run_id=<run id>``, or of the
runs of ``mlflow.experiment=<name>`` (benchmark/selection.py ``resolve_target``). The rows: by default
(``parent_run_id=latest``) the newest complete run of each (model, terrain) under the input protocol
(``inputs``), across evaluates (``selection.latest_complete``): a model evaluated alone joins the board
beside the others, and the newer runs that are not complete (failed, killed, running, other split files)
are left out and named; of the caller's own runs (``user``: null = yours, i.e. ``mlflow.user``, a name, or
``all``), and when someone else evaluated the dataset after you a note says so. ``parent_run_id=<run
id>``: one evaluate's runs; null: every child run (which must
then be of one protocol); ``filter``: an MLflow filter string on top. Runs of different protocols are
never ranked together: compare writes one leaderboard per protocol (benchmark/boards.py, every row with
its run id, options digest and versions) and the report sets the protocols side by side per model: what
the wheel response explains (commanded -> response) and what remains when the wheels are known (response
-> measured).
Figs. 3/4 come from the runs' metrics alone; Figs. 5-7 and the wheel response from what evaluate wrote
next to each run's per-window table (benchmark/report_data.py): compare reads no split, loads no fit and
predicts nothing. A figure whose data is absent is skipped, with a note in the report.
"""

from __future__ import annotations

import copy
import datetime as dt
import hashlib
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from skidbench.models.fitting import board_findings
from skidbench.pipeline.errors import one_line
from skidbench.pipeline.io import write_text_atomic
from skidbench.pipeline.layout import Layout, layout_from_cfg
from skidbench.pipeline.protocol import PROTOCOLS, protocol_of

from . import boards as brd
from . import figures as figs
from . import intervals as iv
from . import metrics as mt
from . import mlflow_ui as mu
from . import report_data as rd
from . import selection as sel
from . import standings as st
from . import tracking as trk
from .floor import FLOOR
from .horizon import EvaluationError
from .selection import board_from_runs  # noqa: F401 (compare's board rows; kept importable here)

log = logging.getLogger(__name__)

SPLITS = ("cv", "ld")


class CompareError(EvaluationError):
    pass


# -- selecting runs ---------------------------------------------------------------------------------
def select_runs(
    tracker: trk.Tracker, parent_run_id: str | None, filter_string: str | None, inputs: str | None = None
) -> tuple[pd.DataFrame, str | None]:
    """The child runs (a DataFrame from ``mlflow.search_runs``) and the parent id used (or None);
    ``inputs``: only runs of that input protocol."""
    import mlflow

    parent = parent_run_id
    if parent == "latest":
        parent = tracker.latest_parent(inputs)
        if parent is None:
            raise CompareError(
                f"no `skidbench evaluate` run{f' under inputs={inputs}' if inputs else ''} in experiment "
                f"{tracker.experiment_name!r} at {tracker.uri}; run it first (or set mlflow.experiment)"
            )
    clauses = [f"tags.`{trk.TAG_ROLE}` = 'child'", *tracker.dataset_filter()]
    if inputs:
        clauses.append(f"tags.`{trk.TAG_INPUTS}` = '{inputs}'")
    if parent:
        clauses.append(f"tags.`{trk.TAG_PARENT}` = '{parent}'")
    if filter_string:
        clauses.append(f"({filter_string})" if " or " in filter_string.lower() else str(filter_string))
    mlflow.set_tracking_uri(tracker.uri)
    try:
        runs = mlflow.search_runs(
            experiment_ids=tracker.search_ids() or [tracker.experiment_id],
            filter_string=" AND ".join(clauses),
            order_by=["attributes.start_time DESC"],
            output_format="pandas",
        )
    except mlflow.exceptions.MlflowException as exc:
        raise CompareError(f"MLflow search_runs: {one_line(exc.message)[:300]} (check filter=...)") from None
    if parent and not runs.empty:  # the external rows of `skidbench score` join every evaluate's board
        runs = with_external_runs(tracker, runs, parent, inputs, filter_string)
    if runs.empty:
        what = f"parent run {parent}" if parent else f"experiment {tracker.experiment_name!r}"
        raise CompareError(f"no model runs match in {what} (filter: {filter_string or 'none'})")
    return runs, parent


def with_external_runs(
    tracker: trk.Tracker, runs: pd.DataFrame, parent: str, inputs: str | None, filter_string: str | None
) -> pd.DataFrame:
    """``runs`` (an evaluate's child runs) and the external runs (``skidbench score``, benchmark/external.py:
    tag ``skidbench.external``) of the same dataset and protocol scored on the same split files (per terrain,
    the split fingerprint of the runs)."""
    import mlflow

    if inputs is None:
        inputs = tracker.client.get_run(parent).data.tags.get(trk.TAG_INPUTS)
    clauses = [f"tags.`{trk.TAG_ROLE}` = 'child'", f"tags.`{trk.TAG_EXTERNAL}` = 'true'"]
    clauses += tracker.dataset_filter()
    if inputs:
        clauses.append(f"tags.`{trk.TAG_INPUTS}` = '{inputs}'")
    if filter_string:
        clauses.append(f"({filter_string})" if " or " in filter_string.lower() else str(filter_string))
    ext = mlflow.search_runs(experiment_ids=tracker.search_ids(), filter_string=" AND ".join(clauses),
                             order_by=["attributes.start_time DESC"], output_format="pandas")  # fmt: skip
    if ext.empty:
        return runs
    terrain, fingerprint = f"tags.{trk.TAG_TERRAIN}", f"tags.{trk.TAG_FINGERPRINT}"
    fp = dict(zip(_col(runs, terrain), _col(runs, fingerprint), strict=True))
    same = [
        fp.get(t) == f and r not in set(runs["run_id"])
        for t, f, r in zip(_col(ext, terrain), _col(ext, fingerprint), ext["run_id"], strict=True)
    ]  # fmt: skip
    return pd.concat([runs, ext[same]], ignore_index=True) if any(same) else runs


def _col(runs: pd.DataFrame, name: str) -> pd.Series:
    return runs[name] if name in runs else pd.Series([None] * len(runs), index=runs.index, dtype=object)


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
    (:mod:`skidbench.benchmark.standings`): ranked by its statistic with the ranking rule
    (:func:`standings_table`), every paper metric with its 95 % interval, and the floor."""
    check_one_protocol(board)
    if standings is not None:
        return standings_table(board, horizon_s, standings)
    rank_keys = (  # the aggregate: the mean of the paper's metrics on CV and LD (standings.AGGREGATE)
        [m.metric_key(s, horizon_s) for m in mt.PAPER for s in SPLITS]
        if rank_by == st.AGGREGATE
        else [trk.rank_key(rank_by, horizon_s)]
    )
    rows = []
    for model, g in board.groupby("model", sort=False):
        ok = g[g["status"] == "FINISHED"]
        row: dict[str, Any] = {"model": _marked(model, g)}
        _metric_cells(row, ok, horizon_s)
        row["terrains"] = f"{len(ok)}/{len(g)}"
        bad = g[g["status"] != "FINISHED"]
        row["failed"] = (
            ", ".join(f"{t} ({s})" for t, s in zip(bad["terrain"], bad["status"], strict=True)) or ""
        )
        ranked = [ok[k].to_numpy(float) for k in rank_keys if len(ok) and k in ok]
        means = [np.nanmean(v) if np.isfinite(v).any() else np.nan for v in ranked]
        row["_key"] = float(np.mean(means)) if means and np.isfinite(means).all() else np.nan
        rows.append(row)
    out = pd.DataFrame(rows).sort_values("_key", na_position="last", kind="stable")
    out.insert(0, "rank", np.arange(1, len(out) + 1))
    for metric in (m for m in mt.METRICS if m.optional):
        for split in SPLITS:
            lab = metric.column_label(split)
            out[lab] = _optional_cells(out[lab].astype(float), metric)
    return out.drop(columns="_key").reset_index(drop=True)


def _ci(v: float, lo: float, hi: float, digits: int = 2) -> str:
    """``6.91 [6.20, 7.62]``: a value and its interval as the boards show them (``n/a`` for no value)."""
    if not np.isfinite(v):
        return "n/a"
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return f"{v:.{digits}f} [n/a]"
    return f"{v:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


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
        r = ov.loc[model] if model in ov.index else _no_standing(ov.columns, "no finished run to score")
        row: dict[str, Any] = {"rank": r["rank"], "model": _marked(model, g) if len(g) else model}
        row[agg_label] = _ci(float(r["estimate"]), float(r["lo"]), float(r["hi"]))
        for metric in mt.HEADLINE:
            for split in SPLITS:
                lab = metric.column_label(split)
                if metric.paper:  # with its interval (the mean over terrains, resampled)
                    c = f"{metric.name}|{split}|"
                    row[lab] = _ci(float(r[c + "estimate"]), float(r[c + "lo"]), float(r[c + "hi"]))
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
    r["rank"], r["standing"], r["n_blocks"] = "", f"{iv.NOT_RANKED}: {why}", 0
    return r


def _rank_number(rank: Any) -> int:
    try:
        return int(rank)
    except (TypeError, ValueError):
        return 10**6


def _marked(model: str, rows: pd.DataFrame) -> str:
    """A model's name on the leaderboard: ``<name> (external)`` for a row scored from a predictions file."""
    return f"{model} (external)" if "external" in rows and rows["external"].any() else str(model)


def detail_table(
    board: pd.DataFrame, horizon_s: float, standings: st.Standings | None = None
) -> pd.DataFrame:
    """One row per (model, terrain): every metric, the windows behind it, and for a metric with an interval
    its bounds and independent blocks (``<label> lo``, ``<label> hi``, ``<label> blocks``, as evaluate
    logged them); fit and predict numbers, the run, the reason of a failure. With ``standings``: the
    ranking aggregate on the terrain with its interval, rank and standing, and the floor of the row's
    terrain (``floor <label>``: added columns; the report shows the floor's own rows: report_detail)."""
    models = [_marked(m, board.loc[[i]]) for i, m in zip(board.index, board["model"], strict=True)]
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
            out[col] = [_ci(float(v), float(a), float(b)) if pd.notna(v) else "n/a" for v, a, b in triples]
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


def paper_claim(board: pd.DataFrame, horizon_s: float) -> list[str]:
    """The paper's claim (friction-based best on LD, comparable on CV) where no per-window tables allow
    paired intervals: not resolved by these data, with friction's place by point estimate only."""
    ok = board[board["status"] == "FINISHED"]
    if "friction" not in set(ok["model"]):
        return [
            "The friction-based model was not evaluated (or failed), so the paper's claim cannot be checked."
        ]
    lines = [
        f"**Overall: {st.UNRESOLVED}** (no per-window tables here, so no paired comparison); friction's "
        "place by point estimate only, not a ranking:",
        "",
    ]
    for metric in mt.PAPER:
        kind = metric.name
        for split in SPLITS:
            key = metric.metric_key(split, horizon_s)
            means = ok.groupby("model")[key].mean().dropna().sort_values()
            if "friction" not in means:
                continue
            rank = list(means.index).index("friction") + 1
            best, fr = means.iloc[0], means["friction"]
            lines.append(
                f"- {kind} RMSRE on {split.upper()} (mean over terrains): friction-based ranks {rank} of "
                f"{len(means)} ({fr:.2f} % vs best {means.index[0]} {best:.2f} %)"
            )
    return lines


# -- the three protocols side by side ----------------------------------------------------------------
def decomposition_table(boards: dict[str, pd.DataFrame], horizon_s: float) -> pd.DataFrame:
    """Per model (mean over the terrains scored under every protocol shown): each headline metric under
    each protocol, ``commanded / response / measured``; a comparison of one model's inputs, not a ranking.
    The numbers are also in the hidden columns ``_<metric>_<split>_<protocol>`` (for the figure)."""
    shown = [p for p in PROTOCOLS if p in boards]
    if not shown:
        return pd.DataFrame()
    ok = {p: b[b["status"] == "FINISHED"] for p, b in boards.items()}
    models = figs.order_models(sorted({m for b in ok.values() for m in b["model"]}))
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


# -- figures 5-7 and the wheel response: drawn from what evaluate wrote (benchmark/report_data.py) ----------
def figure5(layout: Layout, terrain: str, model_name: str, inputs: str, path: Path, dpi: int) -> Path:
    """Fig. 5 from the residual series evaluate wrote for ``model_name`` on ``terrain``."""
    df, split = rd.read_residuals(layout.eval_stem(model_name, terrain, inputs))
    return figs.residual_vs_acceleration(
        df["wz_pred"].to_numpy(float),
        df["wz_meas"].to_numpy(float),
        df["accel"].to_numpy(float),
        f"Yaw-rate residual of the {figs.label(model_name).lower()} model vs angular acceleration "
        f"({terrain}, {split.upper()} split)",
        path,
        dpi,
    )


def figure6(layout: Layout, terrain: str, model_name: str, inputs: str, path: Path, dpi: int) -> Path:
    """Fig. 6 from the yaw-rate surfaces evaluate computed with the fitted ``model_name``."""
    z = rd.read_surfaces(layout.eval_stem(model_name, terrain, inputs))
    accels = [float(a) for a in z["accels"]]
    surfaces = {a: z["wz"][i] for i, a in enumerate(accels)}
    marks = {a: z["marked"][i] for i, a in enumerate(accels)} if bool(z["has_marks"]) else {}
    masked, no_root, reduced = (int(c) for c in z["counts"])
    wl = z["wl"]
    title = (
        f"{figs.label(model_name)} model: predicted yaw rate at commanded angular accelerations ({terrain})"
    )
    if masked or no_root or reduced:
        title += (
            f"\nof {wl.size * len(accels)} grid points, marked: {reduced} balanced only at a reduced "
            f"acceleration (shown there), {no_root} with no root (least-squares), {masked} not converged"
        )
    return figs.yaw_rate_surfaces(wl, z["wr"], surfaces, title, path, dpi, no_root=marks)


def figure6_accels(layout: Layout, terrain: str, model_name: str, inputs: str) -> list[float]:
    """The commanded angular accelerations (rad/s²) of the surfaces evaluate wrote ([] when none)."""
    try:
        return [float(a) for a in rd.read_surfaces(layout.eval_stem(model_name, terrain, inputs))["accels"]]
    except rd.ReportDataError:
        return []


def figure7(
    layout: Layout, terrain: str, models: Sequence[str], inputs: str, horizon_s: float, path: Path, dpi: int
) -> Path:
    """Fig. 7 from the windows' true and predicted poses evaluate wrote for each model of ``terrain``."""
    samples: dict[tuple[str, int], dict[str, Any]] = {}
    for m in models:
        try:
            df, h = rd.read_trajectories(layout.eval_stem(m, terrain, inputs))
        except rd.ReportDataError as exc:
            log.warning("Fig. 7: %s/%s skipped (%s)", m, terrain, one_line(str(exc)))
            continue
        if not np.isclose(h, horizon_s):
            log.warning("Fig. 7: %s/%s has %g s windows, not %g s: skipped", m, terrain, h, horizon_s)
            continue
        for (split, j), w in df.groupby(["split", "window"], sort=False):
            w = w.sort_values("k")
            sample = samples.setdefault(
                (str(split), int(j)),
                {"split": str(split), "sequence": str(w["sequence"].iloc[0]), "t0": float(w["t0"].iloc[0]),
                 "truth": w[w["role"] == "truth"][["x", "y", "yaw"]].to_numpy(float), "pred": {}},
            )  # fmt: skip
            sample["pred"][m] = w[w["role"] == "pred"][["x", "y", "yaw"]].to_numpy(float)
    if not samples:
        raise CompareError(f"no {horizon_s:g} s test window written by evaluate for terrain {terrain}")
    order = {sp: i for i, sp in enumerate(SPLITS)}
    return figs.trajectories([samples[k] for k in sorted(samples, key=lambda k: (order.get(k[0], 9), k[1]))],
                             horizon_s, path, dpi)  # fmt: skip


def wheel_response_figure(layout: Layout, terrain: str, path: Path, dpi: int) -> Path:
    """The identified wheel response against the encoders around the largest Train command step, as
    evaluate extracted it (:func:`report_data.write_wheel_response_steps`)."""
    df, title = rd.read_wheel_response_steps(layout, terrain)
    cols = lambda p: df[[f"{p}_wl", f"{p}_wr"]].to_numpy(float)  # noqa: E731
    return figs.wheel_response_steps(df["t"].to_numpy(float), cols("cmd"), cols("enc"), cols("resp"), title,
                                     path, dpi)  # fmt: skip


# -- the stage --------------------------------------------------------------------------------------
@dataclass
class CompareResult:
    report: Path
    leaderboard_md: str
    parent_run_id: str | None
    files: list[Path] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    inputs: str = "commanded"
    decomposition_md: str = ""
    links: dict[str, str] = field(default_factory=dict)  # what -> MLflow UI URL
    left_out: list[str] = field(default_factory=list)  # newer runs not on the board, and why (one line each)
    written: list[str] = field(default_factory=list)  # the leaderboard files, one line per protocol
    dataset: str = ""
    parents: list[str] = field(default_factory=list)  # the evaluate runs the board's rows hang from
    claim: str = ""  # the paper's claim: overall verdict, then per terrain


def _with_inputs(cfg: Any, protocol: str) -> Any:
    """``cfg`` with ``inputs`` set to the protocol of the runs shown (the files evaluate wrote for them)."""
    from omegaconf import OmegaConf, open_dict

    if not OmegaConf.is_config(cfg) or protocol not in PROTOCOLS or cfg.get("inputs") == protocol:
        return cfg
    out = copy.deepcopy(cfg)
    with open_dict(out):
        out.inputs = protocol
    return out


def calibration_windows(
    layout: Layout, finished: pd.DataFrame, inputs: str = "commanded"
) -> dict[str, pd.DataFrame]:
    """Per model with a predictive covariance: its per-window uncertainty columns over every terrain
    (``<ds>/eval/<model>/<terrain>[.<inputs>].windows.parquet`` written by evaluate)."""
    out: dict[str, pd.DataFrame] = {}
    for model, g in finished.groupby("model", sort=False):
        frames = []
        for terrain in g["terrain"]:
            stem = layout.eval_stem(str(model), str(terrain), inputs)
            path = stem.with_name(stem.name + ".windows.parquet")
            try:
                w = pd.read_parquet(path)
            except (OSError, ValueError):
                continue
            if "pos_d2" in w:
                frames.append(w)
        if frames:
            out[str(model)] = pd.concat(frames, ignore_index=True)
    return out


def open_target_from_cfg(cfg: Any) -> tuple[Any, sel.Target, trk.Tracker]:
    """The dataset compare reads, its store and experiment: ``(cfg with that dataset and experiment,
    target, tracker)`` (:func:`selection.target_from_cfg`). CompareError (one line) when there is no store,
    no such dataset or run; StaleInputError when the dataset's last evaluate failed as a stage (a model run
    that failed does not count)."""
    from mlflow.tracking import MlflowClient
    from omegaconf import OmegaConf, open_dict

    from skidbench.pipeline.cache import check_producers
    from skidbench.pipeline.imported import check_stage

    uri = trk.resolve_tracking_uri(cfg, layout_from_cfg(cfg))
    if not trk.has_store(uri):  # compare only reads: it does not create an empty store to find nothing in
        raise CompareError(
            f"no MLflow store at {uri}: nothing was evaluated under this output root; "
            "run `skidbench evaluate` first (or set mlflow.tracking_uri)"
        )
    trk.check_reachable(uri, float((cfg.get("mlflow") or {}).get("timeout_s", 5.0)))
    try:
        target = sel.target_from_cfg(cfg, MlflowClient(tracking_uri=uri))
    except sel.SelectionError as exc:
        raise CompareError(str(exc)) from None
    if target.note:
        log.info("compare: %s", target.note)
    if OmegaConf.is_config(cfg) and (cfg.dataset, cfg.mlflow.experiment) != (target.name, target.experiment):
        cfg = copy.deepcopy(cfg)
        with open_dict(cfg):
            cfg.dataset = target.name
            cfg.mlflow.experiment = target.experiment
    if target.layout.root.is_dir():
        check_producers(target.layout.root, "compare")
        check_stage(cfg, "compare", target.layout.root)
    return cfg, target, trk.tracker_from_cfg(cfg, target.layout, dataset_id=target.dataset_id or "")


def protocol_selections(
    tracker: trk.Tracker, horizon_s: float, filter_string: str | None, user: str | None = None
) -> dict[str, sel.Selection]:
    """``{protocol: selection}`` of every input protocol the dataset has runs under (the newest complete
    run of each (model, terrain): :func:`selection.latest_complete`), in the order of ``PROTOCOLS``."""
    out = {}
    for p in PROTOCOLS:
        try:
            out[p] = sel.latest_complete(tracker, p, horizon_s, filter_string, user)
        except sel.NoRuns:
            continue
    return out


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
    md = "\n".join([*header, "", lb_md, "", markdown_table(display_detail(shown)), ""])
    return rows.to_csv(index=False), md, lb_md


def run_compare(cfg: Any) -> CompareResult:
    cfg, target, tracker = open_target_from_cfg(cfg)
    layout = target.layout
    horizon = float(cfg.horizon)
    parent_cfg = cfg.get("parent_run_id", "latest")
    parent_arg = None if parent_cfg in (None, "", "null") else str(parent_cfg)
    user = sel.whose(cfg.get("user"))  # the caller's own runs unless user=<name> | all
    # latest: the newest complete run of each (model, terrain) under cfg.inputs, across evaluates; a run
    # id: that evaluate's runs; null: the newest run of each (model, terrain) of every child run, which
    # must then be of one protocol (a filter on tags.`skidbench.inputs` narrows them)
    try:
        selections = protocol_selections(tracker, horizon, cfg.get("filter"), user)
    except sel.SelectionError as exc:
        raise CompareError(str(exc)) from None
    left_out: list[str] = []
    if parent_arg == "latest":
        protocol = protocol_of(cfg)
        if protocol not in selections and user and sel.not_yours(tracker, protocol, cfg.get("filter"), user):
            raise CompareError(sel.not_yours(tracker, protocol, cfg.get("filter"), user))
        if protocol not in selections:
            others = f" (runs exist under inputs={', '.join(selections)})" if selections else ""
            if cfg.get("filter"):
                others = f" matching filter {cfg.get('filter')}" + others
            raise CompareError(
                f"no complete model run under inputs={protocol} of dataset {target.name} in experiment "
                f"{tracker.experiment_name!r} at {tracker.uri}{others}; run `skidbench evaluate"
                f"{'' if protocol == 'commanded' else f' inputs={protocol}'}` first"
            )
        runs, parent = selections[protocol].runs, None
        left_out = selections[protocol].left_out
    else:
        runs, parent = select_runs(tracker, parent_arg, cfg.get("filter"), None)
    board = board_from_runs(runs, horizon)
    protocol = check_one_protocol(board)
    cfg = _with_inputs(cfg, protocol)
    if not any(
        m.metric_key(s, horizon) in runs.columns.str.removeprefix("metrics.")
        for m in mt.PAPER
        for s in SPLITS
    ):
        raise CompareError(
            f"the selected runs have no RMSRE at horizon {horizon:g} s; set horizon=<one evaluated>"
        )
    interval_notes: list[str] = []
    standings = standings_from_cfg(cfg, layout, board, protocol, horizon, interval_notes)
    summary = summary_table(board, horizon, str(cfg.rank_by), standings)
    parents = sel.Selection(protocol, horizon, runs).parents if parent is None else [parent]
    links = ui_links(cfg, tracker, parents[0] if len(parents) == 1 else None, board, horizon)
    detail = report_detail(board, horizon, standings)
    out = layout.reports
    out.mkdir(parents=True, exist_ok=True)
    files: list[Path] = []
    written: list[str] = []
    when = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    shown_boards = {protocol: (board, runs, left_out)}
    if parent is None:  # every protocol's board of the dataset, from the same selection
        for p, s in selections.items():
            if p != protocol:
                shown_boards[p] = (board_from_runs(s.runs, horizon), s.runs, s.left_out)
    lb_md = markdown_table(summary)
    for p, (b, r, lo) in shown_boards.items():
        rank_by = str(cfg.rank_by)
        rank_key = st.AGGREGATE if rank_by == st.AGGREGATE else trk.rank_key(rank_by, horizon)
        st_p = standings
        if p != protocol:  # another protocol's board, from its own windows
            st_p = standings_from_cfg(_with_inputs(cfg, p), layout, b, p, horizon, [])
        header = brd.leaderboard_header(target.name, target.dataset_id, tracker.experiment_name, p, parent,
                                        horizon, rank_key, when, lo)  # fmt: skip
        csv_text, md_text, md_ranked = leaderboard_texts(b, r, horizon, str(cfg.rank_by), header, st_p)
        paths, line = brd.write_leaderboard(out, p, csv_text, md_text)
        files += paths
        written.append(f"leaderboard inputs={p}: {line}")
        if p == protocol:
            lb_md = md_ranked
    boards_of = (  # the protocols side by side: the dataset's board of each
        {p: b for p, (b, _r, _lo) in shown_boards.items()}
        if parent is None
        else {p: board_from_runs(s.runs, horizon) for p, s in selections.items()}
    )
    decomp = decomposition_table(boards_of, horizon)
    shown = decomp.attrs.get("protocols", []) if len(decomp) else []
    decomp_md = markdown_table(decomp[[c for c in decomp.columns if not c.startswith("_")]]) if shown else ""

    notes: list[str] = _fit_findings(layout, board, str(cfg.get("inputs") or "commanded")) + interval_notes
    newer = (
        sel.newer_elsewhere(tracker, runs, protocol, cfg.get("filter"), user)
        if parent_arg == "latest"
        else None
    )
    notes += [n for n in (newer, sel.same_data_elsewhere(tracker)) if n]
    log_to = parent or (parents[0] if len(parents) == 1 else None)  # the evaluate run every row hangs from
    owner = tracker.client.get_run(log_to).data.tags.get(trk.TAG_USER) if log_to else None
    if log_to and owner != trk.current_user():  # another person's evaluate run is left as they made it
        log_to = None
        if cfg.get("log_to_mlflow", True):
            notes.append(f"the report is logged to a compare run of yours, not to {owner}'s evaluate run")
    fig_md: list[str] = []
    fc = cfg.figures
    if fc.enabled:
        dpi = int(fc.dpi)
        inputs = str(cfg.get("inputs") or "commanded")  # the protocol of the runs shown (_with_inputs)
        finished = board[board["status"] == "FINISHED"]
        terrains = sorted(finished["terrain"].unique())
        terrain = str(fc.terrain) if fc.get("terrain") else (terrains[0] if terrains else None)
        jobs = [  # Figs. 3 and 4 and every other metric's bar chart
            (
                m.figure.file,
                m.figure.caption,
                lambda p, m=m: figs.metric_bars(board, m, horizon, SPLITS, p, dpi, floor_of(standings, m)),
            )
            for m in mt.METRICS
            if m.figure is not None
        ]
        if len(shown) > 1:
            jobs.append(
                ("fig_protocols.png",
                 f"The input protocols side by side ({' / '.join(shown)}), {horizon:g} s errors, mean over "
                 "terrains",
                 lambda p: figs.protocol_bars(decomp, shown, f"{horizon:g} s errors per input protocol", p,
                                              dpi)),
            )  # fmt: skip
        if terrain is not None:
            jobs.append(
                ("fig_wheel_response.png",
                 f"The wheel response `calibrate` identified vs the encoders ({terrain}, Train)",
                 lambda p: wheel_response_figure(layout, terrain, p, dpi)),
            )  # fmt: skip
        if terrain is not None:
            models = figs.order_models(finished[finished["terrain"] == terrain]["model"].tolist())
            m5, m6 = figs.label(fc.fig5_model).lower(), figs.label(fc.fig6_model).lower()
            accels = figure6_accels(layout, terrain, str(fc.fig6_model), inputs)
            jobs += [
                ("fig5_residual_vs_acceleration.png",
                 f"Fig. 5: yaw-rate residual of the {m5} model against angular acceleration ({terrain})",
                 lambda p: figure5(layout, terrain, str(fc.fig5_model), inputs, p, dpi)),
                ("fig6_yaw_rate_surfaces.png",
                 f"Fig. 6: {m6} model's yaw rate over the wheel-velocity plane at commanded angular "
                 f"accelerations {accels} rad/s² ({terrain})",
                 lambda p: figure6(layout, terrain, str(fc.fig6_model), inputs, p, dpi)),
                ("fig7_trajectories.png",
                 f"Fig. 7: true and predicted {horizon:g} s trajectories ({terrain})",
                 lambda p: figure7(layout, terrain, models, inputs, horizon, p, dpi)),
            ]  # fmt: skip
        calib = calibration_windows(layout, finished, inputs)
        if calib:
            jobs.append(
                ("calibration.png",
                 f"Calibration of the {horizon:g} s pose uncertainty: nominal vs empirical coverage",
                 lambda p: figs.calibration_curves(calib, horizon, p, dpi)),
            )  # fmt: skip
        for name, caption, draw in jobs:
            try:
                files.append(draw(out / name))
                fig_md.append(f"### {caption}\n\n![{caption}]({name})\n")
            except Exception as exc:  # a figure that needs local data we do not have: say so, go on
                note = f"{caption.split(':')[0]} skipped: {type(exc).__name__}: {one_line(str(exc))[:300]}"
                log.warning("%s", note)
                notes.append(note)

    report = out / "report.md"
    write_text_atomic(
        report,
        _report_md(cfg, tracker, parent, board, summary, detail, horizon, fig_md, notes, protocol, decomp_md,
                   shown, links, target=target, parents=parents, left_out=left_out, standings=standings),
    )  # fmt: skip
    files.append(report)
    if cfg.get("log_to_mlflow", True):
        # to your evaluate run every row hangs from; else (several evaluates, another person's): a compare run
        run_id = log_to
        if run_id is None:
            run_id = tracker.start(
                f"compare {cfg.dataset}",
                {trk.TAG_ROLE: "compare", trk.TAG_DATASET: str(cfg.dataset), trk.TAG_INPUTS: protocol},
            )
            tracker.end(run_id)
        for f in files:
            tracker.artifact(run_id, f, "report")
    claim = ""
    if standings is not None:
        claim = "; ".join(f"{scope}: {v}" for scope, (v, _) in standings.claim.items())
    return CompareResult(report, lb_md, parent, files, notes, protocol, decomp_md, links, left_out, written,
                         target.name, parents, claim)  # fmt: skip


def _fit_findings(layout: Layout, board: pd.DataFrame, inputs: str) -> list[str]:
    """The findings of the board's fits (a parameter at its bound: ``roc degenerates to edd on this data:
    b2 at its bound``), for the console notes and the report's Notes (models/fitting.py formats them)."""
    done = board[board["status"] == "FINISHED"] if "status" in board else board
    rows = list(zip(done["model"].astype(str), done["terrain"].astype(str), strict=True))
    return board_findings(layout, rows, inputs)


def standings_from_cfg(
    cfg: Any, layout: Layout, board: pd.DataFrame, protocol: str, horizon: float, notes: list[str]
) -> st.Standings | None:
    """The board's intervals, ranking and claim from the per-window tables evaluate wrote
    (:mod:`skidbench.benchmark.standings`), or None (with a note) when there are none to read."""
    rank_by = str(cfg.get("rank_by") or st.AGGREGATE)
    if rank_by != st.AGGREGATE:
        trk.rank_key(rank_by, horizon)  # a bad rank_by: one line
    windows, missing = st.read_windows(layout, board, protocol, horizon)
    notes += [f"paired intervals: {m}" for m in missing]
    if not any(m != FLOOR for m, _ in windows):
        notes.append(
            "no per-window table of these runs here: the leaderboard shows the logged intervals, ranked "
            "by point estimate (no paired comparison)"
        )
        return None
    return st.build(windows, horizon, iv.IntervalConfig.from_cfg(cfg), rank_by)


def floor_of(standings: st.Standings | None, metric: mt.Metric) -> dict[tuple[str, str], float]:
    """``{(terrain, split): the floor's value}`` of a metric, for its bar chart."""
    if standings is None:
        return {}
    c = standings.cells
    c = c[(c["model"] == FLOOR) & (c["metric"] == metric.name)]
    return {(r.terrain, r.split): float(r.estimate) for r in c.itertuples(index=False)}


def ui_links(cfg: Any, tracker: trk.Tracker, parent: str | None, board: pd.DataFrame, horizon: float):
    """MLflow UI links (model-training pages, not the GenAI ones): the parent run's page, and a saved view
    of the runs shown (the RMSRE columns first, best first; :mod:`mlflow_ui`) as a table and as charts of
    the RMSRE per run."""
    ui = (cfg.get("mlflow") or {}).get("ui_url")
    uri, exp = tracker.uri, tracker.experiment_id
    cols, _ = mu.board_columns(("ld", "cv"), horizon)
    order = _sort_key(str(cfg.rank_by), horizon)  # the aggregate is not a logged metric: sort by ld_trans
    links = {}
    if parent:
        links["parent run"] = mu.run_url(uri, exp, parent, ui)
        key, title = f"evaluate-{parent[:8]}", tracker.client.get_run(parent).info.run_name
        search = mu.children_of(parent)
    else:  # every child run compare selected: a view of those runs
        ids = ", ".join(f"'{r}'" for r in board["run_id"])
        digest = hashlib.sha256(ids.encode()).hexdigest()[:8]
        key, title = f"compare-{digest}", f"compare {cfg.dataset}: {len(board)} runs"
        search = f"attributes.run_id IN ({ids})"
    mu.save_view(tracker.client, exp, key, title, mu.view_state(search, cols, order, mu.chart_title(horizon)))
    links["runs table (saved view)"] = mu.view_url(uri, exp, key, ui)
    links["charts of its model runs"] = mu.view_url(uri, exp, key, ui, charts=True)
    return links


def _sort_key(rank_by: str, horizon: float) -> str:
    """The MLflow metric the runs table is sorted by: ``rank_by``'s, or LD translational RMSRE for the
    aggregate (no one run logs the mean over terrains)."""
    return trk.rank_key("ld_trans" if rank_by == st.AGGREGATE else rank_by, horizon)


def ranked_by_line(rank_by: str, horizon: float, standings: st.Standings | None) -> str:
    if standings is None:
        what = "the four RMSREs" if rank_by == st.AGGREGATE else f"`{_sort_key(rank_by, horizon)}`"
        return f"- ranked by point estimate of the mean over terrains of {what} (no paired intervals here)"
    what = f"the mean over terrains of `{standings.ranked_by}`"
    if standings.ranked_by == st.AGGREGATE:
        what = "the mean of the four RMSREs (translational and rotational, CV and LD) over terrains"
    return (f"- ranked by {what}, with its 95 % interval; best only when its paired difference from every "
            "other model is resolved, else tied; under the minimum of independent blocks not ranked "
            "(docs/intervals.md)")  # fmt: skip


def _report_md(
    cfg, tracker, parent, board, summary, detail, horizon, fig_md, notes, protocol="commanded", decomp_md="",
    shown=(), links=None, target=None, parents=(), left_out=(), standings=None,
) -> str:  # fmt: skip
    failed = board[board["status"] != "FINISHED"]
    rec = (target.record if target is not None else None) or {}
    runs_line = (
        f", parent run `{parent}`"
        if parent
        else f", the newest complete run of each (model, terrain) from {len(parents)} evaluate run(s): "
        + ", ".join(f"`{p}`" for p in parents)
    )
    parts = [
        f"# skidbench report: {cfg.dataset}",
        "",
        f"Horizon {horizon:g} s; RMSRE of the relative translational error (position error / distance "
        "travelled) and rotational error (|yaw error| / absolute rotation), in %, lower is better. "
        "Models fitted per terrain on Train, scored on the constant-velocity (CV) and long-distance (LD) "
        "test splits.",
        *[
            f"Also `{m.short}` ({m.unit}): {m.description}, lower is better."
            for m in mt.HEADLINE
            if not m.paper
        ],
        "",
        f"- dataset: {cfg.dataset} ({rec.get('source', '?')} {rec.get('root', '?')}, fingerprint "
        f"{rec.get('fingerprint', '?')})",
        f"- MLflow: `{tracker.uri}`, experiment `{tracker.experiment_name}`" + runs_line,
        f"- filter: `{cfg.get('filter')}`" if cfg.get("filter") else "- filter: none",
        *[f"- MLflow UI, {what}: <{url}>" for what, url in (links or {}).items()],
        ranked_by_line(str(cfg.rank_by), horizon, standings),
        f"- input protocol: `{protocol}` (every model driven by the same inputs; runs of different protocols "
        "are never ranked together)",
        "",
        f"## Leaderboard, inputs={protocol} (mean over terrains)",
        "",
        markdown_table(summary),
        "",
        *([f"**{standings.verdicts['overall']}.** Each value: estimate [95 % interval] (block bootstrap, "
           "docs/intervals.md); the floor is the ground truth's own velocities through the same windows, "
           "what no model can be expected to beat.", ""] if standings is not None else []),
        *differences_lines(standings),
        "## Per model and terrain",
        "",
        *([f"- {t}: {v}" for t, v in standings.verdicts.items() if t != "overall"] + [""]
          if standings is not None else []),
        markdown_table(display_detail(detail)),
        "",
    ]  # fmt: skip
    if len(failed):
        parts += ["## Failed runs", ""]
        parts += [
            f"- **{r.model} / {r.terrain}**: {r.status}: {r.reason or 'no reason recorded'}"
            for r in failed.itertuples()
        ]
        parts.append("")
    if left_out:
        parts += ["## Newer runs left out", "", "The board keeps the complete run named in each line.", ""]
        parts += [f"- {line}" for line in left_out]
        parts.append("")
    parts += [
        "## The paper's claim (friction-based best on LD, comparable on CV)",
        "",
        *(
            []
            if protocol == "commanded"
            else [
                f"(These runs are under inputs={protocol}; the paper's own check is the `commanded` one.)",
                "",
            ]
        ),
        *(_claim_lines(standings) if standings is not None else paper_claim(board, horizon)),
        "",
    ]
    if decomp_md:
        parts += [
            f"## The input protocols side by side ({' / '.join(shown)})",
            "",
            "Per model, each RMSRE (%) under the latest evaluate of each protocol (mean over the terrains "
            "scored under all of them): commanded -> response is what the identified wheel response "
            "explains; response -> measured is what remains when the wheels' rates are known. A comparison "
            "of inputs, not a ranking.",
            "",
            decomp_md,
            "",
        ]
    if fig_md:
        parts += ["## Figures", "", *fig_md]
    if notes:
        parts += ["## Notes", "", *[f"- {n}" for n in notes], ""]
    parts += [
        "## Reproduce",
        "",
        "```",
        "make reproduce            # or: skidbench evaluate && skidbench compare",
        f"skidbench compare dataset={cfg.dataset} inputs={protocol}"
        + (f" parent_run_id={parent}" if parent else ""),
        "```",
        "",
    ]
    return "\n".join(parts)


def differences_lines(standings: st.Standings | None) -> list[str]:
    """The paired differences the ranking rule decided on, from the leader (the lowest estimate) to every
    other ranked model: ``other - leader`` with its 95 % interval and whether it is resolved."""
    d = standings.differences if standings is not None else pd.DataFrame()
    ov = standings.overall.set_index("model") if standings is not None else pd.DataFrame()
    if not len(d):
        return []
    ranked = ov.loc[[m for m in ov.index if m != FLOOR and bool(ov.loc[m, "rankable"])], "estimate"]
    leader = ranked.astype(float).idxmin()
    rows = []
    for r in d[(d["a"] == leader) | (d["b"] == leader)].itertuples(index=False):
        sign, other = (-1.0, r.b) if r.a == leader else (1.0, r.a)  # differences are a - b: other - leader
        lo, hi = sorted((sign * r.lo, sign * r.hi))
        rows.append({"model": other, "minus": leader, "difference (points)": _ci(sign * r.estimate, lo, hi),
                     "resolved": "yes" if r.resolved else "no", "_e": sign * r.estimate})  # fmt: skip
    table = pd.DataFrame(rows).sort_values("_e").drop(columns="_e")
    what = "mean of the four RMSREs" if standings.ranked_by == st.AGGREGATE else f"`{standings.ranked_by}`"
    return ["### Paired differences from the leader", "",
            f"Each model's {what} over terrains minus {leader}'s, on the same windows and the same resampled "
            "blocks, with its 95 % interval: resolved when the interval excludes 0.", "",
            markdown_table(table), ""]  # fmt: skip


def _claim_lines(standings: st.Standings) -> list[str]:
    """The claim's verdict overall (with every paired difference) and per terrain (the verdict line; with
    one terrain the overall lines are that terrain's)."""
    verdict, lines = standings.claim["overall"]
    out = [f"**Overall: {verdict}.**", "", *lines, ""]
    terrains = [scope for scope in standings.claim if scope != "overall"]
    if len(terrains) > 1:
        out += [standings.claim[t][1][0] for t in terrains]
    return out


def format_console(result: CompareResult) -> str:
    lines = [f"Leaderboard, inputs={result.inputs} (RMSRE %, mean over terrains; estimate [95 % interval]):",
             result.leaderboard_md, ""]  # fmt: skip
    if result.claim:
        lines += [f"The paper's claim (friction best on LD, comparable on CV): {result.claim}", ""]
    if result.decomposition_md:
        lines += ["Input protocols side by side (commanded / response / measured, RMSRE %):",
                  result.decomposition_md, ""]  # fmt: skip
    if result.left_out:
        lines.append(f"Left out: {len(result.left_out)} newer run(s) that are not complete (the board keeps "
                     "the complete run named):")  # fmt: skip
        lines += [f"  {line}" for line in result.left_out]
    lines.append(f"report: {result.report}")
    lines += result.written
    lines += [f"MLflow {what}: {url}" for what, url in result.links.items()]
    lines += [f"note: {n}" for n in result.notes]
    return "\n".join(lines)
