"""The effect catalogue and the pieces of the discovery rule (closed forms, no fitting)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from skidbench.benchmark.discovery.stats import sign_flip_pvalue
from skidbench.models.augmented.effects import (
    CATALOGUE,
    EFFECT_IDS,
    apply_effects,
    base_targets,
    command_features,
)
from skidbench.pipeline.calibrate.actuator import lag_filter, lag_response

SPEC = Path(__file__).resolve().parents[2] / "shared" / "SPEC.md"
SPEC_IDS = (
    "angular_acceleration_slip",
    "linear_acceleration_slip",
    "actuator_lag",
    "centripetal_side_slip",
    "side_asymmetry",
    "curvature_dependent_icr",
    "lateral_drift",
    "speed_dependent_turn_slip",
)


def test_catalogue_holds_exactly_the_spec_ids_each_with_a_one_sentence_explanation():
    assert set(EFFECT_IDS) == set(SPEC_IDS)
    if SPEC.is_file():  # the public contract: the ids of SPEC.md's table
        table = re.findall(r"^\| `([a-z_]+)` \|", SPEC.read_text(), flags=re.M)
        assert set(table) == set(EFFECT_IDS)
    for e in CATALOGUE.values():
        assert e.explanation.endswith(".") and not re.search(r"[a-z]\. [A-Z]", e.explanation), e.id
        assert 1 <= e.n_params <= 2 and len(e.init) == e.n_params


def _table(n=200, seqs=2, dt=0.05):
    t = np.tile(np.arange(n // seqs) * dt, seqs)
    rng = np.random.default_rng(0)
    v = rng.uniform(0, 1, n)
    w = rng.uniform(-1, 1, n)
    r, B = 0.1, 0.4
    wl, wr = (v - w * B / 2) / r, (v + w * B / 2) / r
    return pd.DataFrame(
        {"t": t, "cmd_v": v, "cmd_w": w, "cmd_wl": wl, "cmd_wr": wr, "cmd_dwl": 0.0 * v, "cmd_dwr": 0.0 * v}
    ), np.repeat(np.arange(seqs), n // seqs)


def test_lag_filter_is_a_causal_first_order_response_restarted_per_sequence():
    tab, groups = _table()
    tab.loc[:, ["cmd_v", "cmd_wl", "cmd_wr", "cmd_w"]] = 0.0
    tab.loc[50:99, "cmd_v"] = 1.0  # a step in the first sequence; the second starts at rest
    tab.loc[100:, "cmd_v"] = 2.0  # second sequence: constant from its start
    out = lag_filter(tab, 0.2, groups)
    k = np.arange(50)
    expected = 1 - np.exp(-((k + 1) * 0.05) / 0.2)  # the command acts from the sample it arrives
    np.testing.assert_allclose(out["cmd_v"].to_numpy()[50:100], expected, atol=1e-12)
    np.testing.assert_allclose(out["cmd_v"].to_numpy()[:50], 0.0)
    np.testing.assert_allclose(out["cmd_v"].to_numpy()[100:], 2.0)  # never across the boundary


def test_lag_response_is_the_continuous_lag_of_commands_linear_between_samples():
    # a ramp u = a t from rest at 0: y = a (t - tau (1 - exp(-t / tau))) and dy/dt = a (1 - exp(-t / tau))
    # exactly at every sample (the first-order hold is exact for a piecewise-linear command); restarted
    # at rest on its first command in the second sequence
    tab, groups = _table()
    t = tab["t"].to_numpy()
    for c in ("cmd_v", "cmd_w", "cmd_wl", "cmd_wr"):
        tab[c] = 0.5 * t + np.where(groups == 1, 2.0, 0.0)
    out = lag_response(tab, 0.2, groups)
    ramp = 0.5 * (t - 0.2 * (1 - np.exp(-t / 0.2)))
    np.testing.assert_allclose(out["cmd_v"].to_numpy(), ramp + np.where(groups == 1, 2.0, 0.0), atol=1e-12)
    np.testing.assert_allclose(out["cmd_dwl"].to_numpy(), 0.5 * (1 - np.exp(-t / 0.2)), atol=1e-12)


def test_augmented_fit_recovers_the_lag_of_data_made_by_the_lag(jackal):
    """Velocities made exactly by edd on commands through an 80 ms lag (joystick commands at 30 Hz): the
    augmented fit's search finds tau to 1 % (a parabola through three points of its log grid put it at
    74 ms, a misfit the search then named as an acceleration slip)."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import discover_data as dd

    from skidbench.models.augmented.fit import fit_effects
    from skidbench.models.registry.specs import get_model_class

    r, B = jackal.wheel_radius, jackal.track_width
    frames = []
    for s in range(2):
        t, v, w = dd.joystick(np.random.default_rng(s), 30.0, 1 / 30)
        wl, wr = (v - w * B / 2) / r, (v + w * B / 2) / r
        zero = 0.0 * t
        frames.append(pd.DataFrame(
            {"t": t, "cmd_v": v, "cmd_w": w, "cmd_wl": wl, "cmd_wr": wr, "cmd_dwl": np.gradient(wl, t),
             "cmd_dwr": np.gradient(wr, t), "x": zero, "y": zero, "yaw": zero, "valid": True, "sequence": s}
        ))  # fmt: skip
    table = pd.concat(frames, ignore_index=True)
    lagged = lag_response(table, 0.08, table["sequence"].to_numpy())
    table["vx"], table["vy"], table["wz"] = lagged["cmd_v"], 0.0, lagged["cmd_w"] / 1.5  # edd, chi 1.5
    edd = get_model_class("edd")
    state = fit_effects(table, lambda: edd(jackal), jackal, ["actuator_lag"])
    assert state.params["actuator_lag"][0] == pytest.approx(0.08, rel=0.01)
    assert state.base.get_params()["chi"] == pytest.approx(1.5, rel=0.01)


