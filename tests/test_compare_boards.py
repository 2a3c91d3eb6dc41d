"""One board per dataset and protocol (benchmark/board/selection.py, boards.py, compare.py): the newest
complete run
of each (model, terrain) across evaluates, newer incomplete runs left out and named, leaderboard files kept
with a time stamp and provenance per row, `compare dataset=<name>` on a root with two datasets; and loud,
recoverable failures (a model that raises in predict: its traceback saved; exit statuses 3 and 130).

Runs are logged by ``run_benchmark`` on synthetic splits (tests/_bench_data.py) or, for a second dataset,
directly through the Tracker; one command runs through the CLI (``compare dataset=<name>``)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import mlflow
import pandas as pd
import pytest
from _bench_data import compose, fit_fn, write_splits

from skidbench.benchmark.board import boards as brd
from skidbench.benchmark.board import results as rt
from skidbench.benchmark.board.app import run as run_compare
from skidbench.benchmark.evaluate.app import benchmark as run_benchmark
from skidbench.benchmark.evaluate.console import format_result
from skidbench.benchmark.evaluate.failures import TRACEBACK_ARTIFACT, failure_summary
from skidbench.benchmark.scoring.predictions import Score
from skidbench.benchmark.tracking import store as trk
from skidbench.benchmark.tracking import tags as run_tags
from skidbench.pipeline.core.layout import Layout

DS = "sim-mini"
OTHER = "drive-other-abc123"  # a second dataset of the root, of another source
OTHER_ID = "0123456789ab"
NO_FIGS = ["figures.enabled=false", "log_to_mlflow=false"]


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    """An output root: three evaluates of the synthetic dataset (two models; then one of them alone; then
    the other with a model that raises in predict) and a second dataset whose runs are logged directly."""
    mp = pytest.MonkeyPatch()
    mp.delenv("MLFLOW_TRACKING_URI", raising=False)
    out = tmp_path_factory.mktemp("boards")
    write_splits(out / DS, terrains=("tile",), counts={"train": 1, "cv": 1, "ld": 1}, duration_s=16.0)
    runs = {}
    for k, models in enumerate(("[chi,ideal_t]", "[chi]", "[ideal_t,raiser]")):
        cfg = compose("evaluate", out, [f"models={models}", "horizons=[6.0]"])  # the board's: no strata
        runs[k] = run_benchmark(cfg, fit_fn=fit_fn, log_figures=False)
    _record(compose("evaluate", out), out / DS)
    _other_dataset(out)
    yield out, runs
    mp.undo()


def _record(cfg, ds_root):
    """The dataset.json and an extracted table a stage would have written (`skidbench datasets` lists
    folders with one)."""
    from skidbench.pipeline.core.layout import Layout
    from skidbench.pipeline.datasets.identity import identity_from_cfg, record

    layout = Layout(ds_root.parent, ds_root.name)
    record(layout, identity_from_cfg(cfg))
    (layout.extracted / "s").mkdir(parents=True, exist_ok=True)
    pd.DataFrame({"stamp_ns": [0]}).to_parquet(layout.extracted / "s" / "cmd_vel.parquet")


def _other_dataset(out):
    """A second dataset (another source's identity) with one evaluate of two models, logged as evaluate
    logs them (tags, metrics), in its own experiment, and written to its results table."""
    ds = out / OTHER
    (ds / "raw").mkdir(parents=True)
    (ds / "raw" / "manifest.json").write_text(json.dumps({"schema": 1, "robot": "warthog", "sequences": []}))
    rec = {"schema": 1, "name": OTHER, "source": "drive_df", "root": "/data/other", "fingerprint": OTHER_ID,
           "terrains": ["grass"], "sequences": 0}  # fmt: skip
    (ds / "dataset.json").write_text(json.dumps(rec))
    (ds / "extracted" / "s").mkdir(parents=True)
    pd.DataFrame({"stamp_ns": [0]}).to_parquet(ds / "extracted" / "s" / "cmd_vel.parquet")
    tracker = trk.Tracker(f"sqlite:///{out / 'mlflow.db'}", f"skidbench-{OTHER}", dataset_id=OTHER_ID)
    tags = {run_tags.TAG_DATASET: OTHER, run_tags.TAG_INPUTS: "commanded"}
    parent = tracker.start("evaluate other", {**tags, run_tags.TAG_ROLE: "parent"})
    results = rt.Writer(Layout(out, OTHER), parent)
    for model, err in (("alpha", 10.0), ("beta", 20.0)):
        child = tracker.start(
            f"{model}/grass",
            {**tags, run_tags.TAG_ROLE: "child", run_tags.TAG_MODEL: model, run_tags.TAG_TERRAIN: "grass"},
            parent,
        )
        scores = [Score(k, s, 6.0, err, 40) for s in ("cv", "ld") for k in ("translational", "rotational")]
        facts = rt.RunFacts(parent, child, model, "commanded", "grass", dataset=OTHER, dataset_id=OTHER_ID,
                            experiment=f"skidbench-{OTHER}", min_distance_m=0.5, min_rotation_deg=10.0,
                            horizons=[6.0], splits=["cv", "ld"], models=["alpha", "beta"],
                            user=run_tags.current_user())  # fmt: skip
        rows = rt.rows(facts, scores)
        results.add(rows)
        tracker.log(child, metrics=rt.mlflow_metrics(pd.DataFrame(rows)))
        tracker.end(child)
    results.finish("FINISHED")
    tracker.end(parent)
    return parent


def _board(out, ds=DS, protocol="commanded"):
    return pd.read_csv(out / ds / "reports" / f"leaderboard-{protocol}.csv", dtype=str, keep_default_na=False)


def test_a_model_evaluated_alone_lands_on_the_full_board(root):
    """`evaluate models=[chi]` after a full evaluate, then another evaluate of the others: compare ranks
    every model, each from its newest complete run, with the run id, options digest and versions per row."""
    out, runs = root
    res = run_compare(compose("compare", out, NO_FIGS))
    board = _board(out)
    by_model = board.set_index("model")
    chi_run = next(c.run_id for c in runs[1].children if c.model == "chi")
    ideal_run = next(c.run_id for c in runs[2].children if c.model == "ideal_t")
    assert by_model.loc["chi", "run_id"] == chi_run and by_model.loc["ideal_t", "run_id"] == ideal_run
    assert by_model.loc["raiser", "status"] == "FAILED"  # its only run failed: on the board as FAILED
    assert set(res.parents) == {runs[1].parent_run_id, runs[2].parent_run_id}
    # every model is on the board, in order of its score; this data (one short terrain) is too small to
    # rank (docs/intervals.md: at least 8 independent blocks)
    lines = res.leaderboard_md.splitlines()
    chi, ideal = (next(i for i, t in enumerate(lines) if f"| {m} |" in t) for m in ("chi", "ideal_t"))
    assert chi < ideal and "not ranked" in lines[chi]
    for col in ("run_id", "parent_run_id", "options_digest", "model_version", "git_commit", "env.numpy"):
        assert col in board.columns
    assert board["options_digest"].str.fullmatch(r"[0-9a-f]{12}").all()
    assert by_model.loc["chi", "options_digest"] != by_model.loc["ideal_t", "options_digest"]
    assert by_model.loc["chi", "model_version"] == "0.1"
    import numpy

    assert (board["env.numpy"] == numpy.__version__).all() and board["skidbench_version"].str.len().gt(
        0
    ).all()
    assert (
        by_model.loc["chi", "code_digest"] != ""
    )  # the digest of the model's code (pipeline/runner/environment.py)
    # the protocols table shows every model of the board, not only the newest evaluate's
    shown = {line.split("|")[1].strip() for line in res.decomposition_md.splitlines()[2:]}
    assert {"chi", "ideal_t"} <= shown
    md = (out / DS / "reports" / "leaderboard-commanded.md").read_text()
    assert f"`skidbench compare dataset={DS} inputs=commanded`" in md and chi_run[:8] in md


def test_a_model_that_raises_in_predict_fails_its_run_with_its_traceback_saved(root):
    out, runs = root
    result = runs[2]
    (bad,) = result.failed
    assert bad.model == "raiser" and bad.status == "FAILED"
    assert bad.reason == "predict failed: KeyError: 'vx'"
    client = mlflow.MlflowClient(f"sqlite:///{out / 'mlflow.db'}")
    run = client.get_run(bad.run_id)
    assert run.info.status == "FAILED" and run.data.tags["skidbench.traceback"] == TRACEBACK_ARTIFACT
    text = open(client.download_artifacts(bad.run_id, TRACEBACK_ARTIFACT, str(out / "dl"))).read()
    assert text.startswith("Traceback (most recent call last):")
    assert "in predict" in text and 'table["vx"]' in text and text.rstrip().endswith("KeyError: 'vx'")
    local = out / DS / "eval" / "raiser" / "tile.traceback.txt"
    assert local.read_text() == text
    assert f"artifact {TRACEBACK_ARTIFACT}" in bad.traceback and str(local) in bad.traceback
    console = format_result(result)
    assert (
        "FAILED raiser/tile: predict failed: KeyError: 'vx'" in console
        and f"  traceback: MLflow run {bad.run_id}" in console
    )
    summary = failure_summary(result)
    assert summary.startswith("1 of 2 model run(s) FAILED under inputs=commanded: raiser/tile (FAILED)")
    assert "\n" not in summary


def test_newer_runs_that_are_not_complete_are_left_out_and_named(root):
    """A newer run of a model that was killed (or failed, or is still running) does not push its complete
    run off the board: compare keeps the complete one and names the one left out."""
    out, runs = root
    tracker = trk.Tracker(f"sqlite:///{out / 'mlflow.db'}", f"skidbench-{DS}",
                          dataset_id=runs[0].children[0] and _dataset_id(out))  # fmt: skip
    tags = {
        run_tags.TAG_DATASET: DS,
        run_tags.TAG_INPUTS: "commanded",
        run_tags.TAG_ROLE: "child",
        run_tags.TAG_MODEL: "chi",
        run_tags.TAG_TERRAIN: "tile",
    }
    killed = tracker.start("chi/tile", tags)
    tracker.kill(killed)
    # its rows, as evaluate writes those of the run it was at when interrupted (its cells, KILLED); a run
    # logged without an evaluate (a library call) is judged by itself
    results = rt.Writer(Layout(out, DS), "", name="interrupted")
    facts = rt.RunFacts("", killed, "chi", "commanded", "tile", dataset_id=_dataset_id(out),
                        experiment=f"skidbench-{DS}", user=run_tags.current_user())  # fmt: skip
    results.add(rt.unscored(facts, ["cv", "ld"], [6.0], "KILLED", trk.INTERRUPTED))
    results.finish("KILLED")
    res = run_compare(compose("compare", out, NO_FIGS))
    chi_run = next(c.run_id for c in runs[1].children if c.model == "chi")
    assert _board(out).set_index("model").loc["chi", "run_id"] == chi_run
    (line,) = [x for x in res.left_out if x.startswith("chi/tile")]
    assert f"run {killed[:8]}" in line and "KILLED: interrupted (Ctrl-C)" in line
    assert f"the board has its run {chi_run[:8]}" in line
    assert "## Newer runs left out" in res.report.read_text()
    assert line in (out / DS / "reports" / "leaderboard-commanded.md").read_text()
    # the same rows again: no new time-stamped copy (the rows' columns come in one order)
    again = run_compare(compose("compare", out, NO_FIGS))
    same = "leaderboard inputs=commanded: leaderboard-commanded.csv: the same rows as before"
    assert any(w.startswith(same) for w in again.written), again.written


def _dataset_id(out):
    return json.loads((out / DS / "dataset.json").read_text())["fingerprint"]


@pytest.mark.slow  # a CLI run
def test_compare_names_any_dataset_of_the_root(root):
    """A root with two datasets: `compare dataset=<name>` (no source arguments; the default source is the
    simulator) reads the named one, as do `parent_run_id=<its evaluate>` and `mlflow.experiment=<its
    experiment>`; `skidbench datasets` shows each dataset's board per protocol."""
    out, runs = root
    env = {**os.environ, "SKIDBENCH_OUT": str(out)}
    env.pop("MLFLOW_TRACKING_URI", None)
    cmd = [sys.executable, "-m", "skidbench.pipeline.cli.main", "compare", f"dataset={OTHER}", *NO_FIGS]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "| 1 | alpha |" in proc.stdout and "| 2 | beta |" in proc.stdout
    assert set(_board(out, OTHER)["model"]) == {"alpha", "beta"}
    assert set(_board(out, OTHER)["dataset_id"]) == {OTHER_ID}

    client = mlflow.MlflowClient(f"sqlite:///{out / 'mlflow.db'}")
    parent = client.search_runs(
        [client.get_experiment_by_name(f"skidbench-{OTHER}").experiment_id],
        "tags.`skidbench.role` = 'parent'",
    )[0].info.run_id
    res = run_compare(compose("compare", out, [f"parent_run_id={parent}", *NO_FIGS]))
    assert res.dataset == OTHER and "| alpha |" in res.leaderboard_md
    res = run_compare(compose("compare", out, [f"mlflow.experiment=skidbench-{OTHER}", *NO_FIGS]))
    assert res.dataset == OTHER and "| beta |" in res.leaderboard_md
    res = run_compare(compose("compare", out, NO_FIGS))  # the default dataset is still the simulated one
    assert res.dataset == DS and "| chi |" in res.leaderboard_md

    from skidbench.benchmark.board.selection import dataset_boards

    boards = dataset_boards(out, {DS: _dataset_id(out), OTHER: OTHER_ID})
    assert boards[OTHER] == [
        "inputs=commanded: 2 model(s) x 1 terrain(s) complete, from 1 evaluate(s), newest run "
        + boards[OTHER][0].split("newest run ")[1]
    ]
    assert boards[OTHER][0].endswith(f"(evaluate {parent})")
    assert boards[DS][0].startswith(
        "inputs=commanded: 2 model(s) x 1 terrain(s) complete, 1 without a complete"
    )


def test_leaderboard_files_are_kept_with_a_time_stamp_and_a_latest_copy(tmp_path):
    paths, line = brd.write_leaderboard(tmp_path, "response", "a,b\n1,2\n", "# first\n")
    stamped_csv, stamped_md, latest_csv, latest_md = paths
    assert latest_csv.name == "leaderboard-response.csv" and latest_md.read_text() == "# first\n"
    assert stamped_csv.name.startswith("leaderboard-response-") and stamped_csv.read_text() == "a,b\n1,2\n"
    assert line == f"{stamped_csv.name} (latest: leaderboard-response.csv)"
    # the same rows again: no second stamped copy, and it says so
    _, line = brd.write_leaderboard(tmp_path, "response", "a,b\n1,2\n", "# again\n")
    assert "the same rows as before" in line and len(list(tmp_path.glob("leaderboard-response-*.csv"))) == 1
    # other rows, in the same second: a new stamped pair; the first is kept, unchanged
    paths2, _ = brd.write_leaderboard(tmp_path, "response", "a,b\n3,4\n", "# second\n")
    assert paths2[0] != stamped_csv and stamped_csv.read_text() == "a,b\n1,2\n"
    assert (
        latest_csv.read_text() == "a,b\n3,4\n" and len(list(tmp_path.glob("leaderboard-response-*.csv"))) == 2
    )


def test_a_stage_with_failed_runs_exits_3_and_an_interrupt_130_in_one_line(capsys):
    from skidbench.pipeline.cli.main import stage
    from skidbench.pipeline.core.errors import EXIT_INTERRUPTED, EXIT_PARTIAL, PartialFailure

    @stage("evaluate", home=False, runs=True, interrupted="its open runs are marked KILLED")
    def partly(cfg=None):
        raise PartialFailure("1 of 2 model run(s) FAILED under inputs=commanded: raiser/tile (FAILED)")

    @stage("evaluate", home=False, runs=True, interrupted="its open runs are marked KILLED")
    def interrupted(cfg=None):
        raise KeyboardInterrupt

    with pytest.raises(SystemExit) as exc:
        partly()
    assert exc.value.code == EXIT_PARTIAL == 3
    err = capsys.readouterr().err
    assert (
        err == "skidbench evaluate: 1 of 2 model run(s) FAILED under inputs=commanded: raiser/tile (FAILED)\n"
    )
    with pytest.raises(SystemExit) as exc:
        interrupted()
    assert exc.value.code == EXIT_INTERRUPTED == 130
    err = capsys.readouterr().err
    assert err.strip() == "skidbench evaluate: interrupted (Ctrl-C); its open runs are marked KILLED"
