"""The `make bench` comparisons vo, reproduce and scaling run at toy size and report their keys (no timing
assertions: speed lives in `make bench`)."""

from __future__ import annotations

import math

import pytest

from perf import check, load_all
from perf import reproduce as rep
from perf import scaling as sc
from perf import vo as vo_bench


@pytest.mark.parametrize("name", ["vo", "reproduce", "scaling"])
def test_a_comparison_is_registered_from_its_module_and_its_targets_judge_a_measurement(name):
    comp = load_all()[name]
    assert comp.module == {"vo": vo_bench, "reproduce": rep, "scaling": sc}[name].__name__
    assert comp.targets
    for op, bound in comp.targets.values():
        better, worse = (bound + 1, bound - 1) if op.startswith(">") else (bound - 1, bound + 1)
        assert check(better, (op, bound)) is True and check(worse, (op, bound)) is False
        assert check(f"incomplete ({bound})", (op, bound)) is None  # an unmeasured metric is not judged


def test_vo_tracks_a_short_rendered_drive_and_reports_rates():
    small = {"ground_texture_px": 1024, "wall_texture_px": 256, "n_boxes": 2, "n_posts": 2}
    m = vo_bench.measure(6, small)
    assert m["frames"] == 5 and m["camera_fps"] == 15.0 and m["cores"] <= 2
    assert m["fps"] > 0 and math.isclose(m["realtime_ratio"], m["fps"] / 15.0)
    for key in ("fps_cpu", "decode_ms_per_pair", "keyframes", "lost_frames", "image_size"):
        assert key in m
    assert set(load_all()["vo"].targets) <= set(m)  # a target names a metric the comparison reports


def test_reproduce_stage_wrapper_reports_time_memory_and_a_failing_stage(tmp_path, monkeypatch):
    # evaluate on an empty out root fails fast with a one-line error: the run stops there
    res = rep.run_stage("evaluate", ["scale=tiny"], tmp_path / "outputs", tmp_path)
    assert res["exit"] == 2 and "split" in res["error"]
    assert res["wall_s"] > 0 and res["cpu_s"] > 0 and res["peak_rss_mb"] > 10
    m = rep.metrics({"scale": "tiny", "stages": [res]})
    assert m["stages_ok"] == f"0/{len(rep.STAGES)}" and m["total_wall_min"].startswith("incomplete")
    assert set(load_all()["reproduce"].targets) <= set(m)
    assert m["evaluate_peak_rss_mb"] == res["peak_rss_mb"] and "evaluate_error" in m
    none = rep.metrics(rep.reproduce("tiny", budget_min=0.0))  # no stage started: says why
    assert none["stages_ok"] == f"0/{len(rep.STAGES)}" and none["stopped"].startswith("budget")
    monkeypatch.setenv("SKIDBENCH_OUT", str(tmp_path / "none"))
    ext = rep.extraction_mini_vs_full()
    assert ext["extract_rss_full_mb"].startswith("not measured")


def test_reproduce_counts_the_side_by_side_evaluates_once_as_make_runs_them():
    groups = [[step[0] for step in g] for g in rep._groups()]
    assert ["evaluate", "evaluate_response"] in groups and sum(groups, []) == list(rep.STAGES)
    walls = {"evaluate": 40.0, "evaluate_response": 45.0}
    stages = [
        {"stage": s, "wall_s": walls.get(s, 10.0), "cpu_s": 1.0, "peak_rss_mb": 1.0, "exit": 0,
         "side_by_side": s in rep.SIDE_BY_SIDE}
        for s in rep.STAGES
    ]  # fmt: skip
    m = rep.metrics({"scale": "mini", "stages": stages})
    assert math.isclose(m["total_wall_min"] * 60, 10.0 * (len(rep.STAGES) - 2) + 45.0)
    assert math.isclose(m["total_cpu_min"] * 60, len(rep.STAGES))


def test_scaling_reports_an_exponent_per_model_and_kind():
    m = sc.scaling(factors=(1, 2), seq_rows=240, base_seqs=1, repeats=1, models=["ideal", "edd"])
    assert m["rows"] == "240 / 480"
    for model in ("ideal", "edd"):
        for kind in ("fit", "eval"):
            assert math.isfinite(m[f"{model}_{kind}_exponent"])
            assert len(m[f"{model}_{kind}_cpu_s"].split(" / ")) == 2
    assert m["max_exponent"] == max(v for k, v in m.items() if k.endswith("_exponent"))
    assert set(load_all()["scaling"].targets) <= set(m)
    assert set(sc.builtin_models()) >= {"ideal", "edd", "full_linear", "roc", "enhanced", "friction"}


