"""`skidbench compare`: the leaderboard from the dataset's results table and the paper's Figs. 3-7, written to
``<out_root>/<dataset>/reports/`` (report.md, leaderboard-<protocol>.md/.csv and their time-stamped copies,
fig*.png) and logged to MLflow.

The dataset is ``dataset=<name>`` (any dataset of the output root; its ``dataset.json`` gives the identity
its runs carry, so no source arguments are needed), the dataset of ``parent_run_id=<run id>``, or of the
runs of ``mlflow.experiment=<name>`` (benchmark/board/selection.py ``target_from_cfg``). The rows: by default
(``parent_run_id=latest``) the newest complete run of each (model, terrain) under the input protocol
(``inputs``), across evaluates (``selection.latest_complete``): a model evaluated alone joins the board
beside the others, and the newer runs that are not complete (failed, killed, running, other split files)
are left out and named; of the caller's own runs (``user``: null = yours, i.e. ``mlflow.user``, a name, or
``all``), and when someone else evaluated the dataset after you a note says so. ``parent_run_id=<run
id>``: one evaluate's runs; null: every child run (which must
then be of one protocol); ``filter``: an MLflow filter string on top. Runs of different protocols are
never ranked together: compare writes one leaderboard per protocol (benchmark/board/boards.py, every row with
its run id, options digest and versions) and the report sets the protocols side by side per model: what
the wheel response explains (commanded -> response) and what remains when the wheels are known (response
-> measured).
The board's cells, their intervals, settings and provenance are the rows of the dataset's results table
(benchmark/board/results.py, written once by evaluate and score); MLflow is asked only what it alone knows
(the runs a ``filter`` matches, the end of a run a dead process left open, other users' runs on a shared
server). The ranking's paired intervals are computed from the per-window tables (scoring/standings.py).
Figs. 3/4 come from the runs' metrics alone; Figs. 5-7 and the wheel response from what evaluate wrote
next to each run's per-window table (benchmark/report/data.py): compare reads no split, loads no fit and
predicts nothing. A figure whose data is absent is skipped, with a note in the report.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import hashlib
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from skidbench.benchmark.board import boards as brd
from skidbench.benchmark.board import results as rt
from skidbench.benchmark.board import selection as sel
from skidbench.benchmark.board.horizons import horizon_report
from skidbench.benchmark.board.installed import code_not_here
from skidbench.benchmark.board.selection import board_from_runs
from skidbench.benchmark.board.settings import CompareOptions
from skidbench.benchmark.board.tables import (
    CompareError,
    check_one_protocol,
    decomposition_table,
    leaderboard_texts,
    markdown_table,
    report_detail,
    summary_table,
)
from skidbench.benchmark.report.compare_figures import draw_figures, figure_jobs
from skidbench.benchmark.report.markdown import ReportContent, ReportSettings, report_md, sort_key
from skidbench.benchmark.report.settings import FigureSettings
from skidbench.benchmark.scoring import metrics as mt
from skidbench.benchmark.scoring import standings as st
from skidbench.benchmark.scoring.floor import FLOOR
from skidbench.benchmark.scoring.settings import IntervalConfig
from skidbench.benchmark.tracking import mlflow_ui as mu
from skidbench.benchmark.tracking import store as trk
from skidbench.benchmark.tracking import tags as run_tags
from skidbench.benchmark.tracking.settings import MlflowSettings, StoreSettings, mlflow_from_cfg, tracking_uri
from skidbench.models.registry.saved import board_findings
from skidbench.pipeline.core.io import write_text_atomic
from skidbench.pipeline.core.layout import PROTOCOLS, CommonSettings, Layout, root_from_cfg
from skidbench.pipeline.core.protocol import check_protocol

log = logging.getLogger(__name__)


# -- selecting runs ---------------------------------------------------------------------------------
def select_runs(
    tracker: trk.Tracker,
    table: pd.DataFrame,
    parent_run_id: str | None,
    allowed: set[str] | None,
    inputs: str | None = None,
    filter_string: str | None = None,
) -> tuple[pd.DataFrame, str | None]:
    """The model runs (:func:`results.runs` rows of the results ``table``) of the evaluate
    ``parent_run_id`` (``latest``: the newest complete one; None: every run) among ``allowed`` (the runs
    of compare's ``filter``, ``filter_string``), and the parent id used (or None); ``inputs``: only runs of
    that protocol."""
    parent = parent_run_id
    if parent == "latest":
        parent = rt.latest_evaluate(table, inputs)
        if parent is None:
            raise CompareError(
                f"no `skidbench evaluate` run{f' under inputs={inputs}' if inputs else ''} in experiment "
                f"{tracker.experiment_name!r} at {tracker.uri}; run it first (or set mlflow.experiment)"
            )
    runs = sel.children(table, inputs, allowed)
    if parent:  # its runs, with those it took unchanged from earlier evaluates (its file has their rows)
        mine = table[table["evaluate_id"] == parent]
        status = str(mine["evaluate_status"].iloc[0]) if len(mine) else ""
        own = runs[runs["run_id"].isin(set(mine["run_id"]))].assign(
            evaluate_id=parent, evaluate_status=status
        )
        own = own.reset_index(drop=True)
        # the external rows of `skidbench score` join every evaluate's board
        runs = with_external_runs(table, own, inputs, allowed) if len(own) else own
    if runs.empty:
        what = f"parent run {parent}" if parent else f"experiment {tracker.experiment_name!r}"
        raise CompareError(f"no model runs match in {what} (filter: {filter_string or 'none'})")
    return runs, parent


def with_external_runs(
    table: pd.DataFrame, runs: pd.DataFrame, inputs: str | None, allowed: set[str] | None
) -> pd.DataFrame:
    """``runs`` (an evaluate's model runs) and the external runs (``skidbench score``,
    benchmark/release/score.py) of the same protocol scored on the same split files (per terrain, the split
    fingerprint of the runs), newest first."""
    protocol = inputs or str(runs["inputs"].iloc[0])
    ext = sel.children(table, protocol, allowed)
    ext = ext[ext["external"].fillna(False).astype(bool) & ~ext["run_id"].isin(runs["run_id"])]
    fp = dict(zip(runs["terrain"], runs["splits_fingerprint"], strict=True))
    same = [fp.get(t) == f for t, f in zip(ext["terrain"], ext["splits_fingerprint"], strict=True)]
    if not any(same):
        return runs
    both = pd.concat([runs, ext[same]], ignore_index=True)
    return both.sort_values("start_time", ascending=False, kind="stable").reset_index(drop=True)


# -- the stage ---------------------------------------------------------------------------------------
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
    other_boards: dict[str, str] = field(
        default_factory=dict
    )  # every other protocol's ranked board, Markdown


def open_target(
    cs: CompareSettings, robot: Any, identity: Callable[[], dict]
) -> tuple[sel.Target, trk.Tracker]:
    """The dataset compare reads, in the store and experiment ``cs`` names: ``(target, tracker)``
    (:func:`selection.find_target`; ``robot``: the configured robot, for an imported dataset's check;
    ``identity``: the configured source's identity record, for a folder no stage recorded). CompareError
    (one line) when there is no store, no such dataset or run; StaleInputError when the dataset's last
    evaluate failed as a stage (a model run that failed does not count)."""
    from mlflow.tracking import MlflowClient

    from skidbench.pipeline.core.cache import check_producers
    from skidbench.pipeline.datasets.imported import check_stage

    ms, out_root = cs.mlflow, Path(cs.out_root)
    uri = tracking_uri(ms, Layout(out_root, cs.dataset))
    if not trk.has_store(uri):  # compare only reads: it does not create an empty store to find nothing in
        raise CompareError(
            f"no MLflow store at {uri}: nothing was evaluated under this output root; "
            "run `skidbench evaluate` first (or set mlflow.tracking_uri)"
        )
    trk.check_reachable(uri, ms.timeout_s)
    try:
        client = MlflowClient(tracking_uri=uri)
        target = sel.find_target(out_root, cs.dataset, ms.experiment, cs.parent_run_id, client, identity)
    except sel.SelectionError as exc:
        raise CompareError(str(exc)) from None
    if target.note:
        log.info("compare: %s", target.note)
    if target.layout.root.is_dir():
        check_producers(target.layout.root, "compare")
        check_stage(robot, "compare", target.layout.root)
    artifacts = Path(ms.artifact_root or target.layout.mlflow_artifacts)
    store = StoreSettings(tracking_uri(ms, target.layout), target.experiment, artifacts, ms.timeout_s,
                          target.dataset_id or "", cs.out_root)  # fmt: skip
    return target, trk.open_store(store)


def protocol_selections(
    table: pd.DataFrame,
    tracker: trk.Tracker,
    horizon_s: float,
    allowed: set[str] | None,
    user: str | None = None,
    without: dict[str, str] | None = None,
) -> dict[str, sel.Selection]:
    """``{protocol: selection}`` of every input protocol the results ``table`` has runs under (the newest
    complete run of each (model, terrain): :func:`selection.latest_complete`), in the order of
    ``PROTOCOLS``; ``without``: filled with why a protocol whose runs are all of evaluates that did not
    finish has none."""
    out = {}
    for p in PROTOCOLS:
        try:
            out[p] = sel.latest_complete(table, p, horizon_s, allowed, user, tracker)
        except sel.NoCompleteEvaluate as exc:
            if without is not None:
                without[p] = str(exc)
        except sel.NoRuns:
            continue
    return out


@dataclass(frozen=True)
class CompareSettings:
    """What compare reads of the config, each value once (:meth:`from_cfg`, made by the compare app): the
    output root, the dataset asked for and the ``mlflow`` section (:func:`open_target` finds the dataset
    and experiment from them), the horizon, which runs (``parent_run_id``, ``user``, ``filter``, the
    protocol asked for), how to rank, the report (its dataset: the one found), the figures and whether to
    log to MLflow."""

    horizon: float
    parent_run_id: str | None  # "latest", a run id, or None (every child run)
    user: str | None  # sel.whose: the caller's own runs unless user=<name> | all
    filter: str | None
    asked: str | None  # the checked protocol of ``inputs`` with parent_run_id=latest, else None
    inputs: str  # the configured protocol (unchecked), for a board whose protocol is not one of PROTOCOLS
    rank_by: str
    intervals: IntervalConfig
    report: ReportSettings
    figures: FigureSettings
    ui_url: str | None
    log_to_mlflow: bool
    out_root: str
    dataset: str  # the dataset asked for (``dataset``)
    mlflow: MlflowSettings
    half_track: float = 0.0  # m: the robot's, for the windows' aggressiveness (benchmark/board/horizons.py)

    @classmethod
    def from_cfg(cls, cfg: Any) -> CompareSettings:
        """compare's root keys (:class:`~skidbench.benchmark.board.settings.CompareOptions`), the common
        ones and the typed sections, each read once."""
        opts, common = root_from_cfg(cfg, CompareOptions), root_from_cfg(cfg, CommonSettings)
        parent_arg = None if opts.parent_run_id in (None, "", "null") else opts.parent_run_id
        rank_by, ms = opts.rank_by or st.AGGREGATE, mlflow_from_cfg(cfg)
        if ms is None:
            raise CompareError("compare's config has no mlflow section (mlflow=local)")
        return cls(
            horizon=opts.horizon,
            parent_run_id=parent_arg,
            user=sel.whose(opts.user),
            filter=opts.filter,
            asked=check_protocol(common.inputs) if parent_arg == "latest" else None,
            inputs=common.inputs or "commanded",
            rank_by=rank_by,
            intervals=OmegaConf.to_object(cfg.intervals),
            report=ReportSettings(common.dataset, opts.filter, rank_by),
            figures=OmegaConf.to_object(cfg.figures),
            ui_url=ms.ui_url,
            log_to_mlflow=opts.log_to_mlflow,
            out_root=common.out_root,
            dataset=common.dataset,
            mlflow=ms,
            half_track=float(cfg.robot.track_width) / 2.0 if cfg.get("robot") else 0.0,
        )


def run_compare(cs: CompareSettings, target: sel.Target, tracker: trk.Tracker) -> CompareResult:
    """Compare's orchestration on the dataset ``target`` of ``tracker``'s store and experiment (the compare
    app makes the three: :meth:`CompareSettings.from_cfg`, :func:`open_target`)."""
    layout = target.layout
    horizon = cs.horizon
    parent_arg = cs.parent_run_id
    user = cs.user
    table, selections, (runs, parent, left_out) = _selected(cs, target, tracker)
    board = with_code_here(board_from_runs(table, runs, horizon))
    protocol = check_one_protocol(board)
    # the protocol of the runs shown (the files evaluate wrote for them)
    inputs = protocol if protocol in PROTOCOLS else cs.inputs
    _check_horizon(table, runs, horizon)
    settings = dataclasses.replace(cs.report, dataset=target.name)  # the dataset found
    interval_notes: list[str] = []
    standings = standings_of(cs.rank_by, cs.intervals, layout, board, protocol, horizon, interval_notes)
    summary = summary_table(board, horizon, settings.rank_by, standings)
    parents = sel.Selection(protocol, horizon, runs).parents if parent is None else [parent]
    links = ui_links(settings, cs.ui_url, tracker, parents[0] if len(parents) == 1 else None, board, horizon)
    detail = report_detail(board, horizon, standings)
    out = layout.reports
    out.mkdir(parents=True, exist_ok=True)
    shown_boards = {protocol: (board, runs, left_out)}
    if parent is None:  # every protocol's board of the dataset, from the same selection
        for p, s in selections.items():
            if p != protocol:
                shown_boards[p] = (with_code_here(sel.board_of(s)), s.runs, s.left_out)

    def standings_for(p: str, b: pd.DataFrame) -> st.Standings | None:  # another protocol's: its own windows
        if p == protocol:
            return standings
        return standings_of(cs.rank_by, cs.intervals, layout, b, p, horizon, [])

    boards = _BoardsShown(target, tracker.experiment_name, parent, horizon, settings.rank_by, shown_boards)
    files, written, lb_md, other_mds = _write_boards(boards, out, protocol, summary, standings_for)
    dpi = cs.figures.dpi if cs.figures.enabled else None  # error against horizon, by aggressiveness
    files += horizon_report(layout, {p: b for p, (b, _r, _lo) in shown_boards.items()}, cs.intervals,
                            settings.rank_by, cs.half_track, out, dpi)  # fmt: skip
    boards_of = (  # the protocols side by side: the dataset's board of each
        {p: b for p, (b, _r, _lo) in shown_boards.items()}
        if parent is None
        else {p: sel.board_of(s) for p, s in selections.items()}
    )
    decomp, shown, decomp_md = _decomposition(boards_of, horizon)
    notes: list[str] = _fit_findings(layout, board, inputs) + interval_notes + _code_notes(board)
    newer = sel.newer_elsewhere(tracker, runs, protocol, cs.filter, user) if parent_arg == "latest" else None
    notes += [n for n in (newer, sel.same_data_elsewhere(tracker)) if n]
    log_mlflow = cs.log_to_mlflow
    log_to = _log_target(tracker, parent, parents, log_mlflow, notes)
    fs = cs.figures
    fig_md: list[str] = []
    if fs.enabled:
        jobs = figure_jobs(fs, layout, board, horizon, inputs, standings, decomp, shown)
        fig_md = draw_figures(jobs, out, files, notes)

    report = out / "report.md"
    content = ReportContent(tracker.uri, tracker.experiment_name, parent, board, summary, detail, horizon,
                            protocol, fig_md, notes, decomp_md, shown, links, target.record or {}, parents,
                            left_out, standings)  # fmt: skip
    write_text_atomic(report, report_md(settings, content))
    files.append(report)
    if log_mlflow:
        _log_report(
            tracker, log_to, settings.dataset, protocol, files, _note(lb_md, protocol, horizon, parents)
        )
    claim = ""
    if standings is not None:
        claim = "; ".join(f"{scope}: {v}" for scope, (v, _) in standings.claim.items())
    return CompareResult(report, lb_md, parent, files, notes, protocol, decomp_md, links, left_out, written,
                         target.name, parents, claim, other_mds)  # fmt: skip


def _selected(
    cs: CompareSettings, target: sel.Target, tracker: trk.Tracker
) -> tuple[pd.DataFrame, dict[str, sel.Selection], tuple[pd.DataFrame, str | None, list[str]]]:
    """The dataset's results table (its identity's and experiment's rows), every protocol's selection
    (:func:`protocol_selections`) and the board's runs (:func:`_chosen_runs`). latest: the newest complete
    run of each (model, terrain) under ``cs.asked``, across evaluates; a run id: that evaluate's runs;
    null: the newest run of each (model, terrain) of every model run, which must then be of one protocol (a
    filter on tags.`skidbench.inputs` narrows them)."""
    table = sel.results_of(target.layout, target.dataset_id, tracker.experiment_name)
    unfinished: dict[str, str] = {}
    try:
        allowed = sel.filtered_ids(tracker, cs.filter)
        selections = protocol_selections(table, tracker, cs.horizon, allowed, cs.user, unfinished)
    except sel.SelectionError as exc:
        raise CompareError(str(exc)) from None
    if cs.asked in unfinished and cs.asked not in selections:
        raise CompareError(unfinished[cs.asked])
    chosen = _chosen_runs(target, tracker, table, selections, cs, allowed)
    return table, selections, chosen


def _chosen_runs(
    target: sel.Target,
    tracker: trk.Tracker,
    table: pd.DataFrame,
    selections: dict[str, sel.Selection],
    cs: CompareSettings,
    allowed: set[str] | None,
) -> tuple[pd.DataFrame, str | None, list[str]]:
    """The runs of the board, the parent run they were selected by and the newer runs left out: with
    ``cs.asked`` (a protocol), the newest complete run of each (model, terrain) under it across evaluates
    (parent None); else the runs of ``cs.parent_run_id`` (:func:`select_runs`). CompareError (one line)
    when the protocol asked for has no complete run."""
    filter_string, user = cs.filter, cs.user
    if cs.asked is None:
        runs, parent = select_runs(tracker, table, cs.parent_run_id, allowed, None, filter_string)
        return runs, parent, []
    protocol = cs.asked
    where = f"experiment {tracker.experiment_name!r} at {tracker.uri}"
    mine = sel.not_yours(table, protocol, allowed, user, where) if user else None
    if protocol not in selections and mine:
        raise CompareError(mine)
    if protocol not in selections:
        others = f" (runs exist under inputs={', '.join(selections)})" if selections else ""
        if filter_string:
            others = f" matching filter {filter_string}" + others
        raise CompareError(
            f"no complete model run under inputs={protocol} of dataset {target.name} in {where}{others}; run "
            f"`skidbench evaluate{'' if protocol == 'commanded' else f' inputs={protocol}'}` first"
        )
    return selections[protocol].runs, None, selections[protocol].left_out


def _check_horizon(table: pd.DataFrame, runs: pd.DataFrame, horizon: float) -> None:
    """CompareError when the runs have no paper RMSRE at ``horizon`` in the results table."""
    at = table[table["run_id"].isin(runs["run_id"]) & table["metric"].isin([m.name for m in mt.PAPER])]
    if not np.isclose(at["horizon_s"].to_numpy(float), horizon).any():
        raise CompareError(
            f"the selected runs have no RMSRE at horizon {horizon:g} s; set horizon=<one evaluated>"
        )


@dataclass(frozen=True)
class _BoardsShown:
    """The boards a compare writes, one per protocol ``{protocol: (board, runs, left out)}``, and what
    their headers name."""

    target: sel.Target
    experiment_name: str
    parent: str | None
    horizon: float
    rank_by: str
    boards: dict[str, tuple[pd.DataFrame, pd.DataFrame, list[str]]]


def _write_boards(
    shown: _BoardsShown,
    out: Path,
    protocol: str,
    summary: pd.DataFrame,
    standings_of: Callable[[str, pd.DataFrame], st.Standings | None],
) -> tuple[list[Path], list[str], str, dict[str, str]]:
    """Write each protocol's leaderboard (:func:`boards.write_leaderboard`): ``(files, one line per
    protocol, the ranked table's Markdown of the protocol shown, {other protocol: its ranked table})``."""
    files: list[Path] = []
    written: list[str] = []
    when = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    lb_md = markdown_table(summary)
    others: dict[str, str] = {}
    rank_by, horizon, target = shown.rank_by, shown.horizon, shown.target
    for p, (b, r, lo) in shown.boards.items():
        rank_key = st.AGGREGATE if rank_by == st.AGGREGATE else mt.rank_key(rank_by, horizon)
        header = brd.leaderboard_header(target.name, target.dataset_id, shown.experiment_name, p,
                                        shown.parent, horizon, rank_key, when, lo)  # fmt: skip
        csv_text, md_text, md_ranked = leaderboard_texts(b, r, horizon, rank_by, header, standings_of(p, b))
        paths, line = brd.write_leaderboard(out, p, csv_text, md_text)
        files += paths
        written.append(f"leaderboard inputs={p}: {line}")
        if p == protocol:
            lb_md = md_ranked
        else:
            others[p] = md_ranked
    return files, written, lb_md, others


def _decomposition(boards_of: dict[str, pd.DataFrame], horizon: float) -> tuple[pd.DataFrame, list[str], str]:
    """The protocols side by side (:func:`board_tables.decomposition_table`), the protocols it shows
    ([] when none) and its Markdown ("" when none)."""
    decomp = decomposition_table(boards_of, horizon)
    shown = decomp.attrs.get("protocols", []) if len(decomp) else []
    decomp_md = markdown_table(decomp[[c for c in decomp.columns if not c.startswith("_")]]) if shown else ""
    return decomp, shown, decomp_md


def _log_target(
    tracker: trk.Tracker, parent: str | None, parents: list[str], log_mlflow: bool, notes: list[str]
) -> str | None:
    """The evaluate run every row hangs from, to log the report to; None (a compare run) when the rows come
    from several evaluates or from another person's (left as they made it; a note says so)."""
    log_to = parent or (parents[0] if len(parents) == 1 else None)
    owner = tracker.client.get_run(log_to).data.tags.get(run_tags.TAG_USER) if log_to else None
    if log_to and owner != run_tags.current_user():  # another person's evaluate run is left as they made it
        log_to = None
        if log_mlflow:
            notes.append(f"the report is logged to a compare run of yours, not to {owner}'s evaluate run")
    return log_to


def _note(board_md: str, protocol: str, horizon: float, parents: list[str]) -> str:
    """A compare run's description (``mlflow.note.content``, shown first on its page): the ranked board."""
    title = (f"**Leaderboard**, inputs={protocol}, {horizon:g} s horizon, as `skidbench compare` ranks it "
             "(paired intervals: a gap inside them is a tie), from the runs of "
             f"{len(parents)} evaluate run(s): " + ", ".join(f"`{p}`" for p in parents))  # fmt: skip
    return f"{title}\n\n{board_md}\n\nThe full report: artifact `report/report.md`.\n"[: run_tags.MAX_TAG_LEN]


def _log_report(
    tracker: trk.Tracker, run_id: str | None, dataset: str, protocol: str, files: list[Path], note: str = ""
) -> None:
    """Log the report's files to ``run_id``, or to a new compare run of the caller's when None (its
    description: ``note``, the board)."""
    if run_id is None:
        tags = {
            run_tags.TAG_ROLE: "compare",
            run_tags.TAG_DATASET: str(dataset),
            run_tags.TAG_INPUTS: protocol,
        }
        run_id = tracker.start(f"compare {dataset}", {**tags, **({run_tags.TAG_NOTE: note} if note else {})})
        tracker.end(run_id)
    for f in files:
        tracker.artifact(run_id, f, "report")


def with_code_here(board: pd.DataFrame) -> pd.DataFrame:
    """``board`` with the column ``code_here``: why a row's model code is not installed here ("" when it
    is; benchmark/board/installed.py). Such rows stay on the board, not ranked."""
    return board.assign(code_here=code_not_here(board))


def _code_notes(board: pd.DataFrame) -> list[str]:
    """One line per row whose model code is not installed here."""
    bad = board[board["code_here"].astype(bool)] if "code_here" in board else board.iloc[:0]
    return [f"{m}/{t}: {why}; its numbers are shown, not ranked (install that code to rank it)"
            for m, t, why in zip(bad["model"], bad["terrain"], bad["code_here"], strict=True)]  # fmt: skip


def _fit_findings(layout: Layout, board: pd.DataFrame, inputs: str) -> list[str]:
    """The findings of the board's fits (a parameter at its bound: ``roc degenerates to edd on this data:
    b2 at its bound``), for the console notes and the report's Notes (models/fitting/fit.py formats them)."""
    done = board[board["status"] == "FINISHED"] if "status" in board else board
    rows = list(zip(done["model"].astype(str), done["terrain"].astype(str), strict=True))
    return board_findings(layout, rows, inputs)


def standings_of(
    rank_by: str,
    intervals: IntervalConfig,
    layout: Layout,
    board: pd.DataFrame,
    protocol: str,
    horizon: float,
    notes: list[str],
) -> st.Standings | None:
    """The board's intervals, ranking (by ``rank_by``) and claim from the per-window tables evaluate wrote
    (:mod:`skidbench.benchmark.scoring.standings`), or None (with a note) when there are none to read."""
    if rank_by != st.AGGREGATE:
        mt.rank_key(rank_by, horizon)  # a bad rank_by: one line
    gone = set(board.loc[board["code_here"].astype(bool), "model"]) if "code_here" in board else set()
    rankable = board[~board["model"].isin(gone)]  # a model with a row whose code is not here: not ranked
    windows, missing = brd.read_windows(layout, rankable, protocol, horizon)
    notes += [f"paired intervals: {m}" for m in missing]
    if not any(m != FLOOR for m, _ in windows):
        notes.append(
            "no per-window table of these runs here: the leaderboard shows the logged intervals, ranked "
            "by point estimate (no paired comparison)"
        )
        return None
    return st.build(windows, horizon, intervals, rank_by)


def ui_links(
    settings: ReportSettings,
    ui_url: str | None,
    tracker: trk.Tracker,
    parent: str | None,
    board: pd.DataFrame,
    horizon: float,
) -> dict[str, str]:
    """MLflow UI links (model-training pages, not the GenAI ones): the parent run's page, and a saved view
    of the runs shown (the RMSRE columns first, best first; :mod:`mlflow_ui`) as a table and as charts of
    the RMSRE per run; ``ui_url``: the UI's address (``mlflow.ui_url``; None: from the store's)."""
    uri, exp = tracker.uri, tracker.experiment_id
    cols, _ = mu.board_columns(("ld", "cv"), horizon)
    order = sort_key(settings.rank_by, horizon)  # the aggregate is not a logged metric: sort by ld_trans
    links = {}
    if parent:
        links["parent run"] = mu.run_url(uri, exp, parent, ui_url)
        key, title = f"evaluate-{parent[:8]}", tracker.client.get_run(parent).info.run_name
        search = mu.children_of(parent)
    else:  # every child run compare selected: a view of those runs
        ids = ", ".join(f"'{r}'" for r in board["run_id"])
        digest = hashlib.sha256(ids.encode()).hexdigest()[:8]
        key, title = f"compare-{digest}", f"compare {settings.dataset}: {len(board)} runs"
        search = f"attributes.run_id IN ({ids})"
    mu.save_view(tracker.client, exp, key, title, mu.view_state(search, cols, order, mu.chart_title(horizon)))
    links["runs table (saved view)"] = mu.view_url(uri, exp, key, ui_url)
    links["charts of its model runs"] = mu.view_url(uri, exp, key, ui_url, charts=True)
    links["experiment (its model-training runs)"] = mu.experiment_url(uri, exp, ui_url)
    return links
