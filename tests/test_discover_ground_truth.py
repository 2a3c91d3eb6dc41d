"""The ground truth's own consistency (benchmark/discovery/checks/ground_truth.py): a heading that disagrees
with the direction of travel and a distance scale that drifts are ground-truth findings with their size, the
pool corrected by them, never robot effects; a robot whose own speed or turn changes is not one."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import discover_data as dd  # noqa: E402

from skidbench.benchmark.discovery.checks.ground_truth import ground_truth_findings  # noqa: E402
from skidbench.benchmark.discovery.pool import prepare_pool  # noqa: E402
from skidbench.models.augmented.fit import DiscoverSettings, build_pool  # noqa: E402


def _pool(effects: list[str], seed: int, jackal, **world):
    rng = np.random.default_rng(seed)
    train = []
    for i in range(6):
        cmd, loc = dd.sequence(rng, dd.hidden(effects), 30.0, **world)
        df = dd.to_split(cmd, loc)
        train.append((df, dd.split_meta(df, f"train_{i:02d}")))
    return prepare_pool(build_pool(train, DiscoverSettings()), "commanded", jackal)


def _drift(pool) -> float:
    """The relative change per minute of the measured vx against the commanded speed over the pool."""
    cv = pool.table["cmd_v"].to_numpy(float)
    m = pool.valid & (np.abs(cv) >= 0.2)
    tt = np.concatenate([pool.t[pool.groups == g] - pool.t[pool.groups == g][0]
                         for g in range(len(pool.sequences))]) / 60.0  # fmt: skip
    a, b = np.linalg.lstsq(np.column_stack([cv[m], cv[m] * tt[m]]), pool.target[m, 0], rcond=None)[0]
    return float(b / a)


def test_a_drifting_distance_scale_is_a_ground_truth_finding_and_is_corrected(jackal):
    pool = _pool([], 0, jackal, gt_scale=0.2)
    assert _drift(pool) == pytest.approx(0.2, abs=0.03)
    fixed, found = ground_truth_findings(pool)
    # (the odometry-like truth's heading may be found off its track as well: its rotations drift too)
    scale = [f for f in found if f["what"] == "distance scale drifts against the commanded speeds"]
    assert len(scale) == 1, found
    f = scale[0]
    assert f["mean_drift_pct_per_min"] == pytest.approx(20.0, abs=3.0)
    assert "check the ground truth" in f["text"] and "not a robot effect" in f["text"]
    assert abs(_drift(fixed)) < 0.1 * _drift(pool)  # the pool the search runs on: a tenth of it at most
    # positions re-integrated from the corrected displacements: the path length shrinks by the scale
    seq = fixed.groups == 0
    length = [np.sum(np.hypot(*np.diff(p[seq, :2], axis=0).T)) for p in (pool.pose, fixed.pose)]
    assert length[1] < length[0] and fixed.pose[seq][0, 0] == pool.pose[seq][0, 0]


def test_a_robot_slowing_down_or_turning_less_is_not_a_ground_truth_problem(jackal):
    # a battery running down slows both wheels: vx and the turn rate drift together; a payload loaded at
    # 18 s cuts the turn rate alone; clean data drift only by the odometry's own 0.4 %
    for effects in (["speed_fade"], ["payload_change"], []):
        _, found = ground_truth_findings(_pool(effects, 1, jackal))
        assert not [f for f in found if "scale" in f["what"]], (effects, found)


def test_a_heading_off_its_track_is_a_ground_truth_finding(jackal):
    _, found = ground_truth_findings(_pool([], 2, jackal, heading=(3.0, 1.5)))
    assert [f["what"] for f in found] == ["heading disagrees with the direction of travel"]
    assert found[0]["mean_offset_deg"] == pytest.approx(3.0, abs=0.5)
    assert found[0]["mean_drift_deg_per_min"] == pytest.approx(1.5, abs=0.5)


def _bench_pool(seed: int, jackal, style: str = "mixed", **world):
    """The pool of a bench case (perf/discover_fdr.py: eight 36 s drives of the case's seed)."""
    rng = np.random.default_rng(seed)
    train = []
    for i in range(8):
        df = dd.to_split(*dd.sequence(rng, {}, 36.0, style=style, **world))
        train.append((df, dd.split_meta(df, f"train_{i:02d}")))
    return prepare_pool(build_pool(train, DiscoverSettings()), "commanded", jackal)


def test_heading_estimates_that_noise_explains_are_not_a_finding(jackal):
    """The bench's clean/1007 case (gentle drives, a right ground truth): offset and drift estimates of
    several degrees that cancel each other gave a 2.3 deg RMS heading offset, reported as "check the
    ground truth"; noise (the measured vy's sign flipped in 2 s blocks) gives offsets as large 42 % of the
    time, so it is no finding."""
    from skidbench.benchmark.discovery.checks.ground_truth import heading_finding

    pool = _bench_pool(1007, jackal, style="gentle")
    _, estimate = heading_finding(pool, p_max=1.0)  # the estimate alone, as the check had it
    assert estimate["rms_deg"] > 2.0 and estimate["p_noise"] > 0.05
    assert heading_finding(pool) == (pool, None)


def test_a_heading_offset_in_every_sequence_is_found_beside_a_poorly_determined_one(jackal):
    """The bench's heading/6605 case (3 deg, 1.5 deg/min in each of eight drives): one drive has 72
    moving low-turn rows whose offset and drift noise could match the offsets of all others together;
    each drive weighed by its own noise, the offset is beyond every draw."""
    from skidbench.benchmark.discovery.checks.ground_truth import heading_finding

    _, found = heading_finding(_bench_pool(6605, jackal, heading=(3.0, 1.5)))
    assert found is not None and found["p_noise"] < 0.001
    assert found["mean_offset_deg"] == pytest.approx(3.0, abs=0.7)


def test_a_robots_response_to_held_commands_is_not_a_ground_truth_scale_drift(shared_real, tmp_path):
    """The DRIVE Warthog's sand recording (Train: eleven drives of 6 to 78 s, commands held in 6 s steps,
    a lag of about a second): each drive's few seconds of response to its steps read as a distance scale
    drifting by 105 % RMS (+498 %/min), reported as "check the ground truth" and divided out of the
    pool. Noise (the residual's sign flipped in 6 s blocks) gives drifts as large a fifth of the time:
    no finding, and the pool is searched as it was recorded."""
    from drive_data import drive_splits

    from skidbench.benchmark.discovery.checks.ground_truth import drift_estimate, scale_drift_finding
    from skidbench.pipeline.core.robot import load_robot
    from skidbench.pipeline.core.schema import load_split_tables

    splits = drive_splits(shared_real / "drive", tmp_path, "warthog", "source.label=warthog3",
                          "source.file=[warthog_sand_slip.parquet]", "source.terrain=[sand]",
                          "split.drop_flagged=true")  # fmt: skip
    train = load_split_tables(splits, "sand", "train")
    pool = prepare_pool(build_pool(train, DiscoverSettings()), "commanded", load_robot("warthog"))
    est = drift_estimate(pool)
    assert est["rms_pct"] > 100 and abs(est["mean_drift_pct_per_min"]) > 400, est  # the estimate as reported
    assert est["p_noise"] > 0.05, est["p_noise"]
    assert scale_drift_finding(pool) == (pool, None)
    assert not [f for f in ground_truth_findings(pool)[1] if "scale" in f["what"]]
