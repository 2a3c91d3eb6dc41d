"""The placebo check of discovery (issue 47; docs/discovery.md, "The placebo check"): the same search on the
terrain's pool with its commands moved in time (:func:`placebo_pool`), commands that did not drive this
motion. Nothing may be named.

When the base model cannot be fitted to the moved commands (``edd``'s least squares gives 1/chi <= 0 when
the moved turn commands happen to anti-correlate with the measured yaw rate, as on every shift tried on
the DRIVE Husky), the search still runs, from :class:`GainedBase`: the base model fitted on the recorded
commands of the same training rows (fold by fold: a fold's inner model never sees its held-out units),
each velocity channel's prediction times a gain of at least 0 fitted on the moved ones (for ``edd``, the
bounded version of its own least squares, 1/chi >= 0, plus a free forward gain).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pandas as pd

from skidbench.models.augmented.fit import DiscoverSettings, Pool
from skidbench.models.base import KinematicModel
from skidbench.models.columns import targets, training_rows
from skidbench.pipeline.core.errors import SkidbenchError

#: the command columns a placebo moves (everything a model or a candidate reads of the commands)
PLACEBO_COLUMNS = ("cmd_v", "cmd_w", "cmd_wl", "cmd_wr", "cmd_dwl", "cmd_dwr")


def placebo_pool(pool: Pool, shift_s: float) -> Pool:
    """The pool with every sequence's commands moved ``shift_s`` later in time, circularly (half the
    sequence when it is shorter than twice the shift), the motion and the held-out units kept: commands
    that did not drive this motion. What the search names on it comes from how the data and the search
    are made, not from the robot."""
    table = pool.table.copy()
    for g in range(len(pool.sequences)):
        rows = np.flatnonzero(pool.groups == g)
        if len(rows) < 2:
            continue
        dt = float(np.median(np.diff(pool.t[rows])))
        n = int(round(shift_s / max(dt, 1e-9)))
        n = n if 2 * n <= len(rows) else len(rows) // 2
        for c in PLACEBO_COLUMNS:
            if c in table.columns:
                table.loc[rows, c] = np.roll(table[c].to_numpy(float)[rows], n)
    return dataclasses.replace(pool, table=table, note=pool.note + f"; placebo: commands moved {shift_s:g} s")


class RecordedFits:
    """The base model fitted on the recorded commands of the rows a fit is given (by their index labels in
    ``pool.table``, which every sub-table of the pool keeps), cached per set of rows: :class:`GainedBase`'s
    inner model, so that a fold's inner model has seen that fold's training rows only, never its held-out
    units. ``fitted_on``: the labels of every fit made (the record the tests read)."""

    def __init__(self, recorded: pd.DataFrame, factory):
        self.recorded = recorded
        self.factory = factory
        self.fitted_on: list[pd.Index] = []
        self._cache: dict[bytes, KinematicModel] = {}

    def __call__(self, labels: pd.Index) -> KinematicModel:
        key = np.asarray(labels).tobytes()
        if key not in self._cache:
            if len(self._cache) > 64:
                self._cache.clear()
            self._cache[key] = self.factory().fit(self.recorded.loc[labels])
            self.fitted_on.append(labels)
        return self._cache[key]


class GainedBase(KinematicModel):
    """The placebo's base when the base model cannot be fitted to the moved commands: an inner model (the
    base model fitted on the recorded commands of the same training rows, :class:`RecordedFits`, with the
    measured motion) with its prediction of each velocity channel times a gain g >= 0, fitted by least
    squares through the origin on the training rows with the moved commands (g = 0 where the channel's
    prediction anti-correlates with the measurement: "these commands do not drive it"; 1 where the
    prediction is identically 0, as ``edd``'s vy). Fitted to anything, and able to shrink a prediction
    that moved commands make too large: a base held at the recorded fit (or the ideal model) would
    predict the moved commands' full turn rate and speed, and every candidate that damps a prediction (a
    long lag, a yaw factor) would gain on every unit for that reason alone."""

    name = "placebo_base"

    def __init__(self, recorded: RecordedFits):
        proto = recorded.factory()
        super().__init__(proto.robot)
        self.recorded = recorded
        self.inner: KinematicModel | None = None
        self.required_columns = proto.required_columns
        self.params = {"inner": None, "inner_params": None, "gains": [1.0, 1.0, 1.0]}

    def fit(self, table: pd.DataFrame) -> GainedBase:
        self.check_columns(table, fitting=True)
        train = training_rows(table)
        self.inner = self.recorded(train.index)
        p, y = self.inner.predict(train), targets(train)
        gains = []
        for c in range(3):
            den = float(p[:, c] @ p[:, c])
            gains.append(1.0 if den <= 1e-12 else max(0.0, float(p[:, c] @ y[:, c]) / den))
        self.params = {"inner": self.inner.name, "inner_params": self.inner.get_params(), "gains": gains}
        return self

    def predict(self, table: pd.DataFrame) -> np.ndarray:
        if self.inner is None:
            raise SkidbenchError("placebo_base: predict before fit")
        return self.inner.predict(table) * np.asarray(self.params["gains"], float)


def _search(moved: Pool, factory, robot, settings: DiscoverSettings, terrain: str, base_name: str, cands):
    """One step of the search after the speed scale, on the moved pool, command-free candidates out."""
    from skidbench.benchmark.discovery.discover import discover_terrain
    from skidbench.models.augmented import terms as termlib

    return discover_terrain(
        moved, factory, robot, dataclasses.replace(settings, max_effects=1, scale_spread=float("inf")),
        terrain, base_name, candidates=tuple(c for c in cands if c != "lateral_drift"),
        progress=lambda m: None, exclude_forms=tuple(termlib.command_free_forms()),
    )  # fmt: skip


def _last_step(res) -> tuple[int, dict[str, Any] | None]:
    """How many candidates the placebo's last step scored (its search-wide test's family), and the one
    closest to being named: the smallest ``p_search`` (then the largest penalised held-out gain)."""
    ev = (res.rejected or {}) if not res.steps else res.steps[-1]["evidence"]
    rows = {**(ev.get("candidates") or {}), **(ev.get("terms") or {})}
    if not rows:
        return 0, None
    name = min(rows, key=lambda k: (rows[k].get("p_search", 1.0), -rows[k].get("penalised_gain", 0.0)))
    r = rows[name]
    return len(rows), {"name": name, "penalised_gain": r.get("penalised_gain"), "p_search": r.get("p_search")}


def placebo(pool: Pool, factory, robot, settings: DiscoverSettings, terrain: str, base_name: str, cands,
            shift_s: float) -> dict[str, Any]:  # fmt: skip
    """The placebo check: the search (:func:`_search`) on the pool with its commands moved ``shift_s``
    (:func:`placebo_pool`), one step after the speed scale; nothing may be named. Command-free candidates
    (``lateral_drift``, the library's constant and time forms) are left out: moving the commands leaves
    them what they are. The speed scale is taken when it passes the rule, whatever its spread over speeds
    (``scale_spread`` off): moved commands relate to the motion by their overall level only, which is
    neither a radius nor a drive's effect. When the base model cannot be fitted to the moved commands,
    the search runs from :class:`GainedBase` (``fallback`` says why); ``searched`` is False only when
    even that fails, and then ``passed`` is None: the check could not be made."""
    moved = placebo_pool(pool, shift_s)
    head = f"placebo (commands moved {shift_s:g} s"
    fallback = None
    try:
        res, base = _search(moved, factory, robot, settings, terrain, base_name, cands), base_name
    except SkidbenchError as exc:  # the base model cannot be fitted to commands that did not drive it
        fallback = f"the base model cannot be fitted to them: {exc}"
        try:
            recorded = RecordedFits(pool.table, factory)  # each fit's rows with their recorded commands
            res = _search(moved, lambda: GainedBase(recorded), robot, settings, terrain, base_name, cands)
        except SkidbenchError as exc2:
            return {"shift_s": shift_s, "named": [], "passed": None, "searched": False, "fallback": fallback,
                    "text": f"{head}): NOT RUN ({fallback}; nor from the base fitted on the recorded "
                    f"commands with channel gains: {exc2})"}  # fmt: skip
        base = f"{base_name} fitted on the recorded commands of each fit's rows, channel gains >= 0 fitted"
        head += f"; {fallback}, so from {base}"
    named = res.effects + res.terms
    tested, best = _last_step(res)
    closest = "" if best is None else f" (closest: {best['name']}, p_search {best['p_search']:.2g})"
    return {
        "shift_s": shift_s,
        "named": named,
        "passed": not named,
        "searched": True,
        "base": base,
        "fallback": fallback,
        "n_candidates": tested,
        "best": best,
        "calibration": (res.calibration or {}).get("text"),
        "text": f"{head}): {tested} candidates searched, "
        + (
            "nothing named" + closest
            if not named
            else f"NAMED {', '.join(named)}: what this data names is suspect"
        ),
    }
