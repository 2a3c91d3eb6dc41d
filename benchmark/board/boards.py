"""A dataset's board under one input protocol, every row with its provenance: compare's leaderboard files
(``reports/leaderboard-<protocol>[-<UTC stamp>].csv|.md``), what ``skidbench export`` puts in a bundle
(``board/<protocol>.csv|json``) and what ``skidbench publish`` shows.

The rows are compare's (:func:`skidbench.benchmark.board.selection.latest_complete`: the newest complete run
of
each (model, terrain) under the protocol, across evaluates, external rows of ``skidbench score``
included), so a board here and compare's leaderboard files hold the same numbers. Each row adds where it
comes from: its run and parent run, the digest of the options it was made with (the model's config, the
protocol, the scoring and calibration settings: tag ``skidbench.options_digest``), the model's version
and code, skidbench's version and commit, the libraries' versions, the dataset's identity and the
fingerprint of the split files it was scored on, whether it is an external row (and its predictions
file's sha256), its start time and the command that reproduces it: the columns of its rows in the
dataset's results table (benchmark/board/results.py), read as they were written, never parsed back from
MLflow's strings. The settings every row was scored with (horizons, test splits, the metric's minimum
distance and rotation) are those of the newest evaluate the rows come from.

Leaderboard files are never overwritten silently: each compare writes ``leaderboard-<protocol>-<UTC
stamp>.csv|.md`` (unless the rows are those of the latest file: then it says so) and a ``latest`` copy,
``leaderboard-<protocol>.csv|.md``, beside them.
"""

from __future__ import annotations

import datetime as dt
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow.parquet as pq

from skidbench.benchmark.board import results as rt
from skidbench.benchmark.scoring.floor import FLOOR
from skidbench.pipeline.core.errors import SkidbenchError
from skidbench.pipeline.core.io import read_parquet_metadata, write_json_atomic, write_text_atomic
from skidbench.pipeline.core.layout import PROTOCOLS, Layout

#: the columns a board adds to compare's, in this order (then ``env.<library>`` columns: the versions)
PROVENANCE_COLUMNS = (
    "parent_run_id",
    "start_time_utc",
    "options_digest",
    "model_version",
    "package",
    "code_version",
    "code_digest",
    "skidbench_version",
    "git_commit",
    "dataset_id",
    "splits_fingerprint",
    "external",
    "predictions_sha256",
    "link",
    "submitter",
    "submitted",
    "description",
    "reproduce",
)
#: a submission's identity (``skidbench score``: benchmark/release/submission.py), "" for an evaluated model
SUBMISSION_COLUMNS = ("link", "submitter", "submitted", "description")
TAG_OPTIONS = "skidbench.options_digest"  # the options a child run was made with (evaluate's _start_child)
#: the versions a leaderboard row always has a column for (empty when its run did not record them)
ENV_COLUMNS = ("python", "numpy", "scipy", "numba", "pandas", "pyarrow", "mlflow")


@dataclass
class Board:
    """The board of one input protocol: its rows (compare's columns, then :data:`PROVENANCE_COLUMNS`),
    the parent run they hang from, the settings they were scored with and the horizon shown."""

    protocol: str
    parent_run_id: str
    horizon: float
    settings: dict[str, Any] = field(default_factory=dict)
    rows: pd.DataFrame = field(default_factory=pd.DataFrame)


