"""Confidence intervals, paired comparisons, the ranking rule (benchmark/scoring/intervals.py) and the
floor (benchmark/scoring/floor.py): coverage on the boards' designs with errors of known dependence, blocks
as long as the errors' memory, exact zeros where there is no difference, resolution only where the data
allow it, a floor that is a perfect model's score against a drifting ground truth, and the machinery's
round trip."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import scipy.signal

from skidbench.benchmark.scoring import intervals as iv
from skidbench.benchmark.scoring import ranks as rk
from skidbench.benchmark.scoring import standings as st
from skidbench.benchmark.scoring.floor import FLOOR, floor_windows, truth_velocities
from skidbench.benchmark.scoring.horizon import HorizonConfig, rmsre, window_errors
from skidbench.benchmark.scoring.predictions import TestSequence, score_split
from skidbench.benchmark.scoring.settings import IntervalConfig

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


def test_intervals_cover_on_the_boards_design_with_a_slow_error_component():
    # mini's board (three terrains, a 45 s CV and a 60 s LD drive each), errors with a 3 s and a 30 s
    # component: the full bench (perf/coverage.py, every design, 400 repetitions) asks 0.93; here 100
    # repetitions with a fixed seed, 0.95 within 2 binomial standard errors below (the old intervals: 0.82)
    sys.path.insert(0, str(Path(__file__).parent))
    import coverage_data as cd

    got = cd.coverage("3 terrains, 45 s + 60 s", "3s+30s", reps=100, seed=1, resamples=299)
    assert got["coverage"] >= 0.95 - 2 * np.sqrt(0.95 * 0.05 / 100), got
    assert got["rankable"] > 0.3, got  # not every board is left unranked


def test_blocks_follow_the_errors_memory_and_one_drive_is_labelled_as_such():
    rng = np.random.default_rng(2)
    seq, t0 = _windows(1, 8)  # one 96 s drive
    rows = {}
    for name, phi in (("white", 0.0), ("slow", 0.99)):  # 0.99 per 0.2 s: a 20 s correlation time
        s = iv.Sample()
        s.add("g/ld", seq, t0, {"m": np.exp(np.log(5.0) + 0.5 * _ar1(rng, 1, len(t0), phi)[0])}, H)
        rows[name] = iv.estimate(s, [iv.cell("m", "g/ld", "m")]).iloc[0]
    assert rows["white"]["block_s"] <= 2.0 < 10.0 <= rows["slow"]["block_s"]
    assert rows["white"]["df"] > 30 > 5 > rows["slow"]["df"]  # the same windows, far fewer independent
    assert not rows["slow"]["rankable"] and "effective independent blocks" in rows["slow"]["reason"]
    assert rows["white"]["scope"] == iv.WITHIN_DRIVE
    seq, t0 = _windows(6, 1)  # six drives of 12 s: whole drives are resampled
    s = iv.Sample()
    s.add("g/ld", seq, t0, {"m": np.exp(rng.standard_normal(len(t0)))}, H)
    row = iv.estimate(s, [iv.cell("m", "g/ld", "m")]).iloc[0]
    assert row["scope"] == iv.OVER_DRIVES and row["n_blocks"] == 6 and row["df"] == 5.0


def test_a_board_says_what_its_intervals_cover():
    """compare's board and report say, under the verdict, whether their intervals are within a drive (they
    cannot speak for another drive) or over drives (docs/intervals.md, "What an interval covers")."""
    from types import SimpleNamespace

    from skidbench.benchmark.board.tables import scope_line

    def board(means, cells):
        return SimpleNamespace(overall=pd.DataFrame({"scope": means}), cells=pd.DataFrame({"scope": cells}))

    line = scope_line(board([iv.WITHIN_DRIVES] * 2, [iv.WITHIN_DRIVE] * 4))
    assert "the means over terrains within these drives" in line and "cells within this drive" in line
    assert "not how another drive would differ" in line
    over = scope_line(board([iv.OVER_DRIVES], [iv.OVER_DRIVES]))
    assert "other drives like the recorded ones" in over and "another drive would differ" not in over
    assert scope_line(board([], [])) == ""
    # the error-against-horizon report says it under each stratum's claim
    from skidbench.benchmark.board.horizons import report_markdown

    s = board([iv.WITHIN_DRIVES], [iv.WITHIN_DRIVE])
    s.overall = s.overall.assign(model=["friction"], estimate=[6.0], lo=[5.0], hi=[7.5], rank=["1"])
    s.claim = {"overall": ("not resolved by these data", None)}
    md = report_markdown({"state": {1.0: {"all": s}, 6.0: {"all": s}}})
    assert "| friction | 6.00 [5.00, 7.50] #1 | 6.00 [5.00, 7.50] #1 |" in md
    assert md.count("Intervals: the means over terrains within these drives") == 1


def _two_models(rng, n_seq, blocks_per_seq, ratio, rho=0.8):
    """Windows of two models whose relative errors are correlated (they err on the same windows) and
    whose true RMSREs differ by the factor ``ratio``."""
    seq, t0 = _windows(n_seq, blocks_per_seq)
    z = _ar1(rng, 2, len(t0), 0.9)
    xa, xb = z[0], rho * z[0] + np.sqrt(1 - rho**2) * z[1]
    a, s = np.log(5.0), 0.5
    return seq, t0, np.exp(a + s * xa), ratio * np.exp(a + s * xb), np.exp(a + s**2)


def _board(seq, t0, ea, eb, cfg=None):
    sample = iv.Sample(cfg or IntervalConfig(seed=3))
    sample.add("g/ld", seq, t0, {"A": ea, "B": eb}, H)
    A, B = iv.cell("A", "g/ld", "A"), iv.cell("B", "g/ld", "B")
    res = iv.estimate(sample, [A, B, iv.difference("A-B", A, B), iv.difference("A-A", A, A)]).set_index(
        "stat"
    )
    scores = res.loc[["A", "B"]]
    diffs = pd.DataFrame([res.loc["A-B", ["lo", "hi"]]], index=pd.MultiIndex.from_tuples([("A", "B")]))
    return res, rk.rank_board(scores, diffs)


def test_paired_difference_of_a_model_with_itself_is_exactly_zero():
    rng = np.random.default_rng(0)
    seq, t0, ea, eb, _ = _two_models(rng, 2, 6, 1.0)
    res, _ = _board(seq, t0, ea, eb)
    assert res.loc["A-A", ["estimate", "lo", "hi"]].tolist() == [0.0, 0.0, 0.0]
    assert not rk.resolved(0.0, 0.0)
    # two copies of one model's windows, paired by pair_windows: still exactly 0
    frame = pd.DataFrame({"sequence": seq, "start": np.arange(len(t0)), "t0": t0, "rel_trans": ea})
    both = st.pair_windows({"A": frame, "A2": frame})
    s = iv.Sample()
    s.add("g/ld", both["sequence"], both["t0"], {"A": both["rel_trans.A"], "A2": both["rel_trans.A2"]}, H)
    d = iv.estimate(s, [iv.difference("d", iv.cell("A", "g/ld", "A"), iv.cell("A2", "g/ld", "A2"))]).iloc[0]
    assert (d["estimate"], d["lo"], d["hi"]) == (0.0, 0.0, 0.0)


def test_a_known_difference_is_resolved_with_enough_data_and_a_wide_interval_ties_nothing():
    rng = np.random.default_rng(5)
    # B is truly 6 % worse (in RMSRE) than A; two drives of 24 min resolve it
    seq, t0, ea, eb, true = _two_models(rng, 2, 120, 1.06)
    res, ranks = _board(seq, t0, ea, eb)
    d = res.loc["A-B"]
    assert d["hi"] < 0 and d["lo"] <= -0.06 * true <= d["hi"]
    assert ranks.loc["A", "standing"] == rk.BEST and ranks.loc["B", "standing"] == ""
    assert ranks["rank"].tolist() == ["1", "2"]
    assert rk.board_verdict(ranks["standing"]).startswith("best: A")
    seq, t0, ea, eb, true = _two_models(rng, 1, 10, 1.06)  # one 120 s drive: not resolved, not equivalent
    res, ranks = _board(seq, t0, ea, eb)
    d = res.loc["A-B"]
    assert d["lo"] < 0 < d["hi"] and not rk.equivalent(d["lo"], d["hi"], 0.1)
    leader = "A" if res.loc["A", "estimate"] < res.loc["B", "estimate"] else "B"
    if res.loc["A", "rankable"] and res.loc["B", "rankable"]:
        assert ranks["rank"].tolist() == ["1", "1"]
        assert ranks.loc[leader, "standing"] == rk.LEADS and TIED_NOT in ranks["standing"].tolist()
        assert rk.board_verdict(ranks["standing"]).startswith(f"leads, not resolved: {leader}")


TIED_NOT = ""  # a rank-1 entry only not resolved from the leader: no word


def test_ranks_follow_the_estimate_share_within_tolerance_and_tie_only_on_equivalence():
    # the DRIVE Husky case: C's interval is so wide that nothing is resolved from it; B is resolved worse
    # than A. C's estimate is above B's, so it cannot rank above B (it did: "tied for best" at 26.40 while
    # B at 22.04 ranked 2); D equals B within the tolerance and shares its rank
    scores = pd.DataFrame({"estimate": [20.0, 22.04, 26.40, 22.04 + 1e-8], "rankable": True, "reason": ""},
                          index=list("ABCD"))  # fmt: skip
    pairs = [("A", "B"), ("A", "C"), ("A", "D"), ("B", "C"), ("B", "D"), ("C", "D")]
    diffs = pd.DataFrame({"lo": [-3.0, -100.0, -3.0, -100.0, -1e-9, -100.0],
                          "hi": [-1.0, 100.0, -1.0, 100.0, 1e-9, 100.0]},
                         index=pd.MultiIndex.from_tuples(pairs))  # fmt: skip
    ranks = rk.rank_board(scores, diffs)
    assert ranks["rank"].tolist() == ["1", "2", "2", "2"]
    assert ranks.loc["A", "standing"] == rk.LEADS and ranks.loc["C", "standing"] == ""  # C not resolved
    # equivalence: A and B within +-0.5 point of each other (interval inside the margin): tied for best
    diffs.loc[("A", "B"), ["lo", "hi"]] = [-0.4, 0.3]
    diffs.loc[("A", "D"), ["lo", "hi"]] = [-0.4, 0.3]
    ranks = rk.rank_board(scores, diffs, margin=0.5)
    assert (
        ranks.loc[["A", "B", "D"], "standing"].tolist() == [rk.TIED] * 3 and ranks.loc["C", "standing"] == ""
    )
    assert rk.board_verdict(ranks["standing"], 0.5).startswith("tied for best: A, B, D")


def test_equivalence_passes_a_tenth_of_a_point_with_enough_data_and_not_with_too_little():
    # two models whose RMSREs differ by 0.13 point (6.4 vs 6.5 %): shown equivalent within 1 point on two
    # drives of 24 min, not on one of 48 s (less data can no longer make "comparable" easier)
    rng = np.random.default_rng(9)
    for n_seq, per_seq, rho, expect in ((2, 120, 0.9, True), (1, 4, 0.8, False)):  # 48 min; 48 s
        seq, t0, ea, eb, true = _two_models(rng, n_seq, per_seq, 1.02, rho=rho)
        res, _ = _board(seq, t0, ea, eb)
        d = res.loc["A-B"]
        assert abs(d["estimate"]) < 1.0
        p_tost = max(rk.p_greater(d["estimate"], d["se"], d["df"], -1.0),
                     rk.p_greater(-d["estimate"], d["se"], d["df"], -1.0))  # fmt: skip
        assert (p_tost < 0.05) == expect, (n_seq, per_seq, p_tost, d["df"])


def test_holm_rejects_step_down():
    assert rk.holm([0.01, 0.04, 0.03], 0.05) == [True, False, False]  # 0.01 <= 0.05/3; 0.03 > 0.05/2
    assert rk.holm([0.001, 0.02, 0.04], 0.05) == [True, True, True]  # 0.02 <= 0.025, 0.04 <= 0.05
    assert rk.p_greater(1.0, 0.0, 5.0) == 0.0 and rk.p_greater(np.nan, 1.0, 5.0) == 1.0


def test_a_board_of_one_entry_ranks_nothing_and_says_so():
    alone = pd.DataFrame({"estimate": [1.0], "rankable": True, "reason": ""}, index=["A"])
    ranks = rk.rank_board(alone, pd.DataFrame({"lo": [], "hi": []}))
    assert ranks.loc["A", "rank"] == "" and ranks.loc["A", "standing"] == f"{rk.NOT_RANKED}: {rk.ALONE}"
    assert rk.board_verdict(ranks["standing"]) == f"no entry ranked: {rk.ALONE}"
    two = pd.DataFrame({"estimate": [1.0, 2.0], "rankable": True, "reason": ""}, index=["A", "B"])
    diffs = pd.DataFrame({"lo": [-1.5], "hi": [-0.5]}, index=pd.MultiIndex.from_tuples([("A", "B")]))
    assert rk.rank_board(two, diffs).loc["A", "standing"] == rk.BEST  # one more entry: ranked


def test_a_split_with_one_window_is_shown_but_not_ranked():
    s = iv.Sample()
    s.add("grass/cv", ["raw_00"], [0.0], {"A": [3.79], "B": [73.78]}, H)
    res = iv.estimate(s, [iv.cell("A", "grass/cv", "A"), iv.cell("B", "grass/cv", "B")]).set_index("stat")
    assert res.loc["A", "estimate"] == pytest.approx(3.79) and not res["rankable"].any()
    assert res.loc["A", "n_windows"] == 1 and res.loc["A", "n_blocks"] == 1
    assert res.loc["A", "reason"] == "1 independent block (ranking needs 8)"
    diffs = pd.DataFrame({"lo": [np.nan], "hi": [np.nan]}, index=pd.MultiIndex.from_tuples([("A", "B")]))
    ranks = rk.rank_board(res, diffs)
    assert ranks["rank"].tolist() == ["", ""]
    assert ranks["standing"].str.startswith("not ranked: 1 independent block").all()
    assert rk.board_verdict(ranks["standing"]).startswith("no entry ranked")


def test_a_cell_is_the_same_alone_or_among_other_models_and_strata():
    # evaluate computes a cell from one model's windows, compare from every model's: same draws per stratum
    rng = np.random.default_rng(8)
    seq, t0, ea, eb, _ = _two_models(rng, 2, 3, 1.2)
    alone = iv.Sample(IntervalConfig(seed=4))
    alone.add("g/ld", seq, t0, {"A": ea}, H)
    many = iv.Sample(IntervalConfig(seed=4))
    many.add("t/cv", seq[:300], t0[:300], {"A": eb[:300]}, H)
    many.add("g/ld", seq, t0, {"B": eb, "A": ea}, H)
    one = iv.estimate(alone, [iv.cell("A", "g/ld", "A")]).iloc[0]
    two = iv.estimate(many, [iv.cell("A", "g/ld", "A")]).iloc[0]
    assert (
        one[["estimate", "lo", "hi", "n_blocks"]].tolist()
        == two[["estimate", "lo", "hi", "n_blocks"]].tolist()
    )
    assert one["estimate"] == pytest.approx(rmsre(ea))


def _simulated_cv_drive():
    """A simulated 12 s constant-velocity drive (segments and their steps: the hardest for the
    differentiator): the robot and the simulator's truth."""
    from importlib.resources import files

    import yaml

    from skidbench.pipeline.core.robot import Robot
    from skidbench.pipeline.simulate.physics import load_physics
    from skidbench.pipeline.simulate.scenarios import SequenceSpec
    from skidbench.pipeline.simulate.sequence import RunSettings, simulate_sequence
    from skidbench.pipeline.simulate.settings import SimulateOptions

    conf = files("skidbench.conf")
    robot = Robot.from_config(yaml.safe_load(conf.joinpath("robot/jackal.yaml").read_text()))
    terrains, drive, tyre = load_physics(yaml.safe_load(conf.joinpath("sim/jackal.yaml").read_text()))
    sim = SimulateOptions()  # simulate's defaults
    run = RunSettings(dt=sim.dt, rates=sim.rates, sensors=sim.sensors)
    spec = SequenceSpec("grass_cv_00", "grass", "cv", 12.0, {"cv_segment": 3})
    return robot, simulate_sequence(spec, 0, robot, terrains["grass"], drive, tyre, run, 0, None)


