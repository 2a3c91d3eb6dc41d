"""Which runs a board is made of, and which dataset compare reads.

**One board per dataset and input protocol** (:func:`latest_complete`): of every child run of the dataset
(its identity, tag ``skidbench.dataset_id``) under the protocol, across *complete* evaluates (their parent
run FINISHED: it ran to its end), the newest complete run of each (model, terrain): FINISHED, with the
metrics of the horizon shown, scored on the terrain's current split files (the split fingerprint of the
terrain's newest complete run) with the same scoring settings (``min_distance_m``, ``min_rotation_deg`` of
the newest complete run). So ``evaluate models=[mine]`` after a full evaluate puts ``mine`` on the full
board beside the built-ins, and the runs of an evaluate that was killed, failed or is still running are
never on a board, not even those of its runs that finished: the board never mixes an evaluate that did not
finish with another. Every run newer than the one a row uses is *left out*, with why, in one line each
(compare prints them). A (model, terrain) whose newest run of a complete evaluate FAILED shows that run so
that failures stay on the board; one without any run of a complete evaluate is not on the board (named).

**The dataset** (:func:`target_from_cfg`): ``dataset=<name>`` names a folder of the output root, and its
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

from skidbench.benchmark.errors import EvaluationError
from skidbench.benchmark.scoring import metrics as mt
from skidbench.benchmark.scoring.standings import order_models
from skidbench.benchmark.tracking import store as trk
from skidbench.benchmark.tracking import tags as run_tags
from skidbench.pipeline.core.errors import one_line
from skidbench.pipeline.core.layout import Layout

#: the parameters of an evaluate that decide which windows a score is over (equal on one board)
SCORING_PARAMS = ("min_distance_m", "min_rotation_deg")
SPLITS = ("cv", "ld")


class SelectionError(EvaluationError):
    """No run to make a board of, no such dataset, or a search MLflow refused."""


class NoRuns(SelectionError):
    """The dataset has no run under the protocol (and filter)."""


class NoCompleteEvaluate(NoRuns):
    """The dataset has runs under the protocol, but no evaluate of them ran to its end."""


def evaluate_statuses(tracker: trk.Tracker, parent_ids: list[str]) -> dict[str, tuple[str, str, str]]:
    """``{parent run id: (status, run name, reason)}`` of the evaluates (or scores) ``parent_ids``; one
    that is gone from the store is absent. An evaluate is complete when FINISHED: its parent run ends so
    only when every model run was made (a killed or crashed one is RUNNING until reaped, then KILLED)."""
    out: dict[str, tuple[str, str, str]] = {}
    ids = sorted(set(parent_ids))
    for k in range(0, len(ids), 100):
        quoted = ", ".join(f"'{i}'" for i in ids[k : k + 100])
        for r in tracker.client.search_runs(tracker.search_ids(), f"attributes.run_id IN ({quoted})",
                                            max_results=1000):  # fmt: skip
            reason = one_line(r.data.tags.get(run_tags.TAG_REASON, ""))[:160]
            out[r.info.run_id] = (r.info.status, r.info.run_name or "", reason)
    return out


def _evaluate_gone(parent: str, statuses: dict[str, tuple[str, str, str]]) -> str | None:
    """Why a run of the evaluate ``parent`` is never on a board (None: the evaluate is complete)."""
    if not parent:
        return None  # a run logged without an evaluate (a library call): judged by itself
    if parent not in statuses:
        return f"its evaluate {parent[:8]} is gone from the store"
    status, name, reason = statuses[parent]
    if status == "FINISHED":
        return None
    return (f"its evaluate {name} ({parent[:8]}) ended {status}" + (f" ({reason})" if reason else "")
            + ": the runs of an evaluate that did not finish are never on a board")  # fmt: skip


def _col(runs: pd.DataFrame, name: str) -> pd.Series:
    return runs[name] if name in runs else pd.Series([None] * len(runs), index=runs.index, dtype=object)


def _when(ts: Any) -> str:
    """A run's start time as ``YYYY-MM-DD HH:MM:SS UTC``."""
    t = pd.Timestamp(ts)
    if pd.isna(t):
        return "?"
    t = t.tz_localize("UTC") if t.tzinfo is None else t.tz_convert("UTC")
    return t.strftime("%Y-%m-%d %H:%M:%S UTC")


