"""The input protocol (pipeline/core/protocol.py): a model sees only its inputs, every model the same ones,
and
the protocols' round trips."""

from __future__ import annotations

import sys
import types
from importlib.metadata import EntryPoint

import numpy as np
import pandas as pd
import pytest
from _bench_data import JACKAL, compose, sequence_table, write_splits

from skidbench.benchmark.evaluate import evaluation as ev
from skidbench.benchmark.evaluate.app import benchmark as run_benchmark
from skidbench.models.base import KinematicModel, ModelError
from skidbench.models.fitting.fit import check_inputs
from skidbench.models.kinematic.ideal import IdealDifferentialDrive
from skidbench.models.kinematic.linear import ExtendedDifferentialDrive
from skidbench.models.registry import plugins as registry
from skidbench.pipeline.calibrate.wheel_response import WheelResponse, wheel_response
from skidbench.pipeline.core.protocol import (
    INPUT_COLUMNS,
    PROTOCOLS,
    TARGET_COLUMNS,
    ProtocolError,
    check_protocol,
    fit_table,
    model_inputs,
)
from skidbench.pipeline.core.schema import concat_sequences

DS = "sim-mini"
SEEN: dict[str, list[pd.DataFrame]] = {}


class Cheat(KinematicModel):
    """A plugin that returns the table's own ground truth: what the protocol must make impossible."""

    name = "cheat"
    version = "0.1"

    def fit(self, table):
        self.fit_loss_ = 0.0
        return self

    def predict(self, table):
        return table[["vx", "vy", "wz"]].to_numpy(float)


class Spy(KinematicModel):
    """A plugin that records what it is given and predicts the ideal kinematics."""

    name = "spy"
    version = "0.1"

    def fit(self, table):
        SEEN.setdefault("spy.fit", []).append(table.copy())
        return self

    def predict(self, table):
        SEEN.setdefault("spy", []).append(table.copy())
        v, w = self.robot.twist_from_wheel_rates(table["cmd_wl"].to_numpy(), table["cmd_wr"].to_numpy())
        return np.column_stack([v, 0 * v, w])


def _spying(cls):
    """``cls`` with a predict that records its table under its name."""

    class Spied(cls):
        def predict(self, table):
            SEEN.setdefault(cls.name, []).append(table.copy())
            return super().predict(table)

    Spied.__name__ = cls.__name__
    return Spied


@pytest.fixture
def plugins(monkeypatch):
    mod = types.ModuleType("protocol_plugins")
    mod.Cheat, mod.Spy = Cheat, Spy
    mod.Ideal, mod.Edd = _spying(IdealDifferentialDrive), _spying(ExtendedDifferentialDrive)
    monkeypatch.setitem(sys.modules, "protocol_plugins", mod)
    extra = {
        "cheat": EntryPoint("cheat", "protocol_plugins:Cheat", registry.GROUP),
        "spy": EntryPoint("spy", "protocol_plugins:Spy", registry.GROUP),
        "ideal": EntryPoint("ideal", "protocol_plugins:Ideal", registry.GROUP),
        "edd": EntryPoint("edd", "protocol_plugins:Edd", registry.GROUP),
    }
    real = registry.entry_points
    eps = [e for e in real(group=registry.GROUP) if e.name not in extra] + list(extra.values())
    monkeypatch.setattr(registry, "entry_points", lambda group: eps)
    monkeypatch.setattr(ev, "installed_models", lambda: {e.name: e for e in eps})
    SEEN.clear()
    yield
    SEEN.clear()


def _bench(tmp_path, inputs: str, models: str):
    write_splits(tmp_path / DS, terrains=("tile",))
    cfg = compose(
        "evaluate",
        tmp_path,
        [f"models=[{models}]", "horizons=[2.0]", f"inputs={inputs}", "calibrate.use=false"],
    )
    return run_benchmark(cfg, log_figures=False)


