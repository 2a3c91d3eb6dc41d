"""`skidbench compare` on runs logged by `run_benchmark` (synthetic splits, tiny models, SQLite in tmp):
run selection, the leaderboard (FAILED rows kept, with reasons), the report and its figures."""

from __future__ import annotations

import shutil

import mlflow
import numpy as np
import pandas as pd
import pytest
from _bench_data import JACKAL, TRUE_CHI, calibrate_splits, compose, fit_fn, write_splits

from skidbench.benchmark.board.app import run as run_compare
from skidbench.benchmark.board.tables import CompareError, markdown_table
from skidbench.benchmark.evaluate.app import benchmark as run_benchmark
from skidbench.benchmark.report import data as rd
from skidbench.benchmark.report import figures as figs
from skidbench.benchmark.report.markdown import format_console
from skidbench.benchmark.tracking import store as trk
from skidbench.benchmark.tracking import tags as run_tags
from skidbench.pipeline.core.layout import layout_from_cfg
from skidbench.pipeline.core.schema import read_split

DS = "sim-mini"
#: the board's horizon only: these tests are about run selection, the boards and the report; a compare of
#: evaluates scored at several horizons also ranks every horizon's aggressiveness strata (reports/horizons.md,
#: which the README quick start's compare writes)
H6 = "horizons=[6.0]"


