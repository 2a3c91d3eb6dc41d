"""Fault injection: a stage killed (SIGKILL) mid-write resumes to the same bytes with no partial file left;
a full disk or a permission error is one clear line and keeps earlier outputs; a truncated Parquet
intermediate fails its fingerprint and is rebuilt, not read.

The kill/ENOSPC/EACCES points come from the test-only hook ``SKIDBENCH_FAULT`` (tests/fault_injection,
loaded into the stage's processes by its sitecustomize; at the n-th atomic write whose path matches, after
the temporary file is written, before its rename).
"""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pandas as pd
import pyarrow.parquet as pq
import pytest
from reliability_data import DATASET, STAGE_ARGS, copy_splits, skidbench, snapshot, tmp_files

# subprocess pipelines, servers and sweeps: part of `make test`, not of `make test-fast`
pytestmark = pytest.mark.slow

# stage -> (outputs deleted before the killed run, path fragment of the write that is killed, n-th write)
KILLS = {
    "simulate": ("raw/bags/*.bag", ".bag", 2),
    "extract": ("extracted/*/*.parquet", ".parquet", 7),  # mid-way through the 2nd sequence
    "groundtruth": ("groundtruth/tile_*", ".tum", 2),
    "split": ("splits/*/*/*.parquet", ".parquet", 2),
    "fit": ("fits/edd/tile.json", "tile.json", 1),
}


@pytest.mark.parametrize("stage", list(KILLS))
def test_a_stage_killed_mid_write_resumes_to_identical_outputs_and_no_partial_file(micro_root, stage):
    ds = micro_root / DATASET
    if stage == "fit" and not (ds / "fits/edd/tile.json").is_file():
        skidbench("fit", micro_root, here=True)
    before = snapshot(micro_root)
    pattern, needle, nth = KILLS[stage]
    victims = list(ds.glob(pattern))
    assert victims, pattern
    for p in victims:
        p.unlink()

    killed = skidbench(stage, micro_root, env={"SKIDBENCH_FAULT": f"kill@{nth}:{needle}"}, check=False)
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-2000:]
    left = tmp_files(micro_root)
    assert left, "the kill should have interrupted a write (a .tmp- file left behind)"
    assert all(p.name.startswith(".tmp-") for p in left)  # never under a final name

    skidbench(stage, micro_root, here=True)
    assert tmp_files(micro_root) == []
    assert snapshot(micro_root) == before


def test_a_rerun_with_nothing_changed_skips_every_stage_and_says_so(micro_root):
    for stage, words in (
        ("extract", "3 sequences up to date, skipped"),
        ("groundtruth", "3 sequences up to date, skipped"),
        ("split", "3 sequences up to date, skipped"),
    ):
        proc = skidbench(stage, micro_root, here=True)
        assert words in proc.stdout + proc.stderr, (stage, proc.stderr[-1500:])
    proc = skidbench("simulate", micro_root, here=True)
    assert "(3 up to date)" in proc.stdout


@pytest.mark.parametrize("fault", ["enospc", "eacces"])
def test_disk_full_or_permission_error_is_one_line_and_keeps_earlier_outputs(micro_root, fault):
    ds = micro_root / DATASET
    before = snapshot(micro_root)
    victim = ds / "splits/tile/cv/tile_cv_00.parquet"
    victim.unlink()  # the split stage has one sequence to redo; its write fails
    proc = skidbench("split", micro_root, env={"SKIDBENCH_FAULT": f"{fault}@1:.parquet"}, check=False)
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("skidbench split: error:")]
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    why = "No space left on device" if fault == "enospc" else "Permission denied"
    assert str(victim) in lines[0] and why in lines[0], lines[0]
    assert tmp_files(micro_root) == []
    after = snapshot(micro_root)
    gone = set(before) - set(after)
    assert gone == {victim.relative_to(micro_root).as_posix()}
    assert {k: v for k, v in before.items() if k not in gone} == after  # nothing else touched
    skidbench("split", micro_root, here=True)  # space back: the re-run completes
    assert snapshot(micro_root) == before


@pytest.mark.parametrize(
    ("stage", "rel"),
    [
        ("extract", "extracted/tile_train_00/cmd_vel.parquet"),
        ("split", "splits/tile/train/tile_train_00.parquet"),
    ],
)
def test_a_truncated_parquet_intermediate_fails_its_fingerprint_and_is_rebuilt(micro_root, stage, rel):
    before = snapshot(micro_root)
    path = micro_root / DATASET / rel
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(Exception):  # noqa: B017 (really unreadable)
        pq.read_table(path)
    proc = skidbench(stage, micro_root, here=True)
    out = proc.stdout + proc.stderr
    assert "fails its fingerprint" in out, out[-2000:]
    assert path.read_bytes() == data
    assert snapshot(micro_root) == before


