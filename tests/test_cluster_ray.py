"""Sweeps on a real Ray cluster (``hydra/launcher=ray``): the session's local two-node cluster on 127.0.0.1
(``ray start --head`` and a worker node, tests/conftest.py ``ray_cluster``), a real ``mlflow server``, fits
of two models on three terrains and an evaluation of two datasets as Ray tasks; a worker killed mid-task is
retried and every job still yields exactly one finished run, with the metrics of a joblib sweep. Skipped,
with the reason, where Ray is not installed (``pip install 'skidbench[cluster]'``; ``make test`` installs it
when it can)."""

from __future__ import annotations

import importlib.util
from collections import Counter
from pathlib import Path

import pytest
from _bench_data import write_splits
from mlflow_server import free_port, running_mlflow_server
from ray_cluster import ray_env
from reliability_data import skidbench

from skidbench.benchmark.tracking import store as trk
from skidbench.benchmark.tracking import tags as run_tags
from skidbench.pipeline.core.io import process_alive

needs_ray = pytest.mark.skipif(
    importlib.util.find_spec("ray") is None,
    reason="Ray is not installed: pip install 'skidbench[cluster]' (make test installs it when it can)",
)

MODELS = ("edd", "roc")
TERRAINS = ("tile", "asphalt", "grass")
DATASETS = ("lab-a", "lab-b")  # the same synthetic data twice: their metrics must agree
# calibrate.use=false: the sweeps are about the launcher, not the calibration (only `calibrate` computes it)
FIT = [
    "scale=tiny",
    f"model={','.join(MODELS)}",
    f"terrain={','.join(TERRAINS)}",
    "reuse=false",
    "calibrate.use=false",
]


@pytest.fixture(scope="module")
def out_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("ray-out")
    for ds in ("sim-tiny", *DATASETS):
        write_splits(root / ds, terrains=TERRAINS, counts={"train": 1, "cv": 1, "ld": 1}, duration_s=20.0)
    return root


@pytest.fixture(scope="module")
def ray_address(ray_cluster) -> str:
    """The session's Ray cluster (tests/conftest.py ``ray_cluster``: two nodes, one CPU each)."""
    return ray_cluster.address


@pytest.fixture(scope="module")
def mlflow_uri(tmp_path_factory):
    with running_mlflow_server(tmp_path_factory.mktemp("ray-mlflow")) as uri:
        yield uri


def _runs(uri: str, experiment: str):
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=uri)
    exp = client.get_experiment_by_name(experiment)
    assert exp is not None, experiment
    return client.search_runs([exp.experiment_id], max_results=1000)


def _fit_results(runs) -> dict[tuple[str, str], tuple]:
    """(model, terrain) -> what a fit produced (loss, rows, fitted parameters), of the FINISHED runs."""
    out = {}
    for r in runs:
        if r.info.status != "FINISHED":
            continue
        key = (r.data.tags[run_tags.TAG_MODEL], r.data.tags[run_tags.TAG_TERRAIN])
        assert key not in out, f"two finished runs of {key}"
        params = {k: v for k, v in r.data.params.items() if k.startswith("fitted.")}
        out[key] = (r.data.metrics["fit_loss"], r.data.metrics["n_train"], params)
    return out


@needs_ray
@pytest.mark.slow
def test_a_ray_sweep_survives_a_killed_worker_and_logs_each_fit_once_with_the_joblib_metrics(
    out_root, ray_address, mlflow_uri, tmp_path
):
    # the reference: the same sweep with the joblib launcher, into a SQLite store
    ref_uri = f"sqlite:///{tmp_path / 'joblib.db'}"
    skidbench("fit", out_root, "-m", *FIT, "hydra/launcher=joblib", "hydra.launcher.n_jobs=2",
              f"mlflow.tracking_uri={ref_uri}", base=[])  # fmt: skip
    reference = _fit_results(_runs(ref_uri, "skidbench-sim-tiny"))
    assert set(reference) == {(m, t) for m in MODELS for t in TERRAINS}

    marker = tmp_path / "killed"
    proc = skidbench(
        "fit", out_root, "-m", *FIT, "hydra/launcher=ray", f"hydra.launcher.address={ray_address}",
        "+hydra.callbacks.chaos._target_=ray_cluster.KillOnce", f"+hydra.callbacks.chaos.marker={marker}",
        base=[], env=ray_env({"MLFLOW_TRACKING_URI": mlflow_uri}),
    )  # fmt: skip
    assert f"connected to {ray_address}" in proc.stdout + proc.stderr
    pid, killed_run = marker.read_text().split()  # a worker did die, mid-task, with its run open
    assert not process_alive(int(pid))

    runs = _runs(mlflow_uri, "skidbench-sim-tiny")
    status = Counter(r.info.status for r in runs)
    assert status == Counter({"FINISHED": 6, "KILLED": 1}), status
    by_id = {r.info.run_id: r for r in runs}
    assert by_id[killed_run].info.status == "KILLED"
    assert by_id[killed_run].data.tags[run_tags.TAG_REASON]  # says why
    # the retried job has exactly one finished run, under the same key as its dead attempt
    key = by_id[killed_run].data.tags[run_tags.TAG_RUN_KEY]
    assert [r.info.status for r in runs if r.data.tags.get(run_tags.TAG_RUN_KEY) == key].count(
        "FINISHED"
    ) == 1
    assert len({r.data.tags[run_tags.TAG_RUN_KEY] for r in runs}) == 6
    assert len({r.data.tags["skidbench.sweep_id"] for r in runs}) == 1
    assert _fit_results(runs) == reference  # same losses, rows and fitted parameters as joblib's