def _split(robot, truth, pose):
    from skidbench.pipeline.splits.build import build_split_table

    ns = np.round(truth.t * 1e9).astype(np.int64)
    return build_split_table(robot, ns, pose, [], ns, np.c_[truth.cmd_left, truth.cmd_right], "wheels")


def test_the_round_trip_of_the_ground_truths_own_velocities_is_near_zero():
    # an integration check of the machinery, not a floor: the velocities split derives from the ground
    # truth's poses, integrated back over each window against those same poses (trapezoidal steps)
    robot, truth = _simulated_cv_drive()
    table = _split(robot, truth, np.c_[truth.x, truth.y, truth.yaw])
    pose, vel = table[["x", "y", "yaw"]].to_numpy(), table[["vx", "vy", "wz"]].to_numpy()
    w = window_errors(table["t"].to_numpy(), pose, vel, H, table["valid"].to_numpy(), HorizonConfig(H))
    assert len(w) > 150
    assert 100 * rmsre(w["rel_trans"]) < 0.5 and 100 * rmsre(w["rel_rot"]) < 0.5


def test_the_floor_is_a_perfect_models_score_against_a_drifting_ground_truth():
    # a VO-like ground truth (0.5 % scale error and a heading drift of 1 deg per 10 s): the floor, the
    # simulator's exact velocities scored against it, is above zero and is what a model predicting those
    # velocities scores; the round trip of the ground truth's own velocities hides that error
    robot, truth = _simulated_cv_drive()
    drift = np.deg2rad(0.1) * truth.t
    c, s = np.cos(drift), np.sin(drift)
    vo = np.c_[1.005 * (c * truth.x - s * truth.y), 1.005 * (s * truth.x + c * truth.y), truth.yaw + drift]
    table = _split(robot, truth, vo)
    stamps = np.round(truth.t * 1e9).astype(np.int64)
    true_pose = pd.DataFrame({"bag_time_ns": stamps, "vx": truth.vx, "vy": truth.vy, "wz": truth.wz})
    vel = truth_velocities(table["stamp_ns"].to_numpy(), true_pose, "true_pose.parquet")
    floor = floor_windows([("grass_cv_00", table, vel)], [H], HorizonConfig(H))
    seq = TestSequence("grass_cv_00", Path("grass_cv_00.parquet"), table, {})
    perfect = score_split([seq], [vel], [H], HorizonConfig(H))
    assert FLOOR == "floor" and np.allclose(floor["rel_trans"], perfect["rel_trans"], equal_nan=True)
    trans, rot = 100 * rmsre(floor["rel_trans"]), 100 * rmsre(floor["rel_rot"])
    assert trans > 0.3 and rot > 0.1, (trans, rot)
    own = floor_windows([("grass_cv_00", table, table[["vx", "vy", "wz"]].to_numpy())], [H], HorizonConfig(H))
    assert 100 * rmsre(own["rel_trans"]) < trans / 3  # the round trip: the drift cancels
    with pytest.raises(ValueError, match="does not cover"):
        truth_velocities(table["stamp_ns"].to_numpy() + 10**9, true_pose, "true_pose.parquet")


