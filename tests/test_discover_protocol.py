"""Discovery under an input protocol: on data whose wheels lag their commands, ``actuator_lag`` is the
missing effect under ``commanded``; under ``response`` (the commands through the wheel response identified
from the encoders, the calibration's implementation) there is nothing left for it to explain."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.signal import lfilter

sys.path.insert(0, str(Path(__file__).resolve().parent))
import discover_data as dd  # noqa: E402

from skidbench.benchmark.discovery.discover import discover_terrain  # noqa: E402
from skidbench.benchmark.discovery.pool import prepare_pool  # noqa: E402
from skidbench.models.augmented.fit import DiscoverSettings, build_pool  # noqa: E402
from skidbench.pipeline.calibrate.wheel_response import identify_response  # noqa: E402
from skidbench.pipeline.core.schema import concat_sequences  # noqa: E402

TAU = dd.DEFAULT_SIZES["actuator_lag"]


def _with_encoders(cmd: pd.DataFrame, loc: pd.DataFrame) -> pd.DataFrame:
    """The split table of a sequence of tests/discover_data.py with its wheels' encoders: the motors' lag
    as the generator applies it (180 Hz clock, 45 Hz commands held), sampled on the split's clock."""
    table = dd.to_split(cmd, loc)
    dt = 1.0 / 180.0
    t = np.arange(cmd.t.iloc[0], cmd.t.iloc[-1] + dt / 2, dt)
    idx = np.clip(np.searchsorted(cmd.t.to_numpy(), t + 1e-9, side="right") - 1, 0, len(cmd) - 1)
    v, w = cmd.v.to_numpy()[idx], cmd.w.to_numpy()[idx]
    a = 1 - np.exp(-dt / TAU)
    wheels = []
    for u in ((v - w * dd.TRACK / 2) / dd.R_WHEEL, (v + w * dd.TRACK / 2) / dd.R_WHEEL):
        wheels.append(lfilter([a], [1, a - 1], u, zi=[(1 - a) * u[0]])[0])
    t_split = table["t"].to_numpy() + max(cmd.t.iloc[0], loc.t.iloc[0])
    k = np.clip(np.searchsorted(t, t_split + 1e-9, side="right") - 1, 0, len(t) - 1)
    out = table.assign(enc_wl=wheels[0][k], enc_wr=wheels[1][k])
    out.attrs = dict(table.attrs)  # the hold's timing, as the split file's metadata has it
    return out


@pytest.mark.slow
def test_actuator_lag_is_named_under_commanded_and_not_again_under_response(jackal):
    from skidbench.models.registry.specs import get_model_class

    edd = get_model_class("edd")
    raw = dd.dataset(dd.hidden(["actuator_lag"]), 104, n_train=8, duration=36.0)
    tables = []
    for i, (c, lo) in enumerate(raw["train"]):
        table = _with_encoders(c, lo)
        tables.append((table, dd.split_meta(table, f"train_{i:02d}")))
    s = DiscoverSettings()
    pool = build_pool(tables, s)

    cmd = discover_terrain(
        prepare_pool(pool, "commanded", jackal), lambda: edd(jackal), jackal, s, "tile", "edd"
    )
    assert cmd.effects[:1] == ["actuator_lag"], cmd.effects

    fit = identify_response(concat_sequences(tables))
    assert fit.response.tau_s == pytest.approx(TAU, rel=0.3)  # the one implementation finds the lag
    resp = prepare_pool(pool, "response", jackal, fit.response)
    res = discover_terrain(resp, lambda: edd(jackal), jackal, s, "tile", "edd")
    assert "actuator_lag" not in res.effects, res.effects
