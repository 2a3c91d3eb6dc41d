"""Discovery's pool of training data (:mod:`skidbench.benchmark.discovery.discover`): a terrain's Train
sequences
and nothing else (the test splits are never read), a refusal when they are too few for the test, and the
inputs as the search sees them (the commands aligned with the split's grid, or the input protocol's)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from skidbench.models.augmented.fit import DiscoverError, DiscoverSettings, Pool, build_pool
from skidbench.pipeline.core.protocol import fit_table
from skidbench.pipeline.core.robot import Robot
from skidbench.pipeline.core.schema import load_split_tables as _load_split_tables
from skidbench.pipeline.core.schema import read_split


def load_pool(
    splits_root: Path,
    terrain: str,
    settings: DiscoverSettings,
    files_of: Callable[[str, str], list[Path]] | None = None,
) -> Pool:
    """The held-out pool of a terrain: its ``settings.splits`` sequences (default Train) and nothing else;
    when they are fewer than ``min_units``, cut into time blocks (:func:`build_pool`). Discovery selects
    and fits on these only: the test splits (CV, LD) are never read, so that the ``discovered`` model's
    score there is a held-out one. ``files_of(terrain, split)``: the split files to read (the current
    manifest's); default every file under ``splits_root``."""

    def load_split_tables(root: Path, terrain: str, split: str) -> list[tuple[pd.DataFrame, dict]]:
        if files_of is None:
            return _load_split_tables(root, terrain, split)
        return [read_split(p) for p in files_of(terrain, split)]

    tables = []
    for s in settings.splits:
        tables += load_split_tables(Path(splits_root), terrain, s)
    if not tables:
        raise DiscoverError(f"{splits_root}/{terrain}: no split files for {'/'.join(settings.splits)}")
    pool = build_pool(tables, settings)
    pool.note = f"selected on {'/'.join(settings.splits)} only: " + pool.describe()
    return pool


def too_small(pool: Pool, settings: DiscoverSettings) -> str | None:
    """Why the pool cannot support a discovery (None when it can): fewer held-out units than the
    sign-flip test needs to reject at ``alpha`` (2^-n > alpha), or no unit with a full horizon window."""
    need = max(2, int(np.ceil(np.log2(1.0 / settings.alpha))))
    if pool.n_units < need:
        return (
            f"{pool.describe()}: {pool.n_units} held-out unit(s) of at least {settings.horizon_s:g} s, and "
            f"a sign-flip test over n units cannot reach alpha = {settings.alpha:g} with n < {need}; "
            f"record at least {need * settings.horizon_s:g} s of {'/'.join(settings.splits)} driving"
        )
    return None


def align_commands(pool: Pool, robot: Robot) -> Pool:
    """The pool with each sequence's commands shifted by the timing error of their association with the
    grid (``cmd_association.offset_s`` of its split metadata, :mod:`skidbench.pipeline.splits.build`):
    the wheel commands read at ``t + offset`` (linear interpolation between grid samples, the ends held),
    ``cmd_v``/``cmd_w`` recomputed from them with the robot's ideal kinematics (as the split does) and
    their derivatives taken as the split takes them. Without it a commensurate command rate (45 Hz on the
    30 Hz grid) shows as a lag or a lead of up to a quarter command period, which the search would name
    (``lin.dw*|v|.wz`` for a lead: the catalogue's slips only take a lag). Sequences without the record
    are left as they are, and ``pool.note`` names them; ``pool.alignment`` lists what was applied."""
    table = pool.table.copy()
    applied, unrecorded = {}, []
    for g, meta in enumerate(pool.metas):
        rec = (meta or {}).get("cmd_association")
        if not rec:
            unrecorded.append(pool.sequences[g])
        off = float((rec or {}).get("offset_s") or 0.0)
        if off == 0.0:
            continue
        rows = np.flatnonzero(pool.groups == g)
        t = pool.t[rows]
        wl = np.interp(t + off, t, table["cmd_wl"].to_numpy(float)[rows])
        wr = np.interp(t + off, t, table["cmd_wr"].to_numpy(float)[rows])
        v, w = robot.twist_from_wheel_rates(wl, wr)  # (linear: the same as shifting cmd_v, cmd_w)
        cols = {"cmd_v": v, "cmd_w": w, "cmd_wl": wl, "cmd_wr": wr}
        if len(t) >= 2:
            cols |= {"cmd_dwl": np.gradient(wl, t), "cmd_dwr": np.gradient(wr, t)}
        for c, x in cols.items():
            table.loc[rows, c] = x
        applied[pool.sequences[g]] = off
    note = pool.note
    if unrecorded:  # split files written before the split recorded it
        note += (
            f"; commands not aligned with the grid in {len(unrecorded)} sequence(s) whose split file has "
            f"no cmd_association record (e.g. {unrecorded[0]}; `skidbench split` writes it)"
        )
    return dataclasses.replace(pool, table=table, alignment=applied, note=note)


def apply_protocol(pool: Pool, protocol: str, robot: Robot, response: Any = None) -> Pool:
    """The pool with its inputs replaced by those of the input protocol (pipeline/core/protocol.py), computed
    per original sequence (``pool.groups``), targets and held-out units kept: discovery then searches
    what the base model misses given the protocol's inputs (under ``response`` the wheel response is
    given, so ``actuator_lag`` has nothing left to explain)."""
    table = fit_table(pool.table.assign(sequence=pool.groups), protocol, robot, response)
    table["sequence"] = pool.units
    return dataclasses.replace(pool, table=table)


def prepare_pool(pool: Pool, inputs: str, robot: Robot, response: Any = None) -> Pool:
    """The pool as the search sees it under the input protocol ``inputs``: the commands aligned with
    the grid (:func:`align_commands`) under ``commanded``; the protocol's inputs otherwise
    (:func:`apply_protocol`: the calibrated wheel response already holds the association's timing, the
    encoders have none)."""
    if inputs == "commanded":
        return align_commands(pool, robot)
    return apply_protocol(pool, inputs, robot, response)


def selected_on(pool: Pool, settings: DiscoverSettings) -> dict[str, Any]:
    """What a discovery selected and fitted on: the splits, their sequences, the held-out units."""
    return {
        "splits": list(settings.splits),
        "sequences": list(pool.sequences),
        "n_units": pool.n_units,
        "units": "time blocks" if pool.blocks else "sequences",
        "text": f"{'/'.join(settings.splits)} only: {pool.describe()}",
    }