def test_a_changed_input_reruns_exactly_the_units_downstream_of_it(micro_root):
    before = snapshot(micro_root)
    tum = micro_root / DATASET / "groundtruth/tile_cv_00.tum"
    original = tum.read_bytes()
    tum.write_bytes(original)  # same content, new mtime: nothing to do
    proc = skidbench("split", micro_root, here=True)
    assert "3 sequences up to date, skipped" in proc.stdout + proc.stderr
    lines = original.decode().splitlines(keepends=True)
    k = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    t, *rest = lines[k].split()
    lines[k] = " ".join([t, str(float(rest[0]) + 0.001), *rest[1:]]) + "\n"  # the first pose moves 1 mm
    tum.write_text("".join(lines))
    proc = skidbench("split", micro_root, here=True)
    assert "1 sequences split, 2 up to date" in proc.stdout + proc.stderr, proc.stdout[-1500:]
    assert snapshot(micro_root) != before
    tum.write_bytes(original)
    skidbench("split", micro_root, here=True)
    assert snapshot(micro_root) == before


def test_an_evaluate_killed_mid_run_leaves_its_runs_marked_killed_and_a_rerun_completes(micro_root, tmp_path):
    """SIGKILL during the second (model, terrain) of an evaluate: the next stage that opens the store marks
    the runs the dead process left RUNNING as KILLED, with the reason; the re-run takes the run that
    finished as it is and runs the killed one again, and compare reads the finished evaluation, the taken
    run as its own, never the killed one."""

    from mlflow import MlflowClient

    from skidbench.benchmark.tracking import tags as run_tags

    root = tmp_path / "out"
    copy_splits(micro_root, root)
    killed = skidbench("evaluate", root, env={"SKIDBENCH_FAULT": "kill@2:.params.json"}, check=False)
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-2000:]
    client = MlflowClient(f"sqlite:///{root / 'mlflow.db'}")
    (exp,) = [e for e in client.search_experiments() if e.name != "Default"]

    def runs():
        return {r.info.run_id: r for r in client.search_runs([exp.experiment_id])}

    dead = runs()
    assert sorted(r.info.status for r in dead.values()) == [
        "FINISHED",
        "RUNNING",
        "RUNNING",
    ]  # the first child finished; the parent and the second child were left RUNNING

    again = skidbench("evaluate", root, here=True).stdout
    after = runs()
    for run_id, run in dead.items():
        if run.info.status == "RUNNING":
            assert after[run_id].info.status == "KILLED"
            assert "ended without closing the run" in after[run_id].data.tags[run_tags.TAG_REASON]
    new = [r for k, r in after.items() if k not in dead]
    assert sorted(r.info.status for r in new) == ["FINISHED"] * 2  # the parent and the killed model's run
    (finished,) = [k for k, r in dead.items() if r.info.status == "FINISHED"]
    assert "ended KILLED; taken into this one" in again and "taken as they are: ideal/tile" in again
    assert tmp_files(root) == []

    skidbench("compare", root, base=[*STAGE_ARGS["split"], "figures.enabled=false"], here=True)
    board = pd.read_csv(root / DATASET / "reports" / "leaderboard-commanded.csv")
    assert sorted(board["model"]) == ["edd", "ideal"] and (board["status"] == "FINISHED").all()
    (parent,) = [r for r in new if r.data.tags[run_tags.TAG_ROLE] == "parent"]
    assert set(board["parent_run_id"]) == {parent.info.run_id}  # the taken run as the complete one's
    assert finished in set(board["run_id"]) and parent.data.tags["skidbench.reused_runs"] == finished
    assert (
        f"1 evaluate run(s): `{parent.info.run_id}`" in (root / DATASET / "reports" / "report.md").read_text()
    )

    # a newer evaluate killed after a finished one: compare marks its runs KILLED, reads the finished evaluate
    # and names the killed runs it left out
    killed = skidbench(
        "evaluate", root, "force=true", env={"SKIDBENCH_FAULT": "kill@1:.params.json"}, check=False
    )
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-2000:]
    proc = skidbench("compare", root, base=[*STAGE_ARGS["split"], "figures.enabled=false"], here=True)
    statuses = {r.info.run_id: r.info.status for k, r in runs().items() if k not in after}
    assert sorted(statuses.values()) == ["KILLED", "KILLED"]  # the parent and its first child
    board = pd.read_csv(root / DATASET / "reports" / "leaderboard-commanded.csv")
    assert set(board["parent_run_id"]) == {parent.info.run_id} and (board["status"] == "FINISHED").all()
    (left,) = [line for line in proc.stdout.splitlines() if " left out: its evaluate " in line]
    assert left.strip().startswith("ideal/tile: run ") and any(f"run {k[:8]}" in left for k in statuses)
    assert "ended KILLED" in left and "never on a board" in left


def _raising_plugin(folder):
    """An installed model plugin (a distribution on ``sys.path``, entry point ``skidbench.models``) that
    fits and then raises in ``predict``: it reads a column no model is given."""
    (folder / "raising_plugin.py").write_text(
        "import numpy as np\n"
        "from skidbench.models.base import KinematicModel\n\n\n"
        "class Raiser(KinematicModel):\n"
        "    name = 'raiser'\n"
        "    version = '0.1'\n\n"
        "    def fit(self, table):\n"
        "        self.params, self.fit_loss_ = {}, 0.0\n"
        "        return self\n\n"
        "    def predict(self, table):\n"
        "        return np.column_stack([table['vx'], table['vx'], table['vx']])\n"
    )
    info = folder / "raising_plugin-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: raising-plugin\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[skidbench.models]\nraiser = raising_plugin:Raiser\n")
    return folder