def test_render_comparison_reports_both_thread_counts_and_identical_pixels():
    from perf import render as render_bench

    assert load_all()["render"].targets == {"max_pixel_diff": ("<=", 0)}
    small = {"ground_texture_px": 1024, "wall_texture_px": 256, "n_boxes": 3, "n_posts": 2}
    m = render_bench.measure(4, rounds=1, render_options=small)
    assert m["pairs"] == 4 and m["max_pixel_diff"] == 0
    assert m["cpu_ms_1thread"] > 0 and m["cpu_ms_2threads"] > 0
    assert math.isclose(m["cpu_ratio"], m["cpu_ms_2threads"] / m["cpu_ms_1thread"])


def test_startup_times_a_command_with_its_cpu_and_names_a_failing_one():
    import os
    import sys

    from perf import startup

    assert load_all()["startup"].module == startup.__name__
    wall, cpu = startup.timed([sys.executable, "-c", "sum(range(10**6))"], dict(os.environ))
    assert wall > 0 and 0 < cpu <= wall + 0.5  # the child's own CPU, reaped: not this process's
    failing = [sys.executable, "-c", "import sys; sys.stderr.write('boom'); sys.exit(3)"]
    with pytest.raises(RuntimeError, match=r"failed \(3\): boom"):
        startup.timed(failing, dict(os.environ))


def test_snapshot_copies_the_boards_with_their_provenance_and_without_the_figures(tmp_path):
    """``python -m perf.snapshot``: report.md's boards without figures, the other protocol's board from its
    leaderboard, the dataset's fingerprint and the runs' commit in the header."""
    from perf import snapshot

    ds = tmp_path / "out" / "sim-x"
    rep = ds / "reports"
    rep.mkdir(parents=True)
    (ds / "dataset.json").write_text('{"name": "sim-x", "fingerprint": "abc123"}')
    (rep / "report.md").write_text(
        "# skidbench report: sim-x\n\nintro\n\n## Leaderboard, inputs=commanded (mean over terrains)\n\n"
        "| rank | model |\n|---|---|\n| 1 | friction |\n\n## Figures\n\n![fig](f.png)\n\n"
        "## Notes\n\n- a note\n\n## Reproduce\n\nmake reproduce\n"
    )
    (rep / "leaderboard-response.md").write_text(
        "# Leaderboard\n\nWritten by ...\n\n| rank | model |\n|---|---|\n| 1 | edd |\n\nbest: edd\n\n"
        "| model | inputs | terrain |\n|---|---|---|\n| edd | response | tile |\n"
    )
    (rep / "leaderboard-response-20261128T000000Z.md").write_text("| old |\n")
    (rep / "leaderboard-commanded.csv").write_text(
        "model,git_commit,start_time_utc\nfriction,c0ffee,2026-11-28 10:00\n"
    )
    page = snapshot.main([str(tmp_path / "out"), "sim-x", "t", "--results", str(tmp_path / "res")])
    text = page.read_text()
    assert page.name == "board_t.md"
    assert "fingerprint abc123" in text and "commit c0ffee" in text and "2026-11-28 10:00" in text
    assert "| 1 | friction |" in text and "- a note" in text
    assert "## Leaderboard, inputs=response (mean over terrains)" in text and "best: edd" in text
    assert "f.png" not in text and "make reproduce" not in text.split("\n", 1)[1]
    assert "| edd | response | tile |" not in text and "| old |" not in text
    assert str(tmp_path / "out") not in text and "python -m perf.snapshot <out> sim-x t" in text  # no path


def test_the_suite_page_says_each_workers_share_and_when_it_ended():
    from perf import test_suite as ts

    start = 1000.0
    records = [
        {"id": "tests/test_a.py::x", "cpu_s": 2.0, "wall_s": 3.0, "worker": "gw0", "end": start + 60.0},
        {"id": "tests/test_b.py::y", "cpu_s": 5.0, "wall_s": 6.0, "worker": "gw0", "end": start + 180.0},
        {"id": "tests/test_c.py::z", "cpu_s": 1.5, "wall_s": 2.0, "worker": "gw1", "end": start + 90.0},
    ]
    page = ts.summary(records, 10.0, "a run", start=start)
    assert "| gw0 | 2 | 7 | 9 | 3.0 | tests/test_b.py |" in page  # its last test ended 3 min in
    assert "| gw1 | 1 | 2 | 2 | 1.5 | tests/test_c.py |" in page
    assert "## The workers" not in ts.summary(records, 10.0, "a run")  # no start: no timeline
