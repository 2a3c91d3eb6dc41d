"""A board's intervals, ranking rule and the paper's claim (benchmark/scoring/standings.py), on synthetic
windows:
compare's cells equal what evaluate logs, a model with one pathological metric does not lead, the claim is
"holds", "does not hold" or "not resolved by these data" as the differences are resolved, and a board of
one-window splits ranks nothing and says why."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from skidbench.benchmark.board.boards import Board
from skidbench.benchmark.release import publish
from skidbench.benchmark.release.settings import PublishOptions
from skidbench.benchmark.report import markdown
from skidbench.benchmark.scoring import metrics as mt
from skidbench.benchmark.scoring import ranks as rk
from skidbench.benchmark.scoring import standings as st
from skidbench.benchmark.scoring.floor import FLOOR
from skidbench.benchmark.scoring.predictions import summarise

H = 6.0


def _windows(
    rng, terrain, scale: dict[str, float], seconds: float, shared: dict, rot_scale=None
) -> pd.DataFrame:
    """Windows of one (model, terrain): a CV and an LD sequence of ``seconds``, 5 windows a second; relative
    errors lognormal around ``scale[split]`` (%, as fractions), correlated with every model's (``shared``:
    the same hard windows for everyone)."""
    frames = []
    for split in ("cv", "ld"):
        n = int(seconds * 5)
        z = shared.setdefault(split, rng.standard_normal(n))
        x = 0.8 * z + 0.6 * rng.standard_normal(n)
        rel = scale[split] / 100 * np.exp(0.4 * x)
        rot = (rot_scale or scale)[split] / 100 * np.exp(0.4 * (0.8 * z + 0.6 * rng.standard_normal(n)))
        frames.append(pd.DataFrame({"split": split, "horizon_s": H, "sequence": f"{terrain}_{split}_00",
                                    "start": np.arange(n) * 6, "t0": np.arange(n) / 5.0,
                                    "rel_trans": rel, "rel_rot": rot, "trans_err": rel}))  # fmt: skip
    return pd.concat(frames, ignore_index=True)


def _board(models: dict[str, dict], terrains=("grass", "tile"), seconds=120.0, seed=0):
    rng = np.random.default_rng(seed)
    out = {}
    for t in terrains:
        shared: dict = {}
        for m, spec in models.items():
            out[(m, t)] = _windows(rng, t, spec["trans"], seconds, shared, spec.get("rot"))
    return out


def test_cells_equal_what_evaluate_logs_and_the_floor_is_a_reference_row():
    w = _board({"edd": {"trans": {"cv": 8, "ld": 6}}, "friction": {"trans": {"cv": 7, "ld": 4}},
                FLOOR: {"trans": {"cv": 0.05, "ld": 0.05}}})  # fmt: skip
    s = st.build(w, H)
    logged = summarise(w[("friction", "tile")][lambda d: d["split"] == "ld"], "ld", [H])
    cell = s.cell("friction", "tile", "ld", "translational")
    assert cell["estimate"] == pytest.approx(logged["ld_6s_trans_rmsre_pct"], abs=1e-3)
    assert (cell["lo"], cell["hi"]) == pytest.approx(
        (logged["ld_6s_trans_rmsre_pct_ci_lo"], logged["ld_6s_trans_rmsre_pct_ci_hi"]), abs=1e-4
    )
    assert cell["n_blocks"] == logged["ld_6s_trans_blocks"] > 10  # errors with a 0.2 s memory: short blocks
    assert ov_blocks(s, "friction") > 40  # two terrains, CV and LD
    ov = s.overall.set_index("model")
    assert ov.loc[FLOOR, "rank"] == "" and ov.loc[FLOOR, "standing"].startswith("reference")
    assert ov.loc["friction", "standing"] == rk.BEST and ov.loc["edd", "rank"] == "2"
    # the aggregate is the mean of the four RMSREs over the terrains
    four = [s.cell("friction", t, sp, m)["estimate"] for t in ("grass", "tile") for sp in ("cv", "ld")
            for m in ("translational", "rotational")]  # fmt: skip
    assert ov.loc["friction", "estimate"] == pytest.approx(np.mean(four))


def ov_blocks(s, model):
    return int(s.overall.set_index("model").loc[model, "n_blocks"])


def test_a_pathological_metric_keeps_a_model_from_leading():
    # like friction on the Warthog ice: best LD translation, but a 353 % LD rotation
    w = _board({"friction": {"trans": {"cv": 6, "ld": 4}, "rot": {"cv": 6, "ld": 353}},
                "edd": {"trans": {"cv": 7, "ld": 6}},
                "roc": {"trans": {"cv": 7.02, "ld": 6.02}}})  # fmt: skip
    s = st.build(w, H)
    ov = s.overall.set_index("model")
    assert s.cell("friction", "grass", "ld", "translational")["estimate"] < 5
    assert ov.loc["friction", "rank"] == "3" and ov.loc["friction", "standing"] == ""
    assert ov.loc["edd", "standing"] == ov.loc["roc", "standing"] == rk.TIED  # 0.3 % apart: not resolved
    assert s.verdicts["overall"].startswith("tied for best: edd, roc")
    # the paired differences behind it: a - b of the aggregates, resolved only where the interval excludes 0
    d = s.differences.set_index(["a", "b"])
    for (a, b), r in d.iterrows():
        assert r["estimate"] == pytest.approx(ov.loc[a, "estimate"] - ov.loc[b, "estimate"], abs=1e-9)
        assert r["lo"] <= r["estimate"] <= r["hi"] and r["resolved"] == (r["lo"] > 0 or r["hi"] < 0)
    pair = ("edd", "roc") if ("edd", "roc") in d.index else ("roc", "edd")
    assert not d.loc[pair, "resolved"] and d.filter(like="friction", axis=0)["resolved"].all()
    report = "\n".join(markdown.differences_lines(s))
    assert "minus" in report and "| friction | " in report and "| yes |" in report and "| no |" in report
    # ranked by one metric instead (rank_by=ld_trans), friction leads
    assert (
        st.build(w, H, rank_by="ld_trans").overall.set_index("model").loc["friction", "standing"] == rk.BEST
    )


def test_the_papers_claim_holds_fails_or_is_not_resolved():
    others = {m: {"trans": {"cv": 7, "ld": 6}} for m in ("ideal", "edd", "roc")}
    holds = st.build(_board({**others, "friction": {"trans": {"cv": 7, "ld": 4}}}), H)
    assert holds.claim["overall"][0] == st.HOLDS and holds.claim["grass"][0] == st.HOLDS
    fails = st.build(_board({**others, "friction": {"trans": {"cv": 7, "ld": 8}}}), H)
    assert fails.claim["overall"][0] == st.FAILS
    worse_cv = st.build(_board({**others, "friction": {"trans": {"cv": 10, "ld": 4}}}), H)
    assert worse_cv.claim["overall"][0] == st.FAILS
    close = st.build(_board({**others, "friction": {"trans": {"cv": 7, "ld": 5.9}}}), H)
    assert close.claim["overall"][0] == st.UNRESOLVED
    assert any("not resolved" in line for line in close.claim["overall"][1])


def test_the_overall_only_standings_equal_the_full_ones():
    """detail=False (the error-against-horizon report's) computes only the overall ranking and claim: the
    same rows, intervals, ranks and claim as the full standings, and nothing per terrain."""
    others = {m: {"trans": {"cv": 7, "ld": 6}} for m in ("ideal", "edd", "roc")}
    w = _board(
        {**others, "friction": {"trans": {"cv": 7, "ld": 4}}, FLOOR: {"trans": {"cv": 0.05, "ld": 0.05}}}
    )
    full, light = st.build(w, H), st.build(w, H, detail=False)
    cols = ["model", "estimate", "lo", "hi", "n_blocks", "rankable", "rank", "standing"]
    pd.testing.assert_frame_equal(light.overall[cols], full.overall[cols])
    pd.testing.assert_frame_equal(light.differences, full.differences)
    assert light.claim == {"overall": full.claim["overall"]} and light.claim["overall"][0] == st.HOLDS
    assert light.verdicts == {"overall": full.verdicts["overall"]}
    assert light.cells.empty and light.per_terrain.empty and not full.per_terrain.empty


def test_a_board_of_one_window_splits_ranks_nothing_and_says_why():
    w = _board({"friction": {"trans": {"cv": 74, "ld": 6}}, "full_linear": {"trans": {"cv": 3.8, "ld": 78}}},
               terrains=("grass",), seconds=0.2)  # fmt: skip
    s = st.build(w, H)
    ov = s.overall.set_index("model")
    assert (ov["rank"] == "").all()
    assert ov.loc["friction", "standing"].startswith("not ranked: 1 independent block in cv@6s:grass_cv_00")
    assert s.verdicts["overall"] == (  # one window per split: each stratum needs 2 blocks (not the floor)
        "no entry ranked: 1 independent block in cv@6s:grass_cv_00 (each stratum needs 2)"
    )
    assert s.claim["overall"][0] == st.UNRESOLVED


def _board_rows(windows) -> pd.DataFrame:
    """One finished run per (model, terrain) of ``windows`` (not the floor), with what evaluate logs."""
    rows = []
    for (model, terrain), w in windows.items():
        if model == FLOOR:
            continue
        row = {"model": model, "terrain": terrain, "inputs": "commanded", "status": "FINISHED",
               "run_id": f"{model}-{terrain}-run", "reason": "", "fit_loss": 0.0, "fit_time_s": 0.1,
               "predict_time_s": 0.1}  # fmt: skip
        for split in ("cv", "ld"):
            row.update(summarise(w[w["split"] == split], split, [H]))
        rows.append(row)
    out = pd.DataFrame(rows)
    for m in mt.METRICS:  # the optional metrics (a predictive covariance) these models have not
        for split in ("cv", "ld"):
            for key in (m.metric_key(split, H), m.windows_key(split, H)):
                if key is not None and key not in out:
                    out[key] = np.nan
    return out


def test_the_published_leaderboard_shows_intervals_ties_the_floor_and_the_claim(tmp_path):
    w = _board({"edd": {"trans": {"cv": 7, "ld": 6}}, "roc": {"trans": {"cv": 7.02, "ld": 6.02}},
                FLOOR: {"trans": {"cv": 0.05, "ld": 0.05}}})  # fmt: skip
    board = Board("commanded", "parent", H, {}, _board_rows(w))
    settings = publish.PublishSettings(PublishOptions(figures=False, dpi=72))
    s = st.build(w, H)
    page = publish._protocol_section(board, tmp_path, settings, s)
    assert "tied for best: " in page and 'title="best"' not in page  # 0.3 % apart on the same windows
    edd = s.overall.set_index("model").loc["edd"]
    ci = f'<span class="ci">[{edd["lo"]:.2f}, {edd["hi"]:.2f}]</span>'
    assert f"{edd['estimate']:.2f}{ci}" in page  # the aggregate with its interval
    assert '<span class="floor">floor</span>' in page  # the floor's row, never ranked
    assert "not resolved by these data" in page  # the paper's claim: friction was not evaluated here
    lo, hi = board.rows.loc[0, ["ld_6s_trans_rmsre_pct_ci_lo", "ld_6s_trans_rmsre_pct_ci_hi"]]
    assert f'<span class="ci">[{lo:.2f}, {hi:.2f}]</span>' in page  # every row's logged interval (details)
    # without the per-window tables: listed, not ranked, and it says so
    bare = publish._protocol_section(board, tmp_path, settings, None)
    assert "not ranked" in bare and "tied for best" not in bare


def test_figs_3_4_draw_each_cells_interval_and_the_floor(tmp_path, monkeypatch):
    import matplotlib.axes

    from skidbench.benchmark.report import figures as figs

    w = _board({"edd": {"trans": {"cv": 7, "ld": 6}}, FLOOR: {"trans": {"cv": 0.05, "ld": 0.05}}},
               terrains=("grass",), seconds=30.0)  # fmt: skip
    rows = _board_rows(w)
    drawn, floors = [], []
    axes = matplotlib.axes.Axes
    monkeypatch.setattr(axes, "errorbar", lambda ax, x, y, yerr, **kw: drawn.append((y, yerr)))
    monkeypatch.setattr(axes, "hlines", lambda ax, y, *a, **kw: floors.append(y))
    trans = mt.get("trans")
    figs.metric_bars(rows, trans, H, ("cv", "ld"), tmp_path / "fig3.png", 40, {("grass", "ld"): 0.05})
    for split, (y, yerr) in zip(("cv", "ld"), drawn, strict=True):
        key = trans.metric_key(split, H)
        v, lo, hi = rows.loc[0, [key, f"{key}_ci_lo", f"{key}_ci_hi"]]
        assert y[0] == v and yerr[:, 0] == pytest.approx([v - lo, hi - v])
    assert floors == [0.05]  # the floor's line on the LD panel only (no CV floor given)


class _Tracker:
    """What log_floor asks of a tracker: artifacts and metrics/tags, remembered."""

    def __init__(self):
        self.logged: list[dict] = []

    def artifact(self, run_id, path, where):
        pass

    def log(self, run_id, params=None, metrics=None, tags=None):
        self.logged.append({"metrics": metrics or {}, "tags": tags or {}})


def test_a_recording_without_an_independent_truth_has_an_unknown_floor_and_the_board_says_why(tmp_path):
    # a real recording: no simulator truth table next to its extracted tables; the floor is not
    # estimated from the ground truth's own velocities, it is declared unknown with the reason
    from skidbench.benchmark.board.boards import read_windows
    from skidbench.benchmark.evaluate.references import log_floor
    from skidbench.benchmark.scoring.horizon import HorizonConfig
    from skidbench.benchmark.scoring.predictions import TestSequence
    from skidbench.benchmark.scoring.settings import IntervalConfig
    from skidbench.pipeline.core.layout import Layout

    sys.path.insert(0, str(Path(__file__).parent))
    from _bench_data import sequence_table

    layout = Layout(tmp_path, "drive")
    seq = TestSequence("husky_ld_00", tmp_path / "husky_ld_00.parquet", sequence_table(0, 20.0), {})
    tracker = _Tracker()
    stem, settings = layout.eval_stem(FLOOR, "grass"), IntervalConfig(resamples=200)
    got = log_floor(tracker, "p", stem, "grass", {"ld": [seq]}, [H], HorizonConfig(H), settings, "commanded",
                    None, layout.extracted)  # fmt: skip
    assert got == ({}, []) and not any(entry["metrics"] for entry in tracker.logged)
    reason = tracker.logged[0]["tags"]["floor.grass.unknown"]
    assert reason.startswith("floor unknown: no independent truth") and "husky_ld_00" in reason
    rows = pd.DataFrame(
        {"model": ["friction"], "terrain": ["grass"], "status": ["FINISHED"], "run_id": ["r"]}
    )
    windows, notes = read_windows(layout, rows, "commanded", H)
    assert (FLOOR, "grass") not in windows and notes[-1] == f"grass: {reason}"
