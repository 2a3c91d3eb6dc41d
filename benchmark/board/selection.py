"""Which runs a board is made of, and which dataset compare reads.

**One board per dataset and input protocol** (:func:`latest_complete`): of every model run in the dataset's
results table (benchmark/board/results.py: the rows of its identity, ``dataset_id``, and experiment) under
the protocol, across *complete* evaluates (their ``evaluate_status`` FINISHED: the evaluate ran to its
end), the newest complete run of each (model, terrain): FINISHED, with the metrics of the horizon shown,
scored on the terrain's current split files (the split fingerprint of the terrain's newest complete run)
with the same scoring settings (``min_distance_m``, ``min_rotation_deg`` of the newest complete run). So
``evaluate models=[mine]`` after a full evaluate puts ``mine`` on the full board beside the built-ins, and
the runs of an evaluate that was killed, failed or is still running are never on a board, not even those
of its runs that finished: the board never mixes an evaluate that did not finish with another. Every run
newer than the one a row uses is *left out*, with why, in one line each (compare prints them). A (model,
terrain) whose newest run of a complete evaluate FAILED shows that run so that failures stay on the board;
one without any run of a complete evaluate is not on the board (named).

The numbers, settings and run columns come from the table; the MLflow store is asked only what it alone
knows: the run ids an MLflow ``filter`` string matches (:func:`filtered_ids`), the end a dead process could
not write (a run or evaluate the store's bookkeeping reaped KILLED since, with its reason and run name:
:func:`store_statuses`), and the runs of other output roots on a shared server (:func:`newer_elsewhere`,
:func:`same_data_elsewhere`).

**The dataset** (:func:`find_target`): ``dataset=<name>`` names a folder of the output root, and its
``dataset.json`` gives the identity the runs carry, whatever ``source`` is configured (so ``compare
dataset=<name>`` needs no source arguments); ``parent_run_id=<run id>`` takes the dataset and experiment
of that run; ``mlflow.experiment=<name>`` alone takes the dataset of that experiment's runs.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from skidbench.benchmark.board import results as rt
from skidbench.benchmark.errors import EvaluationError
from skidbench.benchmark.scoring.standings import order_models
from skidbench.benchmark.tracking import store as trk
from skidbench.benchmark.tracking import tags as run_tags
from skidbench.pipeline.core.errors import one_line
from skidbench.pipeline.core.layout import Layout

#: the settings of an evaluate that decide which windows a score is over (equal on one board)
SCORING_PARAMS = ("min_distance_m", "min_rotation_deg")
SPLITS = ("cv", "ld")


class SelectionError(EvaluationError):
    """No run to make a board of, no such dataset, or a search MLflow refused."""


class NoRuns(SelectionError):
    """The dataset has no run under the protocol (and filter)."""


class NoCompleteEvaluate(NoRuns):
    """The dataset has runs under the protocol, but no evaluate of them ran to its end."""


def store_statuses(tracker: trk.Tracker | None, run_ids: list[str]) -> dict[str, tuple[str, str, str]]:
    """``{run id: (status, run name, reason)}`` of the runs ``run_ids`` in the MLflow store (None: no
    store); a run gone from the store is absent."""
    out: dict[str, tuple[str, str, str]] = {}
    ids = sorted(set(run_ids))
    if tracker is None or not ids or not tracker.search_ids():
        return out
    for k in range(0, len(ids), 100):
        quoted = ", ".join(f"'{i}'" for i in ids[k : k + 100])
        for r in tracker.client.search_runs(tracker.search_ids(), f"attributes.run_id IN ({quoted})",
                                            max_results=1000):  # fmt: skip
            reason = one_line(r.data.tags.get(run_tags.TAG_REASON, ""))[:160]
            out[r.info.run_id] = (r.info.status, r.info.run_name or "", reason)
    return out


def _ended(status: str, stored: tuple[str, str, str] | None) -> tuple[str, str, str]:
    """A run's ``(status, run name, reason)``: the table's, unless the table still says RUNNING (a dead
    process could not write its end) and the store has ended it since."""
    if stored is not None and status == "RUNNING" and stored[0] != "RUNNING":
        return stored
    return status, (stored[1] if stored else ""), (stored[2] if stored else "")


def _when(ts: Any) -> str:
    """A run's start time as ``YYYY-MM-DD HH:MM:SS UTC``."""
    t = pd.Timestamp(ts)
    if pd.isna(t):
        return "?"
    t = t.tz_localize("UTC") if t.tzinfo is None else t.tz_convert("UTC")
    return t.strftime("%Y-%m-%d %H:%M:%S UTC")