def test_pairing_windows_is_the_outer_join_whether_or_not_the_models_share_every_window():
    """pair_windows is the table of the outer join on (sequence, start, t0), sorted by window, whether the
    models share every window or one lacks a window."""
    rng = np.random.default_rng(3)
    seq = np.repeat(["b_01", "a_00"], 6)
    base = pd.DataFrame(
        {"sequence": seq, "start": np.tile(np.arange(6) * 5, 2), "t0": np.tile(np.arange(6.0), 2)}
    )
    frames = {m: base.assign(rel_trans=rng.random(12), rel_rot=rng.random(12)) for m in ("A", "B", "C")}

    def joined(fr):
        out = None
        for m, df in fr.items():
            df = df.rename(columns={c: f"{c}.{m}" for c in ("rel_trans", "rel_rot")})
            out = df if out is None else out.merge(df, on=["sequence", "start", "t0"], how="outer")
        return out.sort_values(["sequence", "start"], kind="stable").reset_index(drop=True)

    same = st.pair_windows(frames)
    pd.testing.assert_frame_equal(same, joined(frames))
    assert same["sequence"].tolist()[:2] == ["a_00", "a_00"] and len(same) == 12
    frames["C"] = frames["C"].iloc[1:]  # C lacks a window: joined, NaN there
    gap = st.pair_windows(frames)
    pd.testing.assert_frame_equal(gap, joined(frames))
    assert len(gap) == 12 and int(gap["rel_trans.C"].isna().sum()) == 1


