"""Sweep: the same fit sweep on the joblib launcher (2 local processes) and on Ray (``hydra/launcher=ray``),
on this machine: wall times, their ratio (Ray's overhead) and the overhead per job in ms.

The sweep is ``skidbench fit -m model=edd,roc terrain=tile,asphalt,grass reuse=false`` (6 jobs), and the
12-job ``model=ideal,edd,full_linear,roc`` for the cost of one more job; each run is a fresh process with
a fresh SQLite MLflow store, on synthetic splits (``scaling.write_splits``: 2 Train sequences of 1,500
rows per terrain), so a job is mostly fixed cost (a Python process importing skidbench, Hydra and
MLflow; composing the config; one MLflow run), which is where a launcher's overhead shows. Ray runs:

- ``ray``: a one-node cluster with 2 CPUs already running (``local_cluster``, started outside the
  timing, as a lab's cluster would be), joined with ``hydra.launcher.address``;
- ``ray_local``: ``hydra.launcher.address`` null: the sweep starts its own local instance and stops it.

``per_job_overhead_ms`` = (Ray's wall - joblib's wall) / jobs on the 6-job sweep; ``marginal_job_ms`` =
(12-job wall - 6-job wall) / 6 for each launcher (what one more job costs once the sweep is running).
Wall times carry the machine's load (the 1-minute load average at the end is reported): the launchers
alternate, 6 then 12 jobs. CPU seconds do not: the driver and every process it waited for (joblib's
workers), plus, for the running cluster, the CPU its processes (GCS, raylet, workers) used during the
sweep, sampled from ``/proc`` (``_ClusterCPU``). ``ray_local_cpu_s`` is a lower bound: Ray reaps the
workers of a local instance without accounting their CPU to anyone.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from . import register

TERRAINS = ("tile", "asphalt", "grass")
MODELS_6 = ("edd", "roc")
MODELS_12 = ("ideal", "edd", "full_linear", "roc")
DATASET = "bench-sweep"


def write_data(out_root: Path, seq_rows: int = 1500) -> None:
    from skidbench.pipeline.core.robot import load_robot

    from .scaling import write_splits

    robot = load_robot("jackal")
    for k, terrain in enumerate(TERRAINS):
        write_splits(out_root, robot, DATASET, n_seq=2, seq_rows=seq_rows, seed=100 * k, terrain=terrain)


def run_sweep(
    out_root: Path, models: tuple[str, ...], launcher: list[str], tag: str, cluster: Any = None
) -> dict[str, Any]:
    """One ``skidbench fit -m`` sweep in a fresh process: wall and CPU seconds (with ``cluster``, a
    :class:`~skidbench.pipeline.runner.cluster.LocalCluster`, its processes' CPU during the sweep), its
    log."""
    env = dict(os.environ)
    env.update({"SKIDBENCH_OUT": str(out_root), "RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0"})
    env.pop("MLFLOW_TRACKING_URI", None)
    cmd = [
        sys.executable, "-m", "skidbench.pipeline.cli.main", "fit", "-m", f"dataset={DATASET}",
        f"model={','.join(models)}", f"terrain={','.join(TERRAINS)}", "reuse=false",
        f"mlflow.tracking_uri=sqlite:///{out_root / f'mlflow-{tag}.db'}", *launcher,
    ]  # fmt: skip
    log_path = out_root / f"sweep-{tag}.log"
    sampler = _ClusterCPU(cluster) if cluster is not None else None
    started = time.perf_counter()
    with log_path.open("w") as log:
        proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - started
    cpu = usage.ru_utime + usage.ru_stime  # the driver and every process it waited for (joblib's workers)
    if sampler is not None:  # a running cluster's processes (its workers) are not the driver's children
        cpu += sampler.stop()
    text = log_path.read_text()
    if os.waitstatus_to_exitcode(status) != 0:
        tail = text.strip().splitlines()[-1:] or ["no output"]
        raise RuntimeError(f"sweep {tag} failed: {tail[0]}")
    return {"wall_s": wall, "cpu_s": cpu, "log": text}


class _ClusterCPU:
    """CPU seconds the cluster's processes use while it runs: ``/proc`` polled every 0.1 s (Ray reaps
    its workers without accounting them to the raylet, so a worker's CPU is its last sample; at most
    0.1 s of each worker's life is missed)."""

    def __init__(self, cluster: Any) -> None:
        self.cluster = cluster
        self.base = cluster.cpu_ticks()
        self.last = dict(self.base)
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.done.wait(0.1):
            self.last.update(self.cluster.cpu_ticks())

    def stop(self) -> float:
        self.done.set()
        self.thread.join()
        self.last.update(self.cluster.cpu_ticks())
        used = sum(t - self.base.get(k, 0) for k, t in self.last.items())
        return used / os.sysconf("SC_CLK_TCK")


def sweep(quick: bool = False) -> dict[str, Any]:
    from skidbench.pipeline.runner.cluster import local_cluster

    joblib = ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"]
    res: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory(prefix="skidbench-sweep-") as tmp:
        out = Path(tmp)
        write_data(out, 300 if quick else 1500)
        env = {**os.environ, "RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0"}
        cluster_started = time.perf_counter()
        with local_cluster(num_cpus=2, env=env) as cluster:
            cluster_start_s = time.perf_counter() - cluster_started
            ray = ["hydra/launcher=ray", f"hydra.launcher.address={cluster.address}"]
            for n, models in ((6, MODELS_6), (12, MODELS_12))[: 1 if quick else 2]:
                res[f"joblib_{n}"] = run_sweep(out, models, joblib, f"joblib{n}")
                res[f"ray_{n}"] = run_sweep(out, models, ray, f"ray{n}", cluster)
        own = ["hydra/launcher=ray", "hydra.launcher.local.num_cpus=2"]  # starts its own instance
        res["ray_local_6"] = run_sweep(out, MODELS_6, own, "raylocal6")
    started = re.search(r"started a local instance in ([0-9.]+) s", res["ray_local_6"]["log"])
    jobs = len(MODELS_6) * len(TERRAINS)
    j6, r6, l6 = res["joblib_6"], res["ray_6"], res["ray_local_6"]
    m: dict[str, Any] = {
        "jobs": jobs,
        "joblib_wall_s": round(j6["wall_s"], 2),
        "ray_wall_s": round(r6["wall_s"], 2),
        "ray_vs_joblib_wall_ratio": round(r6["wall_s"] / j6["wall_s"], 3),
        "per_job_overhead_ms": round(1000 * (r6["wall_s"] - j6["wall_s"]) / jobs, 1),
        "joblib_cpu_s": round(j6["cpu_s"], 2),
        "ray_cpu_s": round(r6["cpu_s"], 2),
        "ray_vs_joblib_cpu_ratio": round(r6["cpu_s"] / j6["cpu_s"], 3),
        "per_job_cpu_overhead_ms": round(1000 * (r6["cpu_s"] - j6["cpu_s"]) / jobs, 1),
        "ray_local_wall_s": round(l6["wall_s"], 2),
        "ray_local_cpu_s": round(l6["cpu_s"], 2),
        "ray_local_vs_joblib_wall_ratio": round(l6["wall_s"] / j6["wall_s"], 3),
        "ray_local_instance_start_s": float(started.group(1)) if started else "not logged",
        "cluster_start_s": round(cluster_start_s, 2),
        "load_average_1min": round(os.getloadavg()[0], 1),
    }
    if not quick:
        for name in ("joblib", "ray"):
            a, b = res[f"{name}_6"], res[f"{name}_12"]
            m[f"{name}_12_wall_s"] = round(b["wall_s"], 2)
            m[f"{name}_marginal_job_ms"] = round(1000 * (b["wall_s"] - a["wall_s"]) / 6, 1)
            m[f"{name}_marginal_job_cpu_ms"] = round(1000 * (b["cpu_s"] - a["cpu_s"]) / 6, 1)
    return m


@register(
    "sweep",
    "fit sweep (6 jobs): joblib launcher (2 processes) vs Ray (a running 2-CPU local cluster); overhead",
)
def sweep_bench(quick: bool) -> dict[str, Any]:
    try:
        import ray  # noqa: F401
    except ImportError:
        return {"skipped": "Ray is not installed (pip install 'skidbench[cluster]')"}
    return sweep(quick)