def test_corrections_invert_for_the_base_refit():
    tab, _ = _table()
    f = command_features(tab, 0.1, 0.4)
    f["dv"] = np.random.default_rng(1).normal(size=len(tab))
    f["dw"] = np.random.default_rng(2).normal(size=len(tab))
    base = np.column_stack([tab.cmd_v, 0 * tab.cmd_v, tab.cmd_w / 1.3])
    params = {e: np.array(CATALOGUE[e].init) + 0.05 for e in EFFECT_IDS if CATALOGUE[e].kind != "input"}
    aug = apply_effects(base, f, params)
    np.testing.assert_allclose(base_targets(aug, base, f, params), base, atol=1e-9)


def test_sign_flip_p_value_is_exact_and_one_sided():
    assert sign_flip_pvalue(np.ones(10)) == 1 / 1024
    assert sign_flip_pvalue(-np.ones(10)) == 1.0
    d = np.array([1.0, -1.0, 2.0, -2.0])
    assert 0.3 < sign_flip_pvalue(d) < 0.8


def test_search_wide_p_value_is_the_sign_flip_p_value_of_the_best_of_the_candidates():
    from skidbench.benchmark.discovery.stats import search_pvalues

    d = np.array([0.3, 0.2, 0.1, 0.4, 0.2, -0.05, 0.3, 0.1])
    # one candidate (or copies of it): the one-candidate sign-flip p-value
    assert search_pvalues(d[None])[0] == pytest.approx(sign_flip_pvalue(d))
    assert search_pvalues(np.vstack([d, d, d]))[0] == pytest.approx(sign_flip_pvalue(d))
    # more candidates: the best of them under the same flips is at least as large, so p only grows
    rng = np.random.default_rng(0)
    others = rng.normal(0.0, 0.3, size=(12, 8))
    p = search_pvalues(np.vstack([d, others]))
    assert p[0] >= sign_flip_pvalue(d) and p[0] <= 1.0
    # exact: 2^8 flips; a candidate better than every other in every flip keeps the minimum 1/256
    assert search_pvalues(np.vstack([np.ones(8), 0.1 * np.ones(8)]))[0] == 1 / 256


