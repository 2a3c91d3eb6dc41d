"""A predictions file (``skidbench score``'s input, benchmark/release/score.py): read, its columns checked,
and each test sequence's rows aligned with its split, every problem one line naming the file and the
sequence (a test sequence without rows, a sequence the splits do not have, a missing column, a NaN or
infinite value, a row count or times that differ from the split's: a shifted clock is named as such)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from skidbench.benchmark.scoring.predictions import TestSequence
from skidbench.pipeline.core.errors import SkidbenchError, one_line

PRED_COLUMNS = ("sequence", "t", "vx", "vy", "wz")
COV_COLUMNS = ("cov_vx_vx", "cov_vx_vy", "cov_vx_wz", "cov_vy_vy", "cov_vy_wz", "cov_wz_wz")
#: |t - t_split| allowed (s): a clock written with 6 decimals still matches; a one-sample shift does not
T_TOL = 1e-6


class PredictionsError(SkidbenchError):
    """A predictions file that cannot be scored (format, columns, rows, values, times)."""


# -- reading and checking the file --------------------------------------------------------------------
def read_predictions(path: Path) -> pd.DataFrame:
    """The predictions table of a ``.parquet`` or ``.csv`` (``.csv.gz``) file, columns checked."""
    path = Path(path)
    if not path.is_file():
        raise PredictionsError(f"{path}: no such file")
    name = path.name.lower()
    try:
        if name.endswith((".parquet", ".pq")):
            df = pd.read_parquet(path)
        elif name.endswith((".csv", ".csv.gz")):
            df = pd.read_csv(path)
        else:
            raise PredictionsError(f"{path}: not a .parquet or .csv file")
    except PredictionsError:
        raise
    except Exception as exc:  # pyarrow / the CSV parser: the file is not what it says
        raise PredictionsError(
            f"{path}: unreadable ({type(exc).__name__}: {one_line(str(exc))[:200]})"
        ) from None
    missing = [c for c in PRED_COLUMNS if c not in df.columns]
    if missing:
        raise PredictionsError(
            f"{path}: missing column(s) {missing}; a predictions file has {', '.join(PRED_COLUMNS)} "
            f"(and optionally {', '.join(COV_COLUMNS)})"
        )
    cov = [c for c in COV_COLUMNS if c in df.columns]
    if cov and len(cov) != len(COV_COLUMNS):
        raise PredictionsError(
            f"{path}: covariance column(s) {sorted(set(COV_COLUMNS) - set(cov))} missing; give all six "
            f"({', '.join(COV_COLUMNS)}) or none"
        )
    for c in ("t", "vx", "vy", "wz", *cov):
        if not pd.api.types.is_numeric_dtype(df[c]):
            raise PredictionsError(f"{path}: column {c} is not numeric (first value {df[c].iloc[0]!r})")
    df = df.assign(sequence=df["sequence"].astype(str))
    return df


def _clock(t: np.ndarray) -> str:
    if len(t) < 2:
        return f"t {t[0]:.4g} s" if len(t) else "no rows"
    return f"t from {t[0]:.4g} to {t[-1]:.4g} s every {np.median(np.diff(t)):.4g} s"


def check_sequence(path: Path, seq: TestSequence, rows: pd.DataFrame) -> tuple[np.ndarray, np.ndarray | None]:
    """(T, 3) velocities (and (T, 3, 3) covariances or None) of one test sequence's rows, aligned with its
    split; PredictionsError (one line) for a row count, a clock or a value that is not the split's."""
    rows = rows.sort_values("t", kind="stable")
    t = rows["t"].to_numpy(float)
    want = seq.table["t"].to_numpy(float)
    where = f"{path}: sequence {seq.name}"
    if len(t) != len(want):
        raise PredictionsError(
            f"{where}: {len(t)} rows, its split has {len(want)} ({_clock(want)}); one prediction per input "
            "row"
        )
    if not np.all(np.isfinite(t)):
        raise PredictionsError(f"{where}: {int(np.sum(~np.isfinite(t)))} non-finite value(s) in t")
    diff = t - want
    if np.any(np.abs(diff) > T_TOL):
        k = int(np.argmax(np.abs(diff) > T_TOL))
        shift = float(np.median(diff))
        if np.allclose(diff, shift, atol=T_TOL):
            raise PredictionsError(
                f"{where}: times shifted by {shift:+.6g} s against its split (first row t={t[0]:.6g} s, the "
                f"split's {want[0]:.6g} s); predict at the input table's own times"
            )
        raise PredictionsError(
            f"{where}: row {k} has t={t[k]:.6g} s, its split {want[k]:.6g} s ({_clock(want)}); predict at "
            "the input table's own times"
        )
    vel = rows[["vx", "vy", "wz"]].to_numpy(float)
    cov = None
    cols = ["vx", "vy", "wz"]
    if COV_COLUMNS[0] in rows:
        cols += list(COV_COLUMNS)
    values = rows[cols].to_numpy(float)
    bad = ~np.isfinite(values)
    if bad.any():
        j = int(np.argmax(bad.any(axis=0)))
        i = int(np.argmax(bad[:, j]))
        raise PredictionsError(
            f"{where}: {int(bad[:, j].sum())} NaN or infinite value(s) in {cols[j]} (first at t={t[i]:.6g} s)"
        )
    if COV_COLUMNS[0] in rows:
        c = rows[list(COV_COLUMNS)].to_numpy(float)
        cov = np.empty((len(c), 3, 3))
        idx = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
        for j, (a, b) in enumerate(idx):
            cov[:, a, b] = cov[:, b, a] = c[:, j]
        neg = np.flatnonzero((c[:, [0, 3, 5]] < 0).any(axis=1))
        if len(neg):
            raise PredictionsError(f"{where}: a negative variance at t={t[neg[0]]:.6g} s")
    return vel, cov


def align(
    path: Path, preds: pd.DataFrame, tests: dict[str, dict[str, list[TestSequence]]]
) -> dict[str, dict[str, tuple[list[np.ndarray], list[np.ndarray] | None]]]:
    """Per terrain and test split: the per-sequence velocities (and covariances) of the file, in the
    splits' order; PredictionsError for a missing or an unknown sequence or a bad sequence's rows."""
    groups = {str(k): g for k, g in preds.groupby("sequence", sort=False)}
    wanted = {
        s.name: (terrain, split) for terrain, sp in tests.items() for split, seqs in sp.items() for s in seqs
    }
    unknown = [s for s in groups if s not in wanted]
    if unknown:
        raise PredictionsError(
            f"{path}: sequence {unknown[0]!r} is not a test sequence of this dataset"
            f"{f' (and {len(unknown) - 1} more)' if len(unknown) > 1 else ''}; its test sequences: "
            f"{', '.join(sorted(wanted)[:8])}{' ...' if len(wanted) > 8 else ''}"
        )
    out: dict[str, dict[str, tuple[list[np.ndarray], list[np.ndarray] | None]]] = {}
    for terrain, sp in tests.items():
        for split, seqs in sp.items():
            vels, covs = [], []
            for s in seqs:
                if s.name not in groups:
                    raise PredictionsError(
                        f"{path}: no rows for sequence {s.name} ({terrain} {split.upper()}); every "
                        f"{split.upper()} "
                        f"sequence of the protocol needs its predictions"
                    )
                v, c = check_sequence(path, s, groups[s.name])
                vels.append(v)
                covs.append(c)
            has_cov = all(c is not None for c in covs)
            out.setdefault(terrain, {})[split] = (vels, covs if has_cov else None)
    return out