@dataclass
class Selection:
    """The runs of one board: ``runs`` (:func:`results.runs` rows, one run per (model, terrain)), the
    lines naming each newer run left out and why (``left_out``), the protocol, the horizon and the
    dataset's results table the runs' cells are read from (:func:`board_of`)."""

    protocol: str
    horizon_s: float
    runs: pd.DataFrame
    left_out: list[str] = field(default_factory=list)
    table: pd.DataFrame = field(default_factory=pd.DataFrame)

    @property
    def parents(self) -> list[str]:
        """The evaluate (or score) runs the rows hang from, newest first."""
        p = self.runs.sort_values("start_time", ascending=False)["evaluate_id"]
        return list(dict.fromkeys(str(x) for x in p if isinstance(x, str) and x))


def results_of(layout: Layout, dataset_id: str | None, experiment: str | None = None) -> pd.DataFrame:
    """The dataset's results table (:func:`results.read`): only the rows of ``dataset_id`` (its identity:
    the rows of another content under the same folder name never join its board) and of the MLflow
    ``experiment`` (a transfer evaluate has its own), each when given."""
    table = rt.read(layout)
    keep = pd.Series(True, index=table.index)
    if dataset_id:
        keep &= table["dataset_id"] == dataset_id
    if experiment:
        keep &= table["experiment"] == experiment
    return table[keep].reset_index(drop=True)


def search_children(
    tracker: trk.Tracker, inputs: str | None, filter_string: str | None = None, user: str | None = None
) -> pd.DataFrame:
    """Every child run of the tracker's dataset in the MLflow store (under ``inputs``; of ``user``;
    narrowed by an MLflow ``filter_string``), newest first, as a ``search_runs`` frame."""
    import mlflow

    clauses = [f"tags.`{run_tags.TAG_ROLE}` = 'child'", *tracker.dataset_filter()]
    if inputs:
        clauses.append(f"tags.`{run_tags.TAG_INPUTS}` = '{inputs}'")
    if user:
        clauses.append(f"tags.`mlflow.user` = '{user.replace(chr(39), '')}'")
    if filter_string:
        clauses.append(f"({filter_string})" if " or " in filter_string.lower() else str(filter_string))
    ids = tracker.search_ids()
    if not ids:
        return pd.DataFrame()
    mlflow.set_tracking_uri(tracker.uri)
    try:
        return mlflow.search_runs(
            experiment_ids=ids,
            filter_string=" AND ".join(clauses),
            order_by=["attributes.start_time DESC"],
            output_format="pandas",
        )
    except mlflow.exceptions.MlflowException as exc:
        raise SelectionError(
            f"MLflow search_runs: {one_line(exc.message)[:300]} (check filter=...)"
        ) from None


def filtered_ids(tracker: trk.Tracker, filter_string: str | None) -> set[str] | None:
    """The ids of the dataset's child runs an MLflow filter string (compare's ``filter``) matches; None
    without a filter (every run). SelectionError (one line) when MLflow refuses the filter."""
    if not filter_string:
        return None
    runs = search_children(tracker, None, filter_string)
    return set(runs["run_id"]) if len(runs) else set()


def children(
    table: pd.DataFrame, inputs: str | None, allowed: set[str] | None = None, user: str | None = None
) -> pd.DataFrame:
    """The model runs of the results ``table`` (:func:`results.runs`, newest first) under ``inputs``,
    among ``allowed`` (the run ids of a filter; None: every run) and of ``user`` (None: anyone's)."""
    runs = rt.runs(table)
    keep = pd.Series(True, index=runs.index)
    if inputs:
        keep &= runs["inputs"] == inputs
    if allowed is not None:
        keep &= runs["run_id"].isin(allowed)
    if user:
        keep &= runs["user"] == user
    return runs[keep].reset_index(drop=True)


def _evaluate_gone(parent: str, status: str, stored: dict[str, tuple[str, str, str]]) -> str | None:
    """Why a run of the evaluate ``parent`` (its ``evaluate_status`` in the table) is never on a board
    (None: the evaluate is complete)."""
    if not parent:
        return None  # a run logged without an evaluate (a library call): judged by itself
    if status == "FINISHED":
        return None
    known = stored.get(parent)  # the store's end when it has one (a failed evaluate's runs reaped KILLED)
    if known is not None and known[0] not in ("RUNNING", "FINISHED"):
        status = known[0]
    name, reason = (known[1], known[2]) if known else ("", "")
    return (f"its evaluate {f'{name} ({parent[:8]})' if name else parent[:8]} ended {status}"
            + (f" ({reason})" if reason else "")
            + ": the runs of an evaluate that did not finish are never on a board")  # fmt: skip


