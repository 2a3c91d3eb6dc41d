"""`skidbench compare` on runs logged by `run_benchmark` (synthetic splits, tiny models, SQLite in tmp):
run selection, the leaderboard (FAILED rows kept, with reasons), the report and its figures."""

from __future__ import annotations

import mlflow
import numpy as np
import pandas as pd
import pytest
from _bench_data import JACKAL, compose, fit_fn, write_splits

from skidbench.benchmark import figures as figs
from skidbench.benchmark.compare import CompareError, markdown_table, run_compare
from skidbench.benchmark.evaluate import run_benchmark

DS = "sim-mini"


@pytest.fixture(scope="module")
def two_evaluations(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    mp.delenv("MLFLOW_TRACKING_URI", raising=False)
    out = tmp_path_factory.mktemp("compare")
    write_splits(out / DS, counts={"train": 1, "cv": 1, "ld": 1}, duration_s=20.0)
    first = run_benchmark(compose("evaluate", out, ["models=[ideal_t]"]), fit_fn=fit_fn, log_figures=False)
    second = run_benchmark(
        compose("evaluate", out, ["models=[chi,ideal_t,broken]"]), fit_fn=fit_fn, log_figures=False
    )
    # the newest evaluate is under another input protocol: never ranked with the commanded ones
    third = run_benchmark(
        compose("evaluate", out, ["models=[chi,ideal_t]", "inputs=measured"]),
        fit_fn=fit_fn,
        log_figures=False,
    )
    assert third.inputs == "measured"
    yield out, first, second
    mp.undo()


def test_latest_parent_by_default_with_failed_rows_and_reasons(two_evaluations):
    out, _, second = two_evaluations
    res = run_compare(compose("compare", out))
    assert res.parent_run_id == second.parent_run_id  # the latest under inputs=commanded (the default)
    assert res.inputs == "commanded"
    lb = res.leaderboard_md.splitlines()
    assert lb[2].startswith("| 1 | chi |")  # best first
    assert any(line.startswith("| 3 | broken |") and "grass (FAILED)" in line for line in lb)
    csv = pd.read_csv(out / DS / "reports" / "leaderboard.csv")
    assert set(csv["model"]) == {"chi", "ideal_t", "broken"} and len(csv) == 6
    assert (csv[csv["model"] == "broken"]["status"] == "FAILED").all()
    text = res.report.read_text()
    assert "## Failed runs" in text and "singular normal equations" in text
    for f in ("fig3_translational_rmsre.png", "fig4_rotational_rmsre.png"):
        assert (out / DS / "reports" / f).stat().st_size > 5000 and f"]({f})" in text
    # Figs. 5-7 need fits on disk (the tests' models have none): skipped with a note, not a crash
    assert any(n.startswith("Fig. 6 skipped") for n in res.notes) and "## Notes" in text
    # the protocols side by side per model (commanded / measured: the latest evaluate of each)
    assert "## The input protocols side by side (commanded / measured)" in text
    chi = next(line for line in res.decomposition_md.splitlines() if line.startswith("| chi |"))
    assert chi.count(" / ") == 4  # one pair of values per metric
    assert (out / DS / "reports" / "fig_protocols.png").stat().st_size > 5000
    client = mlflow.MlflowClient(f"sqlite:///{out / 'mlflow.db'}")
    arts = {a.path for a in client.list_artifacts(second.parent_run_id, "report")}
    assert {"report/report.md", "report/leaderboard.csv", "report/fig3_translational_rmsre.png"} <= arts


def test_select_an_older_parent_a_filter_or_every_run(two_evaluations):
    out, first, _ = two_evaluations
    res = run_compare(
        compose("compare", out, [f"parent_run_id={first.parent_run_id}", "figures.enabled=false"])
    )
    assert "| ideal_t |" in res.leaderboard_md and "| chi |" not in res.leaderboard_md
    res = run_compare(
        compose("compare", out, ["figures.enabled=false", "filter=\"tags.`skidbench.terrain` = 'tile'\""])
    )
    csv = pd.read_csv(out / DS / "reports" / "leaderboard.csv")
    assert set(csv["terrain"]) == {"tile"}
    # every child run: of two protocols here, which compare refuses to rank together
    with pytest.raises(CompareError, match=r"different input protocols \['commanded', 'measured'\]"):
        run_compare(compose("compare", out, ["parent_run_id=null", "figures.enabled=false"]))
    only = "filter=\"tags.`skidbench.inputs` = 'commanded'\""
    res = run_compare(
        compose("compare", out, ["parent_run_id=null", only, "figures.enabled=false", "log_to_mlflow=false"])
    )
    csv = pd.read_csv(out / DS / "reports" / "leaderboard.csv")
    assert len(csv) == 6  # the latest run of each (model, terrain) across both commanded evaluations
    assert set(csv["inputs"]) == {"commanded"}


def test_compare_ranks_the_runs_of_the_protocol_asked_for(two_evaluations):
    out, _, _ = two_evaluations
    res = run_compare(compose("compare", out, ["inputs=measured", "figures.enabled=false"]))
    assert res.inputs == "measured" and "| broken |" not in res.leaderboard_md
    assert "inputs=measured" in res.report.read_text()


def test_a_board_of_two_protocols_is_refused():
    from skidbench.benchmark.compare import summary_table

    board = pd.DataFrame(
        {"model": ["chi", "chi"], "inputs": ["commanded", "response"], "terrain": ["tile", "tile"],
         "status": ["FINISHED"] * 2, "rmsre_translational_ld_6s": [0.1, 0.05]}
    )  # fmt: skip
    with pytest.raises(CompareError, match="never ranked together"):
        summary_table(board, 6.0, "rmsre_translational_ld")


def test_no_match_and_bad_filter_are_one_line_errors(two_evaluations):
    out, _, _ = two_evaluations
    with pytest.raises(CompareError, match="no model runs match"):
        run_compare(compose("compare", out, ["filter=\"tags.`skidbench.model` = 'nope'\""]))
    with pytest.raises(CompareError, match="search_runs"):
        run_compare(compose("compare", out, ["filter='metrics.x >>> 1'"]))
    with pytest.raises(
        CompareError, match="no `skidbench evaluate` run under inputs=commanded in experiment"
    ):
        run_compare(compose("compare", out, ["mlflow.experiment=empty-one"]))


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
