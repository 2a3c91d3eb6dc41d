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
Wall times carry the machine's load: both launchers run in one comparison, one after the other.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from . import register

TERRAINS = ("tile", "asphalt", "grass")
MODELS_6 = ("edd", "roc")
MODELS_12 = ("ideal", "edd", "full_linear", "roc")
DATASET = "bench-sweep"


def write_data(out_root: Path, seq_rows: int = 1500) -> None:
    from skidbench.pipeline.robot import load_robot

    from .scaling import write_splits

    robot = load_robot("jackal")
    for k, terrain in enumerate(TERRAINS):
        write_splits(out_root, robot, DATASET, n_seq=2, seq_rows=seq_rows, seed=100 * k, terrain=terrain)


def run_sweep(out_root: Path, models: tuple[str, ...], launcher: list[str], tag: str) -> dict[str, Any]:
    """One ``skidbench fit -m`` sweep in a fresh process; wall seconds and its output."""
    env = dict(os.environ)
    env.update({"SKIDBENCH_OUT": str(out_root), "RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0"})
    env.pop("MLFLOW_TRACKING_URI", None)
    cmd = [
        sys.executable, "-m", "skidbench.pipeline.cli", "fit", "-m", f"dataset={DATASET}",
        f"model={','.join(models)}", f"terrain={','.join(TERRAINS)}", "reuse=false",
        f"mlflow.tracking_uri=sqlite:///{out_root / f'mlflow-{tag}.db'}", *launcher,
    ]  # fmt: skip
    started = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=1800)
    wall = time.perf_counter() - started
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
        raise RuntimeError(f"sweep {tag} failed ({proc.returncode}): {tail[0]}")
    return {"wall_s": wall, "log": proc.stdout + proc.stderr}


def sweep(quick: bool = False) -> dict[str, Any]:
    from skidbench.benchmark.cluster import local_cluster

    joblib = ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"]
    with tempfile.TemporaryDirectory(prefix="skidbench-sweep-") as tmp:
        out = Path(tmp)
        write_data(out, 300 if quick else 1500)
        env = {**os.environ, "RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0"}
        cluster_started = time.perf_counter()
        with local_cluster(num_cpus=2, env=env) as address:
            cluster_start_s = time.perf_counter() - cluster_started
            ray = ["hydra/launcher=ray", f"hydra.launcher.address={address}"]
            walls = {
                "joblib_6": run_sweep(out, MODELS_6, joblib, "joblib6")["wall_s"],
                "ray_6": run_sweep(out, MODELS_6, ray, "ray6")["wall_s"],
            }
            if not quick:
                walls["joblib_12"] = run_sweep(out, MODELS_12, joblib, "joblib12")["wall_s"]
                walls["ray_12"] = run_sweep(out, MODELS_12, ray, "ray12")["wall_s"]
        own = ["hydra/launcher=ray", "hydra.launcher.local.num_cpus=2"]  # starts its own instance
        local = run_sweep(out, MODELS_6, own, "raylocal6")
    started = re.search(r"started a local instance in ([0-9.]+) s", local["log"])
    jobs = len(MODELS_6) * len(TERRAINS)
    m: dict[str, Any] = {
        "jobs": jobs,
        "joblib_wall_s": round(walls["joblib_6"], 2),
        "ray_wall_s": round(walls["ray_6"], 2),
        "ray_vs_joblib_wall_ratio": round(walls["ray_6"] / walls["joblib_6"], 3),
        "per_job_overhead_ms": round(1000 * (walls["ray_6"] - walls["joblib_6"]) / jobs, 1),
        "ray_local_wall_s": round(local["wall_s"], 2),
        "ray_local_vs_joblib_wall_ratio": round(local["wall_s"] / walls["joblib_6"], 3),
        "ray_local_instance_start_s": float(started.group(1)) if started else "not logged",
        "cluster_start_s": round(cluster_start_s, 2),
    }
    if not quick:
        for name in ("joblib", "ray"):
            m[f"{name}_12_wall_s"] = round(walls[f"{name}_12"], 2)
            m[f"{name}_marginal_job_ms"] = round(1000 * (walls[f"{name}_12"] - walls[f"{name}_6"]) / 6, 1)
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