def latest_complete(
    table: pd.DataFrame,
    inputs: str,
    horizon_s: float,
    allowed: set[str] | None = None,
    user: str | None = None,
    tracker: trk.Tracker | None = None,
) -> Selection:
    """The board's runs under ``inputs`` (see the module docstring) from the dataset's results ``table``:
    the newest complete run of each (model, terrain), and a line for each newer run left out
    (``allowed``: the run ids of compare's ``filter``, :func:`filtered_ids`; ``tracker``: the store asked
    for the end of runs the table still has RUNNING, and the names of unfinished evaluates). NoRuns when
    there is no run under the protocol."""
    where = f"experiment {tracker.experiment_name!r} at {tracker.uri}" if tracker else "the results table"
    runs = children(table, inputs, allowed, user)
    if runs.empty:
        who = f" of user {user}" if user else ""
        raise NoRuns(
            f"no model runs{who} under inputs={inputs} in {where}"
            f"{' (among the runs of the filter)' if allowed is not None else ''}; run `skidbench evaluate` "
            "first"
        )
    parent = runs["evaluate_id"].fillna("").astype(str).tolist()
    open_ = [p for p, s in zip(parent, runs["evaluate_status"], strict=True) if p and s != "FINISHED"]
    stored = store_statuses(tracker, open_ + runs.loc[runs["status"] == "RUNNING", "run_id"].tolist())
    ended = [_ended(s, stored.get(r)) for s, r in zip(runs["status"], runs["run_id"], strict=True)]
    was = runs["status"].tolist()  # a run the store ended since: its end and reason are the store's
    runs["reason"] = [e[2] if e[0] != w else r for e, w, r in zip(ended, was, runs["reason"].fillna(""),
                                                                  strict=True)]  # fmt: skip
    runs["status"] = [e[0] for e in ended]
    gone = [_evaluate_gone(p, s, stored) for p, s in zip(parent, runs["evaluate_status"], strict=True)]
    has = runs["horizons_scored"].map(lambda hs: any(np.isclose(h, horizon_s) for h in hs))
    complete = (runs["status"] == "FINISHED") & has & pd.Series([g is None for g in gone])
    why_not = _objections(runs, complete, gone, horizon_s)
    keep: list[int] = []
    left_out: list[str] = []
    for (m, t), idx in runs.groupby([runs["model"], runs["terrain"]], sort=False).groups.items():
        order = list(idx)  # newest first (runs is sorted)
        kept, lines = _pick(runs, order, [why_not(i) for i in order], gone)
        keep += kept
        left_out += [f"{m}/{t}: {line}" for line in lines]
    why = next((g for g in gone if g), None)  # the newest run's evaluate that did not finish
    if not keep and why:
        raise NoCompleteEvaluate(
            f"no complete evaluate under inputs={inputs} in {where}: {why.removeprefix('its ')}; run "
            "`skidbench evaluate` again (it runs what is missing)"
        )
    chosen = runs.loc[sorted(keep)].reset_index(drop=True)
    return Selection(inputs, float(horizon_s), chosen, left_out, table)


def _objections(runs: pd.DataFrame, complete: pd.Series, gone: list[str | None], horizon_s: float):
    """``why_not(i)``: why run ``i`` is not the complete run of its (model, terrain) (None: it is), against
    the board's data and scoring settings: those of the newest complete runs."""
    terrain, fingerprint = runs["terrain"].astype(str), runs["splits_fingerprint"].fillna("")
    ref_fp: dict[str, str] = {}
    for t, f, c in zip(terrain, fingerprint, complete, strict=True):
        if c and f and t not in ref_fp:  # newest first
            ref_fp[t] = f
    settings = {name: pd.to_numeric(runs[name], errors="coerce") for name in SCORING_PARAMS}
    ref_set = {}
    for name, values in settings.items():
        done = values[complete & values.notna()]
        if len(done):
            ref_set[name] = float(done.iloc[0])

    def why_not(i: int) -> str | None:
        if gone[i] is not None:
            return gone[i]
        status = str(runs.at[i, "status"])
        if status != "FINISHED":
            reason = str(runs.at[i, "reason"] or "")
            return status + (f": {one_line(reason)[:160]}" if reason else "")
        if not complete.iat[i]:
            return f"no {horizon_s:g} s metrics (evaluated at other horizons)"
        t = terrain.iat[i]
        if t in ref_fp and fingerprint.iat[i] and fingerprint.iat[i] != ref_fp[t]:
            return "scored on other split files of this terrain (the data changed since)"
        for name, want in ref_set.items():
            have = settings[name].iat[i]
            if np.isfinite(have) and not np.isclose(have, want):
                return f"scored with {name}={have:g} (the board's: {want:g})"
        return None

    return why_not


