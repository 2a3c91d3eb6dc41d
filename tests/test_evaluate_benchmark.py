"""`run_benchmark` on synthetic splits with a tiny model, logged to a SQLite MLflow store in tmp."""

from __future__ import annotations

import math
import time
from pathlib import Path

import mlflow
import numpy as np
import pandas as pd
import pytest
from _bench_data import compose, fit_fn, write_splits

from skidbench.benchmark.errors import EvaluationError
from skidbench.benchmark.evaluate.app import benchmark as run_benchmark
from skidbench.benchmark.scoring import metrics as mt
from skidbench.benchmark.tracking import tags as run_tags
from skidbench.pipeline.core.layout import Layout

DS = "sim-mini"


def _cfg(tmp_path, *over):
    return compose(
        "evaluate", tmp_path, ["models=[chi,ideal_t,broken,nan_model]", "horizons=[2.0,6.0]", *over]
    )


@pytest.fixture(scope="module")
def bench(tmp_path_factory, monkeypatch_module):
    out = tmp_path_factory.mktemp("bench")
    write_splits(out / DS)
    cfg = _cfg(out)
    return out, cfg, run_benchmark(cfg, fit_fn=fit_fn, log_figures=True)


@pytest.fixture(scope="module")
def monkeypatch_module():
    mp = pytest.MonkeyPatch()
    mp.delenv("MLFLOW_TRACKING_URI", raising=False)
    yield mp
    mp.undo()


def _runs(out, parent_id):
    mlflow.set_tracking_uri(Layout(out, DS).mlflow_uri)
    return mlflow.search_runs(
        experiment_names=[f"skidbench-{DS}"], filter_string=f"tags.mlflow.parentRunId = '{parent_id}'"
    )


def test_one_parent_and_a_child_per_model_and_terrain(bench):
    out, _, res = bench
    assert (out / "mlflow.db").is_file()
    runs = _runs(out, res.parent_run_id)
    assert len(runs) == 8  # 4 models x 2 terrains
    assert set(runs["tags.skidbench.model"]) == {"chi", "ideal_t", "broken", "nan_model"}
    assert set(runs["tags.skidbench.terrain"]) == {"tile", "grass"}
    parent = mlflow.get_run(res.parent_run_id)
    assert parent.data.tags["skidbench.role"] == "parent"
    assert parent.data.params["horizons"] == "[2.0, 6.0]"
    assert parent.info.status == "FINISHED"


def test_metrics_params_tags_and_artifacts_of_a_child(bench):
    out, _, res = bench
    runs = _runs(out, res.parent_run_id)
    ok = runs[(runs["status"] == "FINISHED")]
    assert set(ok["tags.skidbench.model"]) == {"chi", "ideal_t"}
    for split in ("cv", "ld"):
        for kind in ("trans", "rot"):
            for h in ("2s", "6s"):
                col = f"metrics.{split}_{h}_{kind}_rmsre_pct"
                assert np.isfinite(ok[col]).all()
    chi = ok[ok["tags.skidbench.model"] == "chi"]
    ideal = ok[ok["tags.skidbench.model"] == "ideal_t"]
    # in percent: chi is recovered (small error: lateral slip); ideal ignores the 30 % yaw slip
    assert (chi["metrics.ld_6s_rot_rmsre_pct"] < 5.0).all()
    assert (ideal["metrics.ld_6s_rot_rmsre_pct"] > 20.0).all()
    for m in ("fit_loss", "fit_time_s", "predict_time_s", "n_train"):
        assert np.isfinite(ok[f"metrics.{m}"]).all()
    row = chi.iloc[0]
    assert row["params.model"] == "chi" and row["params.min_distance_m"] == "0.5"
    assert row["tags.skidbench.model_version"] == "0.1"
    assert row["tags.skidbench.plugin_package"]
    assert len(row["tags.skidbench.dataset_fingerprint"]) == 32
    assert row["tags.skidbench.git_commit"]
    # provenance: skidbench and the libraries it ran with, the platform and code paths, the model's code
    assert row["tags.skidbench.version"] and row["tags.skidbench.env.numpy"] == np.__version__
    assert row["tags.skidbench.env.platform"] and "openblas=" in row["tags.skidbench.env.code_paths"]
    assert len(row["tags.skidbench.code.digest"]) == 32 and row["tags.skidbench.code.module"]
    client = mlflow.MlflowClient()
    arts = {a.path for d in ("fit", "windows", "figures") for a in client.list_artifacts(row["run_id"], d)}
    assert any(a.endswith(".params.json") for a in arts)
    assert any(a.endswith(".windows.parquet") for a in arts)
    assert any(a.endswith(".png") for a in arts)
    local = client.download_artifacts(
        row["run_id"], f"windows/{row['tags.skidbench.terrain']}.windows.parquet"
    )
    w = pd.read_parquet(local)
    assert {"split", "horizon_s", "sequence", "rel_trans", "rel_rot", "pred_x", "gt_x"} <= set(w.columns)
    assert set(w["split"]) == {"cv", "ld"} and set(w["horizon_s"]) == {2.0, 6.0}
    assert (out / "mlartifacts").is_dir()


