"""One dataset, one home (pipeline/datasets/identity.py): datasets run one after the other in one output root
keep
their folders, MLflow experiments and runs apart; stages take terrains and sequences from the current
manifest; two roots at one explicit name are refused in one line."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import discover_data as dd
import mlflow
import pandas as pd
import pytest
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra

from skidbench.pipeline.core.layout import layout_from_cfg
from skidbench.pipeline.datasets.identity import (
    DatasetError,
    home_from_cfg,
    identity_from_cfg,
    list_datasets,
    open_home,
)

FIXTURE = Path(__file__).parent / "fixtures" / "amrl"
EVALUATE = ["models=[ideal,edd]", "log_figures=false", "horizons=[6.0]"]  # the homes, not the horizons
COMPARE = ["figures.enabled=false"]
DISCOVER = [
    "model=edd",
    "discover.candidates=[side_asymmetry]",
    "discover.max_effects=1",
    # a few seconds of Train per dataset: a looser test level and a shorter horizon give the sign-flip
    # test enough held-out units (discover refuses a Train too short for it); this file tests the homes
    "discover.alpha=0.25",
    "discover.horizon_s=2.0",
    "discover.figure=false",
]


@pytest.fixture(autouse=True)
def _local_store(monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)


def cfg(stage: str, out: Path, *over: str):
    GlobalHydra.instance().clear()
    with initialize_config_module("skidbench.conf", version_base="1.3"):
        return compose(stage, [f"out_root={out}", *over])


def run_stage(stage: str, out: Path, *over: str):
    """A stage as the CLI runs it (``stage`` wrapper: open_home first), in this process."""
    from skidbench.benchmark.board import app as compare_app
    from skidbench.benchmark.discovery import app as discover_app
    from skidbench.benchmark.evaluate import app as evaluate_app
    from skidbench.pipeline.calibrate import app as calibrate_app
    from skidbench.pipeline.extract import app as extract
    from skidbench.pipeline.groundtruth import app as groundtruth
    from skidbench.pipeline.splits import app as split

    runners = {
        "extract": extract.run,
        "groundtruth": groundtruth.run,
        "split": split.run,
        "calibrate": calibrate_app.run,  # evaluate reads its calibration (only calibrate computes it)
        "evaluate": evaluate_app.run,
        "compare": compare_app.run,
        "discover": discover_app.run,
    }
    extra = {"evaluate": EVALUATE, "compare": COMPARE, "discover": DISCOVER}.get(stage, [])
    # as in a new process: mlflow.set_tracking_uri (compare) exports MLFLOW_TRACKING_URI, which the
    # config reads (mlflow.tracking_uri) and a later stage's stamp would see as a changed config
    os.environ.pop("MLFLOW_TRACKING_URI", None)
    c = cfg(stage, out, *over, *extra)
    open_home(home_from_cfg(c), stage)
    return runners[stage](c)


def pipeline(out: Path, *source: str) -> dict:
    return {
        s: run_stage(s, out, *source)
        for s in ("extract", "groundtruth", "split", "calibrate", "evaluate", "discover", "compare")
    }


def child_runs(out: Path, layout) -> pd.DataFrame:
    mlflow.set_tracking_uri(layout.mlflow_uri)
    return mlflow.search_runs(
        experiment_names=[f"skidbench-{layout.dataset}"], filter_string="tags.`skidbench.role` = 'child'"
    )


def assert_both_intact(out: Path, a: tuple, b: tuple, results: dict) -> None:
    """Each dataset's folder, manifest terrains, split files, MLflow experiment, compare and discovery
    hold its own terrain only."""
    from skidbench.benchmark.board.compare import select_runs
    from skidbench.benchmark.board.selection import results_of
    from skidbench.benchmark.tracking import store as trk

    for (source, terrain), other in ((a, b[1]), (b, a[1])):
        c = cfg("compare", out, *source)
        layout = layout_from_cfg(c)
        ident = identity_from_cfg(c)
        rec = json.loads(layout.dataset_json.read_text())
        assert rec["fingerprint"] == ident.fingerprint and rec["terrains"] == [terrain]
        assert {p.name for p in layout.splits.iterdir() if p.is_dir()} == {terrain}
        assert {p.parents[1].name for p in layout.splits.glob("*/*/*.parquet")} == {terrain}
        assert {p.name for p in (layout.fits / "edd").iterdir()} == {f"{terrain}.json"}
        runs = child_runs(out, layout)
        assert set(runs["tags.skidbench.terrain"]) == {terrain}
        assert set(runs["tags.skidbench.dataset_id"]) == {ident.fingerprint}
        assert len(runs) == 2 * len(results[ident.name])  # ideal, edd per evaluate run
        table = results_of(layout, ident.fingerprint)
        shown, _ = select_runs(trk.tracker_from_cfg(c, layout), table, "latest", None)
        assert set(shown["terrain"]) == {terrain}
        board = pd.read_csv(layout.reports / "leaderboard-commanded.csv")  # (its CPU flags may hold "tile")
        assert set(board["terrain"].dropna()) == {terrain} and other not in set(board["terrain"])
        doc = json.loads((layout.discovery / "discovery.json").read_text())
        assert set(doc["terrains"]) == {terrain}


@pytest.mark.slow
def test_two_amrl_roots_run_one_after_the_other_keep_their_own_homes(tmp_path):
    out = tmp_path / "out"
    root_a = dd.write_amrl(dd.dataset({}, 1, n_train=2, duration=15.0), tmp_path / "day1", "Tile")
    root_b = dd.write_amrl(dd.dataset({}, 2, n_train=2, duration=15.0), tmp_path / "day2", "Grass")
    a = (["source=amrl_txt", f"source.root={root_a}"], "tile")
    b = (["source=amrl_txt", f"source.root={root_b}"], "grass")
    first = pipeline(out, *a[0])
    second = pipeline(out, *b[0])
    la, lb = (layout_from_cfg(cfg("split", out, *s[0])) for s in (a, b))
    assert la.dataset.startswith("amrl-day1-") and lb.dataset.startswith("amrl-day2-") and la.root != lb.root
    assert not first["evaluate"][0].failed and not second["evaluate"][0].failed
    assert_both_intact(out, a, b, {la.dataset: [1], lb.dataset: [1]})

    # the first again: every stage finds it up to date; nothing of the second is touched
    before = {p: p.stat().st_mtime_ns for p in lb.root.rglob("*") if p.is_file()}

    def mine():
        return {
            p: p.stat().st_mtime_ns for d in (la.extracted, la.groundtruth, la.splits) for p in d.rglob("*.*")
        }

    mine_before = mine()
    for s in ("extract", "groundtruth", "split"):
        run_stage(s, out, *a[0])
    assert mine() == mine_before
    result, skipped = run_stage("evaluate", out, *a[0])
    assert skipped and result.parent_run_id == first["evaluate"][0].parent_run_id
    assert {p: p.stat().st_mtime_ns for p in lb.root.rglob("*") if p.is_file()} == before

    rows = {r["name"]: r for r in list_datasets(out)}
    assert rows[la.dataset]["terrains"] == "tile" and rows[lb.dataset]["terrains"] == "grass"
    assert rows[la.dataset]["root"] == str(root_a.resolve()) and rows[la.dataset]["source"] == "amrl_txt"
    assert first["evaluate"][0].parent_run_id in rows[la.dataset]["last_evaluate"]


def _bag_folder(micro: Path, root: Path, terrain: str) -> Path:
    """A user's bags folder ``<root>/<terrain>/<category>/<seq>.bag`` from the micro simulated bags."""
    for bag in sorted((micro / "sim-micro" / "raw" / "bags").glob("*.bag")):
        category = bag.stem.split("_")[1]
        dest = root / terrain / category / f"{terrain}_{category}_00.bag"
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(bag, dest)
    return root


