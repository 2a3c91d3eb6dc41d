"""The dataset card (pipeline/simulate/card.py): Table I columns from the truth, in closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest

from skidbench.pipeline.simulate.card import (
    PAPER_TABLE_I,
    build_rows,
    render_card,
    row_stats,
    sequence_moments,
)

R, B = 0.1, 0.4


def truth(v: float, w: float, seconds: float, wheel_scale: float = 1.0) -> dict:
    t = np.arange(0.0, seconds + 1e-9, 0.02)
    n = len(t)
    wl, wr = (v - w * B / 2) / R * wheel_scale, (v + w * B / 2) / R * wheel_scale
    return {
        "t": t,
        "vx": np.full(n, v),
        "vy": np.zeros(n),
        "wz": np.full(n, w),
        "cmd_left": np.full(n, wl),
        "cmd_right": np.full(n, wr),
        "wheel_left": np.full(n, wl),
        "wheel_right": np.full(n, wr),
    }


def test_constant_motion_gives_closed_form_columns():
    stats = row_stats([sequence_moments(truth(1.0, 0.5, 10.0), B, R)])
    assert stats["duration"] == pytest.approx(10.0)
    assert stats["distance"] == pytest.approx(10.0)
    assert stats["abs_rotation_kdeg"] == pytest.approx(math.degrees(5.0) / 1000)
    assert stats["lin_mean"] == pytest.approx(1.0) and stats["lin_std"] == pytest.approx(0.0, abs=1e-6)
    assert stats["ang_mean"] == pytest.approx(math.degrees(0.5))
    assert stats["slip_mean"] == pytest.approx(0.0, abs=1e-12)


def test_pooling_two_sequences_is_time_weighted_and_slip_is_measured_against_commands():
    a = sequence_moments(truth(1.0, 0.0, 10.0, wheel_scale=1.1), B, R)  # wheels commanded 10 % fast
    b = sequence_moments(truth(0.0, 0.0, 30.0), B, R)
    stats = row_stats([a, b])
    assert stats["duration"] == pytest.approx(40.0)
    assert stats["lin_mean"] == pytest.approx(0.25)
    assert stats["lin_std"] == pytest.approx(math.sqrt(0.25 * 0.75))
    assert stats["slip_mean"] == pytest.approx(0.1 * 10 / 40)


def test_card_prints_simulated_rows_next_to_the_papers():
    seqs = [
        {"category": "train", "terrain": "tile", "moments": sequence_moments(truth(1.3, 0.6, 20.0), B, R)},
        {"category": "loop", "terrain": "grass", "moments": sequence_moments(truth(0.7, 0.3, 25.0), B, R)},
    ]
    rows = build_rows(seqs)
    assert [(r["category"], r["terrain"]) for r in rows] == [("train", "tile"), ("loop", "grass")]
    card = render_card(rows, "sim-test")
    lines = card.splitlines()
    sim_row = next(i for i, line in enumerate(lines) if "| Training | tile | sim (1) |" in line)
    assert (
        "paper Train1 | 384 | 463.2 | 31.10 | 1.30 | 0.48 | 34.30 | 48.60 | 0.15 | 0.12" in lines[sim_row + 1]
    )
    assert "| Loop trials | grass | sim (1) | 25 |" in card
    assert len(PAPER_TABLE_I) == 9
