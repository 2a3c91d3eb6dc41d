"""The data stages as Ray tasks on a real multi-node Ray cluster on this machine (``ray start --head`` and
``ray start --address`` worker nodes on 127.0.0.1: the session's one cluster, tests/conftest.py
``ray_cluster``, shared with tests/test_cluster_ray.py): ``extract``, stereo-VO ``groundtruth``,
``split`` and ``calibrate`` of a micro stereo dataset through the cluster write the same bytes as the
local forked workers; a worker node killed mid-stage, its task stopped between writing a
file and renaming it, leaves no partial file and the stage still completes. Skipped, with the reason,
where Ray is not installed (``pip install 'skidbench[cluster]'``)."""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from ray_cluster import ray_env
from reliability_data import (
    DATASET,
    FAULT_ENV,
    FAULT_INJECTION,
    SCALE,
    SIMULATE,
    skidbench,
    snapshot,
    tmp_files,
)

needs_ray = pytest.mark.skipif(
    importlib.util.find_spec("ray") is None,
    reason="Ray is not installed: pip install 'skidbench[cluster]' (make test installs it when it can)",
)
pytestmark = [needs_ray, pytest.mark.slow]

#: the micro dataset with its stereo images (VO is the stage a cluster is for)
STEREO = [a for a in SIMULATE if a != "images=false"]
#: stage -> its overrides on the micro dataset (calibrate: no MLflow run; the stamps are what matters)
STAGES = {
    "extract": [*SCALE, "extract.progress=false"],
    "groundtruth": [*SCALE, "groundtruth.method=vo"],
    "split": SCALE,
    "calibrate": [*SCALE, "track=false"],
}


def _outputs(ds: Path) -> None:
    """Remove every output of the stages after simulate (their stamps too): the raw bags stay."""
    for name in ("extracted", "groundtruth", "splits", "calibration", ".stamps", "dataset.json"):
        p = ds / name
        shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)


@pytest.fixture(scope="module")
def local_run(tmp_path_factory) -> tuple[Path, dict[str, str]]:
    """The micro stereo dataset simulated, then every data stage run by local forked workers: (out_root,
    the snapshot of those stages' outputs)."""
    root = tmp_path_factory.mktemp("stages")
    skidbench("simulate", root, *STEREO, base=[])
    for stage, args in STAGES.items():
        skidbench(stage, root, *args, base=[])
    return root, snapshot(root / DATASET)


@pytest.fixture
def cluster(ray_cluster):
    """The session's Ray cluster (tests/conftest.py ``ray_cluster``): a head and a worker node, one CPU
    each, a lost node noticed in about three seconds; the tests' folder importable on both."""
    return ray_cluster


def _on_ray(cluster) -> list[str]:
    return ["hydra/launcher=ray", f"hydra.launcher.address={cluster.address}"]


def test_the_data_stages_on_a_two_node_ray_cluster_write_the_local_bytes(local_run, cluster):
    root, reference = local_run
    _outputs(root / DATASET)
    for stage, args in STAGES.items():
        proc = skidbench(stage, root, *args, *_on_ray(cluster), base=[], env=ray_env())
        assert f"connected to {cluster.address}" in proc.stdout + proc.stderr, proc.stderr
    assert snapshot(root / DATASET) == reference
    assert tmp_files(root) == []
    # a rerun through the cluster does only what is missing: here nothing
    proc = skidbench("groundtruth", root, *STAGES["groundtruth"], *_on_ray(cluster), base=[], env=ray_env())
    assert "3 sequences up to date, skipped" in proc.stdout + proc.stderr, proc.stderr


def _stopped(node: subprocess.Popen) -> list[int]:
    """The processes of a node's tree stopped by SIGSTOP (state T)."""
    from skidbench.pipeline.runner.cluster import _tree_stats

    return [pid for pid, f in _tree_stats(node.pid) if f[0] == "T"]


def test_a_worker_node_killed_mid_write_leaves_no_partial_file_and_the_stage_completes(local_run, cluster):
    root, reference = local_run
    ds = root / DATASET
    for p in [*(ds / "groundtruth").glob("*"), *(ds / ".stamps" / "groundtruth").glob("*")]:
        p.unlink()
    # a third node whose workers stop at their first ground-truth write, the file written but not renamed
    path = os.pathsep.join([str(FAULT_INJECTION), ray_env()["PYTHONPATH"]])
    victim = cluster.add_node(num_cpus=1, env={"PYTHONPATH": path, FAULT_ENV: "stop@1:/groundtruth/"})
    cli = [sys.executable, "-m", "skidbench.pipeline.cli.main"]
    cmd = [*cli, "groundtruth", *STAGES["groundtruth"], *_on_ray(cluster)]
    env = {**ray_env(), "SKIDBENCH_OUT": str(root), "PYTHONHASHSEED": "0"}
    with subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as stage:
        deadline = time.monotonic() + 300
        while not (stopped := _stopped(victim)):
            assert stage.poll() is None and time.monotonic() < deadline, "no task stopped on the victim node"
            time.sleep(0.5)
        partial = [p for p in tmp_files(root) if f".{stopped[0]}." in p.name]
        assert partial, tmp_files(root)  # mid-write: the temporary file is there ...
        final = partial[0].parent / partial[0].name.removeprefix(".tmp-").split(f".{stopped[0]}.")[0]
        assert not final.exists()  # ... and its output is not
        cluster.kill_node(victim)
        out, err = stage.communicate(timeout=600)
    assert stage.returncode == 0, err
    assert tmp_files(root) == []  # the retry cleared the dead task's temporary file
    assert snapshot(ds) == reference