@pytest.mark.parametrize("inputs", ["commanded", "measured"])
def test_a_model_returning_ground_truth_cannot_see_it(tmp_path, plugins, inputs):
    res = _bench(tmp_path, inputs, "cheat,ideal")
    by = {c.model: c for c in res.children}
    assert by["cheat"].status == "FAILED"
    assert "predict failed: KeyError" in by["cheat"].reason and "vx" in by["cheat"].reason
    assert by["ideal"].status == "FINISHED"
    assert all(c.inputs == inputs for c in res.children)


def test_every_model_gets_the_same_input_columns_and_values(tmp_path, plugins):
    res = _bench(tmp_path, "measured", "ideal,edd,spy")
    assert [c.status for c in res.children] == ["FINISHED"] * 3
    # two built-in models of different kinds and a plugin: the last two calls are the CV and LD predictions
    # (a built-in may also predict its own training table while fitting)
    for a, b, c in zip(SEEN["ideal"][-2:], SEEN["edd"][-2:], SEEN["spy"][-2:], strict=True):
        assert tuple(a.columns) == tuple(b.columns) == tuple(c.columns) == INPUT_COLUMNS
        pd.testing.assert_frame_equal(a, b)
        pd.testing.assert_frame_equal(a, c)
    fit = SEEN["spy.fit"][0]  # fit: the same inputs, plus the targets, never the encoders
    assert set(fit.columns) == set(INPUT_COLUMNS) | set(TARGET_COLUMNS)


def test_a_model_that_requires_a_non_input_column_is_refused():
    class NeedsEncoders(Spy):
        required_columns = ("cmd_wl", "enc_wl")

    with pytest.raises(ModelError, match=r"enc_wl"):
        check_inputs(NeedsEncoders(JACKAL), "needs_encoders")


def _two_sequences():
    a, b = sequence_table(0, 8.0), sequence_table(1, 6.0)
    return concat_sequences([(a, {"sequence": "a"}), (b, {"sequence": "b"})])


def test_predict_table_holds_only_the_input_columns():
    table = _two_sequences()
    for p in PROTOCOLS:
        got = model_inputs(table, p, JACKAL, WheelResponse(delay_s=0.1, tau_s=0.2, tau_d_s=0.2))
        assert tuple(got.columns) == INPUT_COLUMNS and len(got) == len(table)
        assert not {"x", "y", "yaw", "vx", "vy", "wz", "valid", "enc_wl", "enc_wr"} & set(got.columns)


def test_measured_with_perfect_encoders_equals_commanded():
    """Wheels that follow their commands exactly (encoders = commands): on linear ramps, which both the
    split's central differences and the Savitzky-Golay derivative differentiate exactly, the measured
    inputs are the commanded ones, in every column; the derivative never crosses a sequence boundary."""
    frames = []
    for k, (slope_l, slope_r) in enumerate([(0.5, -0.3), (-1.0, 2.0)]):
        t = np.arange(0.0, 5.0, 1 / 30)
        wl, wr = 1.0 + slope_l * t, -2.0 + slope_r * t
        v, w = JACKAL.twist_from_wheel_rates(wl, wr)
        frames.append(
            (pd.DataFrame({"t": t, "cmd_v": v, "cmd_w": w, "cmd_wl": wl, "cmd_wr": wr,
                           "cmd_dwl": np.gradient(wl, t), "cmd_dwr": np.gradient(wr, t),
                           "enc_wl": wl, "enc_wr": wr}), {"sequence": f"s{k}"})
        )  # fmt: skip
    table = concat_sequences(frames)
    cmd = model_inputs(table, "commanded", JACKAL)
    meas = model_inputs(table, "measured", JACKAL)
    pd.testing.assert_frame_equal(cmd, meas, check_exact=False, atol=1e-9, rtol=0)


