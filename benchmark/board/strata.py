"""The windows' aggressiveness strata, and each run's cells on each of them: the results table's stratum rows.

A window's aggressiveness is the RMS commanded acceleration of a wheel contact point over it
(benchmark/scoring/aggressiveness.py): under ``state`` the window tables carry it, under the other
protocols it is computed here from the test splits' commands (the same measure). The strata are the
dataset's terciles at each horizon, pooled over its terrains and test splits, on one model's windows per
terrain (every model of a board scores the same windows). evaluate scores every run's cells on each stratum
(:func:`strata_records`, rows of ``stratum`` ``low``/``mid``/``high`` beside the ``all`` rows) with the
same metrics and intervals as its ``all`` cells; compare ranks each stratum with the board's rule
(benchmark/board/horizons.py) on the same strata (:func:`stratum_windows`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd

from skidbench.benchmark.evaluate.testsets import load_test_split
from skidbench.benchmark.scoring import aggressiveness as ag
from skidbench.benchmark.scoring.floor import FLOOR
from skidbench.benchmark.scoring.horizon import horizon_steps
from skidbench.benchmark.scoring.predictions import Score, score_cells
from skidbench.benchmark.scoring.settings import IntervalConfig
from skidbench.pipeline.core.io import read_parquet_metadata
from skidbench.pipeline.core.layout import Layout

Windows = dict[tuple[str, str], pd.DataFrame]  # (model, terrain) -> its windows at one horizon
#: (terrain, split) -> {sequence: (its times, its wheel contact points' commanded acceleration)}
Commands = dict[tuple[str, str], dict[str, tuple[np.ndarray, np.ndarray]]]


def add_aggressiveness(
    layout: Layout, windows: Windows, horizon_s: float, half_track: float, cache: Commands | None = None
) -> None:
    """Adds ``aggressiveness`` to every window table lacking it, from the test splits' commands (read into
    ``cache``, when given, for the next horizon's windows: they are the same at every horizon)."""
    cache = {} if cache is None else cache
    for (_model, terrain), w in windows.items():
        if "aggressiveness" in w:
            continue
        values = np.full(len(w), np.nan)
        for split in w["split"].unique():
            if (terrain, split) not in cache:
                cache[(terrain, split)] = {s.name: (s.table["t"].to_numpy(float),
                                                    ag.sample_acceleration(s.table, half_track))
                                           for s in load_test_split(layout, terrain, str(split))}  # fmt: skip
            for seq, (t, acc) in cache[(terrain, split)].items():
                rows = ((w["split"] == split) & (w["sequence"].astype(str) == seq)).to_numpy()
                if rows.any():
                    values[rows] = ag.window_aggressiveness(acc, w.loc[rows, "start"].to_numpy(int),
                                                            horizon_steps(t, horizon_s))  # fmt: skip
        w["aggressiveness"] = values


def stratum_windows(
    layout: Layout, windows: Windows, horizon_s: float, half_track: float, commands: Commands | None = None
) -> dict[str, Windows]:
    """``{stratum: windows}``: every window (``all``) and each tercile's, of the windows of one horizon
    (copies with ``aggressiveness``); a stratum no model's window falls in is left out. ``commands``: the
    test splits' commands read so far (:func:`add_aggressiveness`)."""
    windows = {k: w.copy() for k, w in windows.items()}
    add_aggressiveness(layout, windows, horizon_s, half_track, commands)
    first: dict[str, pd.DataFrame] = {}  # the dataset's terciles: each window once (one model per terrain)
    for (model, terrain), w in windows.items():
        if model != FLOOR:
            first.setdefault(terrain, w)
    edges = ag.tercile_edges([w["aggressiveness"].to_numpy(float) for w in first.values()])
    out = {ag.ALL: windows}
    for name in ag.STRATA:
        part = {}
        for key, w in windows.items():
            sel = ag.strata(w["aggressiveness"].to_numpy(float), edges) == name
            if sel.any():
                part[key] = w[sel]
        if any(m != FLOOR for m, _ in part):
            out[name] = part
    return out


def _run_windows(layout: Layout, runs: pd.DataFrame, protocol: str) -> dict[tuple[str, str], pd.DataFrame]:
    """The windows file of each FINISHED run (``runs``: model, terrain, run_id) that this run wrote."""
    out = {}
    for r in runs.itertuples(index=False):
        stem = layout.eval_stem(str(r.model), str(r.terrain), protocol)
        path = stem.with_name(stem.name + ".windows.parquet")
        try:
            w = pd.read_parquet(path)
            made_by = str(read_parquet_metadata(path).get("run_id") or "")
        except (OSError, ValueError):
            continue
        if len(w) and (not made_by or made_by == str(r.run_id)):
            out[(str(r.model), str(r.terrain))] = w
    return out


def strata_records(
    layout: Layout, records: Sequence[Mapping], protocol: str, horizons: Sequence[float],
    intervals: IntervalConfig, half_track: float,
) -> list[dict]:  # fmt: skip
    """The stratum rows of the FINISHED model runs among ``records`` (a results file's rows): each run's
    cells (every metric, split and horizon, with its interval) on each tercile, as its ``all`` rows are
    scored, the run's other columns copied from its ``all`` rows."""
    df = pd.DataFrame(list(records))
    if not len(df):
        return []
    own = df[(df["role"] == "model") & (df["status"] == "FINISHED") & (df["stratum"] == ag.ALL)]
    runs = own.drop_duplicates("run_id")[["model", "terrain", "run_id"]]
    files = _run_windows(layout, runs, protocol)
    template = {str(r["run_id"]): r for r in own.drop_duplicates("run_id").to_dict("records")}
    run_of = {(str(m), str(t)): str(r) for m, t, r in runs.itertuples(index=False)}
    out: list[dict] = []
    commands: Commands = {}
    for h in horizons:
        at = {k: w[np.isclose(w["horizon_s"].to_numpy(float), h)] for k, w in files.items()}
        by_stratum = stratum_windows(layout, {k: w for k, w in at.items() if len(w)}, h, half_track, commands)
        for name, part in by_stratum.items():
            if name == ag.ALL:
                continue
            for key, w in part.items():
                base = template[run_of[key]]
                for split in sorted(w["split"].unique()):
                    for s in score_cells(w[w["split"] == split], str(split), [h], intervals):
                        out.append(_row(base, s, name))
    return out


def _row(base: Mapping, s: Score, stratum: str) -> dict:
    return {**base, "horizon_s": float(s.horizon_s), "split": s.split, "metric": s.metric,
            "stratum": stratum, "estimate": float(s.estimate), "lo": float(s.lo), "hi": float(s.hi),
            "n_windows": int(s.n_windows), "n_blocks": s.n_blocks, "seed_sd": None, "seed_min": None,
            "seed_max": None}  # fmt: skip