@dataclass
class Selection:
    """The runs of one board: ``runs`` (a ``search_runs`` frame, one run per (model, terrain)), the lines
    naming each newer run left out and why (``left_out``), the protocol and the horizon."""

    protocol: str
    horizon_s: float
    runs: pd.DataFrame
    left_out: list[str] = field(default_factory=list)

    @property
    def parents(self) -> list[str]:
        """The evaluate (or score) runs the rows hang from, newest first."""
        p = _col(self.runs.sort_values("start_time", ascending=False), f"tags.{run_tags.TAG_PARENT}")
        return list(dict.fromkeys(str(x) for x in p if isinstance(x, str) and x))


def search_children(
    tracker: trk.Tracker, inputs: str | None, filter_string: str | None = None, user: str | None = None
) -> pd.DataFrame:
    """Every child run of the tracker's dataset (under ``inputs``; of ``user``; narrowed by an MLflow
    ``filter_string``), newest first, as a ``search_runs`` frame."""
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


def _has_metrics(runs: pd.DataFrame, horizon_s: float) -> pd.Series:
    """Per run: does it have a paper metric (RMSRE) at ``horizon_s``?"""
    have = pd.Series(False, index=runs.index)
    for m in mt.PAPER:
        for split in SPLITS:
            col = f"metrics.{m.metric_key(split, horizon_s)}"
            if col in runs:
                have |= pd.to_numeric(runs[col], errors="coerce").notna()
    return have


def _setting(runs: pd.DataFrame, name: str) -> pd.Series:
    """A scoring parameter of each run as a number (NaN when the run did not log it)."""
    return pd.to_numeric(_col(runs, f"params.{name}"), errors="coerce")


def latest_complete(
    tracker: trk.Tracker,
    inputs: str,
    horizon_s: float,
    filter_string: str | None = None,
    user: str | None = None,
) -> Selection:
    """The board's runs under ``inputs`` (see the module docstring): the newest complete run of each
    (model, terrain), and a line for each newer run left out. SelectionError when the dataset has no run
    under the protocol."""
    runs = search_children(tracker, inputs, filter_string, user)
    if runs.empty:
        who = f" of user {user}" if user else ""
        raise NoRuns(
            f"no model runs{who} under inputs={inputs} in experiment {tracker.experiment_name!r} at "
            f"{tracker.uri}{f' (filter: {filter_string})' if filter_string else ''}; run `skidbench "
            "evaluate` first"
        )
    runs = runs.sort_values("start_time", ascending=False, kind="stable").reset_index(drop=True)
    model = _col(runs, f"tags.{run_tags.TAG_MODEL}").astype(str)
    terrain = _col(runs, f"tags.{run_tags.TAG_TERRAIN}").astype(str)
    fingerprint = _col(runs, f"tags.{run_tags.TAG_FINGERPRINT}").fillna("")
    parent = [p if isinstance(p, str) else "" for p in _col(runs, f"tags.{run_tags.TAG_PARENT}")]
    statuses = evaluate_statuses(tracker, [p for p in parent if p])
    gone = [_evaluate_gone(p, statuses) for p in parent]
    complete = (
        (runs["status"] == "FINISHED") & _has_metrics(runs, horizon_s) & pd.Series([g is None for g in gone])
    )
    # the data and the scoring settings of the board: those of the newest complete runs
    ref_fp: dict[str, str] = {}
    for t, f, c in zip(terrain, fingerprint, complete, strict=True):
        if c and f and t not in ref_fp:  # newest first
            ref_fp[t] = f
    settings = {name: _setting(runs, name) for name in SCORING_PARAMS}
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
            reason = str(_col(runs, f"tags.{run_tags.TAG_REASON}").iat[i] or "")
            reason = "" if reason in ("nan", "None") else reason
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

    keep: list[int] = []
    left_out: list[str] = []
    for (m, t), idx in runs.groupby([model, terrain], sort=False).groups.items():
        order = list(idx)  # newest first (runs is sorted)
        kept, lines = _pick(runs, order, [why_not(i) for i in order], gone)
        keep += kept
        left_out += [f"{m}/{t}: {line}" for line in lines]
    why = next((g for g in gone if g), None)  # the newest run's evaluate that did not finish
    if not keep and why:
        raise NoCompleteEvaluate(
            f"no complete evaluate under inputs={inputs} in experiment {tracker.experiment_name!r} at "
            f"{tracker.uri}: {why.removeprefix('its ')}; run `skidbench evaluate` again (it runs what is "
            "missing)"
        )
    chosen = runs.loc[sorted(keep)].reset_index(drop=True)
    return Selection(inputs, float(horizon_s), chosen, left_out)


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


