"""What every raw (non-bag) source shares: writing one sequence's extracted-table folder atomically.

Tables follow CONTRIBUTING.md "Extracted tables": ``stamp_ns`` and ``bag_time_ns`` (int64; equal for raw
sources, which have a single clock), then ``cmd_vel`` (Twist columns), ``cmd_wheels`` / ``enc_wheels``
(``wl wr``, rad/s) or ``gt_pose`` (``x y yaw`` [+ ``z qx qy qz qw``]). Every table is written with an
atomic rename; ``_extract.json`` is written last, so a folder without it is incomplete.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa

from skidbench.pipeline.core.cache import Stamp, stamp_file
from skidbench.pipeline.core.io import fingerprint_file, write_json_atomic, write_parquet_atomic

EXTRACT_INFO = "_extract.json"
TWIST_COLUMNS = ("linear_x", "linear_y", "linear_z", "angular_x", "angular_y", "angular_z")


def stamped(stamp_ns: np.ndarray, **columns: np.ndarray) -> pd.DataFrame:
    """A table with ``stamp_ns``/``bag_time_ns`` from one clock and float64 columns."""
    stamp_ns = np.asarray(stamp_ns, dtype=np.int64)
    data = {"stamp_ns": stamp_ns, "bag_time_ns": stamp_ns.copy()}
    data.update({k: np.asarray(v, dtype=float) for k, v in columns.items()})
    return pd.DataFrame(data)


def write_sequence(out_dir: Path, tables: dict[str, pd.DataFrame], sources: list[Path], info: dict) -> dict:
    """Write ``<out_dir>/<key>.parquet`` for every table, then ``_extract.json`` (returned)."""
    out_dir = Path(out_dir)
    for key, df in tables.items():
        write_parquet_atomic(pa.Table.from_pandas(df, preserve_index=False), out_dir / f"{key}.parquet")
    for stale in out_dir.glob("*.parquet"):  # a table this run did not write must not linger
        if stale.stem not in tables and not stale.name.startswith("."):
            stale.unlink()
    record: dict[str, Any] = {
        **info,
        "tables": {k: int(len(v)) for k, v in tables.items()},
        "sources": {str(p): fingerprint_file(p) for p in sources},
    }
    write_json_atomic(out_dir / EXTRACT_INFO, record)
    return record


def category_by_rank(keys: list, fractions: tuple[float, float, float]) -> dict:
    """Deterministic contiguous assignment of ordered ``keys`` to train/cv/ld by ``fractions`` (sums to 1)."""
    n = len(keys)
    n_train = int(round(fractions[0] * n))
    n_cv = int(round(fractions[1] * n))
    if n >= 3:  # every split gets at least one key
        n_train = min(max(n_train, 1), n - 2)
        n_cv = min(max(n_cv, 1), n - n_train - 1)
    out = {}
    for i, k in enumerate(keys):
        out[k] = "train" if i < n_train else "cv" if i < n_train + n_cv else "ld"
    return out


def source_stamp(layout, unit: str, inputs: list[Path], config: Any) -> tuple[Stamp, str, list[dict] | None]:
    """The stamp of one raw-source unit (a file or a sequence): ``(stamp, key, records)`` where
    ``records`` (the ``_extract.json`` records) is not None when the unit is up to date."""
    stamp = Stamp(stamp_file(layout.root, "extract", f"{unit}.json"), "extract")
    key = stamp.key(inputs, config)
    if stamp.is_fresh(key):
        try:
            return stamp, key, [json.loads(Path(p).read_text()) for p in stamp.data["info"]["records"]]
        except (OSError, KeyError, ValueError):
            pass
    return stamp, key, None


def record_stamp(stamp: Stamp, key: str, out_dirs: list[Path], extra: list[Path] = ()) -> None:
    """Record a raw-source unit: every file of its sequence folders (and ``extra``) is an output."""
    outs = [
        p for d in out_dirs for p in sorted(Path(d).iterdir()) if p.is_file() and not p.name.startswith(".")
    ]
    infos = [str(Path(d) / EXTRACT_INFO) for d in out_dirs]
    stamp.record(key, [*outs, *extra], {"records": infos})