@needs_ray
@pytest.mark.slow
def test_evaluate_runs_one_ray_task_per_dataset_into_one_mlflow_server(out_root, ray_address, mlflow_uri):
    skidbench(
        "evaluate", out_root, "-m", f"dataset={','.join(DATASETS)}", "models=[edd,roc]", "log_figures=false",
        "calibrate.use=false", "hydra/launcher=ray", f"hydra.launcher.address={ray_address}",
        base=[], env=ray_env({"MLFLOW_TRACKING_URI": mlflow_uri}),
    )  # fmt: skip
    scores = {}
    for ds in DATASETS:
        runs = _runs(mlflow_uri, f"skidbench-{ds}")
        parents = [r for r in runs if r.data.tags[run_tags.TAG_ROLE] == "parent"]
        assert [p.info.status for p in parents] == ["FINISHED"]
        children = [r for r in runs if r.data.tags.get(run_tags.TAG_PARENT) == parents[0].info.run_id]
        assert sorted(
            (c.data.tags[run_tags.TAG_MODEL], c.data.tags[run_tags.TAG_TERRAIN]) for c in children
        ) == sorted((m, t) for m in MODELS for t in TERRAINS)
        assert {c.info.status for c in children} == {"FINISHED"}
        scores[ds] = {
            (c.data.tags[run_tags.TAG_MODEL], c.data.tags[run_tags.TAG_TERRAIN]): c.data.metrics[
                "cv_6s_trans_rmsre_pct"
            ]
            for c in children
        }
    assert scores["lab-a"] == scores["lab-b"]  # the same data scored the same on any worker


@needs_ray
def test_an_unreachable_ray_cluster_is_a_one_line_error(out_root):
    address = f"ray://127.0.0.1:{free_port()}"  # nothing listens there
    proc = skidbench("fit", out_root, "-m", *FIT, "track=false", "hydra/launcher=ray",
                     f"hydra.launcher.address={address}", base=[], env=ray_env(), check=False)  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        f"skidbench fit: error: cannot reach the Ray cluster at {address} ("
    ), proc.stderr


def test_the_ray_launcher_without_ray_installed_is_a_one_line_error(out_root, tmp_path):
    blocker = tmp_path / "noray" / "ray"
    blocker.mkdir(parents=True)
    (blocker / "__init__.py").write_text("raise ImportError(\"No module named 'ray'\")\n")
    env = {"PYTHONPATH": str(blocker.parent)}  # before site-packages: `import ray` fails
    proc = skidbench(
        "fit", out_root, "-m", *FIT, "track=false", "hydra/launcher=ray", base=[], env=env, check=False
    )
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "pip install 'skidbench[cluster]'" in lines[0], proc.stderr
    assert lines[0].startswith("skidbench fit: error: hydra/launcher=ray needs Ray")


def test_a_retried_job_closes_its_dead_attempts_runs_and_logs_once(tmp_path):
    """Tracker.claim_key, the store side of a retry: an open run of the key (from any machine) and its
    open children are marked KILLED; once a run of the key finished, the job logs nothing more."""
    tracker = trk.Tracker(f"sqlite:///{tmp_path / 'm.db'}", "claims", artifact_root=tmp_path / "art")
    other_machine = {run_tags.TAG_HOST: "node-7", run_tags.TAG_BOOT: "another-boot", run_tags.TAG_PID: "1"}
    key = "20261123-120000-000000/3"
    dead = tracker.start("attempt 1", {run_tags.TAG_RUN_KEY: key})
    tracker.log(dead, tags=other_machine)  # reap_dead_runs cannot judge another machine's process
    child = tracker.start("child", {}, parent_id=dead)
    unrelated = tracker.start("another job", {run_tags.TAG_RUN_KEY: key[:-1] + "4"})
    assert tracker.reap_dead_runs() == []
    assert tracker.claim_key(key) is None
    status = {r: tracker.client.get_run(r).info.status for r in (dead, child, unrelated)}
    assert status == {dead: "KILLED", child: "KILLED", unrelated: "RUNNING"}
    assert "retried" in tracker.client.get_run(dead).data.tags[run_tags.TAG_REASON]
    with tracker.run("attempt 2", {run_tags.TAG_RUN_KEY: key}) as second:
        pass
    assert tracker.claim_key(key) == second  # a third attempt finds the finished run: logs nothing
    assert tracker.client.get_run(dead).info.status == "KILLED"


def test_a_retried_evaluate_job_whose_first_attempt_finished_logs_nothing_again(tmp_path, monkeypatch):
    from _bench_data import compose, fit_fn
    from _bench_data import write_splits as write_chi_splits

    from skidbench.benchmark.evaluate.app import benchmark as run_benchmark
    from skidbench.benchmark.tracking import sweep

    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    write_chi_splits(tmp_path / "sim-mini")
    cfg = compose("evaluate", tmp_path, ["models=[chi,ideal_t]"])
    monkeypatch.setattr(sweep, "run_key", lambda: "20261123-120000-000000/0")  # both: one job's attempts
    first = run_benchmark(cfg, fit_fn=fit_fn, log_figures=False)
    again = run_benchmark(cfg, fit_fn=fit_fn, log_figures=False)
    assert again.parent_run_id == first.parent_run_id

    def scores(res):
        return sorted((c.model, c.terrain, c.run_id, c.status, c.metrics["cv_6s_trans_rmsre_pct"])
                      for c in res.children)  # fmt: skip

    assert scores(again) == scores(first) and len(first.children) == 4
    store = trk.Tracker(f"sqlite:///{tmp_path / 'mlflow.db'}", "skidbench-sim-mini")
    runs = store.client.search_runs([store.experiment_id])
    assert len(runs) == 5  # one parent and its four children, logged once
