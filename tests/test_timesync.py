"""Time association (pipeline/core/timesync.py) on closed-form cases: exact stamps, ties, gaps, coverage."""

from __future__ import annotations

import numpy as np
import pytest

from skidbench.pipeline.core.timesync import bracket, hold, interp_se2, interp_with_gaps, nearest

REF = np.array([100, 200, 300, 1000], dtype=np.int64)


def test_nearest_finds_exact_stamps_and_the_closer_neighbour():
    i, ok = nearest(np.array([100, 200, 1000, 240, 260, 990]), REF, 50)
    assert i.tolist() == [0, 1, 3, 1, 2, 3]
    assert ok.all()


def test_nearest_gives_a_tie_to_the_earlier_stamp():
    i, ok = nearest(np.array([150, 250, 650]), REF, 350)
    assert i.tolist() == [0, 1, 2]
    assert ok.all()


def test_nearest_outside_the_tolerance_or_the_coverage_is_unmatched():
    i, ok = nearest(np.array([0, 49, 50, 1051, 1050, 650]), REF, 50)
    assert i.tolist() == [0, 0, 0, 3, 3, 2]
    assert ok.tolist() == [False, False, True, False, True, False]


def test_nearest_with_one_reference_stamp():
    i, ok = nearest(np.array([90, 111]), np.array([100]), 10)
    assert i.tolist() == [0, 0]
    assert ok.tolist() == [True, False]


def test_hold_is_the_last_sample_at_or_before_and_zero_before_the_first_or_when_stale():
    stamps = np.array([100, 200], dtype=np.int64)
    values = np.array([[1.0, -1.0], [2.0, -2.0]])
    grid = np.array([99, 100, 199, 200, 250, 251], dtype=np.int64)
    held = hold(stamps, values, grid, timeout_ns=50)
    assert held.tolist() == [[0, 0], [1, -1], [0, 0], [2, -2], [2, -2], [0, 0]]
    assert hold(stamps, values, grid, timeout_ns=None)[-1].tolist() == [2, -2]


def test_bracket_fraction_is_exact_between_samples():
    t = np.array([100, 150, 200, 275, 1000], dtype=np.int64)
    i, frac, valid = bracket(REF, t, max_gap_ns=100)
    assert i.tolist() == [0, 0, 1, 1, 2]
    assert frac.tolist() == [0.0, 0.5, 0.0, 0.75, 1.0]
    assert valid.tolist() == [True, True, True, True, True]


def test_bracket_never_extrapolates():
    _, _, valid = bracket(REF, np.array([99, 1001, -5]), max_gap_ns=10_000)
    assert not valid.any()


@pytest.mark.parametrize("trust_samples", [True, False])
def test_bracket_inside_a_long_gap_is_untrusted(trust_samples):
    # 300 -> 1000 is a 700 ns gap, over the 100 ns limit
    _, _, valid = bracket(REF, np.array([301, 650, 999]), 100, trust_samples)
    assert not valid.any()


def test_a_time_on_the_sample_before_a_gap_is_trusted_only_when_samples_are_trusted():
    t = np.array([300, 1000], dtype=np.int64)
    assert bracket(REF, t, 100, trust_samples=True)[2].tolist() == [True, True]
    # the split's grid asks the interval starting at the sample to be short; the last sample is exact
    assert bracket(REF, t, 100, trust_samples=False)[2].tolist() == [False, True]


def test_bracket_with_one_sample_is_valid_only_on_it():
    i, frac, valid = bracket(np.array([100]), np.array([99, 100, 101]), 1_000)
    assert i.tolist() == [0, 0, 0] and frac.tolist() == [0.0, 0.0, 0.0]
    assert valid.tolist() == [False, True, False]


def test_interp_with_gaps_is_linear_and_masks_gaps_and_coverage():
    stamps = np.array([0, 100, 200, 300], dtype=np.int64)
    values = np.column_stack([stamps * 2.0, -stamps * 1.0])
    grid = np.array([-10, 0, 50, 150, 250, 300, 310], dtype=np.int64)
    out, ok = interp_with_gaps(stamps, values, grid, 100, gaps=[(100, 200)])
    assert out[:, 0].tolist() == [0, 0, 100, 300, 500, 600, 600]
    assert out[:, 1].tolist() == [0, 0, -50, -150, -250, -300, -300]
    # 150 lies strictly inside the gap (100, 200); -10 and 310 are outside the samples
    assert ok.tolist() == [False, True, True, False, True, True, False]


def test_interp_se2_unwraps_yaw_and_interpolates_the_short_way():
    t_ref = np.array([0.0, 1.0])
    se2 = np.array([[0.0, 0.0, np.pi - 0.1], [2.0, -4.0, -np.pi + 0.1]])
    out = interp_se2(t_ref, se2, np.array([0.5, 2.0]))
    np.testing.assert_allclose(out[0], [1.0, -2.0, np.pi], atol=1e-12)
    np.testing.assert_allclose(out[1], [2.0, -4.0, np.pi + 0.1], atol=1e-12)