def board_from_runs(runs: pd.DataFrame, horizon_s: float) -> pd.DataFrame:
    """One row per (model, terrain), the latest run of each: model, terrain, status, reason, every metric
    of :data:`~skidbench.benchmark.scoring.metrics.METRICS` at ``horizon_s`` (and its window count),
    fit/predict
    numbers, run_id."""
    df = pd.DataFrame(
        {
            "model": _col(runs, f"tags.{run_tags.TAG_MODEL}"),
            "inputs": _col(runs, f"tags.{run_tags.TAG_INPUTS}").fillna("unknown"),
            "terrain": _col(runs, f"tags.{run_tags.TAG_TERRAIN}"),
            "status": runs["status"],
            "reason": _col(runs, f"tags.{run_tags.TAG_REASON}").fillna(""),
            "version": _col(runs, f"tags.{run_tags.TAG_MODEL_VERSION}").fillna(""),
            "package": _col(runs, f"tags.{run_tags.TAG_PLUGIN}").fillna(""),
            "code_digest": _col(runs, "tags.skidbench.code.digest").fillna(
                ""
            ),  # pipeline/runner/environment.py
            "code_distribution": _col(runs, "tags.skidbench.code.distribution").fillna(""),
            # a row scored from a predictions file (`skidbench score`, benchmark/release/score.py)
            "external": _col(runs, f"tags.{run_tags.TAG_EXTERNAL}").fillna("false").eq("true"),
            "run_id": runs["run_id"],
            "start_time": runs["start_time"],
        }
    )
    for metric in mt.METRICS:  # an optional one (models with a predictive covariance): NaN for the others
        for split in SPLITS:
            keys = [metric.metric_key(split, horizon_s), metric.windows_key(split, horizon_s)]
            if metric.bootstrap is not None:  # its 95 % interval and the independent blocks behind it
                keys += list(metric.interval_keys(split, horizon_s))
                seed_sd = f"{metric.metric_key(split, horizon_s)}_seed_sd"  # evaluate seeds=N > 1
                keys += [seed_sd] if f"metrics.{seed_sd}" in runs else []
            for key in keys:
                if key is not None:  # the value, and the windows behind it
                    df[key] = pd.to_numeric(_col(runs, f"metrics.{key}"), errors="coerce")
    for m in ("fit_loss", "fit_time_s", "predict_time_s"):
        df[m] = pd.to_numeric(_col(runs, f"metrics.{m}"), errors="coerce")
    df.loc[df["status"] == "RUNNING", "reason"] = "still running (or killed)"
    df = df.sort_values("start_time", ascending=False)
    df = df.drop_duplicates(["model", "inputs", "terrain"], keep="first")
    order = {m: i for i, m in enumerate(order_models(df["model"].dropna().unique().tolist()))}
    df = df.assign(_o=df["model"].map(order)).sort_values(["_o", "terrain"]).drop(columns="_o")
    return df.reset_index(drop=True)


def parent_runs(
    tracker: trk.Tracker, parent: str, inputs: str | None, filter_string: str | None
) -> pd.DataFrame:
    """The child runs of one evaluate (``parent_run_id=<run id>``), newest first."""
    extra = f"tags.`{run_tags.TAG_PARENT}` = '{parent}'"
    return search_children(tracker, inputs, f"{extra} AND ({filter_string})" if filter_string else extra)


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