def provenance(runs: pd.DataFrame) -> pd.DataFrame:
    """Per run (``run_id``, :data:`PROVENANCE_COLUMNS`, then ``env.<name>`` for :data:`ENV_COLUMNS` and
    every other library version a run recorded) from the runs' rows of the results table
    (:func:`results.runs`)."""
    start = pd.to_datetime(runs["start_time"], utc=True, errors="coerce")
    text = lambda name: runs[name].fillna("").astype(str)  # noqa: E731
    out = pd.DataFrame(
        {
            "run_id": runs["run_id"],
            "parent_run_id": text("evaluate_id"),
            "start_time_utc": start.dt.strftime("%Y-%m-%d %H:%M:%S").fillna(""),
            **{c: text(c) for c in ("options_digest", "model_version", "package", "code_version",
                                    "code_digest", "skidbench_version", "git_commit", "dataset_id",
                                    "splits_fingerprint")},
            "external": runs["external"].fillna(False).astype(bool),
            "predictions_sha256": text("predictions_sha256"),
            # a submission's identity (benchmark/release/submission.py); "" for an evaluated model
            **{k: text(k) for k in SUBMISSION_COLUMNS},
            "reproduce": text("reproduce"),
        }
    )  # fmt: skip
    names = sorted({k for v in runs["versions"] for k in (v or {})})
    for name in dict.fromkeys([*ENV_COLUMNS, *names]):  # one order, whatever the runs
        out[f"env.{name}"] = [str((v or {}).get(name, "")) for v in runs["versions"]]
    return out


def with_provenance(board: pd.DataFrame, runs: pd.DataFrame) -> pd.DataFrame:
    """compare's board rows (``board_from_runs``) and the provenance of each row's run."""
    prov = provenance(runs)
    prov = prov.drop(columns=[c for c in prov.columns if c in board.columns and c != "run_id"])
    rows = board.merge(prov, on="run_id", how="left")
    rows["start_time"] = rows["start_time"].astype(str)
    return rows.reset_index(drop=True)


def protocol_board(table: pd.DataFrame, protocol: str) -> Board | None:
    """The board of ``protocol`` from the dataset's results ``table`` (None when it has no evaluate), with
    provenance: the newest complete run of each (model, terrain) at the first horizon of the protocol's
    latest evaluate."""
    from skidbench.benchmark.board.selection import NoRuns, board_of, latest_complete

    parent = rt.latest_evaluate(table, protocol)
    if parent is None:
        return None
    settings = rt.settings_of(table, parent)
    horizon = float((settings.get("horizons") or [6.0])[0])
    try:
        sel = latest_complete(table, protocol, horizon)
    except NoRuns:
        return None
    newest = sel.parents[0] if sel.parents else parent
    if newest != parent:
        settings = rt.settings_of(table, newest)
    return Board(protocol, newest, horizon, settings, with_provenance(board_of(sel), sel.runs))


def all_boards(table: pd.DataFrame) -> dict[str, Board]:
    """``{protocol: board}`` of every protocol with an evaluate in the results ``table``, in the order of
    ``PROTOCOLS``."""
    out = {}
    for p in PROTOCOLS:
        b = protocol_board(table, p)
        if b is not None:
            out[p] = b
    return out


# -- compare's leaderboard files ----------------------------------------------------------------------
def utc_stamp(when: dt.datetime | None = None) -> str:
    """``20261125T101500Z``: a file name's UTC time stamp."""
    return (when or dt.datetime.now(dt.UTC)).strftime("%Y%m%dT%H%M%SZ")


def leaderboard_paths(folder: Path, protocol: str, stamp: str | None = None) -> tuple[Path, Path]:
    """``(<folder>/leaderboard-<protocol>[-<stamp>].csv, .md)``; no stamp: the latest copy."""
    stem = f"leaderboard-{protocol}" + (f"-{stamp}" if stamp else "")
    return Path(folder) / f"{stem}.csv", Path(folder) / f"{stem}.md"