def _pick(
    runs: pd.DataFrame, order: list[int], reasons: list[str | None], gone: list[str | None]
) -> tuple[list[int], list[str]]:
    """Of one (model, terrain)'s runs (``order``: their rows, newest first; ``reasons``: why each is not
    complete, None when it is; ``gone``: why its evaluate is not complete), the row on the board (none or
    one) and a line for each newer run left out."""
    use = next((k for k, r in enumerate(reasons) if r is None), None)
    keep, newer = ([order[use]], order[:use]) if use is not None else ([], order[:1])
    if use is None:  # no complete run: its newest run of a complete evaluate stays when it failed
        failed = [k for k, i in enumerate(order) if gone[i] is None and runs.at[i, "status"] != "FINISHED"]
        keep, newer = ([order[failed[0]]], order[: failed[0]]) if failed else ([], order[:1])
    uses = "no complete run of it is on the board"
    if use is not None:
        i = order[use]
        uses = f"the board has its run {runs.at[i, 'run_id'][:8]} of {_when(runs.at[i, 'start_time'])}"
    lines = [
        f"run {runs.at[i, 'run_id'][:8]} ({_when(runs.at[i, 'start_time'])}) left out: "
        f"{reasons[order.index(i)]}; {uses}"
        for i in newer
    ]
    return keep, lines


def board_from_runs(table: pd.DataFrame, runs: pd.DataFrame, horizon_s: float) -> pd.DataFrame:
    """One row per (model, terrain), the latest run of each (``runs``: :func:`results.runs` rows), its
    cells read from the results ``table`` (:func:`results.board`): model, terrain, status, reason, every
    metric of :data:`~skidbench.benchmark.scoring.metrics.METRICS` at ``horizon_s`` (and its window count,
    interval and blocks, as evaluate computed them), fit/predict numbers, run_id; in the board's order."""
    df = rt.board(table, runs, horizon_s)
    df = df.sort_values("start_time", ascending=False)
    df = df.drop_duplicates(["model", "inputs", "terrain"], keep="first")
    order = {m: i for i, m in enumerate(order_models(df["model"].dropna().unique().tolist()))}
    df = df.assign(_o=df["model"].map(order)).sort_values(["_o", "terrain"]).drop(columns="_o")
    return df.reset_index(drop=True)


def board_of(selection: Selection) -> pd.DataFrame:
    """The board of a selection (:func:`board_from_runs` of its runs, at its horizon)."""
    return board_from_runs(selection.table, selection.runs, selection.horizon_s)


# -- the dataset compare reads ---------------------------------------------------------------------
@dataclass
class Target:
    """The dataset a command reads runs of: its name, folder, identity (``dataset.json``'s fingerprint)
    and MLflow experiment; ``note``: how it was found when not named (said on the console)."""

    name: str
    layout: Layout
    dataset_id: str | None
    experiment: str
    record: dict[str, Any]
    note: str = ""


def datasets_of(out_root: Path) -> list[str]:
    """The datasets an output root holds (folders with a ``dataset.json``)."""
    root = Path(out_root)
    if not root.is_dir():
        return []
    return sorted(p.name for p in root.iterdir() if (p / "dataset.json").is_file())


def _no_dataset(out_root: Path, name: str) -> SelectionError:
    have = datasets_of(out_root)
    held = f"it holds {', '.join(have)}: `skidbench compare dataset=<name>`" if have else "it holds none"
    return SelectionError(f"{Path(out_root) / name}: no dataset {name!r} under {out_root}; {held}")


