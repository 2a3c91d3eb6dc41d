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
from skidbench.benchmark.scoring import metrics as mt
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


def test_an_evaluate_that_took_runs_is_the_latest_by_its_own_newest_run(tmp_path):
    """e2 took e1's first run (chi) unchanged, its rows in e2's file too with their start time
    (benchmark/evaluate/reuse.py), and made ideal's an hour later: e2 is the latest evaluate (not a tie at
    e1's first run's start), and the taken run's row is that of a FINISHED evaluate (results.runs)."""
    import datetime as dt

    layout = Layout(tmp_path, "ds")
    t0, hour = dt.datetime(2026, 11, 28, 12, tzinfo=dt.UTC), dt.timedelta(hours=1)
    made = {"e1": [("e1-chi", "chi", t0), ("e1-ideal", "ideal", t0 + hour / 60)],
            "e2": [("e1-chi", "chi", t0), ("e2-ideal", "ideal", t0 + hour)]}  # fmt: skip
    for ev, runs in made.items():
        w = rt.Writer(layout, ev)
        for run_id, m, when in runs:
            facts = rt.RunFacts(ev, run_id, m, "commanded", "tile", horizons=[6.0], splits=["cv", "ld"],
                                models=["chi", "ideal"], start_time=when)  # fmt: skip
            w.add(rt.rows(facts, [Score("translational", sp, 6.0, 5.0, 40) for sp in ("cv", "ld")]))
        w.finish("FINISHED")
    table = rt.read(layout)
    for status in ("FINISHED", "KILLED"):  # e1 complete, or killed after its runs
        table.loc[table["evaluate_id"] == "e1", "evaluate_status"] = status
        assert rt.latest_evaluate(table, "commanded") == "e2"
        taken = rt.runs(table).set_index("run_id").loc["e1-chi"]
        assert taken["evaluate_status"] == "FINISHED" and (
            status == "FINISHED" or taken["evaluate_id"] == "e2"
        )


def test_the_board_is_the_newest_run_of_a_complete_evaluate_with_its_settings_from_the_table(tmp_path):
    """Two evaluates, the newer one killed: its run that finished is left out and named, the board keeps
    the complete evaluate's, and the settings and the latest evaluate are read from the rows (no MLflow)."""
    import datetime as dt

    from skidbench.benchmark.board import boards as brd
    from skidbench.benchmark.board import selection as sel

    layout = Layout(tmp_path, "ds")
    t0 = dt.datetime(2026, 11, 28, 12, tzinfo=dt.UTC)
    for k, (ev, status, models) in enumerate(
        (("e1", "FINISHED", ("chi", "ideal")), ("e2", "KILLED", ("chi",)))
    ):
        w = rt.Writer(layout, ev)
        for j, m in enumerate(models):
            when = t0 + dt.timedelta(hours=k, minutes=j)
            facts = rt.RunFacts(ev, f"{ev}-{m}", m, "commanded", "tile", horizons=[6.0], splits=["cv", "ld"],
                                models=list(models), min_distance_m=0.5 + k, min_rotation_deg=10.0,
                                start_time=when, reproduce=f"cmd {ev}")  # fmt: skip
            w.add(rt.rows(facts, [Score("translational", sp, 6.0, 5.0 + k + j, 40) for sp in ("cv", "ld")]))
        w.finish(status)
    table = rt.read(layout)
    assert rt.latest_evaluate(table, "commanded") == "e1" and rt.latest_evaluate(table, "response") is None
    assert rt.settings_of(table, "e2") == {"horizons": [6.0], "splits": ["cv", "ld"], "min_distance_m": 1.5,
                                           "min_rotation_deg": 10.0, "models": ["chi"]}  # fmt: skip
    s = sel.latest_complete(table, "commanded", 6.0)
    assert dict(zip(s.runs["model"], s.runs["run_id"], strict=True)) == {"chi": "e1-chi", "ideal": "e1-ideal"}
    (line,) = s.left_out
    assert line.startswith("chi/tile: run e2-chi") and "its evaluate e2 ended KILLED" in line
    assert "the board has its run e1-chi" in line
    board = brd.protocol_board(table, "commanded")
    assert board.parent_run_id == "e1" and board.settings["min_distance_m"] == 0.5
    rows = board.rows.set_index("model")
    assert rows.loc["ideal", "ld_6s_trans_rmsre_pct"] == 6.0 and rows.loc["chi", "reproduce"] == "cmd e1"
    only = sel.latest_complete(table, "commanded", 6.0, allowed={"e1-ideal"})  # compare's filter
    assert list(only.runs["run_id"]) == ["e1-ideal"] and not only.left_out
    with pytest.raises(sel.NoRuns, match="no model runs of user bob under inputs=commanded"):
        sel.latest_complete(table, "commanded", 6.0, user="bob")


