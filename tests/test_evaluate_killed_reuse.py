"""A killed evaluate's finished runs are taken, not run again (benchmark/evaluate/reuse.py): the kill is
simulated as the store's bookkeeping leaves it (the parent and the run that was running marked KILLED, the
results file of the evaluate never finished). The next evaluate takes the finished run unchanged, runs the
killed one again, carries the taken run's rows in its own results file and lists it in its parent's tag;
the board is that one complete evaluate's, the taken run as its run, never as the killed evaluate's. On
the same state: an edit of one model's module runs that model again and takes the other."""

from __future__ import annotations

import contextlib
import io

import pandas as pd
import pytest
from _bench_data import compose, write_splits

from skidbench.benchmark.board import results as rt
from skidbench.benchmark.board import selection
from skidbench.benchmark.board.compare import select_runs
from skidbench.benchmark.evaluate.app import benchmark as run_benchmark
from skidbench.benchmark.evaluate.reuse import TAG_REUSED, records
from skidbench.benchmark.tracking import store as trk
from skidbench.pipeline.core.io import write_parquet_atomic
from skidbench.pipeline.core.layout import Layout

DS = "sim-mini"
ARGS = ["models=[ideal,edd]", "calibrate.use=false", "log_figures=false", "horizons=[6.0]"]


def _killed(out, res) -> None:
    """``res``'s evaluate as a kill during its edd run leaves it, once reaped: the parent and that run
    KILLED in the store, the evaluate's results file with the run RUNNING and the evaluate not finished."""
    tracker = trk.Tracker(Layout(out, DS).mlflow_uri, f"skidbench-{DS}")
    edd = next(c.run_id for c in res.children if c.model == "edd")
    tracker.client.set_terminated(edd, "KILLED")
    tracker.client.set_terminated(res.parent_run_id, "KILLED")
    path = rt.folder(Layout(out, DS)) / f"{res.parent_run_id}.parquet"
    table = rt.read(Layout(out, DS))
    rows = table[table["evaluate_id"] == res.parent_run_id].assign(evaluate_status="RUNNING")
    rows.loc[rows["run_id"] == edd, "status"] = "RUNNING"
    write_parquet_atomic(rt.to_table(records(rows)), path)


@pytest.fixture(scope="module")
def rerun(tmp_path_factory):
    """An evaluate of ideal and edd killed during edd's run, and the evaluate after it (and its console)."""
    out = tmp_path_factory.mktemp("killed")
    mp = pytest.MonkeyPatch()
    mp.delenv("MLFLOW_TRACKING_URI", raising=False)
    write_splits(out / DS, terrains=("tile",), counts={"train": 1, "cv": 1, "ld": 1}, duration_s=16.0)
    first = run_benchmark(compose("evaluate", out, ARGS), log_figures=False)
    _killed(out, first)
    console = io.StringIO()
    with contextlib.redirect_stdout(console):
        second = run_benchmark(compose("evaluate", out, ARGS), log_figures=False)
    yield out, first, second, console.getvalue()
    mp.undo()


def test_a_killed_evaluates_finished_run_is_taken_and_the_killed_one_run_again(rerun):
    out, first, second, console = rerun
    before = {c.model: c for c in first.children}
    after = {c.model: c for c in second.children}
    assert after["ideal"].reused and after["ideal"].run_id == before["ideal"].run_id  # taken as it is
    assert not after["edd"].reused and after["edd"].run_id != before["edd"].run_id  # made again
    assert after["edd"].status == "FINISHED"
    (why,) = [line for line in console.splitlines() if line.startswith("evaluate: edd: ")]
    assert f"its run {before['edd'].run_id[:8]} is KILLED" in why
    assert "ended KILLED; taken into this one" in console and "evaluate: ideal/tile: finished in" in console
    tracker = trk.Tracker(Layout(out, DS).mlflow_uri, f"skidbench-{DS}")
    parent = tracker.client.get_run(second.parent_run_id)
    assert parent.info.status == "FINISHED" and parent.data.tags[TAG_REUSED] == before["ideal"].run_id
    # its results file carries the taken run's rows as its own, equal to the killed evaluate's but for it
    table = rt.read(Layout(out, DS))
    own = table[(table["evaluate_id"] == second.parent_run_id) & (table["role"] == rt.MODEL)]
    assert set(own["run_id"]) == {before["ideal"].run_id, after["edd"].run_id}
    assert (own["evaluate_status"] == "FINISHED").all()
    old = table[(table["evaluate_id"] == first.parent_run_id) & (table["run_id"] == before["ideal"].run_id)]
    new = own[own["run_id"] == before["ideal"].run_id]
    cols = ["metric", "split", "horizon_s", "estimate", "lo", "hi", "n_windows"]
    pd.testing.assert_frame_equal(old[cols].reset_index(drop=True), new[cols].reset_index(drop=True))


def test_the_board_is_the_complete_evaluates_with_the_taken_run_as_its_own(rerun):
    out, _, second, _ = rerun
    tracker = trk.Tracker(Layout(out, DS).mlflow_uri, f"skidbench-{DS}")
    table = rt.read(Layout(out, DS))
    runs = {c.model: c.run_id for c in second.children}
    chosen = selection.latest_complete(table, "commanded", 6.0, tracker=tracker)
    assert dict(zip(chosen.runs["model"], chosen.runs["run_id"], strict=True)) == runs
    assert chosen.parents == [second.parent_run_id]  # one evaluate: the complete one
    assert chosen.left_out == []  # the killed run is older than the one on the board: not a newer one
    taken = runs["ideal"]
    for files in (table, table.iloc[::-1]):  # whichever file is read last: the complete evaluate's row
        run = rt.runs(files.reset_index(drop=True)).set_index("run_id").loc[taken]
        assert (run["evaluate_id"], run["evaluate_status"]) == (second.parent_run_id, "FINISHED")
    picked, _ = select_runs(tracker, table, second.parent_run_id, None, "commanded")
    assert sorted(picked["run_id"]) == sorted(runs.values())
    assert set(picked["evaluate_id"]) == {second.parent_run_id}


@pytest.mark.parametrize(
    "rel, again",
    [(None, set()), ("models/kinematic/linear.py", {"edd"}), ("models/base.py", {"ideal", "edd"})],
)
def test_an_edit_of_one_models_module_runs_that_model_again_and_takes_the_others(
    rerun, monkeypatch, rel, again
):
    """The next evaluate's plan on the same state (benchmark/evaluate/reuse.py ``plan_reuse``; nothing is
    run or written): with a model's module edited (its content hash changed: the digest's source,
    tests/test_code_digest.py) that model runs again, saying why, and the other is taken; an edit of
    models/base.py, which both run, runs both again."""
    from test_code_digest import edited

    from skidbench.benchmark.evaluate.reuse import plan_reuse
    from skidbench.benchmark.evaluate.settings import EvaluateSettings
    from skidbench.benchmark.evaluate.testsets import load_evaluation_data

    out = rerun[0]
    es = EvaluateSettings.from_cfg(compose("evaluate", out, ARGS))
    data = load_evaluation_data(es.layout, es.fit.calibrations, ["tile"], es.splits, es.horizons, es.protocol)
    if rel:
        edited(monkeypatch, rel)
    with contextlib.redirect_stdout(io.StringIO()) as console:
        plan = plan_reuse(es, trk.open_store(es.store), data.files_of, ["tile"])
    assert set(plan.again) == again and {m for m, _ in plan.taken} == {"ideal", "edd"} - again
    for model in again:
        assert f"evaluate: {model}: its code changed (digest " in console.getvalue()
