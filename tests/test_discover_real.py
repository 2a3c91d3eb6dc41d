"""Discovery on real recordings (issue 47): the placebo check on the DRIVE Husky (its commands moved 30 s:
``edd`` cannot be fitted to them, where the placebo used to say "nothing named" without searching; now
the search runs from the base held at its recorded fit with channel gains, and names nothing; skips when
``../shared`` or ``SKIDBENCH_SHARED_REAL`` is absent), and a speed scale against commands where the radius
was measured against encoders (DRIVE's calibration) told as the wheels' shortfall, not a radius."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))


def test_gained_base_takes_a_channel_that_does_not_follow_its_commands_to_zero():
    """A channel whose prediction anti-correlates with the measurement gets gain 0 (the bounded least
    squares), one that follows it its least-squares gain, one the base never predicts gain 1."""
    from skidbench.benchmark.discovery.checks.placebo import GainedBase, RecordedFits
    from skidbench.models.registry.specs import get_model_class
    from skidbench.pipeline.core.robot import load_robot

    robot = load_robot("husky")
    rng = np.random.default_rng(0)
    wl, wr = rng.uniform(-4, 6, 400), rng.uniform(-4, 6, 400)
    v, w = robot.twist_from_wheel_rates(wl, wr)
    table = pd.DataFrame(
        {"cmd_wl": wl, "cmd_wr": wr, "vx": 0.7 * v, "vy": 0.0, "wz": -0.5 * w, "valid": True}
    )
    recorded = RecordedFits(table.assign(wz=0.5 * w), lambda: get_model_class("edd")(robot))  # chi 2
    m = GainedBase(recorded).fit(table)
    assert m.params["gains"] == pytest.approx([0.7, 1.0, 0.0])
    assert np.allclose(m.predict(table)[:, 0], 0.7 * v) and np.allclose(m.predict(table)[:, 2], 0.0)


def test_the_placebos_inner_base_never_sees_a_folds_held_out_rows(jackal):
    """The base model behind the placebo's gained base is fitted, in each fold, on that fold's training rows
    (less the buffer around its held-out blocks) with their recorded commands, never on the whole pool:
    a base fitted on every row has seen the held-out units it then predicts. A base that refuses the moved
    commands (as ``edd`` does on DRIVE) sends the placebo to the gained base; every fit of it on the
    recorded commands is logged. Three 60 s sequences (time blocks, so the buffer applies)."""
    import discover_data as dd

    from skidbench.benchmark.discovery.checks.placebo import placebo
    from skidbench.benchmark.discovery.pool import prepare_pool
    from skidbench.benchmark.discovery.stats import folds_of, training_rows
    from skidbench.models.augmented.fit import DiscoverSettings, build_pool
    from skidbench.models.registry.specs import get_model_class
    from skidbench.pipeline.core.errors import SkidbenchError

    rng, train = np.random.default_rng(3), []
    for i in range(3):
        cmd, loc = dd.sequence(rng, {}, 60.0)
        df = dd.to_split(cmd, loc)
        train.append((df, dd.split_meta(df, f"train_{i:02d}")))
    s = DiscoverSettings(open_ended=False)
    pool = prepare_pool(build_pool(train, s), "commanded", jackal)
    recorded, fits = pool.table, []

    class RefusesMovedCommands(get_model_class("edd")):
        def fit(self, table):
            if not np.allclose(table["cmd_w"], recorded.loc[table.index, "cmd_w"]):
                raise SkidbenchError("cannot be fitted to commands that did not drive the motion")
            fits.append(frozenset(table.index[table["valid"].to_numpy(bool)]))
            return super().fit(table)

    out = placebo(
        pool, lambda: RefusesMovedCommands(jackal), jackal, s, "tile", "edd", ("actuator_lag",), 30.0
    )
    assert out["searched"] and "did not drive" in out["fallback"], out
    assert pool.blocks and fits
    every = frozenset(pool.table.index[pool.valid])
    fold_rows = [
        frozenset(pool.table.index[training_rows(pool, held, s.horizon_s)])
        for held in folds_of(pool, s.folds)
    ]
    for rows in fold_rows:  # each fold's inner base, fitted on its training rows
        assert rows in fits and len(rows) < len(every)
    assert set(fits) <= set(fold_rows) | {every}  # and no other: the whole pool only for the final model


@pytest.mark.slow
def test_a_placebo_on_the_drive_husky_searches_and_names_nothing(shared_real, tmp_path):
    """The first three Train sequences of the DRIVE Husky (198 s, 9 time blocks; about 10 CPU-s): the
    base model cannot be fitted to the moved commands, the search runs anyway (every candidate scored,
    the search-wide test made) and names nothing."""
    from drive_data import drive_splits

    from skidbench.benchmark.discovery.checks.placebo import placebo
    from skidbench.benchmark.discovery.pool import prepare_pool
    from skidbench.models.augmented.effects import EFFECT_IDS
    from skidbench.models.augmented.fit import DiscoverSettings, build_pool
    from skidbench.models.registry.specs import get_model_class
    from skidbench.pipeline.core.robot import load_robot
    from skidbench.pipeline.core.schema import load_split_tables

    splits = drive_splits(shared_real / "drive", tmp_path, "husky", "source.file=husky_windows.parquet")
    robot, s = load_robot("husky"), DiscoverSettings()
    pool = prepare_pool(
        build_pool(load_split_tables(splits, "unspecified", "train")[:3], s), "commanded", robot
    )
    edd = get_model_class("edd")
    out = placebo(pool, lambda: edd(robot), robot, s, "unspecified", "edd", EFFECT_IDS, 30.0)
    # the case the placebo used to pass without a search: edd's 1/chi < 0 on the moved commands
    assert out["searched"] and "1/chi" in out["fallback"], out
    assert out["n_candidates"] >= 8, out  # the catalogue's command-driven members at least
    assert out["named"] == [] and out["passed"] is True, out


def test_a_speed_scale_against_encoder_measured_radius_is_not_a_radius_to_configure():
    """The DRIVE Warthog case: a scale of 0.690 against an encoder-measured 0.2693 m is the wheels turning
    slower than commanded; without encoders behind the radius the finding stays a radius."""
    from types import SimpleNamespace

    from skidbench.benchmark.discovery.checks.scale import against_encoders

    text = "the effective wheel radius is 0.1857 m ...; put wheel_radius: 0.1857 in the robot's config"
    cal = {"configured": 0.2693, "ci": [0.1578, 0.2136], "speed_scale": 0.690, "text": text}
    step = {"kind": "calibration", "explanation": text}
    res = SimpleNamespace(calibration=dict(cal), message=f"calibration: {text}; no missing effect found",
                          steps=[step])  # fmt: skip
    against_encoders(res, "straight settled rows: vx = r (wl + wr) / 2 through the origin; wheels: encoders")
    assert "0.690 of the speed its commands ask for" in res.calibration["text"]
    assert "put wheel_radius" not in res.message and "put wheel_radius" not in step["explanation"]
    assert res.calibration["text"] in res.message
    lo, hi = res.calibration["text"].split("interval ")[1].split(")")[0].split("-")
    assert float(lo) == pytest.approx(0.1578 / 0.2693, abs=1e-3) and float(hi) == pytest.approx(
        0.2136 / 0.2693, abs=1e-3
    )
    res2 = SimpleNamespace(calibration=dict(cal), message=text, steps=[])
    against_encoders(res2, "settled straight rows of the ground truth")  # no encoders: the radius it is
    assert res2.calibration["text"] == text


def test_the_speed_scale_is_restated_as_the_final_model_has_it():
    """Asked first, the scale takes what a lag named after it explains (DRIVE Warthog gravel: 0.719 asked
    first, 1.007 in the final model): the finding is restated from the final fit and its folds, and an
    interval that holds 1 is no finding."""
    from types import SimpleNamespace

    from skidbench.benchmark.discovery.checks.scale import _calibration, restate_scale
    from skidbench.models.augmented.effects import SPEED_SCALE

    def run_with(final_ks):
        cal = _calibration(0.2658, -0.281, -0.35, -0.21)
        steps = [{"kind": "calibration", "effect": SPEED_SCALE, "explanation": cal["text"]},
                 {"kind": "catalogue", "effect": "actuator_lag"}]  # fmt: skip
        return SimpleNamespace(
            calibration=cal, steps=steps, base_info={}, terrain="gravel", say=lambda m: None,
            state=SimpleNamespace(params={SPEED_SCALE: np.array([np.mean(final_ks)])}),
            cur=SimpleNamespace(fold_params=[{SPEED_SCALE: [k]} for k in final_ks]),
        )  # fmt: skip

    run = run_with([0.02, -0.01, 0.0, 0.015, 0.012])
    restate_scale(run)
    assert run.calibration is None and not run.base_info["speed_scale_check"]["final"]["holds"]
    assert "no speed scale once actuator_lag" in run.steps[0]["explanation"]
    assert "0.719 when asked first" in run.steps[0]["explanation"]
    run = run_with([-0.10, -0.09, -0.095, -0.1, -0.09])
    restate_scale(run)
    assert run.calibration["holds"] and run.calibration["speed_scale"] == pytest.approx(0.905)
    assert run.calibration["first_question"]["speed_scale"] == pytest.approx(0.719)