@pytest.mark.slow
def test_two_bag_folders_run_one_after_the_other_keep_their_own_homes(tmp_path, micro_root):
    out = tmp_path / "out"
    common = ["source=bag", "+source.groundtruth_method=pose_topic"]
    root_a = _bag_folder(micro_root, tmp_path / "robot1", "tile")
    root_b = _bag_folder(micro_root, tmp_path / "robot2", "asphalt")
    a = ([*common, f"source.root={root_a}"], "tile")
    b = ([*common, f"source.root={root_b}"], "asphalt")
    pipeline(out, *a[0])
    pipeline(out, *b[0])
    la, lb = (layout_from_cfg(cfg("split", out, *s[0])) for s in (a, b))
    assert la.dataset.startswith("bags-robot1-") and lb.dataset.startswith("bags-robot2-")
    assert_both_intact(out, a, b, {la.dataset: [1], lb.dataset: [1]})
    _, skipped = run_stage("evaluate", out, *a[0])
    assert skipped


def test_a_dataset_is_named_by_its_place_and_identified_by_its_content(tmp_path):
    for where, value in (("x", "1"), ("y", "2"), ("mnt", "1")):
        (tmp_path / where / "data" / "Tile").mkdir(parents=True)
        (tmp_path / where / "data" / "Tile" / "a.txt").write_text(value)
    (tmp_path / "mnt" / "data" / ".DS_Store").write_text("hidden: not data")
    os.symlink(tmp_path / "x" / "data", tmp_path / "link")
    ident = lambda root: identity_from_cfg(cfg("split", tmp_path, "source=amrl_txt", f"source.root={root}"))  # noqa: E731
    x = ident(tmp_path / "x" / "data")
    assert x == ident(tmp_path / "link") == ident(tmp_path / "x" / ".." / "x" / "data")
    assert x.name.startswith("amrl-data-")
    mnt, y = ident(tmp_path / "mnt" / "data"), ident(tmp_path / "y" / "data")
    assert mnt.fingerprint == x.fingerprint and mnt.name != x.name  # the same files elsewhere: one id
    assert y.fingerprint != x.fingerprint and y.name != x.name  # other content: never the same
    (tmp_path / "x" / "data" / "Tile" / "b.txt").write_text("3")  # edited data: the same home, another id
    edited = ident(tmp_path / "x" / "data")
    assert edited.name == x.name and edited.fingerprint != x.fingerprint
    assert (
        str(cfg("split", tmp_path, "source=amrl_txt", "source.root=/a", "source.dataset=lab").dataset)
        == "lab"
    )
    # the simulated dataset is its scale and seed
    assert str(cfg("split", tmp_path).dataset) == "sim-mini"
    assert str(cfg("split", tmp_path, "scale=tiny", "seed=1").dataset) == "sim-tiny-seed1"
    sim0, sim1 = (identity_from_cfg(cfg("split", tmp_path, f"seed={s}")) for s in (0, 1))
    assert sim0.fingerprint != sim1.fingerprint


