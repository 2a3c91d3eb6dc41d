"""The split table: the contract between the pipeline and every model and metric (SPEC.md "splits").

One Parquet file per sequence at ``splits/<terrain>/<split>/<sequence>.parquet`` on a uniform clock.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa

from skidbench.pipeline.core.errors import SplitError
from skidbench.pipeline.core.io import read_parquet_metadata, write_parquet_atomic

SCHEMA_VERSION = 1

# name -> (dtype, nullable, meaning)
SPLIT_COLUMNS: dict[str, tuple[str, bool, str]] = {
    "t": ("float64", False, "s from sequence start"),
    "stamp_ns": ("int64", False, "absolute time, ns"),
    "cmd_v": ("float64", False, "commanded linear velocity, m/s"),
    "cmd_w": ("float64", False, "commanded angular velocity, rad/s"),
    "cmd_wl": ("float64", False, "commanded left wheel angular velocity, rad/s"),
    "cmd_wr": ("float64", False, "commanded right wheel angular velocity, rad/s"),
    "cmd_dwl": ("float64", False, "d/dt cmd_wl, rad/s^2"),
    "cmd_dwr": ("float64", False, "d/dt cmd_wr, rad/s^2"),
    "enc_wl": ("float64", True, "measured left wheel angular velocity, rad/s (null when absent)"),
    "enc_wr": ("float64", True, "measured right wheel angular velocity, rad/s (null when absent)"),
    "x": ("float64", False, "ground-truth x, m"),
    "y": ("float64", False, "ground-truth y, m"),
    "yaw": ("float64", False, "ground-truth yaw, rad, unwrapped"),
    "vx": ("float64", False, "ground-truth body longitudinal velocity, m/s"),
    "vy": ("float64", False, "ground-truth body lateral velocity, m/s"),
    "wz": ("float64", False, "ground-truth yaw rate, rad/s"),
    "valid": ("bool", False, "ground truth present and trusted"),
}

SPLIT_METADATA_KEYS = ("schema_version", "sequence", "terrain", "split", "robot", "sources", "rate_hz")


def split_arrow_schema() -> pa.Schema:
    types = {"float64": pa.float64(), "int64": pa.int64(), "bool": pa.bool_()}
    return pa.schema([pa.field(n, types[d], nullable=nb) for n, (d, nb, _) in SPLIT_COLUMNS.items()])


def validate_split_frame(df: pd.DataFrame, where: str) -> None:
    """Raise SplitError if a column is missing or a non-nullable column holds NaN where valid."""
    missing = [c for c in SPLIT_COLUMNS if c not in df.columns]
    if missing:
        raise SplitError(f"{where}: missing split columns {missing}")
    if len(df) and not np.all(np.diff(df["t"].to_numpy()) > 0):
        raise SplitError(f"{where}: time column t is not strictly increasing")


def write_split(df: pd.DataFrame, path: Path, metadata: dict[str, Any]) -> None:
    validate_split_frame(df, str(path))
    meta = {"schema_version": SCHEMA_VERSION, **metadata}
    absent = [k for k in SPLIT_METADATA_KEYS if k not in meta]
    if absent:
        raise SplitError(f"{path}: split metadata lacks {absent}")
    extra = [c for c in df.columns if c not in SPLIT_COLUMNS]
    table = pa.Table.from_pandas(df[list(SPLIT_COLUMNS) + extra], preserve_index=False)
    write_parquet_atomic(table, path, meta)


def read_split(path: Path) -> tuple[pd.DataFrame, dict[str, Any]]:
    """Read one split file: (table, metadata)."""
    import pyarrow.parquet as pq

    path = Path(path)
    try:
        table = pq.read_table(path)
    except (OSError, pa.ArrowInvalid) as exc:
        raise SplitError(f"{path}: unreadable split file ({exc})") from exc
    df = table.to_pandas()
    validate_split_frame(df, str(path))
    return df, read_parquet_metadata(path)


def list_split_files(splits_root: Path, terrain: str | None = None, split: str | None = None) -> list[Path]:
    """Split files under ``splits_root`` (sorted), optionally for one terrain and/or split."""
    t = terrain or "*"
    s = split or "*"
    return sorted(p for p in Path(splits_root).glob(f"{t}/{s}/*.parquet") if not p.name.startswith("."))


def load_split_tables(splits_root: Path, terrain: str, split: str) -> list[tuple[pd.DataFrame, dict]]:
    files = list_split_files(splits_root, terrain, split)
    return [read_split(p) for p in files]


def concat_sequences(tables: list[tuple[pd.DataFrame, dict]] | list[pd.DataFrame]) -> pd.DataFrame:
    """Concatenate split tables of several sequences, adding a ``sequence`` column (int codes kept
    stable by order) so that models and metrics never integrate or differentiate across a boundary."""
    frames = []
    for i, item in enumerate(tables):
        df, meta = item if isinstance(item, tuple) else (item, {})
        df = df.copy()
        df["sequence"] = meta.get("sequence", str(i))
        frames.append(df)
    if not frames:
        raise SplitError("no sequences to concatenate")
    return pd.concat(frames, ignore_index=True)