def target_from_cfg(cfg: Any, client: Any | None) -> Target:
    """The dataset and experiment ``cfg`` asks for (see the module docstring). ``client``: an MlflowClient
    of the store (None: no store yet)."""
    from skidbench.pipeline.datasets.identity import read_record

    out_root = Path(str(cfg.out_root))
    name = str(cfg.dataset)
    experiment = str(cfg.mlflow.experiment)
    parent = cfg.get("parent_run_id")
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
        from dataclasses import asdict

        from skidbench.pipeline.datasets.identity import identity_from_cfg

        try:
            rec = asdict(identity_from_cfg(cfg))
        except Exception:  # noqa: BLE001 - a source that cannot say: as if the folder were not there
            raise _no_dataset(out_root, name) from None
    return Target(name, layout, str(rec.get("fingerprint") or "") or None, experiment, rec)


# -- `skidbench datasets`: each dataset's boards ---------------------------------------------------------
def board_lines(tracker: trk.Tracker, horizon_s: float = 6.0) -> list[str]:
    """One line per input protocol the tracker's dataset has runs under: the board's latest runs (the
    newest complete run of each (model, terrain): :func:`latest_complete`), how many evaluates they come
    from, the newest, and how many newer runs are left out."""
    from skidbench.pipeline.core.protocol import PROTOCOLS

    lines = []
    for p in PROTOCOLS:
        try:
            s = latest_complete(tracker, p, horizon_s)
        except NoRuns:
            continue
        runs = s.runs
        ok = runs[runs["status"] == "FINISHED"]
        models = _col(ok, f"tags.{run_tags.TAG_MODEL}").nunique()
        terrains = _col(ok, f"tags.{run_tags.TAG_TERRAIN}").nunique()
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


def dataset_boards(uri: str, names_ids: dict[str, str], horizon_s: float = 6.0) -> dict[str, list[str]]:
    """``{dataset: board_lines}`` of each dataset (name -> identity) in the store ``uri`` (its experiment
    ``skidbench-<name>``); a dataset without runs gets no entry, a store that cannot be read one line."""
    if not trk.has_store(uri):
        return {}
    out: dict[str, list[str]] = {}
    for name, ident in names_ids.items():
        try:
            tracker = trk.Tracker(uri, f"skidbench-{name}", dataset_id=ident or None)
            lines = board_lines(tracker, horizon_s)
        except EvaluationError as exc:
            lines = [f"MLflow: {one_line(str(exc))[:200]}"]
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


def others_runs(tracker: trk.Tracker, inputs: str, filter_string: str | None, user: str) -> pd.DataFrame:
    """The dataset's child runs under ``inputs`` made by anyone but ``user``, newest first."""
    runs = search_children(tracker, inputs, filter_string)
    if runs.empty:
        return runs
    return runs[_col(runs, f"tags.{run_tags.TAG_USER}").fillna("?") != user]


def not_yours(tracker: trk.Tracker, inputs: str, filter_string: str | None, user: str) -> str | None:
    """When ``user`` has no run under ``inputs`` but others have: the line that says whose and what to
    type; else None."""
    others = others_runs(tracker, inputs, filter_string, user)
    if others.empty:
        return None
    names = list(dict.fromkeys(_col(others, f"tags.{run_tags.TAG_USER}").fillna("?")))
    return (
        f"no model run of user {user} under inputs={inputs} in experiment {tracker.experiment_name!r} at "
        f"{tracker.uri}; runs of {', '.join(names)} exist: `skidbench compare user={names[0]}` (or "
        "user=all), or run `skidbench evaluate` first"
    )


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
    parents = _col(others, f"tags.{run_tags.TAG_PARENT}").fillna("").astype(str)
    statuses = evaluate_statuses(tracker, [p for p in parents if p])
    done = [(p in statuses and statuses[p][0] == "FINISHED") for p in parents]
    others = others[pd.Series(done, index=others.index) & (others["status"] == "FINISHED")]
    if others.empty or others["start_time"].iloc[0] <= runs["start_time"].max():
        return None
    who = str(_col(others, f"tags.{run_tags.TAG_USER}").fillna("?").iloc[0])
    parent = str(_col(others, f"tags.{run_tags.TAG_PARENT}").iloc[0])
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