def test_failed_fit_and_bad_prediction_are_failed_runs_with_reasons(bench):
    out, _, res = bench
    runs = _runs(out, res.parent_run_id)
    bad = runs[runs["status"] == "FAILED"]
    assert set(bad["tags.skidbench.model"]) == {"broken", "nan_model"}
    reasons = dict(zip(bad["tags.skidbench.model"], bad["tags.skidbench.failure_reason"], strict=False))
    assert "fit failed" in reasons["broken"] and "singular normal equations" in reasons["broken"]
    assert "non-finite" in reasons["nan_model"]
    assert {(c.model, c.status) for c in res.failed} == {(m, "FAILED") for m in ("broken", "nan_model")}
    parent = mlflow.get_run(res.parent_run_id)
    assert parent.data.metrics["n_failed"] == 4
    assert "FAILED" in parent.data.tags["skidbench.status"]


def test_empty_test_split_is_one_line_error(tmp_path, monkeypatch_module):
    write_splits(tmp_path / DS, terrains=("tile",), counts={"train": 1, "ld": 1})
    (tmp_path / DS / "splits" / "tile" / "cv").mkdir()
    with pytest.raises(EvaluationError, match=r"tile/cv: empty cv split") as e:
        run_benchmark(_cfg(tmp_path), fit_fn=fit_fn)
    assert "\n" not in str(e.value)
    assert not (tmp_path / "mlflow.db").exists()  # nothing logged for a benchmark that cannot run


def test_horizon_longer_than_every_sequence_is_one_line_error(tmp_path, monkeypatch_module):
    write_splits(tmp_path / DS, terrains=("tile",), duration_s=8.0)
    with pytest.raises(
        EvaluationError, match=r"horizon 10 s is longer than every sequence \(longest 8.0 s\)"
    ):
        run_benchmark(_cfg(tmp_path, "horizons=[10]"), fit_fn=fit_fn)


def test_no_splits_is_one_line_error(tmp_path, monkeypatch_module):
    with pytest.raises(EvaluationError, match="no splits; run `skidbench split`"):
        run_benchmark(_cfg(tmp_path), fit_fn=fit_fn)


def test_unreachable_tracking_server_is_one_line_error_fast(tmp_path, monkeypatch):
    import socket

    write_splits(tmp_path / DS, terrains=("tile",), counts={"train": 1, "cv": 1, "ld": 1})
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: nothing listens there
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"http://127.0.0.1:{port}")
    t0 = time.monotonic()
    with pytest.raises(
        EvaluationError, match=rf"MLflow tracking server http://127.0.0.1:{port} is unreachable"
    ):
        run_benchmark(_cfg(tmp_path), fit_fn=fit_fn)
    assert time.monotonic() - t0 < 10


def test_metric_names_and_flatten():
    assert mt.metric_key("translational", "cv", 6.0) == "cv_6s_trans_rmsre_pct"
    assert mt.metric_key("rotational", "ld", 2.5) == "ld_2.5s_rot_rmsre_pct"
    assert mt.rank_key("ld_trans", 6.0) == "ld_6s_trans_rmsre_pct"
    with pytest.raises(EvaluationError, match="rank_by='translational_ld'"):
        mt.rank_key("translational_ld", 6.0)
    assert run_tags.flatten({"a": {"b": 1, "c": [1, 2]}, "d": None}) == {
        "a.b": "1",
        "a.c": "[1, 2]",
        "d": "null",
    }
    assert not math.isnan(0.0)


def test_the_evaluate_stamp_changes_when_a_models_config_changes(tmp_path, monkeypatch):
    """A changed conf/model/<name>.yaml (initial params, options) re-runs evaluate, like a new version."""
    from hydra import compose, initialize_config_module

    from skidbench.benchmark.evaluate import app as evaluate_app
    from skidbench.benchmark.evaluate.settings import EvaluateSettings
    from skidbench.models.fitting import fit as fitting
    from skidbench.pipeline.core.cache import Stamp

    with initialize_config_module("skidbench.conf", version_base="1.3"):
        es = EvaluateSettings.from_cfg(compose("evaluate", [f"out_root={tmp_path}", "models=[edd,friction]"]))
        stamp = Stamp(tmp_path / "evaluate.json", "evaluate")
        key = evaluate_app._stamp_key(es, stamp)
        assert evaluate_app._stamp_key(es, stamp) == key
        real = fitting.model_config

        def changed(c, name):
            mc = real(c, name)
            return {**mc, "options": {**mc["options"], "max_nfev": 1}} if name == "friction" else mc

        monkeypatch.setattr(fitting, "model_config", changed)
        assert evaluate_app._stamp_key(es, stamp) != key