def test_measured_interpolates_a_missing_reading_and_refuses_a_split_without_encoders():
    table = _two_sequences()
    gap = table.copy()
    gap.loc[10, "enc_wl"] = np.nan
    got = model_inputs(gap, "measured", JACKAL)
    assert np.isfinite(got["cmd_wl"]).all()
    assert got["cmd_wl"][10] == pytest.approx((table["enc_wl"][9] + table["enc_wl"][11]) / 2, rel=1e-3)
    none = table.assign(enc_wl=np.where(table["sequence"] == "b", np.nan, table["enc_wl"]))
    with pytest.raises(ProtocolError, match=r"no wheel encoders .* \['b'\]"):
        model_inputs(none, "measured", JACKAL)


def test_response_inputs_are_the_wheel_response_and_its_kinematics():
    table = _two_sequences()
    resp = WheelResponse(delay_s=0.1, tau_s=0.25, tau_d_s=0.25)
    got = model_inputs(table, "response", JACKAL, resp)
    w = wheel_response(table, resp)
    np.testing.assert_allclose(got[["cmd_wl", "cmd_wr", "cmd_dwl", "cmd_dwr"]].to_numpy(), w)
    v, om = JACKAL.twist_from_wheel_rates(w[:, 0], w[:, 1])
    np.testing.assert_allclose(got["cmd_v"], v)
    np.testing.assert_allclose(got["cmd_w"], om)
    # each sequence restarts from its own first command (nothing carried over the boundary)
    first_b = int(np.flatnonzero(table["sequence"].to_numpy() == "b")[0])
    assert got["cmd_wl"][first_b] == pytest.approx(table["cmd_wl"][first_b])
    with pytest.raises(ProtocolError, match="calibrate"):
        model_inputs(table, "response", JACKAL, None)


def test_fit_table_keeps_targets_and_replaces_inputs():
    table = _two_sequences()
    resp = WheelResponse(delay_s=0.2, tau_s=0.3, tau_d_s=0.3)
    got = fit_table(table, "response", JACKAL, resp)
    assert set(got.columns) == set(INPUT_COLUMNS) | set(TARGET_COLUMNS)
    np.testing.assert_array_equal(got["vx"], table["vx"])
    assert not np.allclose(got["cmd_wl"], table["cmd_wl"])


def test_unknown_protocol_is_one_line():
    with pytest.raises(ProtocolError, match=r"inputs='oracle': unknown input protocol; expected one of"):
        check_protocol("oracle")


def test_measured_skips_a_split_without_encoders_in_one_line_and_a_dataset_without_any(tmp_path, plugins):
    from skidbench.benchmark.evaluate.evaluation import ProtocolSkipped
    from skidbench.pipeline.core.schema import read_split, write_split

    write_splits(tmp_path / DS, terrains=("tile",))
    cv = next((tmp_path / DS / "splits" / "tile" / "cv").glob("*.parquet"))
    df, meta = read_split(cv)
    write_split(df.assign(enc_wl=np.nan, enc_wr=np.nan), cv, meta)
    over = ["models=[ideal]", "horizons=[2.0]", "inputs=measured", "calibrate.use=false"]
    res = run_benchmark(compose("evaluate", tmp_path, over), log_figures=False)
    assert len(res.skipped) == 1 and "tile/cv: no wheel encoders in tile_cv_00" in res.skipped[0]
    assert "split skipped under this protocol" in res.skipped[0]
    metrics = res.children[0].metrics
    assert "ld_2s_trans_rmsre_pct" in metrics and "cv_2s_trans_rmsre_pct" not in metrics
    # no encoders in Train: the protocol is skipped for the whole dataset (not a failed run)
    for p in (tmp_path / DS / "splits" / "tile" / "train").glob("*.parquet"):
        df, meta = read_split(p)
        write_split(df.assign(enc_wl=np.nan, enc_wr=np.nan), p, meta)
    with pytest.raises(ProtocolSkipped, match=r"inputs=measured: nothing to evaluate .* no wheel encoders"):
        run_benchmark(compose("evaluate", tmp_path, over), log_figures=False)