def test_two_mount_points_of_one_dataset_are_one_dataset_id(tmp_path, capsys):
    out = tmp_path / "out"
    for mount in ("mnt1", "mnt2"):
        shutil.copytree(FIXTURE / "Tile", tmp_path / mount / "amrl" / "Tile")
    a, b = (["source=amrl_txt", f"source.root={tmp_path / m / 'amrl'}"] for m in ("mnt1", "mnt2"))
    for args in (a, b):
        run_stage("extract", out, *args)
    ida, idb = (identity_from_cfg(cfg("extract", out, *s)) for s in (a, b))
    assert ida.fingerprint == idb.fingerprint and ida.root != idb.root
    recs = [json.loads((out / i.name / "dataset.json").read_text()) for i in (ida, idb)]
    assert [r["fingerprint"] for r in recs] == [ida.fingerprint] * 2 and recs[0]["schema"] == 2
    # named: one home, taken over by the other mount point of the same files (no error), its root updated
    for args in (a, b):
        run_stage("extract", out, *args, "source.dataset=lab")
    rec = json.loads((out / "lab" / "dataset.json").read_text())
    assert rec["fingerprint"] == ida.fingerprint and rec["root"] == idb.root
    # an output root inside the data's root is not part of the data
    inside = tmp_path / "mnt1" / "amrl" / "outputs"
    run_stage("extract", inside, *a)
    assert identity_from_cfg(cfg("extract", inside, *a)).fingerprint == ida.fingerprint
    capsys.readouterr()