def _constant_twist_sequence(name: str, n: int, rate_hz: float, v: float, w: float):
    """A sequence driven at a constant twist (v m/s, w rad/s) whose ground truth is that twist exactly
    (no slip): the ideal model's prediction."""
    from _bench_data import JACKAL

    from skidbench.benchmark.scoring.predictions import TestSequence
    from skidbench.pipeline.core.geometry import integrate_body_velocity

    t = np.arange(n) / rate_hz
    wl, wr = JACKAL.wheel_rates_from_twist(np.full(n, v), np.full(n, w))
    true = np.column_stack([np.full(n, v), np.zeros(n), np.full(n, w)])
    pose = integrate_body_velocity(np.zeros(3), true[:-1], np.diff(t))
    table = pd.DataFrame(
        {"t": t, "cmd_v": v, "cmd_w": w, "cmd_wl": wl, "cmd_wr": wr, "cmd_dwl": 0.0, "cmd_dwr": 0.0,
         "x": pose[:, 0], "y": pose[:, 1], "yaw": pose[:, 2], "vx": true[:, 0], "vy": true[:, 1],
         "wz": true[:, 2], "valid": np.ones(n, bool)}
    )  # fmt: skip
    return TestSequence(name, Path(f"{name}.parquet"), table, {"sequence": name})


def test_predict_and_score_the_ideal_model_without_slip_has_zero_error_on_every_window():
    """No slip: the ideal model predicts the truth, so every scored window has zero error; a sequence of
    T samples at rate r has T - round(h r) windows of horizon h. A straight line turns by 0 rad (under the
    minimum rotation: no rotational window, RMSRE NaN); an arc of 0.5 rad/s turns by 3 rad in 6 s."""
    from _bench_data import JACKAL, IdealModel

    from skidbench.benchmark.scoring.horizon import HorizonConfig
    from skidbench.benchmark.scoring.predictions import keyed, predict_and_score

    rate, h = 30.0, 6.0
    tests = {
        "cv": [_constant_twist_sequence("line20", 600, rate, 1.0, 0.0),
               _constant_twist_sequence("line10", 300, rate, 0.5, 0.0)],
        "ld": [_constant_twist_sequence("arc20", 600, rate, 1.0, 0.5)],
    }  # fmt: skip
    model = IdealModel(JACKAL).fit(None)
    steps = []
    scores, windows, velocities, predict_s = predict_and_score(
        model, tests, [h], HorizonConfig(h, 0.5, np.deg2rad(10.0)), on_step=steps.append
    )
    metrics = keyed(scores)
    n_h = round(h * rate)
    assert metrics[mt.windows_key("translational", "cv", h)] == (600 - n_h) + (300 - n_h)
    assert metrics[mt.windows_key("rotational", "cv", h)] == 0
    assert math.isnan(metrics[mt.metric_key("rotational", "cv", h)])
    assert metrics[mt.windows_key("translational", "ld", h)] == 600 - n_h
    assert metrics[mt.windows_key("rotational", "ld", h)] == 600 - n_h
    for key in (mt.metric_key("translational", "cv", h), mt.metric_key("translational", "ld", h),
                mt.metric_key("rotational", "ld", h)):  # fmt: skip
        assert metrics[key] == 0.0
    assert predict_s >= 0.0
    assert list(windows.columns[:3]) == ["split", "horizon_s", "sequence"]
    assert windows.groupby(["split", "sequence"]).size().to_dict() == {
        ("cv", "line10"): 300 - n_h, ("cv", "line20"): 600 - n_h, ("ld", "arc20"): 600 - n_h
    }  # fmt: skip
    assert np.allclose(windows["trans_err"], 0.0, atol=1e-9) and np.allclose(
        windows["rot_err"], 0.0, atol=1e-9
    )
    for split, seqs in tests.items():
        for s, vel in zip(seqs, velocities[split], strict=True):
            assert np.allclose(vel, s.table[["vx", "vy", "wz"]].to_numpy(), atol=1e-12)
    assert steps == ["score cv", "predict", "score ld", "predict"]


