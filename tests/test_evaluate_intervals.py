"""Confidence intervals, paired comparisons, the ranking rule (benchmark/scoring/intervals.py) and the floor
(benchmark/scoring/floor.py): coverage at the nominal rate on errors of known correlation, exact zeros where
there is no difference, resolution only where the blocks allow it, and a floor near zero on exact truth."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import scipy.signal

from skidbench.benchmark.scoring import intervals as iv
from skidbench.benchmark.scoring.floor import FLOOR, floor_windows
from skidbench.benchmark.scoring.horizon import HorizonConfig, rmsre

H = 6.0
SPACING = 0.2  # s between window starts: a block (two horizons, 12 s) holds 60 windows


def _windows(n_seq: int, blocks_per_seq: int) -> tuple[np.ndarray, np.ndarray]:
    """(sequence, t0) of ``n_seq`` sequences of ``blocks_per_seq`` blocks (of the default two horizons)."""
    per = int(round(blocks_per_seq * 2 * H / SPACING))
    seq = np.repeat([f"s{i}" for i in range(n_seq)], per)
    t0 = np.tile(np.arange(per) * SPACING, n_seq)
    return seq, t0


def _ar1(rng, reps: int, n: int, phi: float) -> np.ndarray:
    """(reps, n) standard normal series, AR(1) with coefficient ``phi`` over windows (stationary start)."""
    x = rng.standard_normal((reps, n))
    if phi == 0.0:
        return x
    y = scipy.signal.lfilter([np.sqrt(1 - phi**2)], [1.0, -phi], x, axis=1)
    return y + phi ** np.arange(1, n + 1) * rng.standard_normal(reps)[:, None]


def _coverage(phi: float, reps: int = 300) -> float:
    """Fraction of ``reps`` 95 % intervals of an RMSRE (lognormal errors, AR(1) with ``phi`` over
    windows, 16 blocks in 2 sequences) that hold its true value exp(a + s^2)."""
    rng = np.random.default_rng(11)
    seq, t0 = _windows(2, 8)
    a, s = np.log(5.0), 0.5  # in %: a median of 5 %, skewed as relative errors are
    x = _ar1(rng, reps, len(t0), phi)
    true = np.exp(a + s**2)
    hits = 0
    for r in range(reps):
        sample = iv.Sample(iv.IntervalConfig(resamples=999, seed=r))
        sample.add("t/ld", seq, t0, {"m": np.exp(a + s * x[r])}, H)
        row = iv.estimate(sample, [iv.cell("m", "t/ld", "m")]).iloc[0]
        hits += bool(row["lo"] <= true <= row["hi"])
    return hits / reps


@pytest.mark.parametrize("phi", [0.0, 0.9], ids=["white", "ar1"])
def test_interval_covers_the_true_rmsre_at_the_nominal_rate(phi):
    # AR(1) at 0.9 per window (0.2 s apart): a correlation time of 2 s; 95 % +- 3 binomial standard errors
    # of 300 repetitions (percentile intervals reach 0.78-0.88 here, docs/intervals.md)
    reps = 300
    cov = _coverage(phi, reps)
    tol = 3 * np.sqrt(0.95 * 0.05 / reps)
    assert abs(cov - 0.95) <= tol, cov


def test_blocks_stay_within_a_sequence_and_are_a_horizon_long():
    seq = np.array(["a"] * 5 + ["b"] * 4)
    t0 = np.array([10.0, 11.0, 16.5, 22.0, 22.1, 0.0, 5.9, 6.0, 18.0])
    block, adjacent = iv.assign_blocks(seq, t0, 6.0)
    assert block.tolist() == [0, 0, 1, 2, 2, 3, 3, 4, 5]
    assert adjacent.tolist() == [True, True, False, True, False]  # a's 3rd interval; b's 2nd, then a gap
    with pytest.raises(iv.IntervalError, match="shorter than the 6 s horizon"):
        iv.IntervalConfig(block_s=3.0).block_length(6.0)
    assert iv.IntervalConfig(block_s=6.0).block_length(6.0) == 6.0
    assert iv.IntervalConfig().block_length(6.0) == 12.0  # two horizons unless set


def _two_models(rng, n_seq, blocks_per_seq, ratio, rho=0.8):
    """Windows of two models whose relative errors are correlated (they err on the same windows) and
    whose true RMSREs differ by the factor ``ratio``."""
    seq, t0 = _windows(n_seq, blocks_per_seq)
    z = _ar1(rng, 2, len(t0), 0.9)
    xa, xb = z[0], rho * z[0] + np.sqrt(1 - rho**2) * z[1]
    a, s = np.log(5.0), 0.5
    return seq, t0, np.exp(a + s * xa), ratio * np.exp(a + s * xb), np.exp(a + s**2)


def _board(seq, t0, ea, eb, cfg=None):
    sample = iv.Sample(cfg or iv.IntervalConfig(seed=3))
    sample.add("g/ld", seq, t0, {"A": ea, "B": eb}, H)
    A, B = iv.cell("A", "g/ld", "A"), iv.cell("B", "g/ld", "B")
    res = iv.estimate(sample, [A, B, iv.difference("A-B", A, B), iv.difference("A-A", A, A)]).set_index(
        "stat"
    )
    scores = res.loc[["A", "B"]]
    diffs = pd.DataFrame([res.loc["A-B", ["lo", "hi"]]], index=pd.MultiIndex.from_tuples([("A", "B")]))
    return res, iv.rank_board(scores, diffs)


def test_paired_difference_of_a_model_with_itself_is_exactly_zero():
    rng = np.random.default_rng(0)
    seq, t0, ea, eb, _ = _two_models(rng, 2, 6, 1.0)
    res, _ = _board(seq, t0, ea, eb)
    assert res.loc["A-A", ["estimate", "lo", "hi"]].tolist() == [0.0, 0.0, 0.0]
    assert not iv.resolved(0.0, 0.0)
    # two copies of one model's windows, paired by pair_windows: still exactly 0
    frame = pd.DataFrame({"sequence": seq, "start": np.arange(len(t0)), "t0": t0, "rel_trans": ea})
    both = iv.pair_windows({"A": frame, "A2": frame})
    s = iv.Sample()
    s.add("g/ld", both["sequence"], both["t0"], {"A": both["rel_trans.A"], "A2": both["rel_trans.A2"]}, H)
    d = iv.estimate(s, [iv.difference("d", iv.cell("A", "g/ld", "A"), iv.cell("A2", "g/ld", "A2"))]).iloc[0]
    assert (d["estimate"], d["lo"], d["hi"]) == (0.0, 0.0, 0.0)


def test_a_known_difference_is_resolved_with_enough_blocks_and_tied_without():
    rng = np.random.default_rng(5)
    # B is truly 6 % worse (in RMSRE) than A; 240 blocks (48 min of windows) resolve it
    seq, t0, ea, eb, true = _two_models(rng, 8, 30, 1.06)
    res, ranks = _board(seq, t0, ea, eb)
    d = res.loc["A-B"]
    assert d["hi"] < 0 and d["lo"] <= -0.06 * true <= d["hi"]
    assert ranks.loc["A", "standing"] == iv.BEST and ranks.loc["B", "standing"] == ""
    assert ranks["rank"].tolist() == ["1", "2"]
    assert iv.board_verdict(ranks["standing"]).startswith("best: A")
    seq, t0, ea, eb, true = _two_models(rng, 1, 8, 1.06)  # 8 blocks (96 s): ranked, but not resolved
    res, ranks = _board(seq, t0, ea, eb)
    d = res.loc["A-B"]
    assert res.loc["A", "rankable"] and d["lo"] < 0 < d["hi"]
    assert ranks["standing"].tolist() == [iv.TIED, iv.TIED] and ranks["rank"].tolist() == ["1", "1"]
    assert iv.board_verdict(ranks["standing"]).startswith("tied for best: A, B")


def test_a_model_behind_another_is_not_tied_for_best_even_when_the_leader_is_not_resolved_from_it():
    # A leads; B and C are not resolved from A, but B is resolved better than C: C is behind, rank 2
    scores = pd.DataFrame({"estimate": [1.0, 1.1, 1.3], "rankable": True, "reason": ""}, index=list("ABC"))
    diffs = pd.DataFrame({"lo": [-0.5, -0.6, -0.3], "hi": [0.3, 0.1, -0.1]},
                         index=pd.MultiIndex.from_tuples([("A", "B"), ("A", "C"), ("B", "C")]))  # fmt: skip
    ranks = iv.rank_board(scores, diffs)
    assert ranks["rank"].tolist() == ["1", "1", "2"]
    assert ranks["standing"].tolist() == [iv.TIED, iv.TIED, ""]


def test_a_split_with_one_window_is_shown_but_not_ranked():
    s = iv.Sample()
    s.add("grass/cv", ["raw_00"], [0.0], {"A": [3.79], "B": [73.78]}, H)
    res = iv.estimate(s, [iv.cell("A", "grass/cv", "A"), iv.cell("B", "grass/cv", "B")]).set_index("stat")
    assert res.loc["A", "estimate"] == pytest.approx(3.79) and not res["rankable"].any()
    assert res.loc["A", "n_windows"] == 1 and res.loc["A", "n_blocks"] == 1
    assert res.loc["A", "reason"] == "1 independent block (ranking needs 8)"
    diffs = pd.DataFrame({"lo": [np.nan], "hi": [np.nan]}, index=pd.MultiIndex.from_tuples([("A", "B")]))
    ranks = iv.rank_board(res, diffs)
    assert ranks["rank"].tolist() == ["", ""]
    assert ranks["standing"].str.startswith("not ranked: 1 independent block").all()
    assert iv.board_verdict(ranks["standing"]).startswith("no entry ranked")


def test_a_cell_is_the_same_alone_or_among_other_models_and_strata():
    # evaluate computes a cell from one model's windows, compare from every model's: same draws per stratum
    rng = np.random.default_rng(8)
    seq, t0, ea, eb, _ = _two_models(rng, 2, 3, 1.2)
    alone = iv.Sample(iv.IntervalConfig(seed=4))
    alone.add("g/ld", seq, t0, {"A": ea}, H)
    many = iv.Sample(iv.IntervalConfig(seed=4))
    many.add("t/cv", seq[:300], t0[:300], {"A": eb[:300]}, H)
    many.add("g/ld", seq, t0, {"B": eb, "A": ea}, H)
    one = iv.estimate(alone, [iv.cell("A", "g/ld", "A")]).iloc[0]
    two = iv.estimate(many, [iv.cell("A", "g/ld", "A")]).iloc[0]
    assert (
        one[["estimate", "lo", "hi", "n_blocks"]].tolist()
        == two[["estimate", "lo", "hi", "n_blocks"]].tolist()
    )
    assert one["estimate"] == pytest.approx(rmsre(ea))


def test_the_floor_on_the_simulators_exact_truth_is_near_zero():
    # the ground truth's own velocities (as split builds them from poses) through the horizon machinery, on a
    # simulated constant-velocity drive (segments and their steps: the hardest for the differentiator)
    from importlib.resources import files

    import yaml

    from skidbench.pipeline.core.robot import Robot
    from skidbench.pipeline.simulate.physics import load_physics
    from skidbench.pipeline.simulate.scenarios import SequenceSpec
    from skidbench.pipeline.simulate.sequence import RunSettings, simulate_sequence
    from skidbench.pipeline.splits.build import build_split_table

    conf = files("skidbench.conf")
    robot = Robot.from_config(yaml.safe_load(conf.joinpath("robot/jackal.yaml").read_text()))
    terrains, drive, tyre = load_physics(yaml.safe_load(conf.joinpath("sim/jackal.yaml").read_text()))
    sim = yaml.safe_load(conf.joinpath("simulate.yaml").read_text())
    run = RunSettings(dt=sim["dt"], rates=sim["rates"], sensors=sim["sensors"])
    spec = SequenceSpec("grass_cv_00", "grass", "cv", 12.0, {"cv_segment": 3})
    truth = simulate_sequence(spec, 0, robot, terrains["grass"], drive, tyre, run, 0, None)
    ns = np.round(truth.t * 1e9).astype(np.int64)
    table = build_split_table(robot, ns, np.c_[truth.x, truth.y, truth.yaw], [], ns,
                              np.c_[truth.cmd_left, truth.cmd_right], "wheels")  # fmt: skip
    w = floor_windows([(spec.name, table)], [H], HorizonConfig(H))
    assert len(w) > 150 and FLOOR == "floor"
    assert 100 * rmsre(w["rel_trans"]) < 0.5 and 100 * rmsre(w["rel_rot"]) < 0.5