def test_paired_columns_are_the_joined_table_of_pair_windows():
    """The paired sample's arrays (standings._pair_columns) are pair_windows' table: the same windows in the
    same order (sorted by sequence, then start, stably) and the same values, whether the models share every
    window (set side by side), one lacks a window (joined) or a window repeats."""
    rng = np.random.default_rng(5)
    seq = np.array(["b_01"] * 5 + ["a_00"] * 5 + ["b_01"] * 2, dtype=object)
    base = {"sequence": seq, "start": np.r_[np.arange(5) * 5, np.arange(5) * 5, 30, 35],
            "t0": np.r_[np.arange(5.0), np.arange(5.0), 6.0, 7.0]}  # fmt: skip
    frames = {m: {**base, "translational": rng.random(12), "rotational": rng.random(12)} for m in "ABC"}

    def check(fr):
        got = st._pair_columns(fr)
        want = st.pair_windows({m: pd.DataFrame(f) for m, f in fr.items()})
        assert got["sequence"].tolist() == want["sequence"].tolist()
        for col in ["t0", *(f"{c}.{m}" for m in fr for c in ("translational", "rotational"))]:
            assert np.array_equal(got[col], want[col].to_numpy(float), equal_nan=True), col

    check(frames)
    check({m: {k: v[1:] if m == "C" else v for k, v in f.items()} for m, f in frames.items()})
    check({m: {k: np.r_[v, v[-1:]] for k, v in f.items()} for m, f in frames.items()})  # a repeated window