def test_a_folder_recorded_by_its_path_by_an_earlier_release_is_upgraded_with_a_note(tmp_path, capsys):
    from skidbench.pipeline.core.layout import NAME_FP_LEN, fingerprint_of

    out, root = tmp_path / "out", tmp_path / "day1"
    shutil.copytree(FIXTURE / "Tile", root / "Tile")
    args = ["source=amrl_txt", f"source.root={root}"]
    old_fp = fingerprint_of({"source": "amrl_txt", "root": str(root)})
    legacy = out / f"amrl-day1-{old_fp[:NAME_FP_LEN]}"
    legacy.mkdir(parents=True)
    old = {"schema": 1, "name": legacy.name, "source": "amrl_txt", "root": str(root), "fingerprint": old_fp}
    (legacy / "dataset.json").write_text(json.dumps({**old, "terrains": [], "sequences": 0}))
    run_stage("extract", out, *args)
    ident = identity_from_cfg(cfg("extract", out, *args))
    assert ident.name == legacy.name and ident.fingerprint != old_fp
    assert "recorded by its path by an earlier release" in capsys.readouterr().out
    rec = json.loads((legacy / "dataset.json").read_text())
    assert rec["schema"] == 2 and rec["fingerprint"] == ident.fingerprint
    assert (legacy / "extracted" / "tile_train_01").is_dir()
    run_stage("extract", out, *args)  # upgraded: no note any more
    assert [p.name for p in out.iterdir() if p.is_dir()] == [legacy.name]
    assert "note:" not in capsys.readouterr().out


def test_two_roots_at_one_explicit_name_are_one_line_error_unless_replace(tmp_path):
    out = tmp_path / "out"
    roots = []
    for day in ("day1", "day2"):
        shutil.copytree(FIXTURE / "Tile", tmp_path / day / "Tile")
        roots.append(tmp_path / day)
    (roots[1] / "notes.txt").write_text("another day's recording")  # other content (the same: one dataset)
    args = lambda root: ["source=amrl_txt", f"source.root={root}", "source.dataset=lab"]  # noqa: E731
    run_stage("extract", out, *args(roots[0]))
    lab = out / "lab"
    assert (lab / "extracted" / "tile_train_01").is_dir()
    with pytest.raises(DatasetError) as e:
        run_stage("extract", out, *args(roots[1]))
    msg = str(e.value)
    assert "\n" not in msg and str(roots[0]) in msg and str(roots[1]) in msg and "source.replace=true" in msg
    assert json.loads((lab / "dataset.json").read_text())["root"] == str(roots[0])

    # through the CLI: one line on stderr, exit status 2, nothing of the first dataset lost
    env = {**os.environ, "SKIDBENCH_OUT": str(out)}
    proc = subprocess.run(
        [sys.executable, "-m", "skidbench.pipeline.cli.main", "split", *args(roots[1])],
        env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 2
    assert f"skidbench split: dataset lab (amrl_txt {roots[1]}, fingerprint " in proc.stdout  # printed first
    errors = [ln for ln in proc.stderr.splitlines() if "error" in ln]
    assert len(errors) == 1 and str(roots[0]) in errors[0] and str(roots[1]) in errors[0]
    assert (lab / "extracted" / "tile_train_01" / "cmd_vel.parquet").is_file()

    run_stage("extract", out, *args(roots[1]), "source.replace=true")
    assert json.loads((lab / "dataset.json").read_text())["root"] == str(roots[1])
    assert not [p for p in out.iterdir() if p.name.startswith(".tmp-")]


def test_outputs_of_sequences_no_longer_in_the_manifest_are_removed_without_empty_folders(tmp_path):
    out = tmp_path / "out"
    root = tmp_path / "day"
    shutil.copytree(FIXTURE, root)
    src = ["source=amrl_txt", f"source.root={root}"]
    for s in ("extract", "groundtruth", "split"):
        run_stage(s, out, *src)
    layout = layout_from_cfg(cfg("split", out, *src))
    (layout.fits / "edd").mkdir(parents=True)
    for t in ("tile", "grass"):
        (layout.fits / "edd" / f"{t}.json").write_text("{}")
    assert (layout.splits / "grass" / "ld").is_dir()
    shutil.rmtree(root / "Grass")  # the data changed: Grass is gone
    for s in ("extract", "groundtruth", "split"):
        run_stage(s, out, *src)
    assert not (layout.splits / "grass").exists()
    assert not [p for p in layout.extracted.iterdir() if p.name.startswith("grass")]
    assert not list(layout.groundtruth.glob("grass_*"))
    assert [p.name for p in (layout.fits / "edd").iterdir()] == ["tile.json"]
    assert {p.parent.name for p in layout.splits.glob("tile/*/*.parquet")} == {"train", "cv", "ld"}
    empty = [d for d in layout.root.rglob("*") if d.is_dir() and not any(d.iterdir())]
    assert not empty, empty
    assert json.loads(layout.dataset_json.read_text())["terrains"] == ["tile"]
