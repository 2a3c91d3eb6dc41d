"""The general wheel response (pipeline/calibrate/wheel_response.py, the calibration's): its recursion
against the
definition, its reduction to the delay + lag model, identification round trips on responses simulated
from synthetic commands, the structure choice on held-out Train blocks, its uncertainty, and the DRIVE
Warthog's encoders."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from skidbench.pipeline.calibrate import actuator, wheel_response
from skidbench.pipeline.calibrate.wheel_response import WheelResponse

RATE = 30.0


def _commands(n=3600, seed=0, hold_s=2.0, peak=16.0):
    """Held wheel commands, a new random level pair every ``hold_s`` (straight runs, turns and spins of
    every size up to ``peak`` rad/s), on a ``RATE`` Hz clock."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / RATE
    k = int(hold_s * RATE)
    S = rng.uniform(-peak, peak, size=n // k + 1) * rng.uniform(0, 1, size=n // k + 1)
    D = rng.uniform(-peak, peak, size=n // k + 1) * rng.uniform(0, 1, size=n // k + 1)
    wl, wr = np.repeat(S - D, k)[:n], np.repeat(S + D, k)[:n]
    return pd.DataFrame(
        {"t": t, "cmd_v": 0.3 * (wl + wr) / 2, "cmd_w": 0.3 * (wr - wl) / 0.5, "cmd_wl": wl, "cmd_wr": wr,
         "cmd_dwl": np.gradient(wl, t), "cmd_dwr": np.gradient(wr, t)}
    )  # fmt: skip


def _reference(table: pd.DataFrame, r: WheelResponse) -> np.ndarray:
    """(T, 2) the response by its definition, row by row (one sequence, a dead time on the clock's grid):
    the command of ``delay + one step`` earlier, each mode shaped (gain, saturation), the wheels clipped,
    then per mode y_k = y_k-1 + clip(alpha (u_k - y_k-1), -accel dt, accel dt)."""
    t = table["t"].to_numpy(float)
    dt = t[1] - t[0]
    cmd = table[["cmd_wl", "cmd_wr"]].to_numpy(float)
    shift = int(round(r.delay_s / dt)) + 1
    out = np.empty((len(t), 2))
    y = None
    for i in range(len(t)):
        wl, wr = cmd[max(i - shift, 0)]
        S, D = r.gain_s * (wl + wr) / 2, r.gain_d * (wr - wl) / 2
        S = np.clip(S, -r.sat_s, r.sat_s) if r.sat_s > 0 else S
        D = np.clip(D, -r.sat_d, r.sat_d) if r.sat_d > 0 else D
        if r.wheel_max > 0:
            wl, wr = np.clip(S - D, -r.wheel_max, r.wheel_max), np.clip(S + D, -r.wheel_max, r.wheel_max)
            S, D = (wl + wr) / 2, (wr - wl) / 2
        u = np.array([S, D])
        if y is None:
            y = u.copy()
        else:
            for j, (tau, acc) in enumerate(((r.tau_s, r.accel_s), (r.tau_d_s, r.accel_d))):
                step = (1 - np.exp(-dt / tau)) * (u[j] - y[j])
                y[j] += np.clip(step, -acc * dt, acc * dt) if acc > 0 else step
        out[i] = y[0] - y[1], y[0] + y[1]
    return out


TRUTH = WheelResponse(
    delay_s=0.2,
    tau_s=0.25,
    tau_d_s=0.6,
    accel_s=9.0,
    accel_d=4.0,
    gain_s=0.95,
    gain_d=0.8,
    sat_d=6.0,
    wheel_max=12.0,
)


def test_response_follows_its_definition():
    """The closed form per run of a held command (ramp, then geometric decay) is the row-by-row recursion,
    and its rates are the clipped lag's (u - y) / tau."""
    table = _commands(n=1200, seed=3)
    got = wheel_response.wheel_response(table, TRUTH)
    assert got[:, :2] == pytest.approx(_reference(table, TRUTH), abs=1e-9)
    assert np.abs((got[:, 2] + got[:, 3]) / 2).max() <= TRUTH.accel_s + 1e-9
    assert np.abs((got[:, 3] - got[:, 2]) / 2).max() <= TRUTH.accel_d + 1e-9
    assert np.abs(got[:, :2]).max() <= TRUTH.wheel_max + 1e-9


def test_response_with_a_new_command_every_row_takes_the_loop_and_follows_the_definition():
    """A command that changes at every row (or a non-uniform clock) goes through the plain loop."""
    rng = np.random.default_rng(4)
    t = np.cumsum(rng.uniform(0.02, 0.05, size=400))
    u = rng.uniform(-10, 10, size=(400, 2))
    tau, acc = np.array([0.3, 0.5]), np.array([6.0, 0.0])
    ref = np.empty_like(u)
    ref[0] = u[0]
    for k in range(1, len(t)):
        dt = t[k] - t[k - 1]
        step = (1 - np.exp(-dt / tau)) * (u[k] - ref[k - 1])
        ref[k] = ref[k - 1] + np.where(acc > 0, np.clip(step, -acc * dt, acc * dt), step)
    assert wheel_response._slew_lag(t, u, tau, acc) == pytest.approx(ref, abs=1e-12)


def test_unit_gain_and_no_limits_is_exactly_the_delay_lag_model():
    table = _commands(n=1500, seed=1)
    d = 6 / RATE
    lin = WheelResponse(delay_s=d, tau_s=0.45, tau_d_s=0.45)
    assert lin.is_delay_lag
    ref = actuator.apply(table, d, 0.45)[["cmd_wl", "cmd_wr", "cmd_dwl", "cmd_dwr"]].to_numpy()
    assert wheel_response.wheel_response(table, lin) == pytest.approx(ref, abs=1e-9)
    # and a model saved by friction 1.6 (delay and lag only) reads back as that model
    old = WheelResponse.from_params({"actuator_delay_s": d, "actuator_tau_s": 0.45})
    assert old == lin
    assert wheel_response.respond(table, WheelResponse()) is table


def test_identification_recovers_injected_gain_saturation_slew_delay_and_lag():
    table = _commands(n=3600, seed=0)
    enc = _reference(table, TRUTH)
    table = table.assign(enc_wl=enc[:, 0], enc_wr=enc[:, 1])
    fit = wheel_response.identify_response(table, ("delay+lag+slew+gain+modes",), max_nfev=200)
    r = fit.response
    assert fit.rmse_response < 0.01 * fit.rmse_command
    assert r.delay_s == pytest.approx(TRUTH.delay_s, abs=0.5 / RATE)
    for name in ("tau_s", "tau_d_s", "accel_s", "accel_d", "gain_s", "gain_d", "sat_d", "wheel_max"):
        assert getattr(r, name) == pytest.approx(getattr(TRUTH, name), rel=0.05), name
    # no sum-mode saturation was injected: any identified one lies beyond every sum the data commanded
    peak_s = np.abs(TRUTH.gain_s * (table["cmd_wl"] + table["cmd_wr"]) / 2).max()
    assert r.sat_s == 0 or r.sat_s >= 0.99 * min(peak_s, TRUTH.wheel_max)


def test_structure_choice_keeps_the_delay_lag_model_on_data_it_generated():
    """Encoders from a dead time + lag (and 0.1 rad/s of noise): the richer structures fit no better on
    held-out blocks, so the simplest stays; on data with limits the limits are chosen."""
    table = _commands(n=3600, seed=2, peak=8.0)
    lin = WheelResponse(delay_s=0.3, tau_s=0.4, tau_d_s=0.4)
    noise = np.random.default_rng(5).normal(0, 0.1, size=(len(table), 2))
    enc = _reference(table, lin) + noise
    fit = wheel_response.identify_response(table.assign(enc_wl=enc[:, 0], enc_wr=enc[:, 1]))
    assert fit.structure == "delay+lag"
    assert fit.response.delay_s == pytest.approx(0.3, abs=0.5 / RATE)
    assert fit.response.tau_s == pytest.approx(0.4, rel=0.05)
    assert set(fit.candidates) == set(wheel_response.CANDIDATES)
    limited = _commands(n=3600, seed=2)
    enc = _reference(limited, TRUTH) + noise
    fit = wheel_response.identify_response(limited.assign(enc_wl=enc[:, 0], enc_wr=enc[:, 1]))
    assert fit.structure != "delay+lag"
    assert fit.candidates[fit.structure]["heldout_rmse"] < 0.5 * fit.candidates["delay+lag"]["heldout_rmse"]


def test_friction_no_longer_takes_an_actuator_option_nor_keeps_an_old_fits_response():
    """1.9: the wheel response is a calibration shared by every model (inputs=response), not friction's."""
    from skidbench.models.base import ModelError
    from skidbench.models.friction.model import FrictionBased
    from skidbench.pipeline.core.robot import load_robot

    husky = load_robot("husky")
    with pytest.raises(ModelError, match="options.actuator was removed"):
        FrictionBased(husky, actuator="auto")
    old = FrictionBased(husky, {"mu_r": 0.05, "actuator_delay_s": 0.3, "actuator_tau_s": 0.4})
    assert set(old.params) == {"mu_r", "mu_x", "mu_y", "lambda", "C"}
    table = _commands(n=300, seed=6)
    wl, wr, dwl, dwr = old.inputs(table)  # the paper's: the table's inputs as they are
    np.testing.assert_array_equal(dwl, table["cmd_dwl"].to_numpy())


def test_identified_response_reports_per_structure_heldout_rmse_and_parameter_uncertainty():
    table = _commands(n=2400, seed=7)
    truth = WheelResponse(delay_s=0.2, tau_s=0.35, tau_d_s=0.35)
    enc = _reference(table, truth) + np.random.default_rng(1).normal(0, 0.05, (len(table), 2))
    fit = wheel_response.identify_response(table.assign(enc_wl=enc[:, 0], enc_wr=enc[:, 1]))
    doc = fit.to_dict()
    assert doc["structure"] == "delay+lag" and doc["heldout_rmse"] > 0
    se = doc["param_se"]
    assert set(se) == {"delay_s", "tau_s"} and all(np.isfinite(v) and v >= 0 for v in se.values())
    # the block jackknife's error bars cover the injected values (within 4 standard errors + a step)
    assert abs(fit.response.delay_s - 0.2) <= 4 * se["delay_s"] + 1 / RATE
    assert abs(fit.response.tau_s - 0.35) <= 4 * se["tau_s"] + 0.02


@pytest.mark.slow
def test_drive_warthog_response_beats_the_delay_lag_model(shared_real, tmp_path):
    """Real data: on the first 200 s of the DRIVE Warthog's Train split the identified response's encoder
    RMSE is below the delay + lag model's (its wheels saturate and turn at a fraction of the command)."""
    from drive_data import drive_splits, split_table

    splits = drive_splits(shared_real / "drive", tmp_path, "warthog", "source.file=warthog_windows.parquet")
    fit = wheel_response.identify_response(split_table(splits, rows=6000))
    lag = fit.candidates["delay+lag"]
    assert fit.structure != "delay+lag"
    assert fit.rmse_response < 0.8 * lag["train_rmse"] < fit.rmse_command
    assert fit.response.wheel_max > 0  # the saturation the encoders show (no max_wheel_rate in the config)