def write_leaderboard(folder: Path, protocol: str, csv_text: str, md_text: str) -> tuple[list[Path], str]:
    """Writes one protocol's leaderboard: ``leaderboard-<protocol>-<UTC stamp>.csv|.md`` (kept) and the
    latest copy ``leaderboard-<protocol>.csv|.md``, each atomically. When the rows (the CSV) are those of
    the latest copy, no new stamped pair is written and the latest ``.md`` is rewritten only. Returns the
    files written and a line saying what happened."""
    folder = Path(folder)
    latest_csv, latest_md = leaderboard_paths(folder, protocol)
    if latest_csv.is_file() and latest_csv.read_text() == csv_text:
        write_text_atomic(latest_md, md_text)
        return [latest_csv, latest_md], f"{latest_csv.name}: the same rows as before (no new stamped copy)"
    stamp = utc_stamp()
    csv, md = leaderboard_paths(folder, protocol, stamp)
    k = 1
    while csv.exists() or md.exists():  # two compares within one second: never overwrite a kept file
        k += 1
        csv, md = leaderboard_paths(folder, protocol, f"{stamp}-{k}")
    write_text_atomic(csv, csv_text)
    write_text_atomic(md, md_text)
    write_text_atomic(latest_csv, csv_text)
    write_text_atomic(latest_md, md_text)
    return [csv, md, latest_csv, latest_md], f"{csv.name} (latest: {latest_csv.name})"


def _plain(v: Any) -> Any:
    """A cell as JSON: NaN -> None, numpy scalars -> Python."""
    if isinstance(v, float | np.floating):
        return None if not np.isfinite(v) else float(v)
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    return v


def write_board(board: Board, folder: Path, extra: dict[str, Any] | None = None) -> list[Path]:
    """``<folder>/<protocol>.csv`` (the rows) and ``<protocol>.json`` (the settings, the parent run and
    the rows as records; ``extra`` added at the top level), atomically. Returns both paths."""
    folder = Path(folder)
    csv = folder / f"{board.protocol}.csv"
    js = folder / f"{board.protocol}.json"
    write_text_atomic(csv, board.rows.to_csv(index=False))
    records = [{k: _plain(v) for k, v in r.items()} for r in board.rows.to_dict("records")]
    write_json_atomic(
        js,
        {
            "protocol": board.protocol,
            "parent_run_id": board.parent_run_id,
            "horizon_s": board.horizon,
            "settings": board.settings,
            "written_utc": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M:%S"),
            **(extra or {}),
            "rows": records,
        },
    )
    return [csv, js]


def read_board(path: Path) -> Board:
    """A board written by :func:`write_board` (its ``.json``)."""
    doc = json.loads(Path(path).read_text())
    rows = pd.DataFrame(doc.get("rows") or [])
    return Board(str(doc["protocol"]), str(doc.get("parent_run_id") or ""), float(doc.get("horizon_s", 6.0)),
                 dict(doc.get("settings") or {}), rows)  # fmt: skip


def _ranked_by(rank_key: str) -> str:
    """What a board ranks by: ``mean4`` (the ranking rule's aggregate, docs/intervals.md) or one metric."""
    if rank_key == "mean4":
        return ("the mean of the four RMSREs over terrains, with paired 95 % intervals: best only when "
                "resolved from every other model, else tied (docs/intervals.md)")  # fmt: skip
    return f"the mean over terrains of `{rank_key}`"


def leaderboard_header(
    dataset: str, dataset_id: str | None, experiment: str, protocol: str, parent: str | None,
    horizon: float, rank_key: str, when: str, left_out: list[str],
) -> list[str]:  # fmt: skip
    """The lines above a leaderboard file's tables: what it is, the command that wrote it and when, which
    runs its rows are (``parent``: one evaluate's; None: the newest complete ones), the newer runs left
    out."""
    which = (
        f"the child runs of evaluate run {parent}"
        if parent
        else "the newest complete (FINISHED) run of each (model, terrain) of this dataset under this "
        "protocol, across evaluates"
    )
    cmd = f"skidbench compare dataset={dataset} inputs={protocol}" + (
        f" parent_run_id={parent}" if parent else ""
    )
    lines = [
        f"# Leaderboard: dataset {dataset}, inputs={protocol}, {horizon:g} s horizon",
        "",
        f"Written by `{cmd}` on {when}. Rows: {which}. Ranked by {_ranked_by(rank_key)} "
        f"(lower is better). Dataset identity `{dataset_id or '?'}`; MLflow experiment `{experiment}`. "
        "The CSV beside this file has every row's run id, options digest, versions and commit.",
    ]
    if left_out:
        lines += ["", "Newer runs left out (the board keeps the complete run named):", ""]
        lines += [f"- {line}" for line in left_out]
    return lines