@pytest.fixture(scope="module")
def two_evaluations(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    mp.delenv("MLFLOW_TRACKING_URI", raising=False)
    out = tmp_path_factory.mktemp("compare")
    write_splits(out / DS, counts={"train": 1, "cv": 1, "ld": 1}, duration_s=20.0)
    first = run_benchmark(
        compose("evaluate", out, ["models=[ideal_t]", H6]), fit_fn=fit_fn, log_figures=False
    )
    second = run_benchmark(
        compose("evaluate", out, ["models=[chi,ideal_t,broken]", H6]), fit_fn=fit_fn, log_figures=False
    )
    # the newest evaluate is under another input protocol: never ranked with the commanded ones
    third = run_benchmark(
        compose("evaluate", out, ["models=[chi,ideal_t]", "inputs=measured", H6]),
        fit_fn=fit_fn,
        log_figures=False,
    )
    assert third.inputs == "measured"
    yield out, first, second
    mp.undo()


def test_latest_parent_by_default_with_failed_rows_and_reasons(two_evaluations):
    out, _, second = two_evaluations
    res = run_compare(compose("compare", out))
    # the newest complete run of each (model, terrain) under inputs=commanded (the default): the second's
    assert res.parent_run_id is None and res.parents == [second.parent_run_id]
    assert res.inputs == "commanded"
    lb = res.leaderboard_md.splitlines()
    assert lb[2].split("|")[2].strip() == "chi"  # best first (ranked or not: its blocks decide)
    # a model that failed everywhere is shown, not ranked, with the reason; the floor is a reference row
    assert any(line.startswith("|  | broken |") and "grass (FAILED)" in line and "not ranked" in line
               for line in lb)  # fmt: skip
    assert any(line.startswith("|  | floor |") and "reference" in line for line in lb)
    csv = pd.read_csv(out / DS / "reports" / "leaderboard-commanded.csv")
    assert set(csv["model"]) == {"chi", "ideal_t", "broken"} and len(csv) == 6
    assert (csv[csv["model"] == "broken"]["status"] == "FAILED").all()
    # added columns: each cell's interval and blocks, the terrain's floor
    assert {"trans LD % lo", "trans LD % hi", "trans LD % blocks", "floor trans LD %"} <= set(csv.columns)
    assert (csv["floor trans LD %"] < csv[csv["model"] == "chi"]["trans LD %"].min()).all()
    chi = csv[csv["model"] == "chi"]
    assert (chi["trans LD % lo"] <= chi["trans LD %"]).all() and (
        chi["trans LD %"] <= chi["trans LD % hi"]
    ).all()
    text = res.report.read_text()
    assert "## Failed runs" in text and "singular normal equations" in text
    for f in ("fig3_translational_rmsre.png", "fig4_rotational_rmsre.png", "fig_end_position_rmse.png"):
        assert (out / DS / "reports" / f).stat().st_size > 5000 and f"]({f})" in text
    # Fig. 6 shows the friction model by default, which these runs do not have: skipped with a note
    assert any(n.startswith("Fig. 6 skipped") and "friction/grass.surfaces.npz: no Fig. 6 surfaces" in n
               for n in res.notes) and "## Notes" in text  # fmt: skip
    # the protocols side by side per model (commanded / measured: the latest evaluate of each)
    assert "## The input protocols side by side (commanded / measured)" in text
    chi = next(line for line in res.decomposition_md.splitlines() if line.startswith("| chi |"))
    assert chi.count(" / ") == 6  # one pair of values per headline metric (trans, rot, endpos) and split
    assert (out / DS / "reports" / "fig_protocols.png").stat().st_size > 5000
    client = mlflow.MlflowClient(f"sqlite:///{out / 'mlflow.db'}")
    arts = {a.path for a in client.list_artifacts(second.parent_run_id, "report")}
    assert {
        "report/report.md",
        "report/leaderboard-commanded.csv",
        "report/fig3_translational_rmsre.png",
    } <= arts


def test_the_end_position_error_is_logged_printed_and_on_the_leaderboard(two_evaluations):
    """The registry's absolute end-position error (benchmark/scoring/metrics.py) reaches every output: each
    child
    run's MLflow metrics, evaluate's console summary, compare's leaderboard files (the mean over terrains
    of the logged values) and console."""
    from skidbench.benchmark.evaluate.console import format_result

    out, _, second = two_evaluations
    client = mlflow.MlflowClient(f"sqlite:///{out / 'mlflow.db'}")
    logged = {}
    for c in second.children:
        metrics = client.get_run(c.run_id).data.metrics
        if c.status == "FINISHED":
            assert metrics["ld_6s_endpos_rmse_m"] == c.metrics["ld_6s_endpos_rmse_m"] > 0
            assert metrics["ld_6s_endpos_windows"] > 0
            logged.setdefault(c.model, []).append(metrics["ld_6s_endpos_rmse_m"])
    assert "endpos LD 6s m" in format_result(second)
    res = run_compare(compose("compare", out, ["figures.enabled=false", "log_to_mlflow=false"]))
    csv = pd.read_csv(out / DS / "reports" / "leaderboard-commanded.csv")
    assert {"endpos CV m", "endpos LD m", "endpos LD n"} <= set(csv.columns)
    chi = csv[csv["model"] == "chi"]
    assert sorted(chi["endpos LD m"]) == pytest.approx(sorted(logged["chi"]))
    head = res.leaderboard_md.splitlines()[0]
    assert "| endpos CV m | endpos CV n | endpos LD m | endpos LD n |" in head
    row = next(line for line in res.leaderboard_md.splitlines() if line.split("|")[2:3] == [" chi "])
    cells = [c.strip() for c in row.split("|")]
    col = head.split("|").index(" endpos LD m ")
    assert float(cells[col]) == pytest.approx(np.mean(logged["chi"]), abs=0.01)
    assert "endpos LD m" in format_console(res)


def test_select_an_older_parent_a_filter_or_every_run(two_evaluations):
    out, first, _ = two_evaluations
    res = run_compare(
        compose("compare", out, [f"parent_run_id={first.parent_run_id}", "figures.enabled=false"])
    )
    assert "| ideal_t |" in res.leaderboard_md and "| chi |" not in res.leaderboard_md
    res = run_compare(
        compose("compare", out, ["figures.enabled=false", "filter=\"tags.`skidbench.terrain` = 'tile'\""])
    )
    csv = pd.read_csv(out / DS / "reports" / "leaderboard-commanded.csv")
    assert set(csv["terrain"]) == {"tile"}
    # every child run: of two protocols here, which compare refuses to rank together
    with pytest.raises(CompareError, match=r"different input protocols \['commanded', 'measured'\]"):
        run_compare(compose("compare", out, ["parent_run_id=null", "figures.enabled=false"]))
    only = "filter=\"tags.`skidbench.inputs` = 'commanded'\""
    res = run_compare(
        compose("compare", out, ["parent_run_id=null", only, "figures.enabled=false", "log_to_mlflow=false"])
    )
    csv = pd.read_csv(out / DS / "reports" / "leaderboard-commanded.csv")
    assert len(csv) == 6  # the latest run of each (model, terrain) across both commanded evaluations
    assert set(csv["inputs"]) == {"commanded"}


def test_compare_ranks_the_runs_of_the_protocol_asked_for(two_evaluations):
    out, _, _ = two_evaluations
    res = run_compare(compose("compare", out, ["inputs=measured", "figures.enabled=false"]))
    assert res.inputs == "measured" and "| broken |" not in res.leaderboard_md
    assert "inputs=measured" in res.report.read_text()


def test_a_board_of_two_protocols_is_refused():
    from skidbench.benchmark.board.tables import summary_table

    board = pd.DataFrame(
        {"model": ["chi", "chi"], "inputs": ["commanded", "response"], "terrain": ["tile", "tile"],
         "status": ["FINISHED"] * 2, "ld_6s_trans_rmsre_pct": [10.0, 5.0]}
    )  # fmt: skip
    with pytest.raises(CompareError, match="never ranked together"):
        summary_table(board, 6.0, "ld_trans")


def test_no_match_and_bad_filter_are_one_line_errors(two_evaluations):
    out, _, _ = two_evaluations
    with pytest.raises(CompareError, match="no complete model run under inputs=commanded .* matching filter"):
        run_compare(compose("compare", out, ["filter=\"tags.`skidbench.model` = 'nope'\""]))
    with pytest.raises(CompareError, match="search_runs"):
        run_compare(compose("compare", out, ["filter='metrics.x >>> 1'"]))
    with pytest.raises(
        CompareError, match="no complete model run under inputs=commanded .* experiment 'empty-one'"
    ):
        run_compare(compose("compare", out, ["mlflow.experiment=empty-one"]))


def test_compare_under_an_output_root_never_evaluated_creates_no_store(tmp_path):
    """compare only reads: on a root with no MLflow store it says so, and leaves no mlflow.db behind
    (opening a SQLite store creates the file and MLflow's own Default experiment)."""
    with pytest.raises(CompareError, match="no MLflow store at sqlite:.*run `skidbench evaluate` first"):
        run_compare(compose("compare", tmp_path))
    assert not (tmp_path / "mlflow.db").exists()


def test_compare_links_the_parent_and_a_saved_view_of_its_children_in_the_model_training_ui(two_evaluations):
    import json
    import urllib.parse

    out, _, second = two_evaluations
    res = run_compare(compose("compare", out, ["figures.enabled=false", "log_to_mlflow=false"]))
    client = mlflow.MlflowClient(f"sqlite:///{out / 'mlflow.db'}")
    exp = client.get_experiment_by_name(f"skidbench-{DS}")
    base = f"http://127.0.0.1:5000/#/experiments/{exp.experiment_id}"
    # every link opens MLflow's model-training pages, not its GenAI ones
    assert all("workflowType=machine_learning" in url for url in res.links.values())
    assert res.links["parent run"] == f"{base}/runs/{second.parent_run_id}?workflowType=machine_learning"
    view, charts = res.links["runs table (saved view)"], res.links["charts of its model runs"]
    key = urllib.parse.parse_qs(view.split("?")[1])["viewStateShareKey"][0]
    assert urllib.parse.parse_qs(charts.split("?")[1]) == {
        "viewStateShareKey": [key], "workflowType": ["machine_learning"], "compareRunsMode": ["CHART"]
    }  # fmt: skip
    saved = json.loads(exp.tags[f"mlflow.sharedViewState.{key}"])
    state = json.loads(saved["state"])
    assert saved["name"] == client.get_run(second.parent_run_id).info.run_name
    assert state["searchFilter"] == f"tags.`mlflow.parentRunId` = '{second.parent_run_id}'"
    assert state["orderByKey"] == "metrics.`ld_6s_trans_rmsre_pct`" and state["orderByAsc"] is True
    ld = ["metrics.`ld_6s_trans_rmsre_pct`", "metrics.`ld_6s_rot_rmsre_pct`"]
    assert state["selectedColumns"][:2] == ld
    # the charts: one bar chart per RMSRE column, the errors' section first
    assert [c["metricKey"] for c in state["compareRunCharts"]][:2] == [m[9:-1] for m in ld]
    assert {c["type"] for c in state["compareRunCharts"]} == {"BAR"}
    assert state["compareRunSections"][0]["uuid"] == state["compareRunCharts"][0]["metricSectionId"]
    text = format_console(res)
    assert all(url in text for url in res.links.values())


def test_each_protocol_and_each_user_has_a_latest_view_of_its_own(two_evaluations, tmp_path, monkeypatch):
    import json

    from skidbench.benchmark.tracking.mlflow_ui import TAG_SAVED_VIEW, latest_key

    out, first, second = two_evaluations
    exp = mlflow.MlflowClient(f"sqlite:///{out / 'mlflow.db'}").get_experiment_by_name(f"skidbench-{DS}")
    views = {k.removeprefix(TAG_SAVED_VIEW): json.loads(json.loads(v)["state"]) for k, v in exp.tags.items()
             if k.startswith(TAG_SAVED_VIEW)}  # fmt: skip
    assert latest_key("commanded") in views
    assert latest_key("commanded").endswith("-" + run_tags.current_user())
    # the latest view under one protocol shows the latest evaluate under that protocol, whatever came after
    assert views[latest_key("commanded")]["searchFilter"].endswith(f"'{second.parent_run_id}'")
    assert f"evaluate-{first.parent_run_id[:8]}" in views
    monkeypatch.setenv("SKIDBENCH_USER", "someone else")
    assert latest_key("commanded") == "latest-commanded-someone_else"


def test_compare_reads_the_callers_own_latest_runs_and_says_when_someone_evaluated_after(
    tmp_path, monkeypatch
):
    """Two people, one store, one dataset: each compare reports its caller's own latest evaluate (never
    another's newer one), names the other's newer run in one line, and logs the report to a run of its
    own; `user=<name>` and `user=all` read another's or the newest of anyone's."""
    write_splits(tmp_path / DS, terrains=("tile",), counts={"train": 1, "cv": 1, "ld": 1}, duration_s=20.0)
    runs = {}
    for user, models in (("alice", "[chi,ideal_t]"), ("bob", "[chi]")):
        monkeypatch.setenv("SKIDBENCH_USER", user)
        runs[user] = run_benchmark(compose("evaluate", tmp_path, [f"models={models}", H6]), fit_fn=fit_fn,
                                   log_figures=False).parent_run_id  # fmt: skip
    client = mlflow.MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    for user, run_id in runs.items():
        run = client.get_run(run_id)
        assert run.data.tags["mlflow.user"] == user and f" {user}@" in run.info.run_name
        assert run.data.tags["skidbench.out_root"] == str(tmp_path.absolute())
        assert len(run.data.tags["skidbench.session"]) == 12 and run.data.tags["skidbench.heartbeat"]
    monkeypatch.setenv("SKIDBENCH_USER", "alice")
    res = run_compare(compose("compare", tmp_path, ["figures.enabled=false"]))
    assert res.parents == [runs["alice"]]
    assert "| ideal_t |" in res.leaderboard_md  # alice's board (bob evaluated chi only)
    assert [n for n in res.notes if n.startswith("bob evaluated this dataset after you")]
    assert not client.list_artifacts(runs["alice"], "report") == []  # her own run holds her report
    bob = run_compare(compose("compare", tmp_path, ["figures.enabled=false", "user=bob"]))
    assert bob.parents == [runs["bob"]] and "| ideal_t |" not in bob.leaderboard_md
    assert client.list_artifacts(runs["bob"], "report") == []  # alice never writes into bob's run
    assert any("not to bob's evaluate run" in n for n in bob.notes)
    # everyone's: the newest complete run of each (model, terrain): bob's chi beside alice's ideal_t
    anyone = run_compare(compose("compare", tmp_path, ["figures.enabled=false", "user=all"]))
    assert set(anyone.parents) == {runs["alice"], runs["bob"]}
    # its report goes to a compare run of alice's, whose description (shown first in the UI) is the board
    (exp,) = [e.experiment_id for e in client.search_experiments() if e.name != "Default"]
    newest = client.search_runs([exp], "tags.`skidbench.role` = 'compare'", order_by=["start_time DESC"])[0]
    note = newest.data.tags["mlflow.note.content"]
    assert note.startswith("**Leaderboard**, inputs=commanded, 6 s horizon, as `skidbench compare` ranks it")
    assert anyone.leaderboard_md in note and all(f"`{r}`" in note for r in runs.values())
    monkeypatch.setenv("SKIDBENCH_USER", "carol")
    with pytest.raises(CompareError, match="no model run of user carol .* user=bob"):
        run_compare(compose("compare", tmp_path, ["figures.enabled=false"]))


def test_compare_names_other_experiments_holding_runs_of_the_same_content(tmp_path):
    """One recording under two dataset names (two mount points, each with its automatic name): two
    experiments; compare's board of one says, in one line, where the other's runs are and what to type."""
    from skidbench.benchmark.board import selection as sel

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    here = trk.Tracker(uri, "skidbench-amrl-day2-aaaaaa", artifact_root=tmp_path, dataset_id="c0ffee")
    assert sel.same_data_elsewhere(here) is None  # alone in the store
    for name, ident in (("skidbench-amrl-day2-bbbbbb", "c0ffee"), ("skidbench-other-cccccc", "0ther"),
                        ("skidbench-amrl-day2-aaaaaa-transfer", "c0ffee")):  # fmt: skip
        trk.Tracker(uri, name, artifact_root=tmp_path, dataset_id=ident).start("run", {})
    line = sel.same_data_elsewhere(here)
    assert "experiment(s) 'skidbench-amrl-day2-bbbbbb'," in line and "source.dataset=<name>" in line
    assert "skidbench-other" not in line and "transfer" not in line


def test_the_parent_run_shows_the_leaderboard_and_each_models_mean_and_gap_to_the_next():
    from skidbench.benchmark.tracking.mlflow_ui import leaderboard

    rows = [("a+b", "tile", "FINISHED", {"x": 1.0, "y": 9.0}), ("a+b", "grass", "FINISHED", {"x": 3.0,
            "y": 7.0}), ("c", "tile", "FINISHED", {"x": 4.0, "y": 1.0}), ("c", "grass", "FAILED", {}),
            ("d", "tile", "FAILED", {})]  # fmt: skip
    md, metrics = leaderboard(rows, ["x", "y"], ["X %", "Y %"])
    assert metrics == {"a_b.mean_x": 2.0, "a_b.gap_to_next_x": 2.0, "c.mean_x": 4.0,
                       "c.mean_y": 1.0, "c.gap_to_next_y": 7.0, "a_b.mean_y": 8.0}  # fmt: skip
    lines = md.splitlines()
    assert lines[0] == "| order | model | X % | Y % | gap to next (X %) | terrains |"  # not a ranking
    assert lines[2:] == ["| 1 | a+b | 2.00 | 8.00 | 2.00 | 2/2 |", "| 2 | c | 4.00 | 1.00 |  | 1/2 |",
                         "| 3 | d | n/a | n/a |  | 0/1 |"]  # fmt: skip


def test_an_evaluates_parent_run_carries_its_leaderboard(two_evaluations):
    out, _, second = two_evaluations
    run = mlflow.MlflowClient(f"sqlite:///{out / 'mlflow.db'}").get_run(second.parent_run_id)
    note = run.data.tags["mlflow.note.content"]
    assert note.startswith("**Leaderboard**, inputs=commanded, 6 s horizon: mean over terrains")
    assert "| 1 | chi |" in note and "not a ranking" in note and "Benchmark of 3 models on 2 terrains" in note
    chi = [c.metrics["ld_6s_trans_rmsre_pct"] for c in second.children if c.model == "chi"]
    assert run.data.metrics["chi.mean_ld_6s_trans_rmsre_pct"] == pytest.approx(np.mean(chi), abs=1e-3)
    assert run.data.metrics["chi.gap_to_next_ld_6s_trans_rmsre_pct"] > 0


def test_markdown_table_formats_numbers_and_missing_values():
    md = markdown_table(pd.DataFrame({"model": ["a|b"], "x": [1.234], "y": [np.nan], "z": [0.0001]}))
    assert md.splitlines()[2] == "| a\\|b | 1.23 | n/a | <0.01 |"


def test_fig6_and_fig7_drawing_from_arrays(tmp_path):
    g = np.linspace(-10, 10, 11)
    wl, wr = np.meshgrid(g, g)
    _, w = JACKAL.twist_from_wheel_rates(wl, wr)
    p = figs.yaw_rate_surfaces(
        wl, wr, {a: w * (1 - 0.02 * a) for a in (-8.0, 0.0, 8.0)}, "t", tmp_path / "f6.png"
    )
    assert p.stat().st_size > 10_000
    truth = np.column_stack([np.linspace(0, 3, 181), np.zeros(181), np.zeros(181)])
    samples = [
        {
            "split": sp,
            "sequence": "s",
            "t0": 1.0,
            "truth": truth,
            "pred": {"ideal": truth * 1.1, "friction": truth},
        }
        for sp in ("cv", "ld")
    ]
    assert figs.trajectories(samples, 6.0, tmp_path / "f7.png").stat().st_size > 10_000


def test_the_window_error_figure_drawn_again_is_the_png_of_a_new_figure(tmp_path, monkeypatch):
    """window_error_figure redraws one kept figure per number of splits: a run's PNG does not depend on
    the runs drawn before it (more sequences, other splits, larger errors)."""
    rng = np.random.default_rng(0)

    def windows(splits, n_seq, scale):
        keys = [(h, sp, q, t) for h in (6.0, 2.0) for sp in splits for q in range(n_seq) for t in range(18)]
        rows = [{"split": sp, "horizon_s": h, "sequence": f"s{q}", "t0": t / 2,
                 "rel_trans": scale * rng.random(), "rel_rot": scale * rng.random()}
                for h, sp, q, t in keys]  # fmt: skip
        return pd.DataFrame(rows)

    runs = [windows(("cv", "ld"), 3, 5.0), windows(("cv",), 1, 1.0), windows(("cv", "ld"), 1, 0.2)]
    for k, w in enumerate(runs):
        figs.window_error_figure(w, f"run {k}", tmp_path / f"after{k}.png")
    monkeypatch.setattr(figs, "_WINDOW_FIGURES", {})  # no figure kept: each drawn new
    for k, w in enumerate(runs):
        new = figs.window_error_figure(w, f"run {k}", tmp_path / f"new{k}.png")
        assert new.read_bytes() == (tmp_path / f"after{k}.png").read_bytes()
        monkeypatch.setattr(figs, "_WINDOW_FIGURES", {})
    assert (tmp_path / "after0.png").read_bytes() != (tmp_path / "after2.png").read_bytes()


def test_compare_draws_figs_5_to_7_from_what_evaluate_wrote_with_splits_and_fits_gone(tmp_path, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    ds = tmp_path / DS
    write_splits(ds, terrains=("grass",), counts={"train": 1, "cv": 1, "ld": 1}, duration_s=20.0)
    cfg = compose("evaluate", tmp_path, ["models=[chi,ideal_t]", "report_data.fig7_windows=2"])
    calibrate_splits(cfg)  # the wheel-response figure's data: only `calibrate` identifies it
    run_benchmark(cfg, fit_fn=fit_fn, log_figures=False)
    layout = layout_from_cfg(cfg)
    chi, ideal = layout.eval_stem("chi", "grass"), layout.eval_stem("ideal_t", "grass")
    # Fig. 5: the data's yaw rate is chi * the commanded one, which the fitted chi model predicts exactly
    res, split = rd.read_residuals(chi)
    assert split == "ld" and len(res) == 600
    assert np.allclose(res["wz_pred"], res["wz_meas"], atol=1e-9)
    # Fig. 6: the chi model's yaw rate is chi * r (wr - wl) / track at every commanded acceleration
    z = rd.read_surfaces(chi)
    _, w = JACKAL.twist_from_wheel_rates(z["wl"], z["wr"])
    assert list(z["accels"]) == [-8.0, 0.0, 8.0] and z["wz"].shape == (3, 31, 31)
    assert np.allclose(z["wz"], TRUE_CHI * w[None], atol=1e-9)
    # Fig. 7: the same windows for every model, each prediction starting at the true pose; its truth is
    # the split's ground truth, and chi ends nearer it than the ideal model
    tc, _ = rd.read_trajectories(chi)
    ti, _ = rd.read_trajectories(ideal)
    assert tc.groupby(["split", "window"]).ngroups == 4
    assert tc[["split", "sequence", "t0", "k"]].equals(ti[["split", "sequence", "t0", "k"]])
    split_df, _ = read_split(ds / "splits" / "grass" / "ld" / "grass_ld_00.parquet")
    first = tc[(tc["split"] == "ld") & (tc["window"] == 0)]
    truth = first[first["role"] == "truth"]
    k0 = int(np.argmin(np.abs(split_df["t"].to_numpy() - truth["t0"].iloc[0])))
    assert np.allclose(truth[["x", "y", "yaw"]], split_df[["x", "y", "yaw"]].to_numpy()[k0 : k0 + len(truth)])

    def end_error(df):
        ends = df.groupby(["split", "window", "role"])[["x", "y"]].last().unstack("role")
        return np.hypot(ends["x"]["pred"] - ends["x"]["truth"], ends["y"]["pred"] - ends["y"]["truth"])

    assert (end_error(tc) < end_error(ti)).all()
    assert np.allclose(tc.loc[tc["k"] == 0, ["x", "y", "yaw"]].to_numpy()[::2],
                       tc.loc[tc["k"] == 0, ["x", "y", "yaw"]].to_numpy()[1::2])  # fmt: skip

    # compare recomputes nothing: with the splits, the manifest and any fit gone, every figure is drawn
    for d in (layout.splits, layout.manifest.parent, layout.root / "fits"):
        shutil.rmtree(d, ignore_errors=True)
    out = run_compare(compose("compare", tmp_path, ["figures.fig5_model=chi", "figures.fig6_model=chi"]))
    assert not out.notes, out.notes
    figures = ("fig5_residual_vs_acceleration.png", "fig6_yaw_rate_surfaces.png", "fig7_trajectories.png",
               "fig_wheel_response.png")  # fmt: skip
    for f in figures:
        assert (ds / "reports" / f).stat().st_size > 10_000
    assert "accelerations [-8.0, 0.0, 8.0] rad/s²" in out.report.read_text()  # the ones evaluate computed


def test_figures_are_drawn_apart_in_job_order_and_a_failing_one_is_a_note(tmp_path):
    """compare's figures in forked workers (one per core): the files and the report's entries come in the
    order of the jobs, each job's file is written by a worker when there are two cores, and a job that
    raises is one note naming its figure while the others are drawn."""
    import os

    from skidbench.benchmark.report.compare_figures import draw_figures
    from skidbench.pipeline.runner.forked import cores

    def write(path):
        path.write_text(str(os.getpid()))
        return path

    def fails(path):
        raise FileNotFoundError("no fits/friction/tile.json")

    jobs = [
        ("a.png", "Fig. 3: first", write),
        ("b.png", "Fig. 6: needs fits", fails),
        ("c.png", "Fig. 7: last", write),
    ]
    files, notes = [], []
    md = draw_figures(jobs, tmp_path, files, notes)
    assert files == [tmp_path / "a.png", tmp_path / "c.png"]
    assert [m.splitlines()[0] for m in md] == ["### Fig. 3: first", "### Fig. 7: last"]
    assert notes == ["Fig. 6 skipped: FileNotFoundError: no fits/friction/tile.json"]
    pids = {int(f.read_text()) for f in files}
    assert (os.getpid() not in pids) == (cores() >= 2)