def test_every_metric_is_logged_with_its_interval_and_blocks_and_the_floor_on_the_parent(bench):
    """docs/intervals.md: each child logs <metric>_ci_lo/_ci_hi and the blocks behind it; the parent logs the
    floor of each terrain (a perfect model: the simulator's exact velocities through the same windows) and its
    windows go where compare reads them; evaluate's summary prints the intervals and the floor."""
    from skidbench.benchmark.evaluate.console import format_result

    out, _, res = bench
    runs = _runs(out, res.parent_run_id)
    ok = runs[runs["status"] == "FINISHED"]
    for split in ("cv", "ld"):
        v = ok[f"metrics.{split}_6s_trans_rmsre_pct"]
        lo, hi = (
            ok[f"metrics.{split}_6s_trans_rmsre_pct_ci_lo"],
            ok[f"metrics.{split}_6s_trans_rmsre_pct_ci_hi"],
        )
        assert ((lo <= v + 1e-3) & (v <= hi + 1e-3)).all()
        assert (ok[f"metrics.{split}_6s_trans_blocks"] >= 1).all()
    parent = mlflow.get_run(res.parent_run_id).data.metrics
    chi = ok[ok["tags.skidbench.model"] == "chi"].set_index("tags.skidbench.terrain")
    for terrain in ("tile", "grass"):
        # this data's poses are dead-reckoned from its velocities by the left point, not the trapezoid: a
        # floor of a few tenths of a percent, under the best model's error
        floor = parent[f"floor.{terrain}.ld_6s_trans_rmsre_pct"]
        assert 0 <= floor < 1.0 and floor < chi.loc[terrain, "metrics.ld_6s_trans_rmsre_pct"]
        assert (out / DS / "eval" / "floor" / f"{terrain}.windows.parquet").is_file()
    text = format_result(res)
    assert "floor (reference)" in text and "[" in text


def _cut(ds: Path, split: str, keep) -> None:
    """Every ``split`` file of ``ds`` with only the rows ``keep(t)`` valid (the rest cut, as manual-driving
    phases are) and, where ``keep`` is None, driving straight (yaw 0)."""
    from skidbench.pipeline.core.schema import read_split, write_split

    for p in (ds / "splits" / "tile" / split).glob("*.parquet"):
        df, meta = read_split(p)
        if keep is None:
            df["yaw"] = 0.0
            df["y"] = 0.0
        else:
            df["valid"] = keep(df["t"].to_numpy())
        write_split(df, p, meta)


def test_a_recording_too_short_to_score_is_refused_with_seconds_kept_and_needed(tmp_path, monkeypatch_module):
    """A CV split whose valid stretches are 4 s long (8 s kept) cannot hold a 6 s window: refused before
    anything is logged, with the seconds; lowering the horizon as it says scores it."""
    write_splits(tmp_path / DS, terrains=("tile",))
    _cut(tmp_path / DS, "cv", lambda t: ((t >= 2) & (t < 6)) | ((t >= 20) & (t < 24)))
    with pytest.raises(EvaluationError) as e:
        run_benchmark(_cfg(tmp_path, "models=[chi]", "horizons=[6.0]"), fit_fn=fit_fn)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("splits/tile/cv: too short to score at the 6 s horizon: ")
    assert (
        "8.0 s of valid recording kept in 1 sequence(s), the longest stretch 4.0 s, and a window needs 6 s"
        in msg
    )
    assert "lower horizons=[...]" in msg
    assert not (tmp_path / "mlflow.db").exists()  # nothing ranked
    res = run_benchmark(_cfg(tmp_path, "models=[chi]", "horizons=[3.0]"), fit_fn=fit_fn)
    assert [c.status for c in res.children] == ["FINISHED"]


def test_a_split_that_never_turns_is_refused_for_the_rotational_score(tmp_path, monkeypatch_module):
    from skidbench.benchmark.evaluate.testsets import check_scores, load_test_split
    from skidbench.benchmark.scoring.horizon import HorizonConfig

    write_splits(tmp_path / DS, terrains=("tile",))
    _cut(tmp_path / DS, "ld", None)
    with pytest.raises(EvaluationError) as e:
        run_benchmark(_cfg(tmp_path, "models=[chi]", "horizons=[6.0]"), fit_fn=fit_fn)
    msg = str(e.value)
    assert msg.startswith("splits/tile/ld: no 6 s window turns min_rotation_deg=10 deg (")
    assert "the most 0.0 deg): the rotational score has nothing to rank" in msg
    assert not (tmp_path / "mlflow.db").exists()
    seqs = load_test_split(Layout(tmp_path, DS), "tile", "cv")  # a split that turns passes
    check_scores("splits/tile/cv", seqs, 6.0, HorizonConfig(6.0, 0.5, math.radians(10.0)))