def test_resampled_statistics_are_the_same_in_any_chunk_and_the_draws_are_the_multinomials(monkeypatch):
    """The resamples' statistics computed a chunk of resamples at a time are those of all at once, bit for
    bit; the cached draws are numpy's multinomial counts of (seed, key, K), in any order of asking."""
    rng = np.random.default_rng(2)
    K, n = 37, 400
    block = np.sort(np.r_[np.arange(K), rng.integers(0, K, n - K)])
    N = rng.integers(0, 9, n).astype(float)
    cols = [(N * rng.random(n) ** 2, N, agg, c) for agg, c in (("rms", 0.5), ("mean", -0.25), ("rms", 1.0))]
    part = iv._Part(None, np.zeros(K), cols, K)  # type: ignore[arg-type]
    W = iv._draws(7, "ld@6s:x", K, 500)
    want = np.random.default_rng([7, iv.zlib.crc32(b"ld@6s:x"), K]).multinomial(K, np.full(K, 1 / K), 500)
    assert np.array_equal(W, want) and W.dtype == float
    whole = iv._resampled(W, part, block, K)
    theta_b, u_b = np.zeros(500), np.zeros((500, K))  # the formula on all resamples at once
    for S, N, agg, c in cols:
        Sk, Nk = np.bincount(block, weights=S, minlength=K), np.bincount(block, weights=N, minlength=K)
        Sb, Nb = W @ Sk, W @ Nk
        with np.errstate(divide="ignore", invalid="ignore"):
            mb = Sb / Nb
            u_b += (c * iv._slope(mb, agg) / Nb)[:, None] * (Sk[None, :] - mb[:, None] * Nk[None, :])
        theta_b += c * iv._score(Sb, Nb, agg)
    assert np.array_equal(whole[0], theta_b, equal_nan=True)
    assert np.array_equal(whole[1], K / (K - 1.0) * np.sum(W * u_b**2, axis=1), equal_nan=True)
    monkeypatch.setattr(iv, "_CHUNK", 3 * K + 1)  # 3 resamples a chunk, the last one short
    chunked = iv._resampled(W, part, block, K)
    for a, b in zip(whole, chunked, strict=True):
        assert np.array_equal(a, b, equal_nan=True)
    iv._draws(7, "ld@6s:y", K, 500)
    assert np.array_equal(iv._draws(7, "ld@6s:x", K, 500), W)
