"""The effect catalogue and the pieces of the discovery rule (closed forms, no fitting)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd

from skidbench.benchmark.discover_stats import sign_flip_pvalue
from skidbench.models.effects import (
    CATALOGUE,
    EFFECT_IDS,
    apply_effects,
    base_targets,
    command_features,
    lag_filter,
)

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