def test_commands_aligned_with_the_grid_leave_no_timing_error():
    """45 Hz commands on the 30 Hz grid, poses without errors: the split's hold is 5.6 ms younger than
    what the velocities see (a lag of the response, in a regression); aligned, none is left."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import discover_data as dd

    from skidbench.benchmark.discovery.pool import align_commands
    from skidbench.models.augmented.fit import DiscoverSettings, build_pool
    from skidbench.pipeline.core.robot import load_robot

    jackal = load_robot("jackal")
    vo = dd.vo_poses
    try:
        dd.vo_poses = lambda rng, t, pose, rate_hz=20.0, **k: vo(rng, t, pose, 30.0, 0.0, 0.0, 0.0)
        raw = {"train": [dd.sequence(np.random.default_rng(s), {}, 24.0) for s in range(2)]}
    finally:
        dd.vo_poses = vo
    pool = build_pool(dd.split_tables(raw), DiscoverSettings())

    def lag_ms(p) -> float:  # vx ~ a v + b dv: a response lagging by d has b = -a d
        df = p.table[p.valid]
        f = command_features(df, jackal.wheel_radius, jackal.track_width)
        (a, b), *_ = np.linalg.lstsq(np.column_stack([f["v"], f["dv"]]), df["vx"].to_numpy(), rcond=None)
        return -1000 * b / a

    assert lag_ms(pool) == pytest.approx(1000 / 180, abs=0.5)
    aligned = align_commands(pool, jackal)
    assert set(aligned.alignment) == {"train_00", "train_01"}
    assert abs(lag_ms(aligned)) < 0.2


def test_curvature_law_fit_with_the_base_reaches_the_joint_optimum(jackal):
    """Yaw rates made exactly by chi(R) = 1 + b1 / (1 + b2 sqrt R) (R the commanded radius, chi = 1 on a
    straight line): the augmented fit of ``edd`` + ``curvature_dependent_icr`` recovers b1, b2 and edd's
    chi = 1 (the base's chi alone, 1.38 here, absorbs the law's mean; alternating from it used to stall at
    b1 = 0.58, b2 = 17, chi = 1.30 and leave a yaw-rate residual proportional to |v| sign(w))."""
    from skidbench.models.augmented.fit import fit_effects
    from skidbench.models.registry.specs import get_model_class

    rng = np.random.default_rng(4)
    n = 1500
    v = np.repeat(rng.uniform(-0.3, 1.6, n // 15), 15)
    w = np.repeat(rng.uniform(-2.5, 2.5, n // 15), 15)
    r, B = jackal.wheel_radius, jackal.track_width
    b1, b2 = 0.6, 1.0
    R = np.abs(v) / np.maximum(np.abs(w), 1e-9)
    wz = w / (1 + b1 / (1 + b2 * np.sqrt(R)))
    zero = 0.0 * v
    table = pd.DataFrame(
        {"t": np.arange(n) * 0.05, "cmd_v": v, "cmd_w": w, "cmd_wl": (v - w * B / 2) / r,
         "cmd_wr": (v + w * B / 2) / r, "cmd_dwl": zero, "cmd_dwr": zero, "vx": v, "vy": zero, "wz": wz,
         "x": zero, "y": zero, "yaw": zero, "valid": True, "sequence": np.repeat(np.arange(3), n // 3)}
    )  # fmt: skip
    edd = get_model_class("edd")
    state = fit_effects(table, lambda: edd(jackal), jackal, ["curvature_dependent_icr"])
    assert state.params["curvature_dependent_icr"] == pytest.approx([b1, b2], rel=0.02)
    assert state.base.get_params()["chi"] == pytest.approx(1.0, rel=0.01)
    assert np.sqrt(np.mean((state.pred[:, 2] - wz) ** 2)) < 1e-3


def test_side_asymmetry_is_a_radius_difference_in_both_channels(jackal):
    """Wheel radii r (1 - e) and r (1 + e) (the generator's physical form) move the robot exactly as the
    extended differential drive plus ``side_asymmetry`` with k = 2 e / (B chi): the yaw rate by k v and the
    forward speed by e B w / 2. And one side's slip of 10 % on the radius ``calibrate`` measures (r (1 - s /
    2)) is that radius difference, so after the effect's fit no forward-speed residual is left (the vx
    part missing, it left vx += 0.0094 w, which the term library named ``lin.wz_pred.vx``)."""
    import dataclasses
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import discover_data as dd

    from skidbench.models.augmented.fit import fit_effects
    from skidbench.models.registry.specs import get_model_class

    r, B, chi = dd.R_WHEEL, dd.TRACK, dd.CHI
    t, v, w = dd.joystick(np.random.default_rng(5), 30.0, 1 / 30)
    tab = pd.DataFrame({"t": t, "cmd_v": v, "cmd_w": w, "cmd_wl": (v - w * B / 2) / r,
                        "cmd_wr": (v + w * B / 2) / r, "cmd_dwl": 0 * t, "cmd_dwr": 0 * t})  # fmt: skip
    f = command_features(tab, r, B)
    e = 0.02
    vx, _, wz = dd.true_velocity(t, v, w, {"side_asymmetry": e})
    aug = apply_effects(
        np.column_stack([v, 0 * v, w / chi]), f, {"side_asymmetry": np.array([2 * e / (B * chi)])}
    )
    np.testing.assert_allclose(aug[:, 0], vx, atol=1e-12)
    np.testing.assert_allclose(aug[:, 2], wz, atol=1e-12)

    s = 0.1
    vx, vy, wz = dd.true_velocity(t, v, w, {"one_side_slip": ("l", s)})
    robot = dataclasses.replace(jackal, wheel_radius=r * (1 - s / 2), track_width=B)  # the wheel commands: r
    zero = 0 * t
    table = tab.assign(vx=vx, vy=vy, wz=wz, x=zero, y=zero, yaw=zero, valid=True, sequence=0)
    edd = get_model_class("edd")
    state = fit_effects(table, lambda: edd(robot), robot, ["side_asymmetry"])
    assert state.params["side_asymmetry"][0] == pytest.approx(s / (B * chi), rel=0.01)
    res = state.pred - np.column_stack([vx, vy, wz])
    assert np.sqrt(np.mean(res[:, 0] ** 2)) < 1e-4 and np.sqrt(np.mean(res[:, 2] ** 2)) < 1e-4
