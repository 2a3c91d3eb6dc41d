"""The results table (benchmark/board/results.py, docs/results-table.md): what evaluate writes once and every
board reads. Rows round-trip to the MLflow names they are logged under; a file with a column missing, of
another type or of another major version is refused in one line naming the file and the column; and on the
README's quick start (tiny) the board built from the table alone equals what MLflow holds of each run and
the leaderboard compare wrote."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from skidbench.benchmark.board import results as rt
from skidbench.benchmark.scoring.predictions import Score, keyed
from skidbench.pipeline.core.layout import Layout


def _scores() -> list[Score]:
    return [
        Score("translational", "ld", 6.0, 7.25, 120, 6.5, 8.125, 9),
        Score("rotational", "ld", 6.0, float("nan"), 0, float("nan"), float("nan"), 0),
        Score("end_position", "cv", 6.0, 0.4375, 80),  # no interval computed
    ]


def _written(tmp_path, run_id="r1", **facts) -> Layout:
    layout = Layout(tmp_path, "ds")
    base = rt.RunFacts(evaluate_id="e1", run_id=run_id, model="chi", inputs="commanded", terrain="tile",
                       horizons=[6.0], splits=["cv", "ld"], versions={"numpy": "2.0"}, **facts)  # fmt: skip
    w = rt.Writer(layout, "e1")
    w.add(rt.rows(base, _scores()))
    w.finish("FINISHED")
    return layout


def test_rows_read_back_are_the_metrics_mlflow_is_given(tmp_path):
    layout = _written(tmp_path, predict_time_s=0.5)
    table = rt.read(layout)
    assert (
        len(table) == 3
        and set(table["stratum"]) == {"all"}
        and (table["evaluate_status"] == "FINISHED").all()
    )
    got = rt.mlflow_metrics(table)
    want = {**keyed(_scores()), "predict_time_s": 0.5}
    assert got.keys() == want.keys()
    for k, v in want.items():
        assert (math.isnan(v) and math.isnan(got[k])) or got[k] == v, k
    # an interval where one was computed, none where not; a cell without windows: NaN bounds, 0 blocks
    assert got["ld_6s_trans_rmsre_pct_ci_lo"] == 6.5 and got["ld_6s_trans_blocks"] == 9.0
    assert "cv_6s_endpos_rmse_m_ci_lo" not in got and got["ld_6s_rot_blocks"] == 0.0
    assert rt.nan_cells(table) == ["ld_6s_rot_rmsre_pct"]  # over the windows that turn enough: none did
    assert table["versions"].iloc[0] == {"numpy": "2.0"} and list(table["horizons"].iloc[0]) == [6.0]


@pytest.mark.parametrize(
    ("damage", "says"),
    [
        (lambda t: t.drop_columns(["n_blocks"]), "column 'n_blocks' missing"),
        (
            lambda t: t.set_column(
                t.schema.get_field_index("estimate"),
                "estimate",
                pa.array([str(x) for x in t["estimate"].to_pylist()]),
            ),
            "column 'estimate' is string, expected double",
        ),  # fmt: skip
        (lambda t: t.replace_schema_metadata({rt.VERSION_KEY: "2.0"}), "results table schema 2.0"),
    ],
)
def test_a_malformed_results_file_is_refused_in_one_line_naming_the_file_and_column(tmp_path, damage, says):
    layout = _written(tmp_path)
    path = rt.folder(layout) / "e1.parquet"
    pq.write_table(damage(pq.read_table(path)), path)
    with pytest.raises(rt.ResultsTableError) as err:
        rt.read(layout)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(f"{path}: ") and says in msg


def test_a_column_added_by_a_newer_minor_version_is_read(tmp_path):
    layout = _written(tmp_path)
    path = rt.folder(layout) / "e1.parquet"
    t = pq.read_table(path)
    t = t.append_column("new_column", pa.array([1.0] * len(t))).replace_schema_metadata(
        {rt.VERSION_KEY: "1.7"}
    )
    pq.write_table(t, path)
    assert len(rt.read(layout)) == 3


@pytest.mark.slow  # the README's quick start (a session fixture shared with test_e2e)
def test_the_board_from_the_results_table_alone_is_what_mlflow_and_the_leaderboard_hold(readme_reproduce):
    """The quick start's boards (both protocols) built from the results files alone (no MLflow): every cell
    is the metric MLflow holds for that run under its UI name, and the rows are the leaderboard compare
    wrote (the same runs, the same values)."""
    from mlflow import MlflowClient

    from skidbench.benchmark.scoring import metrics as mt

    root = readme_reproduce["root"]
    layout = Layout(root, "sim-tiny")
    table = rt.read(layout)
    client = MlflowClient(f"sqlite:///{root / 'mlflow.db'}")
    for protocol in ("commanded", "response"):
        runs = rt.runs(table)
        runs = runs[runs["inputs"] == protocol].drop_duplicates(["model", "terrain"])  # newest first
        board = rt.board(table, runs, 6.0)
        assert len(board) == 8 * 3 and (board["status"] == "FINISHED").all()
        keys = [c for c in board.columns if c.startswith(("cv_", "ld_"))]
        assert "ld_6s_trans_rmsre_pct" in keys and "ld_6s_trans_rmsre_pct_ci_hi" in keys
        for row in board.itertuples(index=False):
            logged = client.get_run(row.run_id).data.metrics
            for k in keys:
                v, got = getattr(row, k), logged.get(k, np.nan)
                assert got == v or (np.isnan(v) and np.isnan(got)), (row.model, k)
        lb = pd.read_csv(root / "sim-tiny" / "reports" / f"leaderboard-{protocol}.csv").set_index("run_id")
        assert set(lb.index) == set(board["run_id"])
        for m in mt.PAPER:
            for split in ("cv", "ld"):
                shown = lb.loc[board["run_id"], m.column_label(split)].to_numpy(float)
                assert np.allclose(shown, board[m.metric_key(split, 6.0)].to_numpy(float), equal_nan=True)
