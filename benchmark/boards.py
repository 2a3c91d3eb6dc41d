"""A dataset's board under one input protocol, every row with its provenance: what ``skidbench export``
puts in a bundle (``board/<protocol>.csv|json``) and ``skidbench publish`` shows.

The rows are compare's (:func:`skidbench.benchmark.compare.select_runs` and ``board_from_runs``: the
child runs of the latest evaluate under the protocol, external rows of ``skidbench score`` included, the
newest run per (model, terrain)), so a board here and compare's leaderboard files hold the same numbers.
Each row adds where it comes from: its run and parent run, the skidbench commit, the dataset's identity
and the fingerprint of the split files it was scored on, whether it is an external row (and its
predictions file's sha256), its start time and the command that reproduces it (from the run's
description). The settings every row was scored with (horizons, test splits, the metric's minimum
distance and rotation) are the parent evaluate's parameters.
"""

from __future__ import annotations

import ast
import datetime as dt
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from skidbench.pipeline.io import write_json_atomic, write_text_atomic
from skidbench.pipeline.protocol import PROTOCOLS

from . import tracking as trk

#: the columns a board adds to compare's, in this order
PROVENANCE_COLUMNS = (
    "parent_run_id",
    "git_commit",
    "dataset_id",
    "splits_fingerprint",
    "external",
    "predictions_sha256",
    "start_time_utc",
    "reproduce",
)
#: the parent evaluate's parameters every row of its board was scored with (and their defaults)
SETTING_KEYS = ("horizons", "splits", "min_distance_m", "min_rotation_deg", "models")


@dataclass
class Board:
    """The board of one input protocol: its rows (compare's columns, then :data:`PROVENANCE_COLUMNS`),
    the parent run they hang from, the settings they were scored with and the horizon shown."""

    protocol: str
    parent_run_id: str
    horizon: float
    settings: dict[str, Any] = field(default_factory=dict)
    rows: pd.DataFrame = field(default_factory=pd.DataFrame)

    def metric_columns(self) -> list[str]:
        """The RMSRE columns (%) of the horizon shown: ``<split>_<h>s_<trans|rot>_rmsre_pct``."""
        return [c for c in self.rows.columns if c.endswith("_rmsre_pct")]


def _literal(text: Any) -> Any:
    """An MLflow param (a string) back to its value: ``"[6.0]"`` -> [6.0], ``"0.5"`` -> 0.5."""
    if text is None:
        return None
    try:
        return ast.literal_eval(str(text))
    except (ValueError, SyntaxError):
        return str(text)


def parent_settings(tracker: trk.Tracker, parent_id: str) -> dict[str, Any]:
    """The settings of an evaluate (or score) parent run, from its params (``SETTING_KEYS``)."""
    params = tracker.client.get_run(parent_id).data.params
    return {k: _literal(params[k]) for k in SETTING_KEYS if k in params}


def _reproduce(note: Any) -> str:
    """The command(s) of a run's description (the fenced block after "Reproduce:"), one per line."""
    m = re.search(r"Reproduce:\s*```\n(.*?)\n```", str(note or ""), flags=re.S)
    return m.group(1).strip() if m else ""


def _col(runs: pd.DataFrame, name: str) -> pd.Series:
    return runs[name] if name in runs else pd.Series([None] * len(runs), index=runs.index, dtype=object)


def provenance(runs: pd.DataFrame) -> pd.DataFrame:
    """Per run (``run_id`` then :data:`PROVENANCE_COLUMNS`) from the runs' tags (a search_runs frame)."""
    start = pd.to_datetime(runs["start_time"], utc=True, errors="coerce")
    return pd.DataFrame(
        {
            "run_id": runs["run_id"],
            "parent_run_id": _col(runs, f"tags.{trk.TAG_PARENT}").fillna(""),
            "git_commit": _col(runs, f"tags.{trk.TAG_GIT}").fillna(""),
            "dataset_id": _col(runs, f"tags.{trk.TAG_DATASET_ID}").fillna(""),
            "splits_fingerprint": _col(runs, f"tags.{trk.TAG_FINGERPRINT}").fillna(""),
            "external": _col(runs, f"tags.{trk.TAG_EXTERNAL}").fillna("false").eq("true"),
            "predictions_sha256": _col(runs, f"tags.{trk.TAG_PREDICTIONS_SHA256}").fillna(""),
            "start_time_utc": start.dt.strftime("%Y-%m-%d %H:%M:%S").fillna(""),
            "reproduce": _col(runs, f"tags.{trk.TAG_NOTE}").map(_reproduce),
        }
    )


def protocol_board(tracker: trk.Tracker, protocol: str, filter_string: str | None = None) -> Board | None:
    """The board of the latest evaluate under ``protocol`` (None when there is none), with provenance."""
    from .compare import board_from_runs, select_runs

    parent = tracker.latest_parent(protocol)
    if parent is None:
        return None
    settings = parent_settings(tracker, parent)
    horizons = settings.get("horizons") or [6.0]
    horizon = float(horizons[0] if isinstance(horizons, list | tuple) else horizons)
    runs, _ = select_runs(tracker, parent, filter_string, protocol)
    board = board_from_runs(runs, horizon)
    prov = provenance(runs)
    prov = prov.drop(columns=[c for c in prov.columns if c in board.columns and c != "run_id"])
    rows = board.merge(prov, on="run_id", how="left")
    rows["start_time"] = rows["start_time"].astype(str)
    return Board(protocol, parent, horizon, settings, rows.reset_index(drop=True))


def all_boards(tracker: trk.Tracker, filter_string: str | None = None) -> dict[str, Board]:
    """``{protocol: board}`` of every protocol with an evaluate, in the order of ``PROTOCOLS``."""
    out = {}
    for p in PROTOCOLS:
        b = protocol_board(tracker, p, filter_string)
        if b is not None:
            out[p] = b
    return out


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