@pytest.mark.slow  # the README's quick start (a session fixture shared with test_e2e)
def test_the_board_from_the_results_table_alone_is_what_mlflow_and_the_leaderboard_hold(readme_reproduce):
    """The quick start's boards (both protocols) built from the results files alone (no MLflow), as compare
    selects them: every cell (value, interval, windows, blocks) is the metric MLflow holds for that run
    under its UI name and the cell of the leaderboard compare wrote (the same runs); every row's
    provenance is its run's tags, and the board's settings its evaluate's params."""
    import ast

    from mlflow import MlflowClient

    from skidbench.benchmark.board import boards as brd
    from skidbench.benchmark.board.selection import board_of, latest_complete

    root = readme_reproduce["root"]
    layout = Layout(root, "sim-tiny")
    table = rt.read(layout)
    client = MlflowClient(f"sqlite:///{root / 'mlflow.db'}")
    for protocol in ("commanded", "response"):
        board = board_of(latest_complete(table, protocol, 6.0))
        assert len(board) == 8 * 3 and (board["status"] == "FINISHED").all()
        keys = [c for c in board.columns if c.startswith(("cv_", "ld_"))]
        assert "ld_6s_trans_rmsre_pct" in keys and "ld_6s_trans_rmsre_pct_ci_hi" in keys
        lb = pd.read_csv(root / "sim-tiny" / "reports" / f"leaderboard-{protocol}.csv").set_index("run_id")
        assert set(lb.index) == set(board["run_id"])
        for row in board.itertuples(index=False):
            run = client.get_run(row.run_id)
            for k in keys:
                v, got = getattr(row, k), run.data.metrics.get(k, np.nan)
                assert got == v or (np.isnan(v) and np.isnan(got)), (row.model, k)
            assert lb.loc[row.run_id, "options_digest"] == run.data.tags["skidbench.options_digest"]
            assert lb.loc[row.run_id, "code_digest"] == run.data.tags["skidbench.code.digest"]
        for m in (m for m in mt.METRICS if not m.optional):  # an optional one: shown as text, scaled
            for split in ("cv", "ld"):
                label, key = m.column_label(split), m.metric_key(split, 6.0)
                shown = lb.loc[board["run_id"], label].to_numpy(float)
                assert np.allclose(shown, board[key].to_numpy(float), equal_nan=True), label
                if m.bootstrap is not None:
                    lo, hi, _ = m.interval_keys(split, 6.0)
                    shown = lb.loc[board["run_id"], f"{label} lo"].to_numpy(float)
                    assert np.allclose(shown, board[lo].to_numpy(float), equal_nan=True), label
        b = brd.protocol_board(table, protocol)
        params = client.get_run(b.parent_run_id).data.params
        assert b.settings == {k: ast.literal_eval(params[k]) for k in rt.SETTING_KEYS}


@pytest.mark.slow  # the README's quick start (a session fixture shared with test_e2e)
def test_the_stratum_rows_partition_every_cell_of_every_horizon(readme_reproduce):
    """evaluate's default horizons (the board's 6 s first) each have the aggressiveness terciles' rows:
    for every run, split, horizon and metric the terciles' windows add up to the cell's, and an RMS
    metric's value is the pooled RMS of its terciles' (the same windows, cut in three)."""
    layout = Layout(readme_reproduce["root"], "sim-tiny")
    table = rt.read(layout)
    model = table[(table["role"] == "model") & (table["status"] == "FINISHED")]
    assert sorted(set(model["horizon_s"])) == [0.5, 1.0, 2.0, 4.0, 6.0]
    assert set(model["stratum"]) == {"all", "low", "mid", "high"}
    key = ["evaluate_id", "run_id", "split", "horizon_s", "metric"]
    parts = model[model["stratum"] != "all"].copy()
    parts["sq"] = parts["estimate"].fillna(0.0) ** 2 * parts["n_windows"]
    summed = parts.groupby(key)[["n_windows", "sq"]].sum()
    whole = model[model["stratum"] == "all"].set_index(key)
    joined = whole.join(summed.add_suffix("_parts"), how="inner")
    assert len(joined) == len(whole)  # every cell has its terciles
    assert (joined["n_windows"] == joined["n_windows_parts"]).all()
    rms = joined[
        joined.index.get_level_values("metric").isin(
            [m.name for m in mt.METRICS if m.bootstrap is not None and m.bootstrap.aggregation == "rms"]
        )
    ]
    pooled = np.sqrt(rms["sq_parts"] / rms["n_windows"].clip(lower=1))
    ok = rms["n_windows"] > 0
    # each value is logged rounded (5 significant digits): the pooled RMS agrees to that
    np.testing.assert_allclose(pooled[ok], rms.loc[ok, "estimate"], rtol=1e-3, atol=1e-4)


@pytest.mark.slow  # the README's quick start (a session fixture shared with test_e2e)
def test_the_floor_rows_are_the_floor_the_parent_run_logs(readme_reproduce):
    """Each evaluate's floor of each terrain has rows (role floor, the evaluate's run id): every cell's
    value, interval and windows are the parent run's ``floor.<terrain>.<metric key>`` metrics."""
    from mlflow import MlflowClient

    root = readme_reproduce["root"]
    table = rt.read(Layout(root, "sim-tiny"))
    floor = table[(table["role"] == rt.REFERENCE) & (table["stratum"] == rt.ALL)]
    assert set(floor["model"]) == {"floor"} and (floor["run_id"] == floor["evaluate_id"]).all()
    client = MlflowClient(f"sqlite:///{root / 'mlflow.db'}")
    for (parent, terrain), rows in floor.groupby(["evaluate_id", "terrain"]):
        logged = client.get_run(parent).data.metrics
        cells = rt.mlflow_metrics(rows)
        assert cells and len(set(rows["horizon_s"])) == 5
        for key, value in cells.items():
            got = logged.get(f"floor.{terrain}.{key}", np.nan)
            assert got == value or (np.isnan(value) and np.isnan(got)), (terrain, key)
