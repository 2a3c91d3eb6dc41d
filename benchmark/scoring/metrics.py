"""The benchmark's metrics, each defined once: the one place a metric is added.

A :class:`Metric` says what it is (name, short name, unit), how it is computed from the window table of
:func:`~skidbench.benchmark.scoring.horizon.window_errors` (a column and an aggregate over the windows of one
test
split and horizon), how it is aggregated over terrains (the leaderboard's mean), its MLflow name
(``key``, e.g. ``ld_6s_trans_rmsre_pct``) and how compare shows it (column label, figure). Evaluate's
:func:`~skidbench.benchmark.scoring.predictions.summarise`, the MLflow metric names (:func:`metric_key`),
compare's
tables, figures and saved views, and evaluate's console summary all iterate :data:`METRICS`.

Adding a metric: append one :class:`Metric` to :data:`METRICS` (a new window column, if it needs one, goes
to ``horizon.window_errors``) and test its value against a closed form. Pure: no MLflow, no files.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from skidbench.benchmark.errors import EvaluationError
from skidbench.benchmark.scoring.horizon import CHI2_95_1DOF, CHI2_95_2DOF, rmsre


def rmsre_pct(values: np.ndarray) -> float:
    """RMSRE (:func:`~skidbench.benchmark.scoring.horizon.rmsre`, NaN windows left out) in %, to 0.001 % so
    that
    the MLflow UI's columns read as numbers."""
    return round(100.0 * rmsre(values), 3)