def read_windows(
    layout: Layout, rows: pd.DataFrame, protocol: str, horizon_s: float
) -> tuple[dict[tuple[str, str], pd.DataFrame], list[str]]:
    """The windows at ``horizon_s`` of every FINISHED (model, terrain) of a board (``rows``: model, terrain,
    status; ``run_id``) and of the floor of each of its terrains: ``{(model, terrain): windows}``, and a note
    per table that could not be read (a run whose files are elsewhere) or was written by another run than the
    row's (a later evaluate's, killed, say): those cells keep their logged intervals."""
    tables, notes = read_tables(layout, rows, protocol)
    return at_horizon(tables, horizon_s), notes


def at_horizon(
    tables: dict[tuple[str, str], pd.DataFrame], horizon_s: float
) -> dict[tuple[str, str], pd.DataFrame]:
    """The windows at ``horizon_s`` of tables of :func:`read_tables` (a table without one left out)."""
    out = {}
    for k, w in tables.items():
        if "horizon_s" in w:
            w = w[np.isclose(w["horizon_s"].to_numpy(float), horizon_s)]
        if len(w):
            out[k] = w
    return out


def read_tables(
    layout: Layout, rows: pd.DataFrame, protocol: str, columns: Sequence[str] | None = None
) -> tuple[dict[tuple[str, str], pd.DataFrame], list[str]]:
    """The per-window tables (every horizon) of a board's FINISHED (model, terrain) and its floors, read
    once for :func:`at_horizon` to take each horizon's windows from, and the notes of
    :func:`read_windows`; an empty table is left out. ``columns``: only those of a table's columns."""
    out, notes = {}, []
    ok = rows[rows["status"] == "FINISHED"]
    wanted = [(str(m), str(t)) for m, t in zip(ok["model"], ok["terrain"], strict=True)]
    wanted += [(FLOOR, str(t)) for t in sorted(ok["terrain"].unique())]
    runs = ok["run_id"] if "run_id" in ok else [""] * len(ok)
    run_of = {(str(m), str(t)): r for m, t, r in zip(ok["model"], ok["terrain"], runs, strict=True)}
    for model, terrain in wanted:
        stem = layout.eval_stem(model, terrain, protocol)
        path = stem.with_name(stem.name + ".windows.parquet")
        try:
            keep = None if columns is None else [c for c in pq.read_schema(path).names if c in columns]
            w = pd.read_parquet(path, columns=keep)
            made_by = str(read_parquet_metadata(path).get("run_id") or "")
        except (OSError, ValueError, SkidbenchError) as exc:
            if model != FLOOR:  # an evaluate from before the floor existed: no floor row, silently
                notes.append(f"{model}/{terrain}: no per-window table ({path.name}: {type(exc).__name__})")
            continue
        board_run = str(run_of.get((model, terrain)) or "")
        if made_by and board_run and made_by != board_run:  # a later evaluate (killed, say) rewrote it
            notes.append(f"{model}/{terrain}: {path.name} is of run {made_by[:8]}, not of the board's run "
                         f"{board_run[:8]}: its cells keep their logged intervals")  # fmt: skip
            continue
        if model == FLOOR and not len(w):  # a floor that cannot be measured says why (evaluate's note)
            unknown = read_parquet_metadata(path).get("floor_unknown")
            if unknown:
                notes.append(f"{terrain}: {unknown}")
        if len(w):
            out[(model, terrain)] = w
    return out, notes