def find_target(
    out_root: Path, name: str, experiment: str, parent: str | None, client: Any | None, identity: Any
) -> Target:
    """The dataset and experiment a command asks for (see the module docstring): ``dataset=<name>`` in
    ``out_root``, ``mlflow.experiment`` (``experiment``), ``parent_run_id`` (``parent``). ``client``: an
    MlflowClient of the store (None: no store yet). ``identity``: the configured source's identity record
    (a dict), called only for a folder no stage recorded."""
    from skidbench.pipeline.datasets.identity import read_record

    out_root = Path(out_root)
    if client is not None and parent not in (None, "", "null", "latest"):
        from mlflow.exceptions import MlflowException

        try:
            run = client.get_run(str(parent))
        except MlflowException:
            raise SelectionError(f"parent_run_id={parent}: no such run in the MLflow store") from None
        tags = run.data.tags
        found = tags.get(run_tags.TAG_DATASET) or name
        layout = Layout(out_root, found)
        exp = client.get_experiment(run.info.experiment_id).name
        rec = read_record(layout) or {}
        note = f"dataset {found} and experiment {exp!r} of run {parent}" if found != name else ""
        return Target(
            found, layout, tags.get(run_tags.TAG_DATASET_ID) or rec.get("fingerprint"), exp, rec, note
        )
    layout = Layout(out_root, name)
    rec = read_record(layout)
    if experiment != f"skidbench-{name}" and client is not None:
        # the experiment was named: its runs say which dataset they are of
        exp = client.get_experiment_by_name(experiment)
        runs = client.search_runs([exp.experiment_id], order_by=["attributes.start_time DESC"],
                                  max_results=1) if exp is not None else []  # fmt: skip
        if runs:
            tags = runs[0].data.tags
            own = rec is not None and tags.get(run_tags.TAG_DATASET_ID) == rec.get("fingerprint")
            if not own and tags.get(run_tags.TAG_DATASET):
                found = str(tags[run_tags.TAG_DATASET])
                layout = Layout(out_root, found)
                rec2 = read_record(layout) or {}
                note = f"dataset {found}: the dataset of the runs of experiment {experiment!r}"
                ident = tags.get(run_tags.TAG_DATASET_ID) or rec2.get("fingerprint")
                return Target(found, layout, ident, experiment, rec2, note)
    if rec is None:
        if not layout.root.is_dir():
            raise _no_dataset(out_root, name)
        # a folder no stage recorded (runs logged by a library call): the configured source's identity
        try:
            rec = identity()
        except Exception:  # noqa: BLE001 - a source that cannot say: as if the folder were not there
            raise _no_dataset(out_root, name) from None
    return Target(name, layout, str(rec.get("fingerprint") or "") or None, experiment, rec)


# -- `skidbench datasets`: each dataset's boards ---------------------------------------------------------
def board_lines(table: pd.DataFrame, horizon_s: float = 6.0) -> list[str]:
    """One line per input protocol the dataset's results ``table`` has runs under: the board's latest runs
    (the newest complete run of each (model, terrain): :func:`latest_complete`), how many evaluates they
    come from, the newest, and how many newer runs are left out."""
    from skidbench.pipeline.core.layout import PROTOCOLS

    lines = []
    for p in PROTOCOLS:
        try:
            s = latest_complete(table, p, horizon_s)
        except NoRuns:
            continue
        runs = s.runs
        ok = runs[runs["status"] == "FINISHED"]
        models, terrains = ok["model"].nunique(), ok["terrain"].nunique()
        bad = len(runs) - len(ok)
        newest = ok.sort_values("start_time", ascending=False).head(1)
        when = _when(newest["start_time"].iat[0]) if len(newest) else "-"
        parents = s.parents
        line = (
            f"inputs={p}: {models} model(s) x {terrains} terrain(s) complete"
            + (f", {bad} without a complete run" if bad else "")
            + f", from {len(parents)} evaluate(s), newest run {when}"
            + (f" (evaluate {parents[0]})" if parents else "")
        )
        if s.left_out:
            line += f"; {len(s.left_out)} newer run(s) left out (`skidbench compare` names them)"
        lines.append(line)
    return lines


def dataset_boards(out_root: Path, names_ids: dict[str, str], horizon_s: float = 6.0) -> dict[str, list[str]]:
    """``{dataset: board_lines}`` of each dataset (name -> identity) of the output root, from its results
    table (the rows of its experiment ``skidbench-<name>``); a dataset without runs gets no entry, a table
    that cannot be read one line."""
    out: dict[str, list[str]] = {}
    for name, ident in names_ids.items():
        try:
            table = results_of(Layout(Path(out_root), name), ident or None, f"skidbench-{name}")
            lines = board_lines(table, horizon_s)
        except EvaluationError as exc:
            lines = [f"results: {one_line(str(exc))[:200]}"]
        if lines:
            out[name] = lines
    return out


