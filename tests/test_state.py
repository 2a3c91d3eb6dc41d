"""The ``state`` input protocol (models/rollout.py, benchmark/scoring/rollout.py) and the first-order
relaxation model (models/dynamics/relaxation.py): nothing after t0 reaches a model, a first-order fit
recovers its time constants, the true dynamics from the true state score at the floor, the
aggressiveness strata."""

from __future__ import annotations

import dataclasses
import sys
import types
from importlib.metadata import EntryPoint

import numpy as np
import pandas as pd
import pytest
from _bench_data import JACKAL, compose, write_splits

from skidbench.benchmark.evaluate import evaluation as ev
from skidbench.benchmark.evaluate.app import benchmark as run_benchmark
from skidbench.benchmark.scoring import aggressiveness as ag
from skidbench.benchmark.scoring.horizon import HorizonConfig, rmsre
from skidbench.benchmark.scoring.rollout import model_rollout, state_windows
from skidbench.benchmark.scoring.settings import StateSettings
from skidbench.models import rollout as st
from skidbench.models.base import KinematicModel
from skidbench.models.dynamics.relaxation import FirstOrderRelaxation, relax
from skidbench.models.dynamics.state_ridge import StateRidge
from skidbench.models.kinematic.ideal import IdealDifferentialDrive
from skidbench.models.registry import plugins as registry
from skidbench.pipeline.core.geometry import integrate_body_velocity, step_velocities

SEEN: list[tuple] = []