def rms_m(values: np.ndarray) -> float:
    """Root mean square over the finite windows, to 0.1 mm (NaN when there is none)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    return round(float(np.sqrt(np.mean(v**2))), 4) if v.size else float("nan")


def mean_finite(values: np.ndarray) -> float:
    """Mean over the finite values (the leaderboard's mean over terrains); NaN when there is none."""
    v = np.asarray(values, dtype=float)
    return float(np.nanmean(v)) if np.isfinite(v).any() else float("nan")


class Bootstrap(NamedTuple):
    """How a metric is a ratio of sums over windows, for its block-bootstrap interval
    (:mod:`skidbench.benchmark.scoring.intervals`): the ``aggregation`` (``rms`` or ``mean``) of
    ``values(column)``
    per window (None: the column itself; NaN windows left out), times ``scale`` (the logged unit)."""

    aggregation: str
    scale: float = 1.0
    values: Callable[[np.ndarray], np.ndarray] | None = None


def _within(bound: float) -> Callable[[np.ndarray], np.ndarray]:
    """Per window: 1.0 when the value is within ``bound`` (a coverage indicator), NaN kept."""
    return lambda v: np.where(np.isfinite(v), (v <= bound).astype(float), np.nan)


class Figure(NamedTuple):
    """Compare's bar chart of a metric per model, terrain and test split."""

    file: str  # in <ds>/reports/
    caption: str
    axis: str  # the value axis' label
    title: str  # before ", <h> s horizon"
    digits: int = 1  # of the value written on each bar


ALL_WINDOWS = "every window with a full horizon of valid samples"


@dataclass(frozen=True)
class Metric:
    """One metric of a test split at a horizon.

    name: the metric's id (``translational``); short: its short name in keys, column labels and
    ``rank_by`` (``trans``); unit: the unit of the logged value; key: its MLflow name, a template of
    ``{split}``, ``{h}`` (the horizon, ``:g``) and ``{short}``; column: the window-table column it is
    computed from; aggregate: the windows' column values -> the logged value; count_key: the template of
    the logged number of windows behind it (finite values of ``column``), or None; over_terrains: the
    leaderboard's aggregate over terrains; windows: which windows enter (for a warning when none does);
    label, label_unit, scale: compare's column label (``"trans CV %"``) and the factor from the logged
    value to the shown one; optional: logged only when the window table has ``column`` (models with a
    predictive covariance), blank in the tables otherwise; headline: ranked, printed by evaluate, in the
    UI's saved views and the protocol comparison (lower is better); paper: a metric of the paper
    (Rabiee & Biswas 2019, Figs. 3/4), whose claim compare checks; figure: compare's bar chart of it per
    model, terrain and test split (:class:`Figure`), or None; bootstrap: how its confidence interval is
    resampled (:class:`Bootstrap`), or None for a metric without one."""

    name: str
    short: str
    unit: str
    key: str
    column: str
    aggregate: Callable[[np.ndarray], float]
    description: str
    count_key: str | None = None
    over_terrains: Callable[[np.ndarray], float] = mean_finite
    windows: str = ALL_WINDOWS
    label: str = ""
    label_unit: str = ""
    scale: float = 1.0
    optional: bool = False
    headline: bool = False
    paper: bool = False
    figure: Figure | None = None
    bootstrap: Bootstrap | None = None

    def metric_key(self, split: str, horizon_s: float) -> str:
        return self.key.format(split=split, h=f"{horizon_s:g}", short=self.short)

    def windows_key(self, split: str, horizon_s: float) -> str | None:
        if self.count_key is None:
            return None
        return self.count_key.format(split=split, h=f"{horizon_s:g}", short=self.short)

    def interval_keys(self, split: str, horizon_s: float) -> tuple[str, str, str]:
        """The MLflow names of its 95 % interval and of the independent blocks behind it:
        ``(<key>_ci_lo, <key>_ci_hi, <split>_<h>s_<short>_blocks)``."""
        key = self.metric_key(split, horizon_s)
        return f"{key}_ci_lo", f"{key}_ci_hi", f"{split}_{horizon_s:g}s_{self.short}_blocks"

    def window_values(self, windows) -> np.ndarray:
        """The per-window values its interval resamples (:attr:`bootstrap`), in the logged unit's base."""
        vals = windows[self.column].to_numpy(float)
        return self.bootstrap.values(vals) if self.bootstrap and self.bootstrap.values else vals

    def column_label(self, split: str) -> str:
        """Compare's column of the metric on ``split``: ``"trans CV %"``."""
        return " ".join(x for x in (self.label or self.short, split.upper(), self.label_unit) if x)

    def count_label(self, split: str) -> str:
        return f"{self.label or self.short} {split.upper()} n"

    def pattern(self) -> str:
        """Its key as a readable pattern (``<split>_<horizon>_trans_rmsre_pct``), for descriptions."""
        return self.key.format(split="<split>", h="<h>", short=self.short)

    def summarise(self, windows, split: str, horizon_s: float) -> dict[str, float]:
        """The logged value (and window count) of this metric from the windows of one split and horizon;
        {} for an optional metric the window table has no column for."""
        has = len(windows) and self.column in windows
        if self.optional and not has:
            return {}
        vals = windows[self.column].to_numpy(float) if has else np.array([])
        out = {self.metric_key(split, horizon_s): self.aggregate(vals)}
        if self.count_key is not None:
            out[self.windows_key(split, horizon_s)] = float(np.isfinite(vals).sum())
        return out


TRANS_WINDOWS = "windows that travel at least min_distance_m"
ROT_WINDOWS = "windows that turn at least min_rotation_deg"

#: every metric of the benchmark, in the order tables and logs show them
METRICS: tuple[Metric, ...] = (
    Metric("translational", "trans", "%", "{split}_{h}s_{short}_rmsre_pct", "rel_trans", rmsre_pct,
           "RMSRE of the relative translational error (end-position error / distance travelled), in %",
           count_key="{split}_{h}s_{short}_windows", windows=TRANS_WINDOWS, label_unit="%", headline=True,
           paper=True, figure=Figure("fig3_translational_rmsre.png",
                               "Fig. 3: translational RMSRE per model, terrain and test split",
                               "translational RMSRE (%)", "Translational prediction error", 1),
           bootstrap=Bootstrap("rms", 100.0)),
    Metric("rotational", "rot", "%", "{split}_{h}s_{short}_rmsre_pct", "rel_rot", rmsre_pct,
           "RMSRE of the relative rotational error (|yaw error| / absolute rotation), in %",
           count_key="{split}_{h}s_{short}_windows", windows=ROT_WINDOWS, label_unit="%", headline=True,
           paper=True, figure=Figure("fig4_rotational_rmsre.png",
                               "Fig. 4: rotational RMSRE per model, terrain and test split",
                               "rotational RMSRE (%)", "Rotational prediction error", 1),
           bootstrap=Bootstrap("rms", 100.0)),
    Metric("end_position", "endpos", "m", "{split}_{h}s_{short}_rmse_m", "trans_err", rms_m,
           "RMS over windows of the absolute end-position error (|true - predicted end position| after the "
           "horizon, every window from the true start pose), in m",
           count_key="{split}_{h}s_{short}_windows", label_unit="m", headline=True,
           figure=Figure("fig_end_position_rmse.png",
                   "End-position RMSE (m) per model, terrain and test split",
                   "end-position RMSE (m)", "Absolute end-position error", 2),
           bootstrap=Bootstrap("rms")),
    Metric("coverage95_position", "cov95pos", "fraction", "coverage95_position_{split}_{h}s", "pos_d2",
           lambda v: float(np.mean(v <= CHI2_95_2DOF)),
           "fraction of windows whose true end position lies in the predicted 95 % ellipse",
           label="cov95 pos", label_unit="%", scale=100.0, optional=True,
           bootstrap=Bootstrap("mean", values=_within(CHI2_95_2DOF))),
    Metric("coverage95_yaw", "cov95yaw", "fraction", "coverage95_yaw_{split}_{h}s", "yaw_z2",
           lambda v: float(np.mean(v <= CHI2_95_1DOF)),
           "fraction of windows whose true end yaw lies in the predicted 95 % interval",
           label="cov95 yaw", label_unit="%", scale=100.0, optional=True,
           bootstrap=Bootstrap("mean", values=_within(CHI2_95_1DOF))),
    Metric("nll_position", "nllpos", "nats", "nll_position_{split}_{h}s", "nll_pos",
           lambda v: float(np.mean(v)),
           "mean Gaussian negative log-likelihood of the true end position, in nats",
           label="NLL pos", optional=True, bootstrap=Bootstrap("mean")),
)  # fmt: skip

BY_NAME = {m.name: m for m in METRICS}
BY_SHORT = {m.short: m for m in METRICS}
HEADLINE = tuple(m for m in METRICS if m.headline)
PAPER = tuple(m for m in METRICS if m.paper)


def get(name: str) -> Metric:
    """The metric named ``name`` (``translational``) or with that short name (``trans``)."""
    m = BY_NAME.get(name) or BY_SHORT.get(name)
    if m is None:
        raise EvaluationError(f"unknown metric {name!r}; known: {', '.join(BY_NAME)}")
    return m


def metric_key(kind: str, split: str, horizon_s: float) -> str:
    """``ld_6s_trans_rmsre_pct``: the MLflow name of metric ``kind`` (``translational``, ...) on a test split
    at a horizon; the names evaluate logs and compare, the leaderboard and the UI's columns read."""
    return get(kind).metric_key(split, horizon_s)


def windows_key(kind: str, split: str, horizon_s: float) -> str:
    """``ld_6s_trans_windows``: how many windows the metric :func:`metric_key` names is over."""
    key = get(kind).windows_key(split, horizon_s)
    if key is None:
        raise EvaluationError(f"metric {kind!r} logs no window count")
    return key


def rank_key(rank_by: str, horizon_s: float) -> str:
    """The metric of ``rank_by`` = ``<split>_<short>`` (e.g. ``ld_trans``) at ``horizon_s``: a headline
    metric's short name."""
    split, _, short = str(rank_by).partition("_")
    shorts = {m.short: m for m in HEADLINE}
    if short not in shorts or not split:
        raise EvaluationError(f"rank_by={rank_by!r}: expected <split>_<{'|'.join(shorts)}>, e.g. ld_trans")
    return shorts[short].metric_key(split, horizon_s)


def parse_key(key: str) -> tuple[Metric, str, str] | None:
    """``(metric, split, horizon "6s")`` of a metric's MLflow name (not a window count), else None."""
    for m in METRICS:
        rx = re.escape(m.key.format(split="SPLIT", h="HORIZON", short=m.short))
        rx = rx.replace("SPLIT", r"(?P<split>[a-z0-9]+)").replace("HORIZON", r"(?P<h>[0-9.e+-]+)")
        hit = re.fullmatch(rx, key)
        if hit:
            return m, hit["split"], hit["h"] + "s"
    return None


def describe() -> str:
    """One line per metric: its MLflow name pattern and what it is (run descriptions)."""
    return "; ".join(f"`{m.pattern()}`: {m.description}" for m in METRICS if not m.optional)