# -- whose runs (a lab's shared server) -------------------------------------------------------------------
ALL_USERS = "all"


def whose(user: str | None) -> str | None:
    """The user whose runs a board is made of, from compare's ``user`` setting: null = the caller
    (:func:`~skidbench.benchmark.tracking.tags.current_user`), ``all`` = everyone (None), or that name."""
    if user in (None, ""):
        return run_tags.current_user()
    return None if str(user) == ALL_USERS else str(user)


def not_yours(
    table: pd.DataFrame, inputs: str, allowed: set[str] | None, user: str, where: str
) -> str | None:
    """When ``user`` has no run under ``inputs`` in the results ``table`` but others have: the line that
    says whose and what to type (``where``: the experiment and store); else None."""
    runs = children(table, inputs, allowed)
    who = runs["user"].fillna("").replace("", "?")
    others = runs[who != user]
    if others.empty:
        return None
    names = list(dict.fromkeys(who[who != user]))
    return (
        f"no model run of user {user} under inputs={inputs} in {where}; runs of {', '.join(names)} exist: "
        f"`skidbench compare user={names[0]}` (or user=all), or run `skidbench evaluate` first"
    )


def others_runs(tracker: trk.Tracker, inputs: str, filter_string: str | None, user: str) -> pd.DataFrame:
    """The dataset's child runs in the MLflow store under ``inputs`` made by anyone but ``user``, newest
    first (of any output root: a lab's shared server holds the runs of every machine)."""
    runs = search_children(tracker, inputs, filter_string)
    if runs.empty:
        return runs
    return runs[_tag(runs, run_tags.TAG_USER).fillna("?") != user]


def _tag(runs: pd.DataFrame, name: str) -> pd.Series:
    col = f"tags.{name}"
    return runs[col] if col in runs else pd.Series([None] * len(runs), index=runs.index, dtype=object)


def newer_elsewhere(
    tracker: trk.Tracker, runs: pd.DataFrame, inputs: str, filter_string: str | None, user: str | None
) -> str | None:
    """One line when someone other than ``user`` completed an evaluate of this dataset (same protocol) after
    the newest of the board's ``runs`` (an evaluate of theirs that did not finish is not counted)."""
    if not user or runs.empty:
        return None
    others = others_runs(tracker, inputs, filter_string, user)
    if others.empty:
        return None
    parents = _tag(others, run_tags.TAG_PARENT).fillna("").astype(str)
    statuses = store_statuses(tracker, [p for p in parents if p])
    done = [(p in statuses and statuses[p][0] == "FINISHED") for p in parents]
    others = others[pd.Series(done, index=others.index) & (others["status"] == "FINISHED")]
    if others.empty or others["start_time"].iloc[0] <= runs["start_time"].max():
        return None
    who = str(_tag(others, run_tags.TAG_USER).fillna("?").iloc[0])
    parent = str(_tag(others, run_tags.TAG_PARENT).iloc[0])
    what = f"{statuses[parent][1]}, run {parent[:8]}, complete"
    return (
        f"{who} evaluated this dataset after you ({what}); this report is yours, `skidbench compare "
        f"user={who}` shows theirs"
    )


def same_data_elsewhere(tracker: trk.Tracker) -> str | None:
    """One line when other skidbench experiments of the store hold runs of this dataset's content (its
    identity, ``skidbench.dataset_id``): the same recording under another name, e.g. mounted at another path
    on another machine (an automatic name carries its path), whose runs this board leaves out."""
    if not tracker.dataset_id:
        return None
    own = tracker.experiment_name
    exps = {
        e.experiment_id: e.name
        for e in tracker.client.search_experiments(filter_string="name LIKE 'skidbench-%'", max_results=1000)
        if e.name != own and not e.name.startswith(own + "-")  # not its own transfer experiment
    }
    if not exps:
        return None
    runs = tracker.client.search_runs(
        list(exps), f"tags.`{run_tags.TAG_DATASET_ID}` = '{tracker.dataset_id}'", max_results=200
    )
    names = sorted({exps[r.info.experiment_id] for r in runs})
    if not names:
        return None
    return (
        f"runs of this dataset's content (dataset id {tracker.dataset_id}) are also in experiment(s) "
        f"{', '.join(repr(n) for n in names)}, under another dataset name, and not on this board; to compare "
        "them as one, give the data the same name everywhere: source.dataset=<name>"
    )