def test_a_plugin_that_raises_in_predict_fails_loudly_and_compare_ranks_the_others(micro_root, tmp_path):
    """evaluate with a plugin that raises in predict: exit status 3 with a one-line summary, the console
    line says where the traceback is, the traceback is the FAILED run's artifact and in the stage log;
    the stage is not marked failed: compare ranks the other model and shows the failure."""
    from mlflow import MlflowClient

    root = tmp_path / "out"
    copy_splits(micro_root, root)
    env = {
        "PYTHONPATH": os.pathsep.join(
            filter(None, [str(_raising_plugin(tmp_path)), os.environ.get("PYTHONPATH")])
        )
    }
    args = [*STAGE_ARGS["evaluate"], "models=[ideal,raiser]"]
    proc = skidbench("evaluate", root, env=env, base=args, check=False)
    assert proc.returncode == 3, proc.stderr[-3000:]
    (summary,) = [line for line in proc.stderr.splitlines() if "FAILED under inputs=" in line]
    assert summary.startswith(
        "skidbench evaluate: 1 of 2 model run(s) FAILED under inputs=commanded: raiser/tile"
    )
    assert "Traceback" not in proc.stderr
    assert "FAILED raiser/tile: predict failed: KeyError: 'vx'" in proc.stdout
    (where,) = [line for line in proc.stdout.splitlines() if line.startswith("  traceback: MLflow run ")]
    run_id = where.split("MLflow run ")[1].split()[0]
    client = MlflowClient(f"sqlite:///{root / 'mlflow.db'}")
    assert client.get_run(run_id).info.status == "FAILED"
    text = open(client.download_artifacts(run_id, "error/traceback.txt", str(tmp_path))).read()
    assert "raising_plugin.py" in text and "in predict" in text and text.rstrip().endswith("KeyError: 'vx'")
    log_file = Path(where.split("stage log ")[1])  # Hydra's job log of this evaluate
    assert log_file.is_relative_to(root / "hydra") and "raising_plugin.py" in log_file.read_text()

    proc = skidbench("compare", root, env=env, base=[*STAGE_ARGS["split"], "figures.enabled=false"])
    board = pd.read_csv(root / DATASET / "reports" / "leaderboard-commanded.csv").set_index("model")
    assert board.loc["ideal", "status"] == "FINISHED" and board.loc["raiser", "status"] == "FAILED"


def test_ctrl_c_during_evaluate_is_one_line_its_runs_killed_and_compare_keeps_the_complete_ones(
    micro_root, tmp_path
):
    """Ctrl-C (SIGINT) in the middle of an evaluate that follows a complete one: one line, no traceback,
    exit status 130, its runs marked KILLED; compare then ranks the complete evaluate's runs, not even the
    interrupted one's run that finished (one evaluate per board), and names the runs it left out."""
    from mlflow import MlflowClient

    root = tmp_path / "out"
    copy_splits(micro_root, root)
    skidbench("evaluate", root, here=True)
    proc = skidbench(
        "evaluate", root, "force=true", env={"SKIDBENCH_FAULT": "int@2:.params.json"}, check=False
    )
    assert proc.returncode == 130, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr and "KeyboardInterrupt" not in proc.stderr
    assert (
        proc.stderr.strip().splitlines()[-1].startswith("skidbench evaluate: interrupted (Ctrl-C); its open")
    )
    client = MlflowClient(f"sqlite:///{root / 'mlflow.db'}")
    (exp,) = [e for e in client.search_experiments() if e.name != "Default"]
    runs = sorted(client.search_runs([exp.experiment_id]), key=lambda r: r.info.start_time)
    assert [r.info.status for r in runs[3:]] == [
        "KILLED",
        "FINISHED",
        "KILLED",
    ]  # parent, first child, second
    proc = skidbench("compare", root, base=[*STAGE_ARGS["split"], "figures.enabled=false"], here=True)
    board = pd.read_csv(root / DATASET / "reports" / "leaderboard-commanded.csv").set_index("model")
    assert (board["status"] == "FINISHED").all() and board.loc["edd", "run_id"] == runs[2].info.run_id
    assert board.loc["ideal", "run_id"] == runs[1].info.run_id  # not the interrupted evaluate's, finished
    left = [line.strip() for line in proc.stdout.splitlines() if " left out: its evaluate " in line]
    assert {x.split(" (")[0] for x in left} == {
        f"ideal/tile: run {runs[4].info.run_id[:8]}",
        f"edd/tile: run {runs[5].info.run_id[:8]}",
    }
    assert all("ended KILLED (interrupted (Ctrl-C)" in x for x in left)