def first_order_table(
    tau=(0.3, 0.05, 0.6), seed=0, duration_s=40.0, rate_hz=30.0, steps=True
) -> pd.DataFrame:
    """A split-like table whose body velocity follows the ideal kinematics of its commands through the
    first-order law of models/dynamics/relaxation.py with time constants ``tau`` (vx, vy, wz); poses
    integrated from it with the horizon's own steps. Commands: ``steps`` every 1.5 s (speed and turn rate
    at random), else smooth (two sines each, random phases)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    k = (t // 1.5).astype(int)
    v, w = rng.uniform(-0.2, 1.5, k.max() + 1)[k], rng.uniform(-2.0, 2.0, k.max() + 1)[k]
    if not steps:
        ph = rng.uniform(0, 2 * np.pi, 4)
        v = 0.7 + 0.5 * np.sin(1.3 * t + ph[0]) + 0.3 * np.sin(3.1 * t + ph[1])
        w = 1.2 * np.sin(0.9 * t + ph[2]) + 0.6 * np.sin(2.3 * t + ph[3])
    wl, wr = JACKAL.wheel_rates_from_twist(v, w)
    u = np.column_stack([v, 0 * v, w])
    vel = relax(u[None], u[0][None], t[None], np.asarray(tau))[0]
    pose = integrate_body_velocity(np.zeros(3), step_velocities(vel), np.diff(t))
    return pd.DataFrame({"t": t, "cmd_v": v, "cmd_w": w, "cmd_wl": wl, "cmd_wr": wr,
                         "cmd_dwl": np.gradient(wl, t), "cmd_dwr": np.gradient(wr, t), "enc_wl": wl,
                         "enc_wr": wr, "x": pose[:, 0], "y": pose[:, 1], "yaw": pose[:, 2], "vx": vel[:, 0],
                         "vy": vel[:, 1], "wz": vel[:, 2], "valid": np.ones(len(t), bool)})  # fmt: skip


def test_causal_velocity_is_exact_on_a_twist_linear_in_time_and_reads_nothing_after_t0():
    t = np.arange(0.0, 5.0, 1 / 30)
    true = np.column_stack([0.5 + 0.2 * t, 0.1 - 0.05 * t, 0.4 - 0.3 * t])
    pose = integrate_body_velocity(np.array([1.0, -2.0, 0.3]), step_velocities(true), np.diff(t))
    est = st.causal_body_velocity(t, pose, 1.0)
    m = st.history_steps(1 / 30, 1.0)
    assert np.isnan(est[:m]).all()
    np.testing.assert_allclose(est[m:], true[m:], atol=1e-9)
    later = pose.copy()
    later[100:] += 5.0  # the future changes: nothing at or before sample 99 does
    np.testing.assert_array_equal(st.causal_body_velocity(t, later, 1.0)[:100], est[:100])


class Stamps(KinematicModel):
    """A plugin that inspects what each rollout is given: times, arrays, their owners."""

    name = "stamps"
    version = "0.1"

    def fit(self, table):
        self.fit_loss_ = 0.0
        return self

    def predict(self, table):
        return np.zeros((len(table), 3))

    def rollout(self, history, commands):
        assert (history.t <= 0).all() and np.allclose(history.t[:, -1], 0.0)
        assert (commands.t >= 0).all() and np.allclose(commands.t[:, 0], 0.0)
        assert np.allclose(history.pose[:, -1], 0.0)
        arrays = [
            history.t,
            history.pose,
            history.velocity,
            commands.t,
            *history.inputs.values(),
            *commands.inputs.values(),
            *([history.encoders] if history.encoders is not None else []),
        ]
        assert all(a.base is None or a.base.base is None for a in arrays)  # fresh copies, not views
        assert set(commands.inputs) == set(history.inputs) == set(st.STATE_INPUTS)
        SEEN.append((history.t.shape, commands.t.shape))
        return np.repeat(history.velocity[:, None, :], commands.t.shape[1], axis=1)


class Cheat(Stamps):
    """A plugin that asks the window for its future ground truth."""

    name = "cheat"

    def rollout(self, history, commands):
        return np.stack([commands.inputs[c] for c in ("vx", "vy", "wz")], axis=-1)


@pytest.fixture
def plugins(monkeypatch):
    mod = types.ModuleType("state_plugins")
    mod.Stamps, mod.Cheat = Stamps, Cheat
    monkeypatch.setitem(sys.modules, "state_plugins", mod)
    extra = {n: EntryPoint(n, f"state_plugins:{c}", registry.GROUP) for n, c in
             (("stamps", "Stamps"), ("cheat", "Cheat"))}  # fmt: skip
    eps = [e for e in registry.entry_points(group=registry.GROUP) if e.name not in extra] + list(
        extra.values()
    )
    monkeypatch.setattr(registry, "entry_points", lambda group: eps)
    monkeypatch.setattr(ev, "installed_models", lambda: {e.name: e for e in eps})
    SEEN.clear()
    yield
    SEEN.clear()


def test_nothing_after_t0_reaches_a_plugin_and_a_cheat_fails(tmp_path, plugins):
    write_splits(tmp_path / "sim-mini", terrains=("tile",))
    cfg = compose("evaluate", tmp_path, ["models=[stamps,cheat]", "horizons=[2.0,1.0]", "inputs=state",
                                         "calibrate.use=false", "state.history_s=0.5"])  # fmt: skip
    res = run_benchmark(cfg, log_figures=False)
    by = {c.model: c for c in res.children}
    assert by["stamps"].status == "FINISHED", by["stamps"].reason
    assert by["cheat"].status == "FAILED" and "KeyError" in by["cheat"].reason
    assert all(c.inputs == "state" for c in res.children)
    assert {h for h, _ in SEEN} == {(h[0], 16) for h, _ in SEEN} and {c[1] for _, c in SEEN} == {61}
    # every horizon on the same windows, each metric with its interval
    m = by["stamps"].metrics
    assert m["cv_2s_trans_windows"] > 0 and m["cv_1s_endpos_windows"] == m["cv_2s_endpos_windows"]
    assert m["cv_2s_trans_rmsre_pct_ci_lo"] <= m["cv_2s_trans_rmsre_pct"] <= m["cv_2s_trans_rmsre_pct_ci_hi"]


def test_first_order_fit_recovers_its_time_constants():
    table = pd.concat(
        [first_order_table(seed=s).assign(sequence=str(s)) for s in range(2)], ignore_index=True
    )
    # a short history: the quadratic estimate of the initial velocity lags the step responses less
    model = FirstOrderRelaxation(JACKAL, base="ideal", history_s=0.3).fit(table)
    tau = model.params["tau"]
    assert tau["vx"] == pytest.approx(0.3, rel=0.03) and tau["wz"] == pytest.approx(0.6, rel=0.03)
    assert FirstOrderRelaxation.from_json(JACKAL, model.to_json()).tau() == pytest.approx(model.tau())


def test_true_dynamics_from_the_true_state_score_at_the_floor():
    table = first_order_table(seed=3, steps=False)
    fv = table[["vx", "vy", "wz"]].to_numpy(float)  # the table's exact velocities (generated)
    base = IdealDifferentialDrive(JACKAL).fit(table)
    true = FirstOrderRelaxation(
        JACKAL, {"base_model": base.to_json(), "tau": {"vx": 0.3, "vy": 0.05, "wz": 0.6}}
    )
    hcfg, settings = HorizonConfig(4.0), StateSettings(history_s=0.3)

    def score(rollout) -> float:
        return rmsre(state_windows(["s"], [table], rollout, [4.0], hcfg, settings, JACKAL)["rel_trans"])

    floor = score(lambda b: fv[b.ahead])
    given_truth = score(
        lambda b: true.rollout(dataclasses.replace(b.history, velocity=fv[b.starts]), b.commands)
    )
    estimated = score(model_rollout(true, [true.predict(table)]))
    kinematic = score(model_rollout(base, [base.predict(table)]))
    assert floor < 1e-9 and given_truth < 1e-9  # the poses are the integral of these velocities
    assert estimated < 0.001 < 0.05 < kinematic  # from the state the protocol estimates: within 0.1 %


def test_aggressiveness_strata_come_out_as_constructed():
    t = np.arange(0.0, 90.0, 0.1)
    calm, turning = t < 30, (t >= 30) & (t < 60)
    v = np.where(calm, 1.0, np.where(turning, 1.0, 1.0 + 0.5 * np.sign(np.sin(2 * np.pi * t / 2.0))))
    w = np.where(turning, 1.0, 0.0)
    table = pd.DataFrame({"t": t, "cmd_v": v, "cmd_w": w})
    acc = ag.sample_acceleration(table, 0.2)
    starts = np.arange(5, len(t) - 10, 20)  # 1 s windows every 2 s, none across a change of segment
    a = ag.window_aggressiveness(acc, starts, 10)
    np.testing.assert_allclose(a[t[starts] < 30], 0.0, atol=1e-12)  # straight at constant speed
    np.testing.assert_allclose(a[(t[starts] > 30) & (t[starts] < 60)], 1.0, atol=1e-12)  # v w = 1 m/s^2
    assert (a[t[starts] > 60] > 1.5).all()  # a speed step of 1 m/s in every window
    edges = ag.tercile_edges([a])
    got = ag.strata(a, edges)
    expect = np.where(t[starts] < 30, "low", np.where(t[starts] < 60, "mid", "high"))
    assert (got == expect).all()


def test_learned_dynamics_beats_its_base_from_the_state_and_its_seeds_differ():
    train = pd.concat(
        [first_order_table(seed=s).assign(sequence=str(s)) for s in range(2)], ignore_index=True
    )
    test = first_order_table(seed=7)
    hcfg, settings = HorizonConfig(2.0), StateSettings()
    scores, coefs = {}, []
    for seed in (0, 1):
        model = StateRidge(JACKAL, base="ideal", fit_horizon_s=2.0, seed=seed).fit(train)
        w = state_windows(
            ["s"], [test], model_rollout(model, [model.predict(test)]), [2.0], hcfg, settings, JACKAL
        )
        scores[seed] = rmsre(w["rel_trans"])
        coefs.append(model.arrays["coef"])
    base = IdealDifferentialDrive(JACKAL).fit(train)
    w = state_windows(["s"], [test], model_rollout(base, [base.predict(test)]), [2.0], hcfg, settings, JACKAL)
    assert max(scores.values()) < 0.5 * rmsre(w["rel_trans"])
    assert not np.allclose(coefs[0], coefs[1])  # another seed draws other Train windows


def test_the_state_protocol_default_history_is_the_models_default():
    from skidbench.models.rollout import HISTORY_S

    assert StateSettings().history_s == HISTORY_S
