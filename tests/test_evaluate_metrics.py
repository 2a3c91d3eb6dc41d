"""The metric registry (benchmark/scoring/metrics.py) and the pure scoring
(benchmark/scoring/predictions.py): names kept,
keys that parse back, and the absolute end-position error against closed forms."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from skidbench.benchmark.errors import EvaluationError
from skidbench.benchmark.scoring import metrics as mt
from skidbench.benchmark.scoring.horizon import HorizonConfig
from skidbench.benchmark.scoring.predictions import TestSequence, score_split, summarise
from skidbench.pipeline.core.geometry import integrate_body_velocity

RATE, H = 20.0, 6.0


def _line(name: str, n: int, v: float = 1.0) -> tuple[TestSequence, np.ndarray]:
    """A straight drive at ``v`` m/s for ``n`` samples (ground truth) and its true body velocities."""
    t = np.arange(n) / RATE
    true = np.column_stack([np.full(n, v), np.zeros(n), np.zeros(n)])
    pose = integrate_body_velocity(np.zeros(3), true[:-1], np.diff(t))
    table = pd.DataFrame({"t": t, "x": pose[:, 0], "y": pose[:, 1], "yaw": pose[:, 2], "valid": True})
    return TestSequence(name, Path(f"{name}.parquet"), table, {}), true


def test_existing_metric_names_are_kept():
    """Old runs and the docs use these names: the registry must produce them unchanged."""
    assert mt.metric_key("translational", "ld", 6.0) == "ld_6s_trans_rmsre_pct"
    assert mt.metric_key("rotational", "cv", 2.5) == "cv_2.5s_rot_rmsre_pct"
    assert mt.windows_key("translational", "ld", 6.0) == "ld_6s_trans_windows"
    assert mt.metric_key("coverage95_position", "ld", 6.0) == "coverage95_position_ld_6s"
    assert mt.metric_key("coverage95_yaw", "cv", 6.0) == "coverage95_yaw_cv_6s"
    assert mt.metric_key("nll_position", "cv", 6.0) == "nll_position_cv_6s"
    assert mt.metric_key("end_position", "ld", 6.0) == "ld_6s_endpos_rmse_m"
    assert mt.rank_key("ld_endpos", 6.0) == "ld_6s_endpos_rmse_m"
    with pytest.raises(EvaluationError, match=r"expected <split>_<trans\|rot\|endpos>, e.g. ld_trans"):
        mt.rank_key("ld_cov95pos", 6.0)


def test_every_key_is_unique_and_parses_back_to_its_metric():
    keys = {}
    for m in mt.METRICS:
        for split in ("cv", "ld", "train"):
            for h in (6.0, 2.5, 10.0):
                key = m.metric_key(split, h)
                assert key not in keys, f"{key} of {m.name} and {keys.get(key)}"
                keys[key] = m.name
                assert mt.parse_key(key) == (m, split, f"{h:g}s")
                n_key = m.windows_key(split, h)
                if n_key is not None:
                    assert mt.parse_key(n_key) is None  # a window count is not a metric value
    assert mt.parse_key("predict_time_s") is None and mt.parse_key("fit_loss") is None


@pytest.mark.parametrize("bias", [(0.05, 0.0), (0.0, -0.03), (0.03, 0.04)])
def test_a_constant_velocity_bias_gives_an_end_error_of_bias_times_horizon(bias):
    """A model off by a constant body velocity b = (bx, by) on a straight drive ends every window |b| h
    from the truth: the end-position RMSE is |b| h, over every window (none is under a minimum)."""
    seq, true = _line("a", 400)
    pred = true + np.array([bias[0], bias[1], 0.0])
    w = score_split([seq], [pred], [H], HorizonConfig(H))
    out = summarise(w, "ld", [H])
    n = round(H * RATE)
    assert out["ld_6s_endpos_windows"] == 400 - n
    assert np.allclose(w["trans_err"], np.hypot(*bias) * H)
    assert out["ld_6s_endpos_rmse_m"] == pytest.approx(np.hypot(*bias) * H, abs=1e-4)


def test_the_end_position_rmse_is_the_rms_over_every_window_of_a_split():
    """A bias b over the first m samples only: a step moves with the mean of its two ends' velocities, so
    steps 0..m-2 carry b and step m-1 b/2; window i (steps i..i+n-1) ends b dt (clip(m-1-i, 0, n) + 1/2
    if it holds step m-1) off.
    The RMS is over the windows of both sequences together (not a mean of per-sequence values), and the
    exact model's sequence counts with its zero errors."""
    b, m, n = 0.2, 150, round(H * RATE)
    biased, true = _line("biased", 300)
    exact, true2 = _line("exact", 200, v=0.5)
    pred = true.copy()
    pred[:m, 0] += b
    w = score_split([biased, exact], [pred, true2], [H], HorizonConfig(H))
    i = np.arange(300 - n)
    errs = b / RATE * (np.clip(m - 1 - i, 0, n) + 0.5 * ((i <= m - 1) & (m - 1 <= i + n - 1)))
    expected = np.sqrt(np.mean(np.concatenate([errs, np.zeros(200 - n)]) ** 2))
    out = summarise(w, "cv", [H])
    assert out["cv_6s_endpos_rmse_m"] == pytest.approx(expected, abs=1e-4)
    assert out["cv_6s_endpos_windows"] == (300 - n) + (200 - n)


def test_summarise_logs_every_metric_and_optional_ones_only_with_their_column():
    seq, true = _line("a", 300)
    w = score_split([seq], [true], [H], HorizonConfig(H))
    out = summarise(w, "ld", [H], intervals=None)
    plain = [m for m in mt.METRICS if not m.optional]
    assert set(out) == {m.metric_key("ld", H) for m in plain} | {
        m.windows_key("ld", H) for m in plain if m.count_key
    }
    with_ci = summarise(w, "ld", [H])  # by default each metric's interval and blocks too (intervals.py)
    assert set(with_ci) == set(out) | {k for m in plain for k in m.interval_keys("ld", H)}
    assert np.isnan(out["ld_6s_rot_rmsre_pct"]) and out["ld_6s_rot_windows"] == 0  # a line turns 0 rad
    assert out["ld_6s_trans_rmsre_pct"] == 0.0 and out["ld_6s_endpos_rmse_m"] == 0.0
    empty = summarise(pd.DataFrame(), "cv", [H])  # no window at all: NaN values, zero counts
    assert np.isnan(empty["cv_6s_endpos_rmse_m"]) and empty["cv_6s_endpos_windows"] == 0


def test_compare_labels_and_figures_come_from_the_registry():
    assert mt.get("trans").column_label("cv") == "trans CV %"
    assert mt.get("end_position").column_label("ld") == "endpos LD m"
    assert mt.get("end_position").count_label("ld") == "endpos LD n"
    assert mt.get("coverage95_position").column_label("cv") == "cov95 pos CV %"
    assert mt.get("nll_position").column_label("ld") == "NLL pos LD"
    files = [m.figure.file for m in mt.METRICS if m.figure]
    assert files[:2] == ["fig3_translational_rmsre.png", "fig4_rotational_rmsre.png"]
    assert len(set(files)) == len(files)
    with pytest.raises(EvaluationError, match="unknown metric 'nope'"):
        mt.get("nope")
