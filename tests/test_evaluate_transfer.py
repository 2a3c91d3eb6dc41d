"""Transfer evaluation (benchmark/evaluate/transfer.py): fit on dataset A's Train, score dataset B's CV/LD."""

from __future__ import annotations

import json

import mlflow
import pytest
from _bench_data import compose, fit_fn, sequence_table, write_splits

from skidbench.benchmark.errors import EvaluationError
from skidbench.benchmark.evaluate.app import benchmark as run_benchmark
from skidbench.benchmark.scoring.horizon import count_windows
from skidbench.pipeline.core.layout import Layout
from skidbench.pipeline.core.manifest import Manifest, Sequence
from skidbench.pipeline.core.schema import write_split

SCORED = "sim-mini"  # the default dataset of the composed config: B, yaw rate 0.7 of the ideal
TRAIN = "lastweek"  # A: the same robot on a surface where the yaw rate is 0.4 of the ideal


def write_train_dataset(ds_root, chi, robot="jackal"):
    seqs = []
    for k in range(2):
        name = f"tile_train_{k:02d}"
        meta = {"sequence": name, "terrain": "tile", "split": "train", "robot": {"name": robot},
                "sources": {}, "rate_hz": 30.0}  # fmt: skip
        write_split(sequence_table(100 + k, chi=chi), ds_root / "splits/tile/train" / f"{name}.parquet", meta)
        seqs.append(Sequence(name, "tile", "train", f"bags/{name}.bag"))
    Manifest(seqs, robot=robot, base=ds_root / "raw").write(ds_root / "raw" / "manifest.json")


@pytest.fixture()
def two_datasets(tmp_path, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    write_splits(tmp_path / SCORED, terrains=("tile",))
    write_train_dataset(tmp_path / TRAIN, chi=0.4)
    return tmp_path


def _chi(out, dataset=SCORED):
    return json.loads((Layout(out, dataset).eval / "chi" / "tile.params.json").read_text())["params"]["chi"]


@pytest.mark.slow  # two evaluate runs into a new SQLite MLflow store: 36 s on the shared cores
def test_transfer_fits_on_a_and_scores_on_b_in_its_own_experiment(two_datasets):
    out = two_datasets
    same = run_benchmark(compose("evaluate", out, ["models=[chi]"]), fit_fn=fit_fn, log_figures=False)
    assert _chi(out) == pytest.approx(0.7, abs=0.01)  # fitted on B's own Train
    moved = run_benchmark(
        compose("evaluate", out, ["models=[chi]", f"train_dataset={TRAIN}"]), fit_fn=fit_fn, log_figures=False
    )
    assert _chi(out) == pytest.approx(0.4, abs=0.01)  # fitted on A's Train, scored on B
    rot = "ld_6s_rot_rmsre_pct"
    assert moved.children[0].metrics[rot] > 5 * same.children[0].metrics[rot]  # A's chi is wrong on B
    assert moved.experiment == f"skidbench-{SCORED}-transfer" != same.experiment
    mlflow.set_tracking_uri(moved.tracking_uri)
    run = mlflow.get_run(moved.children[0].run_id)
    assert run.data.tags["skidbench.transfer"] == "true"
    assert run.data.tags["skidbench.train_dataset"] == TRAIN
    assert run.data.tags["skidbench.train_terrain"] == "tile"
    assert mlflow.get_run(same.children[0].run_id).data.tags["skidbench.transfer"] == "false"
    # the same-recording experiment holds no transfer run
    runs = mlflow.search_runs(
        experiment_names=[same.experiment], filter_string="tags.`skidbench.role`='child'"
    )
    assert set(runs["tags.skidbench.transfer"]) == {"false"}


def test_transfer_needs_the_same_robot_and_an_existing_dataset(two_datasets):
    out = two_datasets
    write_train_dataset(out / "husky_day", chi=0.4, robot="husky")
    with pytest.raises(EvaluationError, match="holds robot husky.*same robot"):
        run_benchmark(compose("evaluate", out, ["models=[chi]", "train_dataset=husky_day"]), fit_fn=fit_fn)
    with pytest.raises(EvaluationError, match="train_dataset=nowhere: no dataset"):
        run_benchmark(compose("evaluate", out, ["models=[chi]", "train_dataset=nowhere"]), fit_fn=fit_fn)
    with pytest.raises(EvaluationError, match="train_terrain=sand: not a terrain"):
        run_benchmark(compose("evaluate", out, ["models=[chi]", "train_terrain=sand"]), fit_fn=fit_fn)


def test_window_counts_per_horizon_on_short_sequences():
    a, b = sequence_table(0, duration_s=10.0), sequence_table(1, duration_s=4.0)  # 300 and 120 rows
    b.loc[10, "valid"] = False
    # 6 s = 180 steps: 300 - 180 windows from a; b is shorter than the horizon
    assert count_windows([a, b], 6.0) == (120, 2, 1)
    # 2 s = 60 steps: a gives 240; b's 60 windows (starts 0..59) lose the 11 that touch its invalid row 10
    assert count_windows([a, b], 2.0) == (240 + 60 - 11, 2, 0)
